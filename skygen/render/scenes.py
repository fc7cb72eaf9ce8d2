"""Many scenes at once: the vectorised scene builder of the frames stream.

:meth:`skygen.render.frame.Renderer.scene` builds one frame's scene (attitude, light sources,
cosmic-ray charge, stray-light direction) from per-frame numpy generators, ~0.4 ms a
frame, most of it creating generators. :class:`SceneBuilder` builds the scenes of many
samples in one go from counter-based draws (:mod:`skygen.hashrng`), distributed as
``Renderer.scene`` draws them: the same attitude distribution
(:func:`skygen.sky.attitude.boresights_from_uniforms`), the same catalog stars (the
renderer's sky index, cone and sensor margins), photometry and vignetting, false stars as
the renderer draws them, cosmic-ray tracks by :func:`skygen.instrument.corruptions.cosmic_ray_charge`
and the stray-light direction. Sample ``i`` is a pure function of (config, stream key,
``i``), alone or in any batch. Motion blur (per-frame sub-exposure paths) is left to
``Renderer.scene``: with ``corruptions.motion_blur > 0`` every scene comes from it.

Both renderers of the frames stream (:mod:`skygen.render.binned` and the full renderer) rasterise
these scenes, so a sample's stars are the same whichever draws its pixels.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from skygen import hashrng
from skygen.instrument import corruptions as corr
from skygen.render.frame import Scene
from skygen.sky.attitude import attitude_matrices, boresights_from_uniforms

# draw ids under the stream key (skygen.stream.samples keeps its own below 64 and at >= 512)
D_ATT = 0  # 0..2
D_NFALSE = 16
D_COSMIC = 18
D_COSMIC_SEED = 19
D_STRAY = 20
D_FALSE = 1 << 36  # + 4 * k: false star k (x, y, magnitude)


class SceneBuilder:
    """Scenes of one renderer's config under one stream key (see the module docstring)."""

    def __init__(self, renderer, key):
        r = renderer
        self.r, self.key = r, key
        cfg, cam = r.cfg, r.camera
        sky = r.sky
        self.e_star = (
            r.photometry.electrons_per_s(sky.table.mag + r.mag_offset_to_hp, sky.table.bv)
            * cfg.sensor.exposure_s
            * r.star_gain
        )
        radius = r._corner + (r.psf_radius + 2) / cam.f_px  # as Renderer.visible_stars, no blur
        self.chord = 2.0 * np.sin(min(radius, np.pi) / 2.0)
        self.margin_px = r.psf_radius + 1
        self.cosmic_rate = corr.cosmic_ray_rate(
            (cfg.camera.height_px, cfg.camera.width_px), cfg.camera.pixel_pitch_um, cfg.sensor.exposure_s, 1.0
        )

    def scenes(self, idx: np.ndarray, levels: dict[str, np.ndarray]) -> list:
        """Scenes of samples ``idx`` with per-sample corruption ``levels`` (the renderer's levels
        with the stream's ranged ones, arrays of len(idx))."""
        r, key = self.r, self.key
        cfg, cam, sky = r.cfg, r.camera, r.sky
        idx = np.asarray(idx, np.int64)
        B = len(idx)

        def lv(name):
            return np.broadcast_to(np.asarray(levels.get(name, r.levels[name]), np.float64), (B,))

        if (lv("motion_blur") > 0).any():
            out = []
            for j, i in enumerate(idx):
                with r.with_levels({k: float(lv(k)[j]) for k in r.levels}):
                    out.append(r.scene(int(i)))
            return out
        u = hashrng.uniform(key, idx[:, None], D_ATT + np.arange(3)[None, :])
        ra, dec, roll = boresights_from_uniforms(cfg.attitude, idx, u)
        R = attitude_matrices(ra, dec, roll)
        pairs = cKDTree(R[:, :, 2]).sparse_distance_matrix(sky.tree, self.chord + 1e-12, output_type="ndarray")
        order = np.lexsort((pairs["j"], pairs["i"]))  # per frame, catalog order (as cone())
        fr, star = pairs["i"][order].astype(np.int64), pairs["j"][order].astype(np.int64)
        v_cam = np.einsum("nji,nj->ni", R[fr], sky.vectors[star])
        x, y, front = cam.project(v_cam)
        keep = front & cam.inside(x, y, self.margin_px)
        fr, star, x, y = fr[keep], star[keep], x[keep], y[keep]
        e = self.e_star[star] * r.vignetting(x, y)
        bounds = np.searchsorted(fr, np.arange(B + 1))
        t = sky.table
        nf = hashrng.poisson(lv("false_stars"), hashrng.uniform(key, idx, D_NFALSE))
        nc = hashrng.poisson(self.cosmic_rate * lv("cosmic_rays"), hashrng.uniform(key, idx, D_COSMIC))
        stray_on = lv("stray_light") > 0
        out = []
        for j, i in enumerate(idx):
            a, b = bounds[j], bounds[j + 1]
            s = star[a:b]
            stars = {
                "hip_id": t.hip[s],
                "x_px": x[a:b],
                "y_px": y[a:b],
                "mag": t.mag[s],
                "bv": t.bv[s],
                "electrons": e[a:b],
                "paths": None,
            }
            log: dict = {}
            if lv("false_stars")[j] > 0:
                stars = self._false_stars(stars, int(i), int(nf[j]))
                log["false_stars"] = {"n": int(nf[j])}
            cosmic, cboxes = [], []
            if lv("cosmic_rays")[j] > 0:
                if nc[j]:
                    rng = np.random.default_rng(int(hashrng.bits(key, i, D_COSMIC_SEED)))
                    cosmic, cboxes, _ = corr.cosmic_ray_charge(
                        (cfg.camera.height_px, cfg.camera.width_px),
                        cfg.camera.pixel_pitch_um,
                        cfg.sensor.exposure_s,
                        float(lv("cosmic_rays")[j]),
                        rng,
                        n=int(nc[j]),
                    )
                log["cosmic_rays"] = {"n_hits": int(nc[j])}
            stray = None
            if stray_on[j]:
                stray = float(2 * np.pi * hashrng.uniform(key, i, D_STRAY))
                log["stray_light"] = {"direction_deg": round(float(np.degrees(stray)), 4)}
            out.append(
                Scene(
                    int(i),
                    -1,
                    float(ra[j]),
                    float(dec[j]),
                    float(roll[j]),
                    R[j],
                    stars,
                    cosmic,
                    cboxes,
                    stray,
                    log,
                    int(i),
                    int(i),
                )
            )
        return out

    def _false_stars(self, stars: dict, i: int, n: int) -> dict:
        """Append ``n`` false stars as Renderer._false_stars draws them (uniform position on the
        sensor, magnitude from :func:`skygen.instrument.corruptions.false_star_magnitudes`, no colour)."""
        r, cam = self.r, self.r.camera
        d = D_FALSE + 4 * np.arange(n)
        x = -0.5 + cam.width_px * hashrng.uniform(self.key, i, d)
        y = -0.5 + cam.height_px * hashrng.uniform(self.key, i, d + 1)
        c = r.cfg.corruptions
        u = hashrng.uniform(self.key, i, d + 2)
        mag = corr.false_star_magnitudes(u, r.detection_limit_mag, c.false_star_slope, c.false_star_span_mag)
        e = r.photometry.electrons_per_s(mag, None) * r.cfg.sensor.exposure_s * r.vignetting(x, y)
        fake = {
            "hip_id": np.full(n, -1, np.int64),
            "x_px": x,
            "y_px": y,
            "mag": mag,
            "bv": np.full(n, np.nan, np.float32),
            "electrons": e,
        }
        return {k: (np.concatenate([stars[k], fake[k]]) if k != "paths" else None) for k in stars}
