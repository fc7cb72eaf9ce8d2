"""One frame, end to end: attitude -> stars -> optics -> sensor -> detection.

:class:`Renderer` holds everything that is the same for every frame of a dataset (the
catalog index, camera, photometry, static sensor maps). ``Renderer(cfg).render(i)``
is a pure function of (config, i): frame i is identical whether rendered alone, in a
worker pool, or after a resume.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field

import cv2
import numpy as np

from skygen.errors import ConfigError
from skygen.identity import frame_ids, frame_key, legacy_frame_ids, split_bounds
from skygen.instrument import corruptions as corr
from skygen.instrument.camera import Camera
from skygen.instrument.detect import detect, match
from skygen.instrument.photometry import Photometry, dark_current_e_s, star_gains
from skygen.instrument.psf import add_patch, gaussian_stamps, peak_fraction, stamp, stamp_radius_px, streak
from skygen.instrument.sensor import Exposure, ToneCurve, read_out, sensor_maps
from skygen.sky.attitude import attitude_matrix, matrix_to_quaternion, rotation_about, sample_boresight
from skygen.sky.catalog import SkyIndex, StarTable, open_catalog, radec_to_vec

SPLIT_CODES = {"train": 0, "val": 1, "test": 2}
BLUR_STEP_PX = 0.25  # sub-exposure spacing of a motion-blurred star
#: fewest catalogue stars above the detection limit a field must hold on average: below it most
#: frames (Poisson P(0) > 60 %) show no star at all, which no solver and no model can use
MIN_DETECTABLE_PER_FIELD = 0.5
#: fewer catalogue stars than this above the detection limit per field on average: skygen render warns
#: (most frames then hold fewer than three detections, too few to localise or solve)
FEW_DETECTABLE_PER_FIELD = 3.0


@dataclass
class Frame:
    index: int
    split: int
    ra_deg: float
    dec_deg: float
    roll_deg: float
    unit_vector: np.ndarray
    quaternion: np.ndarray
    image: np.ndarray
    image_full: np.ndarray | None
    downsample_factor: int
    stars: dict
    detections: dict
    background_adu: float
    noise_adu: float
    applied: dict
    log: dict = field(default_factory=dict)
    index_in_split: int = 0
    frame_id: int = 0

    @property
    def n_stars(self) -> int:
        return int(np.sum(self.stars["hip_id"] >= 0))

    @property
    def n_detections(self) -> int:
        return len(self.detections["x_px"])


@dataclass(frozen=True)
class Scene:
    """What frame ``index`` shows, before any pixel noise (see :meth:`Renderer.scene`).

    ``stars``: every light source that can reach the sensor, catalog stars then false
    stars, as arrays: ``hip_id`` (-1: false star), ``x_px``/``y_px`` (full-resolution
    pixels at mid-exposure, (0, 0) = centre of the top-left pixel), ``mag`` (Hp), ``bv``,
    ``electrons`` (expected photo-electrons over the exposure, vignetting applied, before
    PRNU) and ``paths`` (None, or (xs, ys) of shape (n_sources, n_substeps): sub-exposure
    positions of a motion-blurred frame, each carrying an equal share of the flux).
    ``cosmic_rays``: [(y0, x0, patch)] of deposited charge in electrons (not Poisson
    sampled again), ``cosmic_boxes`` their half-open (y0, y1, x0, x1) boxes.
    ``stray_light_rad``: direction of the stray-light ramp, or None. ``rotation``: the
    3 x 3 matrix taking camera-frame vectors to ICRS.
    """

    index: int
    split: int
    ra_deg: float
    dec_deg: float
    roll_deg: float
    rotation: np.ndarray
    stars: dict
    cosmic_rays: list
    cosmic_boxes: list
    stray_light_rad: float | None
    log: dict
    index_in_split: int = 0
    rng_key: int | tuple = 0  # the random-stream key of the frame (Renderer.stream_key)


class Renderer:
    """Renders frames of one configuration. Construct once per process."""

    def __init__(self, cfg, catalog: StarTable | None = None, rng_tag: str = "", legacy_streams: bool = False):
        """``rng_tag``: appended to every stage name of the per-frame generators: "" for
        datasets; the streams of :mod:`skygen.stream.samples` use their own tag (and key sample i by
        i alone), so their frames never repeat a dataset's. ``legacy_streams``: key random
        streams by the global frame index, as schema 1.x datasets were rendered (to
        re-render frames of such a dataset exactly)."""
        from skygen.config import config_dict

        self.cfg = cfg
        self.rng_tag = rng_tag
        self.legacy_streams = legacy_streams
        self._config_dict = config_dict(cfg)
        s, o = cfg.sensor, cfg.optics
        self.camera = Camera.from_config(cfg.camera)
        self.photometry = Photometry.from_config(o, cfg.photometry, s)
        # a pixel covers pixel_scale^2 * aspect arcsec^2 of sky (non-square pixels: taller rows see more sky)
        self.sky_e = (
            self.photometry.sky_electrons_per_px_s(cfg.photometry.sky_mag_arcsec2, self.camera.pixel_scale_arcsec)
            * s.exposure_s
            * self.camera.aspect
        )
        self.dark_e = dark_current_e_s(s) * s.exposure_s
        self.background_e = self.dark_e + self.sky_e
        self.levels = corr.levels_of(cfg)
        self.detection_limit_mag = self._detection_limit()
        mag_limit = cfg.catalog.mag_limit
        if mag_limit is None:
            mag_limit = self.detection_limit_mag + cfg.catalog.mag_margin
        self.mag_limit = float(mag_limit)
        table = catalog if catalog is not None else open_catalog(cfg.catalog.source, cfg.catalog.path)
        # the magnitude limit is in Hp; a V-band catalog is shifted onto the same scale
        self.mag_offset_to_hp = cfg.photometry.hp_minus_v if table.band == "V" else 0.0
        self._check_detectable_per_field(table)
        self.sky = SkyIndex(table, cfg.epoch_yr, self.mag_limit - self.mag_offset_to_hp)
        # each indexed star's fixed brightness factor on this sensor (photometry.star_scatter_mag; ones by default)
        self.star_gain = star_gains(self.sky.table.hip, cfg.photometry.star_scatter_mag, cfg.sensor.sensor_seed)
        if cfg.catalog.mag_limit is not None:
            self._check_stars_per_field(table)
        self.maps = sensor_maps(
            cfg.camera.height_px,
            cfg.camera.width_px,
            s.sensor_seed,
            s.prnu_frac,
            s.fpn_adu,
            s.bias_adu - s.black_level_adu,  # a processor's black level: the read-out less it, clipped at 0
            cfg.corruptions.hotpixels,
            s.hot_pixel_dark_e_s,
            s.dead_pixel_fraction,
        )
        self.psf_radius = stamp_radius_px(o.psf, o.psf_sigma_px / min(self.camera.aspect, 1.0))
        self.split_bounds = split_bounds(cfg.n_frames, cfg.output.split_fractions)
        self.factor = cfg.camera.width_px // cfg.output.image_size_px
        self._corner = self.camera.corner_radius_rad()

    # ------------------------------------------------------------------ helpers
    def noise_e(self, extra_read_e: float | None = None) -> float:
        """Background noise per pixel in electrons (shot, read, quantisation, FPN).

        ``extra_read_e``: the read-noise corruption's extra e- rms (None: the current level)."""
        extra = self.levels["read_noise"] if extra_read_e is None else extra_read_e
        return float(np.sqrt(self.background_e + self._floor_e2(extra)))

    def _floor_e2(self, extra_read_e: float) -> float:
        """Variance (e-^2) of the noise that does not grow with the exposure: read, quantisation, FPN."""
        s = self.cfg.sensor
        g = s.gain_e_per_adu
        return s.read_noise_e**2 + extra_read_e**2 + g * g / 12.0 + (g * s.fpn_adu) ** 2

    def _field_sr(self) -> float:
        """Solid angle of the rectangular field, steradians."""
        fx, fy = (np.radians(v) for v in self.camera.fov_deg)
        return float(4 * np.arcsin(np.sin(fx / 2) * np.sin(fy / 2)))

    def _check_detectable_per_field(self, table: StarTable) -> None:
        """Refuse sensor and optics settings whose detection limit leaves a field under
        :data:`MIN_DETECTABLE_PER_FIELD` catalogue stars on average (a unit slip such as
        ``sensor.exposure_s=0.0001``: Hp -1.5, no star on the sky is that bright), when a fainter
        limit would give them (a narrow camera with a thin catalog is not these keys' fault and
        passes). The limit is taken without the read-noise corruption: a robustness sweep may
        drown the stars on purpose."""
        field_sr = self._field_sr()
        mags = np.sort(table.mag[np.isfinite(table.mag)]) + self.mag_offset_to_hp
        self._sorted_hp = mags
        needed = int(np.ceil(MIN_DETECTABLE_PER_FIELD * 4 * np.pi / field_sr))  # stars on the sky for that
        limit = self._detection_limit(extra_read_e=0.0)
        per_field = np.searchsorted(mags, limit, side="right") * field_sr / (4 * np.pi)
        self.detectable_per_field = float(per_field)
        if needed > len(mags) or (np.isfinite(limit) and limit >= mags[needed - 1]):
            return
        need_mag = float(mags[needed - 1])
        s, fx, fy = self.cfg.sensor, *self.camera.fov_deg
        raise ConfigError(
            f"this config detects no star in most frames: its detection limit is Hp {limit:.2f} (a solar-type star "
            f"whose peak pixel reaches detection.threshold_sigma={self.cfg.detection.threshold_sigma:g}), which "
            f"leaves {per_field:.2g} catalog stars per {fx:.1f} x {fy:.1f} deg field (at least "
            f"{MIN_DETECTABLE_PER_FIELD:g} needs Hp {need_mag:.2f}); check the units of sensor.exposure_s "
            f"({s.exposure_s:g} s: Hp {need_mag:.2f} needs >= {self._exposure_for_limit(need_mag):.3g} s), "
            f"optics.aperture_mm ({self.cfg.optics.aperture_mm:g}) and sensor.gain_e_per_adu "
            f"({s.gain_e_per_adu:g} e-/ADU), or lower detection.threshold_sigma"
        )

    def _exposure_for_limit(self, mag_hp: float) -> float:
        """The exposure (s) at which a solar-type star of ``mag_hp`` reaches the detection threshold in
        its peak pixel, the rest of the config kept: solves (F p t)^2 = k^2 (b t + c) for t, with F the
        star's e-/s, p the peak fraction, k the threshold, b the background e-/px/s, c the floor variance."""
        o, s = self.cfg.optics, self.cfg.sensor
        F = float(self.photometry.electrons_per_s(np.array([mag_hp]), np.array([0.65]))[0])
        p = peak_fraction(o.psf, o.psf_sigma_px, o.moffat_beta, self.camera.aspect)
        k2 = self.cfg.detection.threshold_sigma**2
        b, c = self.background_e / s.exposure_s, self._floor_e2(0.0)
        a = (F * p) ** 2
        return float((k2 * b + np.sqrt(k2 * k2 * b * b + 4 * a * k2 * c)) / (2 * a))

    def _check_stars_per_field(self, table: StarTable) -> None:
        """Refuse an explicit ``catalog.mag_limit`` so bright that a field holds under one star
        on average, when a fainter limit would give one (a narrow camera with a thin catalog
        is not this key's fault and passes)."""
        fx, fy = (np.radians(v) for v in self.camera.fov_deg)
        field_sr = self._field_sr()
        per_field = len(self.sky) * field_sr / (4 * np.pi)
        mags = np.sort(table.mag[np.isfinite(table.mag)]) + self.mag_offset_to_hp
        needed = int(np.ceil(4 * np.pi / field_sr))  # stars on the sky for 1 per field
        if per_field >= 1 or needed > len(mags):
            return
        need = float(mags[needed - 1])
        auto = self.detection_limit_mag + self.cfg.catalog.mag_margin
        raise ConfigError(
            f"catalog.mag_limit={self.mag_limit:g} leaves {len(self.sky)} catalog stars (the brightest "
            f"is Hp {mags[0]:.2f}), {per_field:.2g} per {np.degrees(fx):.1f} x {np.degrees(fy):.1f} deg "
            f"field on average: frames would be nearly empty. Give catalog.mag_limit >= {need:.1f} "
            f"(1 star per field), or null (detection limit + catalog.mag_margin = Hp {auto:.2f})"
        )

    def _detection_limit(self, extra_read_e: float | None = None) -> float:
        """Hp magnitude of a solar-type star whose centred peak pixel reaches the threshold, in the frame's ADU
        (through a processor's tone curve, which compresses a peak above its knee, where there is one;
        ``extra_read_e``: as :meth:`noise_e`)."""
        o, s = self.cfg.optics, self.cfg.sensor
        peak = peak_fraction(o.psf, o.psf_sigma_px, o.moffat_beta, self.camera.aspect)
        # a processor's black level above the background takes that much light off the peak first
        crushed_e = max((s.black_level_adu - s.bias_adu) * s.gain_e_per_adu - self.background_e, 0.0)
        excess_e = self.cfg.detection.threshold_sigma * self.noise_e(extra_read_e)
        tone = ToneCurve.of(s)
        if tone is not None:  # the threshold is in the frame's ADU, above the knee compressed: the read-out it needs
            g = s.gain_e_per_adu
            x_bg = max(s.bias_adu - s.black_level_adu + self.background_e / g - tone.pedestal, 0.0)
            y_need = tone.value(x_bg) + tone.slope(x_bg) * excess_e / g
            excess_e = (tone.inverse(y_need) - x_bg) * g
        e_needed = (excess_e + crushed_e) / peak
        return self.photometry.magnitude_for_electrons_per_s(e_needed / self.cfg.sensor.exposure_s, 0.65)

    def sparse_warning(self) -> str | None:
        """A sentence when fewer than :data:`FEW_DETECTABLE_PER_FIELD` catalogue stars per field lie above the
        detection limit on average (the catalogue allowing more): most frames would hold fewer than three
        detections. None otherwise."""
        mags = self._sorted_hp
        needed = int(np.ceil(FEW_DETECTABLE_PER_FIELD * 4 * np.pi / self._field_sr()))
        if self.detectable_per_field >= FEW_DETECTABLE_PER_FIELD or needed > len(mags):
            return None
        need_mag = float(mags[needed - 1])
        return (
            f"only {self.detectable_per_field:.2g} catalog stars per field lie above the detection limit (Hp "
            f"{self._detection_limit(extra_read_e=0.0):.2f}): most frames will hold fewer than 3 detections, too "
            f"few to localise or solve. {FEW_DETECTABLE_PER_FIELD:g} per field needs Hp {need_mag:.2f}: "
            f"sensor.exposure_s >= {self._exposure_for_limit(need_mag):.3g} s (now {self.cfg.sensor.exposure_s:g}), "
            "or a lower detection.threshold_sigma"
        )

    def depth_warning(self) -> str | None:
        """A sentence when the camera sees fainter than Hipparcos-2 is complete and nothing stands in for the
        stars it lacks (no ``corruptions.false_stars``; a fitted camera has them); None otherwise."""
        from skygen.sky.catalog import HIPPARCOS_COMPLETE_HP

        c = self.cfg
        if c.catalog.source != "hipparcos" or c.catalog.path or c.corruptions.false_stars > 0:
            return None
        if self.detection_limit_mag <= HIPPARCOS_COMPLETE_HP:
            return None
        return (
            f"the detection limit (Hp {self.detection_limit_mag:.2f}) is fainter than Hipparcos-2 is complete "
            f"(Hp ~{HIPPARCOS_COMPLETE_HP:g}; it holds about 57 % of the stars at Hp 8-8.5, 38 % at 8.5-9): frames "
            "will show fewer faint stars than the sky has. catalog.source=gaia renders Gaia DR3 to G = 10 merged "
            "with it (data CC BY-SA 3.0 IGO)"
        )

    def saturation_warning(self) -> str | None:
        """A sentence when the background alone (dark current + sky) fills the full well or the ADC
        in every pixel, so no star can be seen; None otherwise."""
        s = self.cfg.sensor
        adu = s.bias_adu - s.black_level_adu + self.background_e / s.gain_e_per_adu
        top = 2**s.bit_depth - 1
        if self.background_e >= s.full_well_e or adu >= top:
            return (
                f"every pixel saturates: the background alone is {self.background_e:.3g} e-/px over the "
                f"{s.exposure_s:g} s exposure (full well {s.full_well_e:g} e-, ADC top {top} ADU); "
                "frames will hold no detectable star. Shorten sensor.exposure_s"
            )
        return None

    def split_of(self, i: int) -> int:
        a, b = self.split_bounds
        return 0 if i < a else (1 if i < b else 2)

    def stream_key(self, i: int) -> tuple[int, int, int | tuple]:
        """(split, index within the split, random-stream key) of global frame ``i``.

        A stream's sample ``i`` (``rng_tag`` set) is keyed by ``i`` alone: its identity does
        not depend on a frame count or split fractions."""
        if self.rng_tag:
            return -1, i, i
        split = self.split_of(i)
        j = i - (0, *self.split_bounds)[split]
        return split, j, (i if self.legacy_streams else frame_key(split, j))

    def vignetting(self, x: np.ndarray, y: np.ndarray, v: float | None = None) -> np.ndarray:
        """Relative illumination at (x, y): 1 - v r^2, r = 1 at the corner (``v``: optics.vignetting)."""
        v = self.cfg.optics.vignetting if v is None else v
        if v == 0:
            return np.ones_like(np.asarray(x, dtype=np.float64))
        return 1.0 - v * self.camera.corner_r2(x, y)

    @property
    def sky_vignetting(self) -> float:
        """The background's corner loss: optics.sky_vignetting, or optics.vignetting when it is None."""
        o = self.cfg.optics
        return o.vignetting if o.sky_vignetting is None else o.sky_vignetting

    # ------------------------------------------------------------------ stages
    def motion_path(self, rng: np.random.Generator) -> tuple[np.ndarray, int, np.ndarray]:
        """Angular-rate vector (rad/s, camera frame), number of sub-steps, sub-times (s)."""
        rate = np.radians(self.levels["motion_blur"])
        t = self.cfg.sensor.exposure_s
        if rate == 0:
            return np.zeros(3), 1, np.zeros(1)
        axis = rng.standard_normal(3)
        omega = rate * axis / np.linalg.norm(axis)
        # worst-case image motion: rotation about an in-plane axis moves the centre by f*dtheta,
        # about the boresight moves the corners by r*dtheta
        path_px = rate * t * max(self.camera.f_px, np.hypot(self.camera.width_px, self.camera.height_px) / 2) * 1.5
        n = max(2, int(np.ceil(path_px / BLUR_STEP_PX)))
        taus = ((np.arange(n) + 0.5) / n - 0.5) * t
        return omega, n, taus

    def visible_stars(self, R: np.ndarray, omega: np.ndarray, taus: np.ndarray) -> dict:
        """Catalog stars whose light can reach the sensor, with sub-exposure positions."""
        cfg = self.cfg
        blur = np.linalg.norm(omega) * cfg.sensor.exposure_s
        margin = (self.psf_radius + 2) / self.camera.f_px
        idx = self.sky.cone(R[:, 2], self._corner + blur + margin)
        v_cam = self.sky.vectors[idx] @ R  # rows: camera-frame directions
        x, y, front = self.camera.project(v_cam)
        table = self.sky.table
        margin_px = self.psf_radius + 1
        keep = front & self.camera.inside(x, y, margin_px + blur * self.camera.f_px * 2)
        idx, v_cam, x, y = idx[keep], v_cam[keep], x[keep], y[keep]
        paths = None
        if len(taus) > 1 and len(idx):
            xs, ys = [], []
            for tau in taus:
                rot = rotation_about(omega, np.linalg.norm(omega) * tau)
                px, py, _ = self.camera.project(v_cam @ rot)  # v_cam(tau) = rot.T @ v_cam
                xs.append(px)
                ys.append(py)
            paths = (np.array(xs).T, np.array(ys).T)
        e = (
            self.photometry.electrons_per_s(table.mag[idx] + self.mag_offset_to_hp, table.bv[idx])
            * cfg.sensor.exposure_s
            * self.star_gain[idx]
        )
        e = e * self.vignetting(x, y)
        return {
            "hip_id": table.hip[idx],
            "x_px": x,
            "y_px": y,
            "mag": table.mag[idx],
            "bv": table.bv[idx],
            "electrons": e,
            "paths": paths,
        }

    def _false_stars(self, rng: np.random.Generator) -> dict:
        n = int(rng.poisson(self.levels["false_stars"]))
        w, h = self.camera.width_px, self.camera.height_px
        x = rng.uniform(-0.5, w - 0.5, n)
        y = rng.uniform(-0.5, h - 0.5, n)
        lim, c = self.detection_limit_mag, self.cfg.corruptions
        if c.false_star_slope > 0:
            mag = corr.false_star_magnitudes(rng.random(n), lim, c.false_star_slope, c.false_star_span_mag)
        else:  # uniform over the span: the draw of frames made before the slope existed, bit for bit
            mag = rng.uniform(lim - c.false_star_span_mag, lim, n).astype(np.float32)
        bv = np.full(n, np.nan, np.float32)
        e = self.photometry.electrons_per_s(mag, None) * self.cfg.sensor.exposure_s * self.vignetting(x, y)
        return {
            "hip_id": np.full(n, -1, np.int64),
            "x_px": x,
            "y_px": y,
            "mag": mag,
            "bv": bv,
            "electrons": e,
            "paths": None,
        }

    def deposit(self, stars: dict, star_e: np.ndarray) -> list:
        """Add every star's stamp (or streak) into ``star_e``; return the boxes touched."""
        o, s = self.cfg.optics, self.cfg.sensor
        flux = np.asarray(stars["electrons"], dtype=np.float64)
        if stars["paths"] is None and o.psf == "gaussian":
            stamps = gaussian_stamps(stars["x_px"], stars["y_px"], flux, o.psf_sigma_px, self.camera.aspect)
        elif stars["paths"] is None:
            stamps = [
                stamp(float(x), float(y), float(f), o.psf, o.psf_sigma_px, o.moffat_beta, self.camera.aspect)
                for x, y, f in zip(stars["x_px"], stars["y_px"], flux)
            ]
        else:
            stamps = [
                streak(xs, ys, float(f), o.psf, o.psf_sigma_px, o.moffat_beta, self.camera.aspect)
                for xs, ys, f in zip(stars["paths"][0], stars["paths"][1], flux)
            ]
        boxes = []
        fw, h = s.full_well_e, star_e.shape[0]
        for (y0, x0, patch), f in zip(stamps, flux):
            box = add_patch(star_e, y0, x0, patch)
            if box is None:
                continue
            if s.blooming and patch.max() > 0.5 * fw:  # may bloom: leave room along the columns
                extra = int(np.ceil(f / fw)) + 2
                box = (max(box[0] - extra, 0), min(box[1] + extra, h), box[2], box[3])
            boxes.append(box)
        return boxes

    def deposit_fixed(self, star_e: np.ndarray) -> list:
        """Add ``sensor.fixed_sources`` (light fixed on the sensor: a round Gaussian of e-/s each, over the
        exposure, in pixels whatever the pixel aspect) into ``star_e``; return the boxes touched."""
        s = self.cfg.sensor
        boxes = []
        for x, y, rate, sigma in s.fixed_sources:
            ((y0, x0, patch),) = gaussian_stamps(
                np.array([x]), np.array([y]), np.array([rate * s.exposure_s]), float(sigma), 1.0
            )
            box = add_patch(star_e, y0, x0, patch)
            if box is not None:
                boxes.append(box)
        return boxes

    # ------------------------------------------------------------------ scene
    def scene(self, i: int) -> "Scene":
        """Everything about frame ``i`` except the pixel noise: attitude, light sources,
        cosmic-ray charge, stray-light direction. A pure function of (config, i); both
        backends (this NumPy renderer and :mod:`skygen.render.torch_frames`) rasterise it."""
        cfg = self.cfg
        seed = cfg.seed
        split, j, key = self.stream_key(i)
        sh = (cfg.camera.height_px, cfg.camera.width_px)
        ra, dec, roll = sample_boresight(cfg.attitude, i, corr.stage_rng(seed, key, "attitude" + self.rng_tag))
        R = attitude_matrix(ra, dec, roll)
        log: dict = {}
        omega, _, taus = self.motion_path(corr.stage_rng(seed, key, "motion_blur" + self.rng_tag))
        if len(taus) > 1:
            log["motion_blur"] = {"rate_deg_s_cam": np.degrees(omega).round(6).tolist(), "substeps": len(taus)}
        stars = self.visible_stars(R, omega, taus)
        if self.levels["false_stars"] > 0:
            fake = self._false_stars(corr.stage_rng(seed, key, "false_stars" + self.rng_tag))
            log["false_stars"] = {"n": len(fake["x_px"])}
            stars = {k: (np.concatenate([stars[k], fake[k]]) if k != "paths" else stars[k]) for k in stars}
            if stars["paths"] is not None and len(fake["x_px"]):
                stars["paths"] = (
                    np.concatenate([stars["paths"][0], np.repeat(fake["x_px"][:, None], len(taus), 1)]),
                    np.concatenate([stars["paths"][1], np.repeat(fake["y_px"][:, None], len(taus), 1)]),
                )
        cosmic, cboxes = [], []
        if self.levels["cosmic_rays"] > 0:
            cosmic, cboxes, n_hits = corr.cosmic_ray_charge(
                sh,
                cfg.camera.pixel_pitch_um,
                cfg.sensor.exposure_s,
                self.levels["cosmic_rays"],
                corr.stage_rng(seed, key, "cosmic_rays" + self.rng_tag),
            )
            log["cosmic_rays"] = {"n_hits": n_hits}
        stray = None
        if self.levels["stray_light"] > 0:
            stray = corr.stray_light_angle(corr.stage_rng(seed, key, "stray_light" + self.rng_tag))
            log["stray_light"] = {"direction_deg": round(float(np.degrees(stray)), 4)}
        return Scene(i, split, ra, dec, roll, R, stars, cosmic, cboxes, stray, log, j, key)

    def background_map(self, scene: "Scene") -> np.ndarray | None:
        """Expected dark + sky (+ stray light) charge per pixel, e-, float32 (H, W); None when uniform."""
        cfg = self.cfg
        if self.levels["stray_light"] == 0 and self.sky_vignetting == 0:
            return None
        sh = (cfg.camera.height_px, cfg.camera.width_px)
        yy, xx = np.mgrid[0 : sh[0], 0 : sh[1]]
        bg_map = (self.dark_e + self.sky_e * self.vignetting(xx, yy, self.sky_vignetting)).astype(np.float32)
        if scene.stray_light_rad is not None:
            bg_map += corr.stray_light_ramp(
                sh, self.levels["stray_light"], cfg.sensor.exposure_s, scene.stray_light_rad
            )
        return bg_map

    # ------------------------------------------------------------------ frame
    def rasterise(self, scene: "Scene") -> tuple[np.ndarray, dict]:
        """The NumPy backend: full-resolution uint16 ADU frame (H, W) of ``scene`` and a log."""
        cfg = self.cfg
        sh = (cfg.camera.height_px, cfg.camera.width_px)
        star_e = np.zeros(sh, np.float32)
        stars, log = self.jittered(scene)
        boxes = self.deposit(stars, star_e)
        boxes += self.deposit_fixed(star_e)
        charge = None
        if scene.cosmic_rays:
            charge = np.zeros(sh, np.float32)
            for y0, x0, p in scene.cosmic_rays:
                add_patch(charge, y0, x0, p)
            boxes += scene.cosmic_boxes
        exposure = Exposure(star_e, charge, boxes, self.background_e, self.background_map(scene))
        full, info = read_out(
            exposure,
            cfg.sensor,
            self.maps,
            corr.stage_rng(cfg.seed, scene.rng_key, "noise" + self.rng_tag),
            self.levels["read_noise"],
        )
        if info["bloomed_columns"]:
            log["blooming"] = {"columns": info["bloomed_columns"]}
        return full, log

    def jittered(self, scene: "Scene") -> tuple[dict, dict]:
        """``scene.stars`` where each star's image is drawn, and a log; its labels stay where the camera puts it.

        * ``camera.bright_shift_px`` (``_x_px``, ``_y_px``) != 0: moved outward from the principal point (and along
          a fixed direction) by :meth:`skygen.instrument.camera.Camera.bright_shift`, with the star's electrons over
          the background's noise (e-) for the detected flux over sigma that the camera's shift is measured in (a
          detection holds most, not all, of its star's light: the renders' shift is a little smaller than the
          frames' where the PSF's wings are wide);
        * ``optics.star_jitter_px`` > 0: then moved by a Gaussian draw per axis, fresh in every frame."""
        j, stars = self.cfg.optics.star_jitter_px, scene.stars
        n = len(stars["x_px"])
        shift = self.camera.has_bright_shift
        if (j <= 0 and not shift) or not n:
            return stars, {}
        log = {}
        d = np.zeros((2, n))
        if shift:
            q = np.log10(np.maximum(np.asarray(stars["electrons"], np.float64), 1e-12) / self.noise_e())
            d += np.array(self.camera.bright_shift(stars["x_px"], stars["y_px"], q))
            log["bright_shift"] = {"max_px": float(np.hypot(d[0], d[1]).max())}
        if j > 0:
            drawn = corr.stage_rng(self.cfg.seed, scene.rng_key, "star_jitter" + self.rng_tag).normal(0.0, j, (2, n))
            d += drawn
            log["star_jitter"] = {"rms_px": float(np.sqrt((drawn**2).mean()))}
        out = {**stars, "x_px": stars["x_px"] + d[0], "y_px": stars["y_px"] + d[1]}
        if stars.get("paths") is not None:  # a streak moves as a whole
            xs, ys = stars["paths"]  # (n_sources, n_substeps)
            out["paths"] = (np.asarray(xs) + d[0][:, None], np.asarray(ys) + d[1][:, None])
        return out, log

    @contextlib.contextmanager
    def with_levels(self, levels: dict | None):
        """Within the block, ``levels`` override the config's corruption severities (scene
        and detection stages; the streams draw them per sample)."""
        saved = self.levels
        if levels:
            self.levels = {**saved, **levels}
        try:
            yield self
        finally:
            self.levels = saved

    def render(self, i: int, levels: dict | None = None) -> Frame:
        """Frame ``i``; ``levels`` overrides corruption severities for this frame only."""
        if levels is not None:
            with self.with_levels(levels):
                return self.render(i)
        scene = self.scene(i)
        full, log = self.rasterise(scene)
        return self.finish(scene, full, log=log)

    def downsample(self, full: np.ndarray) -> np.ndarray:
        """Area-average a full-resolution frame to the stored size (uint16 in, uint16 out)."""
        if self.factor == 1:
            return full
        h, w = full.shape
        return cv2.resize(full, (w // self.factor, h // self.factor), interpolation=cv2.INTER_AREA)

    def finish(
        self, scene: "Scene", full: np.ndarray, image: np.ndarray | None = None, log: dict | None = None
    ) -> Frame:
        """Detect, match and store: the :class:`Frame` of ``scene`` from its full-resolution
        uint16 ADU frame ``full`` (H, W) (and its stored-size ``image``, area-averaged here
        when None). Shared by both backends."""
        cfg = self.cfg
        i = scene.index
        log = {**scene.log, **(log or {})}
        stars = scene.stars
        d = cfg.detection
        det, bg, sigma = detect(full, d.threshold_sigma, d.min_area_px, d.max_detections, d.background_box_px)
        inside = self.camera.inside(stars["x_px"], stars["y_px"])
        true = {k: v[inside] for k, v in stars.items() if k != "paths"}
        # a camera with a bright-star shift draws bright stars outward: matched where the camera puts them
        mx, my = self.camera.unshift(det["x_px"], det["y_px"], det["flux_adu"], sigma)
        sidx = match(mx, my, true["x_px"], true["y_px"], true["electrons"], d.match_radius_px)
        det["star_index"] = sidx
        hip = true["hip_id"][np.maximum(sidx, 0)] if len(true["hip_id"]) else np.full(len(sidx), -1)
        det["hip_id"] = np.where(sidx >= 0, hip, -1).astype(np.int64)  # (a frame may hold no true star)
        det, dlog = corr.apply_detection_corruptions(det, self.levels, cfg.seed, scene.rng_key, stream=self.rng_tag)
        log.update(dlog)
        if image is None:
            image = self.downsample(full)
        q = matrix_to_quaternion(scene.rotation)
        ra, dec = scene.ra_deg, scene.dec_deg
        if self.rng_tag:  # a stream's sample: no dataset identity
            fid = 0
        elif self.legacy_streams:
            fid = legacy_frame_ids(self._config_dict, [i])[0]
        else:
            fid = frame_ids(self._config_dict, [scene.split], [scene.index_in_split], [i])[0]
        return Frame(
            i,
            scene.split,
            ra,
            dec,
            scene.roll_deg,
            radec_to_vec(np.radians(ra), np.radians(dec)),
            q,
            image,
            full if cfg.output.full_res else None,
            self.factor,
            true,
            det,
            bg,
            sigma,
            dict(self.levels),
            log,
            scene.index_in_split,
            int(fid),
        )
