"""Non-square pixels (camera.pixel_aspect = pixel height / width): projection, rendering, detection, solving."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.wcs import WCS

from skygen.config import load_config
from skygen.instrument.camera import Camera
from skygen.sky.attitude import attitude_matrix
from skygen.sky.catalog import radec_to_vec

TALL = [
    "camera.width_px=512",
    "camera.height_px=256",
    "camera.fov_deg=20",
    "camera.pixel_aspect=2",
    "output.image_size_px=512",
    "output.full_res=true",
    "corruptions.cosmic_rays=0",
    "corruptions.hotpixels=0",
]


def test_unproject_inverts_project_with_aspect_and_distortion():
    cam = Camera(640, 240, 900.0, 330.0, 118.0, k1=-0.08, k2=0.02, p1=1e-3, aspect=2.0)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-0.5, 639.5, 500), rng.uniform(-0.5, 239.5, 500)
    px, py, front = cam.project(cam.unproject(x, y))
    assert front.all() and np.max(np.hypot(px - x, py - y)) < 1e-6
    assert cam.fov_deg[1] == pytest.approx(np.degrees(2 * np.arctan(240 * 2 / 2 / 900)))


def test_projection_matches_a_wcs_with_tall_pixels():
    """An astropy TAN WCS whose CD matrix has rows aspect times taller (built from the conventions)."""
    cam = Camera.from_config(load_config(overrides=TALL).camera)
    ra, dec, roll = 120.0, -35.0, 33.0
    r, scale = np.radians(roll), np.degrees(1.0 / cam.f_px)
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [ra, dec]
    w.wcs.crpix = [cam.cx_px + 1, cam.cy_px + 1]
    w.wcs.cd = scale * np.array([[-np.cos(r), -np.sin(r) * cam.aspect], [np.sin(r), -np.cos(r) * cam.aspect]])
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-0.5, cam.width_px - 0.5, 200), rng.uniform(-0.5, cam.height_px - 0.5, 200)
    sky = w.pixel_to_world_values(x, y)
    px, py, _ = cam.project(radec_to_vec(np.radians(sky[0]), np.radians(sky[1])) @ attitude_matrix(ra, dec, roll))
    assert np.max(np.hypot(px - x, py - y)) < 0.01


def test_rendered_tall_pixel_frame_puts_stars_where_projection_says():
    from skygen.render.frame import Renderer

    cfg = load_config(overrides=TALL + ["sensor.exposure_s=0.5"])
    r = Renderer(cfg)
    errs, shapes, n = [], [], 0
    for i in range(6):
        f = r.render(i)
        det, stars = f.detections, f.stars
        ok = det["star_index"] >= 0
        sx, sy = stars["x_px"][det["star_index"][ok]], stars["y_px"][det["star_index"][ok]]
        # isolated, unsaturated, away from the edge: the centroid measures the projection
        iso = [np.sum(np.hypot(stars["x_px"] - a, stars["y_px"] - b) < 8) == 1 for a, b in zip(sx, sy)]
        sel = np.array(iso, bool) & (det["peak_adu"][ok] < 3000) & (sx > 10) & (sx < 500) & (sy > 6) & (sy < 249)
        errs += list(np.hypot(det["x_px"][ok][sel] - sx[sel], det["y_px"][ok][sel] - sy[sel]))
        img = f.image_full.astype(float) - f.background_adu
        for a, b in zip(det["x_px"][ok][sel][:5], det["y_px"][ok][sel][:5]):
            xi, yi = int(round(a)), int(round(b))
            st = np.clip(img[yi - 4 : yi + 5, xi - 6 : xi + 7], 0, None)
            yy, xx = np.mgrid[-4:5, -6:7]
            t = st.sum()
            mx, my = (st * xx).sum() / t, (st * yy).sum() / t
            shapes.append(np.sqrt((st * (yy - my) ** 2).sum() / (st * (xx - mx) ** 2).sum()))
        n += int(sel.sum())
    assert n >= 10
    assert np.median(errs) < 0.15
    # the PSF is round on the sky, so it spans fewer rows than columns (noise in the 9 x 13 box widens both
    # alike; the exact widths are checked on noise-free stamps below)
    assert np.median(shapes) < 0.75


@pytest.mark.parametrize("psf", ["gaussian", "moffat"])
def test_stamp_is_round_on_the_sky(psf):
    """Second moments of a noise-free stamp: rows measure sigma / aspect, columns sigma (plus the pixel's 1/12)."""
    from skygen.instrument.psf import stamp

    s, aspect = 1.5, 2.0
    y0, x0, p = stamp(0.2, -0.3, 1.0, psf, s, 3.0, aspect)
    yy, xx = np.mgrid[y0 : y0 + p.shape[0], x0 : x0 + p.shape[1]]
    assert p.sum() == pytest.approx(1.0)
    assert (p * xx).sum() == pytest.approx(0.2, abs=0.01) and (p * yy).sum() == pytest.approx(-0.3, abs=0.01)
    vx, vy = (p * (xx - 0.2) ** 2).sum() - 1 / 12, (p * (yy + 0.3) ** 2).sum() - 1 / 12
    assert vy * aspect**2 == pytest.approx(vx, rel=0.03)
    if psf == "gaussian":
        assert np.sqrt(vx) == pytest.approx(s, rel=0.01)


def test_sky_background_scales_with_pixel_area():
    from skygen.render.frame import Renderer

    square = Renderer(load_config(overrides=TALL[:3] + ["output.image_size_px=512"]))
    tall = Renderer(load_config(overrides=TALL))
    assert tall.sky_e == pytest.approx(2 * square.sky_e, rel=1e-9)


def test_torch_backend_refuses_tall_pixels():
    from skygen.errors import ConfigError

    with pytest.raises(ConfigError, match="pixel_aspect"):
        load_config(overrides=TALL + ["render.backend=torch"])


def test_tetra3rs_solves_a_tall_pixel_frame():
    pytest.importorskip("tetra3rs")
    from fusion.solve.base import Detections, Solution
    from fusion.solve.tetra import Tetra3Solver
    from skygen.render.frame import Renderer

    cfg = load_config(overrides=TALL + ["sensor.exposure_s=0.5"])
    r = Renderer(cfg)
    solver = Tetra3Solver(r.camera)
    solved = 0
    for i in range(4):
        f = r.render(i)
        res = solver.solve(Detections.from_table(f.detections), r.camera)
        if isinstance(res, Solution):
            solved += 1
            v = radec_to_vec(np.radians(res.ra_deg), np.radians(res.dec_deg))
            assert np.degrees(np.arccos(np.clip(v @ f.unit_vector, -1, 1))) < 0.01
    assert solved >= 3
