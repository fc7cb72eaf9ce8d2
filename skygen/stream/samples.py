"""Endless, deterministic streams of training samples (no files written).

``SampleStream(cfg, kind)`` makes sample ``i`` for any ``i >= 0``, as a pure function of
(resolved config, seed, kind, i): a stream restarted at any index, split over DataLoader
workers or DDP ranks (:func:`partition`), or asked for one sample or a batch gives the
same samples. Two kinds:

``frames``
    Image at the stored size, detections, true stars, labels. The scenes of a batch come
    from :class:`skygen.render.scenes.SceneBuilder` (counter-based, vectorised; distributed as
    ``Renderer.scene`` draws them); ``frames_renderer`` chooses what rasterises them:

    * ``"binned"`` (default): :class:`skygen.render.binned.BinnedRenderer` draws the stored pixels
      directly, equal in distribution to render-then-downsample (its module docstring has
      the derivation, ``tests/test_stream_binned.py`` the two-sample tests), and the
      detections come from the calibrated :mod:`skygen.stream.emulator` run on the scene's light
      sources, as the ``detections`` stream makes them. ~1.2 ms per sample per core.
    * ``"full"``: the full render of :class:`skygen.render.frame.Renderer` — every sensor pixel,
      area-averaged, detections from the real detector: exactly what ``skygen render``
      writes, without writing it. ~12-17 ms per sample per core.

    A config the binned renderer cannot reproduce exactly (see
    :func:`skygen.render.binned.unsupported_reason`), or one the emulator's calibration was not
    made for, falls back to ``"full"`` with one warning per process and reason.
``detections``
    The fast path: attitude, catalog cone search, projection and photometry (the
    renderer's own camera, catalog index and photometry), false stars, then the
    calibrated :mod:`skygen.stream.emulator` instead of pixels and detector, then the corruption
    registry's detection-level corruptions. Same detection table and labels, no image.
    ~0.05 ms per sample per core in batches (``benchmarks/stream_bench.py``).

Sample identity
    A stream never reproduces a dataset's frames, even with the same seed: frame-stream
    sample ``i`` draws counter-based numbers keyed by (seed, ``"@stream-frames"``) and
    generators tagged ``@stream-frames`` (a dataset's frame ``i`` uses untagged generators),
    and the detection stream counter-based numbers keyed by (seed, ``"@stream-detections"``)
    (:mod:`skygen.hashrng`). ``tests/test_stream.py`` checks both.

Corruption-aware training
    ``level_ranges={"dropout": (0, 0.3), ...}`` draws each sample's severity of the named
    scene/detection corruptions uniformly in its range (from the sample's own random
    numbers), on top of nothing: the range replaces the config's level. Only
    :data:`RANGED` corruptions can vary per sample; the others are fixed by the config
    (and, for ``detections``, by the calibration).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Iterator

import numpy as np
from scipy.spatial import cKDTree

from skygen import hashrng
from skygen.errors import ConfigError
from skygen.instrument import corruptions as corr
from skygen.sky.attitude import attitude_matrices, boresights_from_uniforms, matrices_to_quaternions
from skygen.sky.catalog import radec_to_vec
from skygen.stream import emulator as emu

KINDS = ("frames", "detections")
FRAMES_RENDERERS = ("binned", "full")
RANGED = ("false_stars", "dropout", "centroid_noise", "magnitude_noise")
TAGS = {"frames": "@stream-frames", "detections": "@stream-detections"}
DETECTION_KEYS = ("x_px", "y_px", "flux_adu", "peak_adu", "area_px", "hip_id", "star_index")
STAR_KEYS = ("hip_id", "x_px", "y_px", "mag", "electrons")
# draw ids of the detection stream (per sample); per-source ids live above SOURCE_BASE
_D_ATT = 0  # 0..2
_D_LEVEL = 8  # one per RANGED corruption
_D_NFALSE = 16
_D_IMAGE = 17  # frames stream (binned): the seed of the image's noise
_D_SPUR = 1 << 40
_D_CORR = 1 << 44  # detection-level corruptions: + 4 * source id
_FALSE_ID = 1 << 30  # source ids of false stars: _FALSE_ID + k (catalog rows are below)
_FIXED_ID = 1 << 29  # source ids of sensor.fixed_sources: _FIXED_ID + k (above every catalog row, below false stars)
SOURCE_BASE = 64


def check_kind(kind: str) -> str:
    if kind not in KINDS:
        raise ConfigError(f"stream kind {kind!r} is unknown; choose one of: {', '.join(KINDS)}")
    return kind


def check_ranges(level_ranges: dict | None) -> dict[str, tuple[float, float]]:
    out = {}
    for name, rng in (level_ranges or {}).items():
        corr.get(name)
        if name not in RANGED:
            raise ConfigError(
                f"stream level range for {name!r}: only {', '.join(RANGED)} can vary per sample "
                "(sensor-stage corruptions are fixed by the config)"
            )
        lo, hi = (float(v) for v in rng)
        if not (0 <= lo <= hi) or (name == "dropout" and hi > 1):
            raise ConfigError(
                f"stream level range for {name!r}: {[lo, hi]} must satisfy 0 <= lo <= hi"
                f"{' <= 1' if name == 'dropout' else ''}"
            )
        if hi > 0:
            out[name] = (lo, hi)
    return out


@dataclass
class DetectionBatch:
    """Detection sets of several samples, stored flat like a shard's tables.

    ``index`` (B,) sample indices; ``offsets`` (B+1,): detections of sample j are rows
    ``offsets[j]:offsets[j+1]`` of every array in ``detections`` (brightest first);
    ``stars`` likewise with ``star_offsets``; ``labels`` hold per-sample ``ra_deg``,
    ``dec_deg``, ``roll_deg``, ``unit_vector`` (B, 3), ``quaternion`` (B, 4); ``levels``
    the per-sample severity of every ranged corruption.
    """

    index: np.ndarray
    offsets: np.ndarray
    detections: dict
    star_offsets: np.ndarray
    stars: dict
    labels: dict
    levels: dict

    def __len__(self) -> int:
        return len(self.index)

    def sample(self, j: int) -> dict:
        lo, hi = self.offsets[j], self.offsets[j + 1]
        slo, shi = self.star_offsets[j], self.star_offsets[j + 1]
        return {
            "index": int(self.index[j]),
            **{k: (v[j] if np.ndim(v) == 1 else v[j].copy()) for k, v in self.labels.items()},
            "detections": {k: v[lo:hi] for k, v in self.detections.items()},
            "stars": {k: v[slo:shi] for k, v in self.stars.items()},
            "levels": {k: float(v[j]) for k, v in self.levels.items()},
        }


def partition(start: int, rank: int = 0, world: int = 1) -> Iterator[int]:
    """Sample indices ``start + rank, start + rank + world, ...``: disjoint for distinct ranks."""
    if start < 0:
        raise ConfigError(f"stream start index {start} must be >= 0")
    if not 0 <= rank < world:
        raise ConfigError(f"stream partition {rank} of {world}: need 0 <= rank < world")
    i = start + rank
    while True:
        yield i
        i += world


class SampleStream:
    """Samples of one render configuration (see the module docstring)."""

    def __init__(
        self,
        cfg,
        kind: str = "detections",
        *,
        calibration=None,
        level_ranges: dict | None = None,
        catalog=None,
        frames_renderer: str = "binned",
    ):
        from skygen.render.frame import Renderer

        self.kind = check_kind(kind)
        self.level_ranges = check_ranges(level_ranges)
        if frames_renderer not in FRAMES_RENDERERS:
            raise ConfigError(
                f"frames renderer {frames_renderer!r} is unknown; choose one of: {', '.join(FRAMES_RENDERERS)}"
            )
        self.cfg = cfg
        self.renderer = Renderer(cfg, catalog=catalog, rng_tag=TAGS[kind])
        self.key = hashrng.stream_key(cfg.seed, TAGS[kind])
        self._check_detectable()
        self.model = None
        self.binned = None
        self.frames_renderer = frames_renderer if kind == "frames" else None
        if kind == "frames":
            from skygen.render.scenes import SceneBuilder

            self.scene_builder = SceneBuilder(self.renderer, self.key)
            if frames_renderer == "binned":
                self._setup_binned(calibration)
        if kind == "detections":
            self.model = _load_calibration(calibration, cfg)
            r = self.renderer
            sky = r.sky
            e_star = (
                r.photometry.electrons_per_s(sky.table.mag + r.mag_offset_to_hp, sky.table.bv)
                * cfg.sensor.exposure_s
                * r.star_gain
            )
            # only stars the emulator can detect (p > 0 somewhere on the sensor) take part;
            # fainter ones never change a detection set, and skipping them halves the cost
            visible = self.model.p_detect(e_star) > 0
            self._rows = np.flatnonzero(visible)
            self._e_star = e_star[visible]
            self._vectors = sky.vectors[visible]
            self._hip = sky.table.hip[visible].astype(np.int64)
            self._mag = sky.table.mag[visible].astype(np.float32)
            self._tree = cKDTree(self._vectors)
            self._cone = r._corner + 2.0 / r.camera.f_px

    def _setup_binned(self, calibration) -> None:
        """The binned renderer and the emulator for a ``frames`` stream, or the full renderer
        with one warning when either cannot serve this config exactly."""
        from skygen.errors import SkygenError
        from skygen.render.binned import BinnedRenderer, unsupported_reason

        torch = getattr(self.cfg, "render", None) is not None and self.cfg.render.backend == "torch"
        reason = (
            "render.backend=torch rasterises full frames on its device" if torch else unsupported_reason(self.renderer)
        )
        if reason is None:
            try:
                self.model = _load_calibration(calibration, self.cfg)
            except SkygenError as exc:
                if calibration is not None:  # the user's own file: a mistake to report
                    raise
                reason = f"the shipped detector-emulator calibration does not fit this config ({exc})"
        if reason is not None:
            self.frames_renderer = "full"
            if not torch:
                _warn_once(
                    f"skygen frames stream: rendering full frames and downsampling (~15 ms per sample), "
                    f"not the binned renderer: {reason}"
                )
            return
        self.binned = BinnedRenderer(self.renderer)

    def _check_detectable(self) -> None:
        r = self.renderer
        brightest = float(np.nanmin(r.sky.table.mag)) if len(r.sky) else np.inf
        if not np.isfinite(r.detection_limit_mag) or r.detection_limit_mag < brightest + r.mag_offset_to_hp:
            raise ConfigError(
                f"this config detects no star: its detection limit (Hp {r.detection_limit_mag:.2f}) is "
                f"brighter than the brightest catalog star (Hp {brightest:.2f}); lengthen "
                "sensor.exposure_s, enlarge optics.aperture_mm or lower detection.threshold_sigma"
            )

    # ------------------------------------------------------------------ levels
    def levels_of(self, index: np.ndarray) -> dict[str, np.ndarray]:
        """Per-sample severities of the ranged corruptions (others: the config's)."""
        index = np.asarray(index, np.int64)
        out = {}
        for k, name in enumerate(RANGED):
            if name in self.level_ranges:
                lo, hi = self.level_ranges[name]
                out[name] = lo + (hi - lo) * hashrng.uniform(self.key, index, _D_LEVEL + k)
            else:
                out[name] = np.full(len(index), self.renderer.levels[name])
        return out

    # ------------------------------------------------------------------ frames
    def frame(self, i: int):
        """Sample ``i`` of a ``frames`` stream: a :class:`skygen.render.frame.Frame` (split set to -1)."""
        if i < 0:
            raise ConfigError(f"stream index {i} must be >= 0")
        if self.kind != "frames":
            raise ConfigError("frame() needs a stream of kind 'frames'")
        if self.binned is not None:
            return self.binned_frames([i])[0]
        r = self.renderer
        arrays = self.levels_of(np.array([i]))
        levels = {k: float(v[0]) for k, v in arrays.items()} if self.level_ranges else None
        scene = self.scene_builder.scenes(np.array([i]), arrays)[0]
        with r.with_levels(levels):
            full, log = r.rasterise(scene)
            fr = r.finish(scene, full, log=log)
        fr.split = -1
        return fr

    def frames_batch(self, indices, device=None):
        """Samples ``indices`` of a ``frames`` stream: ``(frames, images)``.

        With the NumPy backend ``images`` is None (each frame holds its stored image). With
        ``render.backend=torch`` the batch is rasterised in one go on ``device`` (default
        ``render.device``): ``images`` is a (B, h, w) float32 tensor of stored-size ADU on
        that device, and the frames' detections come from the real detector on the host.
        The torch path's noise is drawn by a generator seeded from (seed, first index):
        equal in distribution to the NumPy frames, not bit for bit, and it depends on the
        batch composition (the stars, scenes and corruption draws do not).
        """
        idx = [int(i) for i in np.asarray(indices, np.int64).ravel()]
        if self.kind != "frames":
            raise ConfigError("frames_batch() needs a stream of kind 'frames'")
        if idx and min(idx) < 0:
            raise ConfigError(f"stream index {min(idx)} must be >= 0")
        if self.binned is not None:
            return self.binned_frames(idx), None
        if getattr(self.cfg, "render", None) is None or self.cfg.render.backend != "torch":
            return [self.frame(i) for i in idx], None
        import torch

        from skygen.render.torch_frames import TorchRenderer

        if getattr(self, "_torch", None) is None or (device is not None and str(self._torch.device) != str(device)):
            self._torch = TorchRenderer(self.cfg, device, renderer=self.renderer)
        levels = self.levels_of(np.array(idx))
        per = (
            [{k: float(v[j]) for k, v in levels.items()} for j in range(len(idx))]
            if self.level_ranges
            else [None] * len(idx)
        )
        scenes = self.scene_builder.scenes(np.array(idx), levels)
        gen = torch.Generator(device=self._torch.device)
        gen.manual_seed(int(hashrng.bits(self.key, idx[0], 7) >> np.uint64(1)))
        batch = self._torch.rasterise(scenes, gen, full_res=True)
        frames = []
        for b, (sc, lv) in enumerate(zip(scenes, per)):
            with self.renderer.with_levels(lv):
                frames.extend(self._torch.frames(_one(batch, b)))
        for f in frames:
            f.split = -1
        return frames, batch.images

    def binned_frames(self, indices) -> list:
        """Samples ``indices`` of a binned ``frames`` stream: :class:`skygen.render.frame.Frame` objects whose
        image is drawn at the stored size (:class:`skygen.render.binned.BinnedRenderer`) and whose
        detections come from the emulator run on the same scene's sources (inside the
        sensor), then the detector's cap and the detection-level corruptions, as in
        :meth:`batch`. ``background_adu`` and ``noise_adu`` are the nominal values (no
        detector ran). Sample ``i`` is the same alone or in any batch."""
        from skygen.render.frame import Frame
        from skygen.sky.attitude import matrix_to_quaternion

        idx = np.asarray(indices, np.int64).ravel()
        if self.binned is None:
            raise ConfigError("binned_frames() needs a frames stream with the binned renderer")
        if len(idx) and idx.min() < 0:
            raise ConfigError(f"stream index {int(idx.min())} must be >= 0")
        r, cam, key, B = self.renderer, self.renderer.camera, self.key, len(idx)
        levels = self.levels_of(idx)
        per = [{k: float(v[j]) for k, v in levels.items()} for j in range(B)] if self.level_ranges else [None] * B
        scenes, images, trues = self.scene_builder.scenes(idx, levels), [], []
        seeds = hashrng.bits(key, idx, _D_IMAGE)
        for sc, lv, seed in zip(scenes, per, seeds):
            with r.with_levels(lv):
                images.append(self.binned.image(sc, int(seed)))
            st = sc.stars
            inside = cam.inside(st["x_px"], st["y_px"])
            trues.append({k: v[inside] for k, v in st.items() if k != "paths"})
        n_src = np.array([len(t["x_px"]) for t in trues], np.int64)
        fr = np.repeat(np.arange(B), n_src)
        row = np.arange(len(fr)) - np.repeat(np.cumsum(n_src) - n_src, n_src)  # row in the frame's table

        def cat(k):
            return np.concatenate([t[k] for t in trues]) if B else np.zeros(0)

        x, y, e, hip = cat("x_px"), cat("y_px"), cat("electrons").astype(np.float64), cat("hip_id")
        det_fr, det = self._emulated(key, idx, fr, row, row, x, y, e, hip, levels)
        det_off = np.concatenate([[0], np.cumsum(np.bincount(det_fr, minlength=B))])
        s = self.cfg.sensor
        bg_adu = max(s.bias_adu - s.black_level_adu + r.background_e / s.gain_e_per_adu, 0.0)
        noise_adu = r.noise_e() / s.gain_e_per_adu
        frames = []
        for j, (sc, img, true, lv) in enumerate(zip(scenes, images, trues, per)):
            d = {k: v[det_off[j] : det_off[j + 1]] for k, v in det.items()}
            ra, dec = sc.ra_deg, sc.dec_deg
            applied = {**r.levels, **(lv or {})}
            frames.append(
                Frame(
                    int(idx[j]),
                    -1,
                    ra,
                    dec,
                    sc.roll_deg,
                    radec_to_vec(np.radians(ra), np.radians(dec)),
                    matrix_to_quaternion(sc.rotation),
                    img,
                    None,
                    r.factor,
                    true,
                    d,
                    bg_adu,
                    noise_adu,
                    applied,
                    {**sc.log, "renderer": "binned"},
                    sc.index_in_split,
                    0,
                )
            )
        return frames

    # ------------------------------------------------------------------ detections
    def batch(self, indices) -> DetectionBatch:
        """Samples ``indices`` of a ``detections`` stream (any order, any count)."""
        if self.kind != "detections":
            raise ConfigError("batch() needs a stream of kind 'detections'; use frame(i) for 'frames'")
        idx = np.asarray(indices, np.int64).ravel()
        if len(idx) and idx.min() < 0:
            raise ConfigError(f"stream index {int(idx.min())} must be >= 0")
        B = len(idx)
        r, cam, key = self.renderer, self.renderer.camera, self.key
        levels = self.levels_of(idx)
        # attitude (the renderer's distribution, counter-based draws)
        u = hashrng.uniform(key, idx[:, None], _D_ATT + np.arange(3)[None, :])
        ra, dec, roll = boresights_from_uniforms(self.cfg.attitude, idx, u)
        R = attitude_matrices(ra, dec, roll)  # (B, 3, 3)
        bore = R[:, :, 2]
        # catalog stars: cone search, projection, photometry
        chord = 2.0 * np.sin(self._cone / 2.0)
        pairs = cKDTree(bore).sparse_distance_matrix(self._tree, chord + 1e-12, output_type="ndarray")
        fr, star = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
        v_cam = np.einsum("nji,nj->ni", R[fr], self._vectors[star])
        x, y, front = cam.project(v_cam)
        ok = front & cam.inside(x, y)
        star, fr, x, y = star[ok], fr[ok], x[ok], y[ok]
        e = self._e_star[star] * r.vignetting(x, y)
        src_id = self._rows[star]  # the catalog row: a star's draws do not depend on the field
        hip = self._hip[star]
        mag = self._mag[star]
        # false stars (scene): Poisson count per sample, uniform positions, magnitudes as the renderer's
        nf = hashrng.poisson(levels["false_stars"], hashrng.uniform(key, idx, _D_NFALSE))
        if nf.sum():
            ffr = np.repeat(np.arange(B), nf)
            k = np.arange(len(ffr)) - np.repeat(np.cumsum(nf) - nf, nf)
            fid = _FALSE_ID + k
            d = (SOURCE_BASE + fid) * emu.DRAWS_PER_SOURCE
            fx = -0.5 + cam.width_px * hashrng.uniform(key, idx[ffr], d + 3)
            fy = -0.5 + cam.height_px * hashrng.uniform(key, idx[ffr], d + 4)
            c = self.cfg.corruptions
            u = hashrng.uniform(key, idx[ffr], d + 5)
            fmag = corr.false_star_magnitudes(u, r.detection_limit_mag, c.false_star_slope, c.false_star_span_mag)
            fe = r.photometry.electrons_per_s(fmag, None) * self.cfg.sensor.exposure_s * r.vignetting(fx, fy)
            star = np.concatenate([star, np.full(len(ffr), -1)])
            fr, x, y = np.concatenate([fr, ffr]), np.concatenate([x, fx]), np.concatenate([y, fy])
            e, src_id = np.concatenate([e, fe]), np.concatenate([src_id, fid])
            hip, mag = np.concatenate([hip, np.full(len(ffr), -1)]), np.concatenate([mag, fmag])
        # light fixed on the sensor (sensor.fixed_sources): in every sample at its pixels, no catalogue star; the
        # emulated detector takes it as a point source of its electrons (its width is not emulated)
        fixed = self.cfg.sensor.fixed_sources
        if fixed:
            k_fix = len(fixed)
            src = np.asarray(fixed, np.float64)
            ffr = np.repeat(np.arange(B), k_fix)
            fx, fy = np.tile(src[:, 0], B), np.tile(src[:, 1], B)
            fe = np.tile(src[:, 2] * self.cfg.sensor.exposure_s, B)
            ref = float(r.photometry.electrons_per_s(np.array([0.0]), None)[0])  # e-/s of magnitude 0
            fmag = np.tile(-2.5 * np.log10(np.maximum(src[:, 2], 1e-30) / ref), B)
            star = np.concatenate([star, np.full(len(ffr), -1)])
            fr, x, y = np.concatenate([fr, ffr]), np.concatenate([x, fx]), np.concatenate([y, fy])
            e, src_id = np.concatenate([e, fe]), np.concatenate([src_id, _FIXED_ID + np.tile(np.arange(k_fix), B)])
            hip, mag = np.concatenate([hip, np.full(len(ffr), -1)]), np.concatenate([mag, fmag])
        # true-star table per sample (order: frame, then brightness)
        order = np.lexsort((-e, fr))
        fr, x, y, e, src_id, hip, mag = (a[order] for a in (fr, x, y, e, src_id, hip, mag))
        n_src = np.bincount(fr, minlength=B)
        star_offsets = np.concatenate([[0], np.cumsum(n_src)])
        row_in_frame = np.arange(len(fr)) - star_offsets[fr]
        # the emulated detector
        det_fr, det = self._emulated(key, idx, fr, src_id, row_in_frame, x, y, e, hip, levels)
        n_det = np.bincount(det_fr, minlength=B)
        labels = {
            "ra_deg": ra,
            "dec_deg": dec,
            "roll_deg": roll,
            "unit_vector": radec_to_vec(np.radians(ra), np.radians(dec)),
            "quaternion": matrices_to_quaternions(R),
        }
        stars = {"hip_id": hip, "x_px": x, "y_px": y, "mag": mag, "electrons": e.astype(np.float32)}
        return DetectionBatch(idx, np.concatenate([[0], np.cumsum(n_det)]), det, star_offsets, stars, labels, levels)

    def _emulated(self, key, idx, fr, src_id, row, x, y, e, hip, levels):
        """The calibrated emulator's detections of sources (frame ``fr``, stream id ``src_id``, row ``row`` in
        its frame's star table, position, electrons, HIP id) plus spurious ones, capped at the detector's
        brightest ``max_detections`` per frame and corrupted at ``levels``: (frame of each, table)."""
        cam, B = self.cfg.camera, len(idx)
        em = self.model.emulate(key, idx[fr], SOURCE_BASE + src_id, fr, x, y, e)
        sp = self.model.spurious_detections(key, idx, _D_SPUR, cam.width_px, cam.height_px)
        det_fr = np.concatenate([em["frame"], sp["frame"]]).astype(np.int64)
        det = {k: np.concatenate([em[k], sp[k]]) for k in ("x_px", "y_px", "flux_adu", "peak_adu", "area_px")}
        det["star_index"] = np.concatenate([row[em["src"]], np.full(len(sp["frame"]), -1)]).astype(np.int32)
        det["hip_id"] = np.concatenate([hip[em["src"]], np.full(len(sp["frame"]), -1)]).astype(np.int64)
        n_sp = np.bincount(sp["frame"], minlength=B)
        k_sp = np.arange(len(sp["frame"])) - np.repeat(np.cumsum(n_sp) - n_sp, n_sp)
        det_id = np.concatenate([src_id[em["src"]], (1 << 31) + k_sp])
        det_fr, det, det_id = _cap(det_fr, det, det_id, B, self.cfg.detection.max_detections)
        return _detection_corruptions(det_fr, det, det_id, idx, levels, key)

    def sample(self, i: int) -> dict:
        """Sample ``i`` as a dict (labels, ``detections``, ``stars``; ``image`` for frames)."""
        if self.kind == "detections":
            return self.batch([i]).sample(0)
        f = self.frame(i)
        return {
            "index": i,
            "ra_deg": f.ra_deg,
            "dec_deg": f.dec_deg,
            "roll_deg": f.roll_deg,
            "unit_vector": f.unit_vector,
            "quaternion": f.quaternion,
            "image": f.image,
            "detections": {k: f.detections[k] for k in DETECTION_KEYS},
            "stars": {k: f.stars[k] for k in STAR_KEYS},
            "levels": {k: f.applied[k] for k in RANGED},
        }

    def __iter__(self):
        return (self.sample(i) for i in partition(0))


# ---------------------------------------------------------------------------------- helpers
_WARNED: set = set()


def _warn_once(message: str) -> None:
    """One warning per process and message (DataLoader workers forked later inherit the set)."""
    if message not in _WARNED:
        _WARNED.add(message)
        warnings.warn(message, RuntimeWarning, stacklevel=3)


def _load_calibration(calibration, cfg) -> "emu.DetectorModel":
    from skygen.config import config_dict

    if calibration is None:
        calibration = emu.default_calibration_path()
    model = calibration if isinstance(calibration, emu.DetectorModel) else emu.load(calibration)
    emu.check_compatible(
        model,
        config_dict(cfg),
        f"detector calibration {calibration if not isinstance(calibration, emu.DetectorModel) else ''}".strip(),
    )
    return model


def _one(batch, b: int):
    """Frame ``b`` of a torch-renderer batch as a batch of one (for per-frame detection levels)."""
    from dataclasses import replace as _replace

    return _replace(
        batch,
        images=batch.images[b : b + 1],
        full=batch.full[b : b + 1],
        scenes=[batch.scenes[b]],
        logs=[batch.logs[b]],
    )


def _cap(fr, det, det_id, B, cap):
    order = np.lexsort((-det["flux_adu"].astype(np.float64), fr))
    fr, det_id = fr[order], det_id[order]
    det = {k: v[order] for k, v in det.items()}
    start = np.concatenate([[0], np.cumsum(np.bincount(fr, minlength=B))])
    keep = (np.arange(len(fr)) - start[fr]) < cap
    return fr[keep], {k: v[keep] for k, v in det.items()}, det_id[keep]


def _detection_corruptions(fr, det, det_id, idx, levels, key):
    """Dropout, centroid noise and magnitude noise with per-sample severities (the registry's
    :func:`skygen.instrument.corruptions.apply_detection_corruptions`, vectorised with counter draws)."""
    s = idx[fr]
    d = _D_CORR + 4 * det_id
    p = levels["dropout"][fr]
    if (p > 0).any():
        keep = hashrng.uniform(key, s, d) >= p
        fr, det, det_id, s, d = fr[keep], {k: v[keep] for k, v in det.items()}, det_id[keep], s[keep], d[keep]
    c = levels["centroid_noise"][fr]
    if (c > 0).any():
        det["x_px"] = det["x_px"] + c * hashrng.normal(key, s, d + 1)
        det["y_px"] = det["y_px"] + c * hashrng.normal(key, s, d + 2)
    m = levels["magnitude_noise"][fr]
    if (m > 0).any():
        f = (10 ** (-0.4 * m * hashrng.normal(key, s, d + 3))).astype(np.float32)
        det["flux_adu"] = det["flux_adu"] * f
        det["peak_adu"] = det["peak_adu"] * f
        order = np.lexsort((-det["flux_adu"].astype(np.float64), fr))
        fr, det = fr[order], {k: v[order] for k, v in det.items()}
    return fr, det


def frames_as_batch(frames) -> DetectionBatch:
    """Rendered frames (``frames`` stream samples) in the :class:`DetectionBatch` layout."""
    det = {k: np.concatenate([f.detections[k] for f in frames]) for k in DETECTION_KEYS}
    stars = {k: np.concatenate([f.stars[k] for f in frames]) for k in STAR_KEYS}

    def off(rows):
        return np.concatenate([[0], np.cumsum([len(r["x_px"]) for r in rows])]).astype(np.int64)

    labels = {
        k: np.array([getattr(f, k) for f in frames])
        for k in ("ra_deg", "dec_deg", "roll_deg", "unit_vector", "quaternion")
    }
    levels = {k: np.array([f.applied[k] for f in frames]) for k in RANGED}
    return DetectionBatch(
        np.array([f.index for f in frames]),
        off([f.detections for f in frames]),
        det,
        off([f.stars for f in frames]),
        stars,
        labels,
        levels,
    )


def stream_summary(batches) -> dict:
    """Detections per sample, magnitudes of detected catalog stars, spurious share."""
    n_det = np.concatenate([np.diff(b.offsets) for b in batches])
    mags, spur, total = [], 0, 0
    for b in batches:
        sidx = b.detections["star_index"]
        spur += int((sidx < 0).sum())
        total += len(sidx)
        fr = np.repeat(np.arange(len(b)), np.diff(b.offsets))
        ok = sidx >= 0
        mags.append(b.stars["mag"][b.star_offsets[fr[ok]] + sidx[ok]])
    mags = np.concatenate(mags) if mags else np.zeros(0)

    def q(a, p):
        return float(np.percentile(a, p)) if len(a) else float("nan")

    return {
        "samples": int(len(n_det)),
        "detections_per_sample": {
            "mean": float(n_det.mean()),
            "p10": q(n_det, 10),
            "median": q(n_det, 50),
            "p90": q(n_det, 90),
            "min": int(n_det.min()),
            "max": int(n_det.max()),
        },
        "fewer_than_3": float((n_det < 3).mean()),
        "detected_mag": {"p10": q(mags, 10), "median": q(mags, 50), "p90": q(mags, 90)},
        "spurious_share": spur / max(total, 1),
    }


__all__ = ["KINDS", "SampleStream", "DetectionBatch", "partition", "stream_summary"]
