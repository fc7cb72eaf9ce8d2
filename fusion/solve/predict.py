"""``fusion predict``: a user's own frames -> detections, the model's regions, optionally a full attitude.

    fusion predict FRAME... --checkpoint CK [--solve] [--overlay DIR] [--top-k 3] [--out FILE.jsonl]
                            [--search fine|coarse] [--search-k N] [--focal-tol 0.02]
    fusion predict FRAME... --camera configs/cameras/NAME.yaml --solve      # no model: tetra3rs, then whole sky
    fusion predict FRAME... --camera C.yaml --solve --solver whole-sky       # any registered solver
    fusion predict FRAME... --fov-range 10 30 --solve                        # unknown field: searched (tetra3rs)

Without a checkpoint nothing about storage matters: a camera file of any sensor size is taken as it is
(``output.image_size_px`` is set to the sensor width). ``--fov-range LO HI`` (no checkpoint): the
horizontal field is not known, only bounded; tetra3rs lost-in-space searches it (a multi-scale
database) and every solution reports the field it found (``fov_deg``); the sensor size comes from
``--camera`` (whose focal length is then not used) or, without it, from the first frame.

Frames: PNG, TIFF (8 or 16 bit), BMP, JPEG, FITS (the first HDU with 2-D data), ``.npy`` (2-D array) files,
a folder of such files (sorted by name), or a skygen dataset folder (its stored detections and
images); ``--max-frames N`` takes the first N of each folder. Each frame must be one
full-resolution sensor read-out of the checkpoint's (or ``--camera``'s) camera, rows = height,
in ADU or any linear unit. Non-finite pixels (NaN, ±inf) are bad pixels: replaced by the median
of the finite ones before detection and counted in the record as ``bad_pixels``.

Per frame:

1. detection: skygen's detector (:func:`skygen.instrument.detect.detect`) with the camera's detection
   settings (threshold in background sigma, minimum area), positions in full-resolution
   pixels (skygen convention: (0, 0) is the centre of the top-left pixel); ``--background-box
   64`` estimates the background per 64 x 64 px box instead of once per frame (ground frames
   with sky glow: on the 8 real Blackfly frames 21-64 detections instead of 4-41);
   ``--detector tetra3rs`` uses tetra3rs's extractor instead (no checkpoint only);
2. with ``--checkpoint``: the model's preprocessing (area-average to the stored size, the
   checkpoint's log stretch and coordinate encoding, :func:`fusion.solvers.priors.model_inputs`)
   and its region probabilities; the top-k regions with probability and the RA/Dec of each
   region's centroid;
3. with ``--solve``: the coarse-to-fine solver (:mod:`fusion.solvers.coarse_fine`) with the
   model's regions as prior — by default its fine regions (``--search fine``, the 20 most
   probable, ``--search-k``), and a focal length known to ±2 % (``--focal-tol``; fitted and
   reported as ``focal_factor`` / ``fov_deg``), and the rest of the sky where those regions refuse
   (``learned+fine>whole-sky``: one search, one false-match budget; at four detections the whole sky first and
   those regions where it refuses, ``fine.SKY_FIRST_FROM``; from five tetra3rs and then the whole sky at once,
   ``fine.WHOLE_SKY_FROM``); ``--lis-first`` tries tetra3rs
   lost-in-space first and the learned path only where it refuses; without a checkpoint, tetra3rs lost-in-space and the
   whole-sky fine stage where it refuses (``tetra3rs>whole-sky``); ``--solver NAME`` picks any registered
   solver (:mod:`fusion.solve.registry`). A full attitude
   (quaternion, RA/Dec/roll in skygen's conventions, matched catalog stars, residual,
   confidence, ``false_match_probability`` (the fine stage's with the catalogue's clustering weighed in;
   ``false_match_probability_mean_density``, the value its bars are on), ``covariance_arcsec`` [x, y, roll] 1 sigma
   and ``covariance_matrix_arcsec2``: :mod:`fusion.solve.base`) with ``"status": "solved"``, or an
   explicit refusal (``"status": "refused"``) with its reason and a ``refusal_status`` code
   (``too_few_stars``, ``no_pattern``, ``budget_exhausted``, ``ambiguous``, ``weak_evidence``,
   ``not_verified``, ...: :data:`fusion.solve.base.REFUSAL_STATUSES`; the fine stage's also ``hypotheses`` and
   ``work``, the units of its budget spent).

``--track [DEG]`` (with ``--solve``): the frames are a sequence (in the order given, folders by name); each
frame's solved attitude is the hint of the next, with a 1-sigma error of DEG degrees (default 1: how far the
camera may turn between frames). The solver then searches only the attitudes within 3 DEG of the hint
(``solve(..., hint=, hint_sigma_deg=)``: three stars can be enough), and where that is refused, lost in
space as without ``--track``; the record says ``"tracking": {"hint_sigma_deg", "hint_zero_point", "tracked",
"refused"}``. The photometric zero point of the last solved frames (the median of their solutions'
``zero_point``, catalogue magnitude minus -2.5 log10 flux) goes with the hint: the tracker then holds each
identification's stars to the brightness the camera gives them. A refused or failed frame leaves the next
without a hint.

``--mask-fixed-sources``: the light a fitted camera knows is fixed on its sensor (``sensor.fixed_sources``, a glow
``skygen fit-camera`` found) loses its detections at detection, before the model, the solver or anything taking the
brightest N reads them (:meth:`Predictor.detect`); the record says ``"fixed_sources_removed"``.

``--defects FILE`` (with ``--solve``): a sensor defect map (``fusion defects``, :mod:`fusion.solve.defects`);
detections at its pixels (static hot pixels) are dropped before the model and the solver read them; the record
keeps every detection, says ``"defects_removed"``, and the solution's matched rows index the record's
detections.

A frame with no detection (blank, capped, overexposed, or a threshold too high for its
exposure) gives no region probabilities and no attitude: its record says ``"status":
"no_detections"`` with the reason (and, with ``--solve``, a refused solution saying so),
one line goes to stderr, and like a refused solve it does not make the exit status 1.
Every other record has ``"status": "ok"``.

Data rendered with other frame settings than the checkpoint's training data (a skygen
dataset folder given as frames, or ``--dataset``; the keys of
:func:`fusion.model.checkpoint.frame_config_differences`) gets one WARNING line naming the
keys (training -> data) and its records list them under ``config_differences``.

Output: one JSON object per frame and line (stdout, or ``--out``); ``--overlay DIR`` writes
``DIR/<frame>.png`` with the detections drawn (green: matched to a catalog star by the
solution, orange: unmatched, numbered brightest first). A frame that cannot be used
(unreadable, empty, colour, wrong size) gives one ``{"frame": ..., "error": ...}`` line and one
line on stderr; the batch continues and the exit status is 1 if any frame failed.

The checkpoint carries everything (``render_config``: camera, sensor, detector, stored
size; centroids; preprocessing), so predict works from any folder. A checkpoint written
before checkpoints carried it is refused with one line, unless ``--dataset DIR`` names its
training dataset.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from skygen.config import build_config as build_render_config
from skygen.instrument.camera import Camera
from skygen.instrument.detect import detect
from skygen.runtime import atomic_path, atomic_write_bytes, dumps_json
from skygen.sky.attitude import quaternion_to_matrix

from ..errors import ConfigError
from ..model.checkpoint import differences_warning, load_checkpoint
from ..model.inputs import downsample
from .base import Detections, Refusal, Solution
from .frames import FrameError, iter_inputs, mask_bad_pixels

#: a detection whose brightest pixel (within 1 px of its centroid) reaches this share of the top of the frame's range
#: is saturated: its flux is a lower bound (tracking's photometry, fusion.solve.match.track_hypotheses). Clipped, not
#: merely bright: at 0.8 (fit-camera's cut for its zero point) nearly every bright star of an 8-bit camera counts,
#: and their fluxes still told stars apart (results/real-frames/saturated)
SATURATED_SHARE = 0.98


def frame_top(img: np.ndarray) -> float:
    """The top of a frame's range: the least 2^b - 1 (b = 8 to 16) at or above its largest value (the largest value
    itself beyond 16 bits). Read from the data, not the file type: 12-bit data in a 16-bit file scaled by 16 gets
    65535, unscaled 4095, an 8-bit JPEG 255."""
    top = float(np.max(img)) if img.size else 0.0
    for bits in range(8, 17):
        if top <= 2**bits - 1:
            return float(2**bits - 1)
    return top


def saturated_rows(img: np.ndarray, x_px, y_px) -> np.ndarray:
    """Which detections at (``x_px``, ``y_px``) are saturated: the 3 x 3 px around the centroid's pixel reach
    ``SATURATED_SHARE`` of :func:`frame_top` (bool per detection)."""
    x = np.clip(np.rint(np.asarray(x_px, np.float64)).astype(np.int64), 0, img.shape[1] - 1)
    y = np.clip(np.rint(np.asarray(y_px, np.float64)).astype(np.int64), 0, img.shape[0] - 1)
    level = SATURATED_SHARE * frame_top(img)
    out = np.zeros(len(x), bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            yy, xx = np.clip(y + dy, 0, img.shape[0] - 1), np.clip(x + dx, 0, img.shape[1] - 1)
            out |= img[yy, xx] >= level
    return out


TRACK_ZERO_POINTS = 10  # --track: the hint's zero point is the median of this many last solved frames'


class Predictor:
    """Detector + (optional) region prior + (optional) solver for one camera."""

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        *,
        camera: str | Path | None = None,
        dataset: str | Path | None = None,
        solve: bool = False,
        top_k: int = 3,
        detector: str = "skygen",
        search: str = "fine",
        search_k: int | None = None,
        focal_tol: float = 0.02,
        background_box: int | None = None,
        lis_first: bool = False,
        solver: str | None = None,
        log=None,
        fov_range: tuple[float, float] | None = None,
        max_hypotheses: int | None = None,
        mask_fixed_sources: bool = False,
    ):
        from .priors import load_prior
        from .registry import build_solver, check_search_options

        if isinstance(top_k, bool) or not isinstance(top_k, int) or top_k < 1:
            raise ConfigError(f"--top-k {top_k}: the number of regions reported must be at least 1")
        if (checkpoint is None) == (camera is None):
            raise ConfigError(
                "give --checkpoint CK (a trained model: its own camera) or --camera FILE.yaml "
                "(prior-free solvers only), exactly one of them"
            )
        if fov_range is not None:
            if checkpoint is not None:
                raise ConfigError(
                    "--fov-range: a checkpoint's camera has a known field; give --fov-range with --camera or alone"
                )
            lo, hi = fov_range
            if not 0 < lo < hi < 120:
                raise ConfigError(f"--fov-range {lo:g} {hi:g}: give 0 < LO < HI < 120 degrees (horizontal field)")
            if solver not in (None, "tetra3rs"):
                raise ConfigError(
                    f"--fov-range searches the field with tetra3rs lost-in-space; --solver {solver} "
                    "needs a known focal length (give --camera without --fov-range)"
                )
        render_config = None
        if dataset is not None:
            from skygen.datasets.shards import open_dataset

            with open_dataset(dataset) as ds:
                render_config = dict(ds.config)
        if camera is not None:
            render_config = camera_render_config(camera)
        self.checkpoint = load_checkpoint(checkpoint) if checkpoint is not None else None
        self.prior = load_prior(self.checkpoint, render_config) if self.checkpoint is not None else None
        self.config_differences = {}  # --dataset's frame settings unlike the checkpoint's training data
        if (
            dataset is not None
            and render_config is not None
            and self.checkpoint is not None
            and self.checkpoint.render_config is not None
        ):
            self.config_differences = self.check_frame_settings(render_config, f"--dataset {dataset}", log)
        if self.prior is not None:
            render_config = self.prior.render_config
            k = len(getattr(self.prior, "coarse_centroids", self.prior.centroids))
            if top_k > k and log is not None:
                log(f"--top-k {top_k}: the model has {k} regions; reporting all {k}")
        self.cfg = build_render_config(render_config)
        self.camera = Camera.from_config(self.cfg.camera)
        self.factor = self.cfg.camera.width_px // self.cfg.output.image_size_px
        self.top_k, self.detector = top_k, detector
        if detector == "tetra3rs" and self.prior is not None:
            raise ConfigError(
                "--detector tetra3rs: the model was trained on skygen's detector; use it only without --checkpoint"
            )
        if background_box is None:  # the camera's own setting (a fitted camera may use a local background)
            background_box = self.cfg.detection.background_box_px
        if background_box and background_box < 8:
            raise ConfigError(
                f"--background-box {background_box}: 0 (one background per frame) or a box of at least 8 px, e.g. 64"
            )
        self.background_box = int(background_box)
        # light fixed on the sensor that the camera file knows (a glow skygen fit-camera found): its detections are no
        # stars, dropped at detection as a tracker drops its calibrated defects
        self.fixed_mask, self.fixed_sources_removed = None, 0
        if mask_fixed_sources:
            from .defects import DefectMap

            sources = self.cfg.sensor.fixed_sources
            if not sources:
                raise ConfigError(
                    "--mask-fixed-sources: the camera has no sensor.fixed_sources (skygen fit-camera writes them where "
                    "it finds light fixed on the sensor; without them there is nothing to drop)"
                )
            self.fixed_mask = DefectMap.from_fixed_sources(sources)
        check_search_options(focal_tol, search_k, max_hypotheses=max_hypotheses)
        self.solver, self.search_level = None, None
        if solve:
            # the default chains: with a model, its prior and the fine stage; without one, the best prior-free
            # chain (tetra3rs lost-in-space, and the whole-sky fine stage where it refuses)
            # (with a model, the rest of the sky is searched where its regions refuse: noisy magnitudes mislead a
            # prior whose reference is the brightest star, and the whole-sky search is what then still solves)
            name = solver or (
                "tetra3rs>whole-sky"
                if self.prior is None
                else "tetra3rs>learned+fine>whole-sky"
                if lis_first
                else "learned+fine>whole-sky"
            )
            if self.prior is not None:
                self.search_level = self.prior.at_level(search).level
            context = None
            if fov_range is not None:
                from .registry import make_context
                from .tetra import Tetra3Solver

                name = "tetra3rs"
                context = make_context(
                    self.camera,
                    tetra=Tetra3Solver(self.camera, log=log, fov_range=fov_range),
                    focal_tol=focal_tol,
                    search_k=search_k,
                    max_hypotheses=max_hypotheses,
                )
            self.solver = build_solver(
                name,
                self.camera,
                prior=self.prior,
                search=search,
                search_k=search_k,
                focal_tol=focal_tol,
                log=log,
                context=context,
                max_hypotheses=max_hypotheses,
            )

    def check_frame_settings(self, config: dict, what: str, warn=None) -> dict:
        """The frame settings of data rendered with ``config`` that differ from the checkpoint's training data
        (:meth:`fusion.model.checkpoint.Checkpoint.config_differences`; ``{}`` without a checkpoint), with one
        WARNING line on ``warn`` when there are any."""
        if self.checkpoint is None:
            return {}
        diffs = self.checkpoint.config_differences(config)
        if diffs and warn is not None:
            warn(differences_warning(what, diffs, self.checkpoint.source))
        return diffs

    def check_shape(self, img: np.ndarray, source: str) -> None:
        want = (self.cfg.camera.height_px, self.cfg.camera.width_px)
        if img.shape != want:
            raise FrameError(
                f"{source}: frame is {img.shape[1]} x {img.shape[0]} px but the camera is "
                f"{want[1]} x {want[0]} px (width x height); give full-resolution frames of that camera"
            )

    def detect(self, img: np.ndarray) -> tuple[Detections, float, float]:
        d = self.cfg.detection
        # with a mask, the detector keeps more than max_detections so that the glow's fragments take no star's place
        keep = d.max_detections if self.fixed_mask is None else 2 * d.max_detections
        if self.detector == "tetra3rs":
            # tetra3rs's extractor (local background, matched filter): centroids relative to the image centre;
            # skygen pixel = centroid + (size - 1) / 2 (checked against rendered true positions to 0.004 px)
            import tetra3rs

            res = tetra3rs.extract_centroids(
                np.ascontiguousarray(img, np.float32),
                sigma_threshold=d.threshold_sigma,
                min_pixels=d.min_area_px,
                max_centroids=keep,
            )
            c = res.centroids
            h, w = img.shape
            table = {
                "x_px": np.array([p.x for p in c]) + (w - 1) / 2,
                "y_px": np.array([p.y for p in c]) + (h - 1) / 2,
                "flux_adu": np.array([p.brightness or 0.0 for p in c]),
            }
            table["saturated"] = saturated_rows(img, table["x_px"], table["y_px"])
            sigma = float(res.background_sigma)
            return (
                self._unshifted(self._unmasked(Detections.from_table(table)), sigma),
                float(res.background_mean),
                sigma,
            )
        det, bg, sigma = detect(img, d.threshold_sigma, d.min_area_px, keep, self.background_box)
        det["saturated"] = saturated_rows(img, det["x_px"], det["y_px"])
        return self._unshifted(self._unmasked(Detections.from_table(det)), sigma), bg, sigma

    def _unshifted(self, det: Detections, sigma: float) -> Detections:
        """``det`` moved back by the camera's brightness-dependent centroid shift (``camera.bright_shift_px``,
        ``_x_px``, ``_y_px``: :meth:`skygen.instrument.camera.Camera.bright_shift`), to where the camera puts their
        stars: what a solver matches against the catalogue. Unchanged where the camera has none."""
        if not self.camera.has_bright_shift or not len(det):
            return det
        x, y = self.camera.unshift(det.x_px, det.y_px, det.flux_adu, sigma)
        return dataclasses.replace(det, x_px=x, y_px=y)  # everything else the detections carry, as it was

    def _unmasked(self, det: Detections) -> Detections:
        """``det`` without the detections of the camera's fixed sources (``mask_fixed_sources``), at most
        ``detection.max_detections`` of them, brightest first."""
        if self.fixed_mask is None:
            return det
        det, self.fixed_sources_removed = self.fixed_mask.remove(det)
        n = self.cfg.detection.max_detections
        return det.brightest(n) if len(det) > n else det

    def no_detections_reason(self, extra: dict) -> str:
        """Why a frame without detections gets no prediction, with what to check."""
        d = self.cfg.detection
        if "noise_adu" in extra:
            seen = (
                f"no star above {d.threshold_sigma:g} sigma in at least {d.min_area_px} px (background "
                f"{extra['background_adu']:.1f} ADU, noise {extra['noise_adu']:.2f} ADU)"
            )
        else:
            seen = "its stored detection table is empty"
        return (
            f"no detections: {seen}, so nothing to predict from; a blank, capped or saturated frame, or an "
            "exposure too short for the camera's detection settings (--background-box 64 for sky glow)"
        )

    def stored_image(self, img: np.ndarray) -> np.ndarray:
        """The frame at the model's stored size (what the image branch sees)."""
        return downsample(img, self.factor)

    def run(
        self,
        source: str,
        det: Detections,
        stored: np.ndarray | None,
        extra: dict,
        hint: np.ndarray | None = None,
        hint_sigma_deg: float = 1.0,
        hint_zero_point: float | None = None,
        defects=None,
    ) -> dict:
        rec = {
            "frame": source,
            "status": "ok",
            **extra,
            "n_detections": len(det),
            "detections": [
                [round(float(x), 3), round(float(y), 3), round(float(f), 1)]
                for x, y, f in zip(det.x_px, det.y_px, det.flux_adu)
            ],
        }
        if not len(det):  # nothing to read: no region probabilities (they would be the model's bias)
            rec.update({"status": "no_detections", "reason": self.no_detections_reason(extra)})
            if self.solver is not None:
                rec["solution"] = Refusal(
                    "no detections in the frame", self.solver.name, status="too_few_stars"
                ).to_dict()
            return rec
        solve_det, rows = det, None  # rows: the record's row of each detection the prior and the solver get
        if defects is not None:  # the sensor's known defect pixels are no stars (the record keeps every detection)
            rows = np.flatnonzero(~defects.flags(det))
            solve_det = det.take(rows)
            rec["defects_removed"] = len(det) - len(rows)
            if not len(rows):
                if self.solver is not None:
                    rec["solution"] = Refusal(
                        "every detection is at a known defect pixel", self.solver.name, status="too_few_stars"
                    ).to_dict()
                return rec
        probs = search_probs = None
        if self.prior is not None:
            t0 = time.perf_counter()
            probs, fine = self.prior.both(solve_det, stored)
            search_probs = fine if self.solver is not None and self.search_level == "fine" else probs
            rec["model_ms"] = (time.perf_counter() - t0) * 1e3
            order = np.argsort(-probs, kind="stable")[: self.top_k]
            c = self.prior.centroids
            rec["regions"] = [
                {
                    "rank": r + 1,
                    "region": int(k),
                    "probability": float(probs[k]),
                    "ra_deg": float(np.degrees(np.arctan2(c[k, 1], c[k, 0])) % 360),
                    "dec_deg": float(np.degrees(np.arcsin(np.clip(c[k, 2], -1, 1)))),
                }
                for r, k in enumerate(order)
            ]
        if self.solver is not None:
            kw = {"probabilities": search_probs} if search_probs is not None else {}
            res = None
            if hint is not None:  # tracking: the previous frame's attitude; lost in space where it fails
                res = self.solver.solve(
                    solve_det,
                    self.camera,
                    stored,
                    hint=hint,
                    hint_sigma_deg=hint_sigma_deg,
                    hint_zero_point=hint_zero_point,
                )
                rec["tracking"] = {
                    "hint_sigma_deg": hint_sigma_deg,
                    "hint_zero_point": hint_zero_point,
                    "tracked": isinstance(res, Solution),
                }
            if not isinstance(res, Solution):
                lost = res
                res = self.solver.solve(solve_det, self.camera, stored, **kw)
                if lost is not None:  # the time spent tracking counts too
                    rec["tracking"]["refused"] = lost.to_dict()
                    res = dataclasses.replace(res, time_ms=res.time_ms + lost.time_ms)
            if rows is not None and isinstance(res, Solution) and len(res.matched):
                # a solution's matched rows index the detections the solver got: back to the record's rows
                matched = res.matched.copy()
                matched[:, 0] = rows[matched[:, 0]]
                res = dataclasses.replace(res, matched=matched)
            rec["solution"] = res.to_dict()
        return rec


def camera_render_config(camera) -> dict:
    """The render config of a camera file (or of a dict of config data) for prediction without a model: storage
    does not matter, so ``output.image_size_px`` is the sensor width (any sensor size is taken)."""
    from skygen import configlib
    from skygen.config import check_camera_section, config_dict

    data = dict(camera) if isinstance(camera, dict) else configlib.read_yaml(camera)
    data = data if isinstance(data, dict) else {}
    width = (data.get("camera") or {}).get("width_px") if isinstance(data.get("camera"), dict) else None
    if not isinstance(camera, dict):
        if "camera" not in data:  # a camera file that describes no camera would mean the default 20 deg one
            raise ConfigError(
                f"camera file {camera}: no camera section; give camera: with width_px, height_px, "
                "pixel_pitch_um and focal_length_mm (or fov_deg), e.g. configs/cameras/default-20deg.yaml"
            )
        check_camera_section(data, f"camera file {camera}")
    if isinstance(width, int) and width > 0:
        data = {**data, "output": {**(data.get("output") or {}), "image_size_px": width}}
    return config_dict(build_render_config(data))


def overlay(path: Path, img: np.ndarray, det: Detections, rec: dict) -> None:
    """The frame (log-stretched to 8 bit) with numbered detections; matched ones green."""
    import cv2

    lo, hi = np.percentile(img, 1), max(float(np.percentile(img, 99.9)), float(np.percentile(img, 1)) + 1)
    x = np.log1p(np.clip(img - lo, 0, None)) / np.log1p(hi - lo)
    rgb = cv2.cvtColor((np.clip(x, 0, 1) * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    sol = rec.get("solution") or {}
    matched = {int(r[0]) for r in sol.get("matched", [])}
    scale = img.shape[1] / rgb.shape[1]
    for i, (xx, yy) in enumerate(zip(det.x_px, det.y_px)):
        colour = (60, 220, 60) if i in matched else (0, 160, 255)
        c = (int(round(xx / scale)), int(round(yy / scale)))
        cv2.circle(rgb, c, 9, colour, 1, cv2.LINE_AA)
        cv2.putText(rgb, str(i + 1), (c[0] + 10, c[1] - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1, cv2.LINE_AA)
    if sol.get("status") == "solved":
        text = (
            f"RA {sol['ra_deg']:.3f} Dec {sol['dec_deg']:.3f} roll {sol['roll_deg']:.2f}  "
            f'{sol["n_matched"]} matched, {sol["residual_arcsec"]:.1f}" rms'
        )
    elif sol:
        text = f"refused: {sol['reason']}"
    else:
        text = f"{len(det)} detections"
    if rec.get("regions"):
        r0 = rec["regions"][0]
        text += f"  | top region {r0['region']} p={r0['probability']:.2f}"
    cv2.putText(rgb, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    ok, buf = cv2.imencode(".png", rgb)
    atomic_write_bytes(path, buf.tobytes())


def predict(
    frames: list[str],
    checkpoint=None,
    *,
    camera=None,
    dataset=None,
    solve=False,
    top_k=3,
    detector="skygen",
    overlay_dir=None,
    out=None,
    max_frames=None,
    log=print,
    err=None,
    search="fine",
    search_k=None,
    focal_tol=0.02,
    background_box=None,
    lis_first=False,
    solver=None,
    fov_range=None,
    channel="luminance",
    track_deg=None,
    max_hypotheses=None,
    defects=None,
    mask_fixed_sources=False,
) -> tuple[list[dict], int]:
    """Run the pipeline on every frame; returns (records, number of failed frames). Colour frame files
    become one plane (``channel``: luminance, r, g, b or sum). ``track_deg`` (with ``solve``): the frames are
    a sequence; each solved attitude is the next frame's hint with that 1-sigma error (degrees), and the
    median zero point of the last :data:`TRACK_ZERO_POINTS` solved frames its ``hint_zero_point``. ``defects``
    (with ``solve``): a defect-map JSON file (:mod:`fusion.solve.defects`, written by ``fusion defects``) whose
    detections are dropped before solving. ``mask_fixed_sources``: the camera file's ``sensor.fixed_sources`` (light
    fixed on the sensor) drop their detections at detection (:meth:`Predictor.detect`)."""
    err = err or (lambda m: print(m, file=sys.stderr))
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"--max-frames {max_frames}: give at least 1 (or leave it out for every frame)")
    if fov_range is not None and not 0 < fov_range[0] < fov_range[1] < 120:
        raise ConfigError(
            f"--fov-range {fov_range[0]:g} {fov_range[1]:g}: give 0 < LO < HI < 120 degrees (horizontal field)"
        )
    if track_deg is not None:
        if not solve:
            raise ConfigError("--track: the previous frame's attitude is the hint of the next solve; add --solve")
        if fov_range is not None:
            raise ConfigError("--track: tracking needs the camera's field; give --camera (not --fov-range)")
        if not 0 < track_deg <= 20:
            raise ConfigError(f"--track {track_deg:g}: the hint's 1-sigma error in (0, 20] degrees, e.g. 1")
    if defects is not None:
        if not solve:
            raise ConfigError("--defects: the defect pixels are dropped before solving; add --solve")
        from .defects import DefectMap

        defects = DefectMap.from_json(defects)
    if fov_range is not None and camera is None and checkpoint is None:
        camera = _camera_of_first_frame(frames, fov_range, channel)
    pred = Predictor(
        checkpoint,
        camera=camera,
        dataset=dataset,
        solve=solve,
        top_k=top_k,
        detector=detector,
        search=search,
        search_k=search_k,
        focal_tol=focal_tol,
        background_box=background_box,
        lis_first=lis_first,
        solver=solver,
        log=lambda m: err(m),
        fov_range=fov_range,
        mask_fixed_sources=mask_fixed_sources,
        max_hypotheses=max_hypotheses,
    )
    if overlay_dir:
        Path(overlay_dir).mkdir(parents=True, exist_ok=True)
    differences = _dataset_differences(frames, pred, err)
    records, failed = [], 0
    previous: np.ndarray | None = None  # tracking: the camera -> ICRS matrix of the frame before, if solved
    zero_points: collections.deque = collections.deque(maxlen=TRACK_ZERO_POINTS)  # of the last solved frames
    with contextlib.ExitStack() as stack:
        # --out is written beside its final name and renamed when every frame is done: an interrupted or
        # failed run (a full disk) leaves no file with fewer lines than frames that looks whole
        sink = stack.enter_context(open(stack.enter_context(atomic_path(out)), "w")) if out else None
        for source, img, table, stored, error in iter_inputs(frames, max_frames, channel):
            t0 = time.perf_counter()
            try:
                if error:
                    raise FrameError(error)
                if img is not None:
                    pred.check_shape(img, source)
                    img, bad = mask_bad_pixels(img, source)
                    det, bg, sigma = pred.detect(img)
                    stored = pred.stored_image(img)
                    extra = {
                        "shape": [int(img.shape[0]), int(img.shape[1])],
                        "background_adu": bg,
                        "noise_adu": sigma,
                        "bad_pixels": bad,
                    }
                else:
                    det = pred._unmasked(Detections.from_table(table))
                    if "noise_adu" in table:  # renders of a camera with a bright-star shift draw it: taken back off
                        det = pred._unshifted(det, table["noise_adu"])
                    extra = {"detections_from": "dataset"}
                if pred.fixed_mask is not None:  # the camera's own glow, dropped at detection
                    extra["fixed_sources_removed"] = pred.fixed_sources_removed
                hint = previous if track_deg is not None else None
                zp = float(np.median(zero_points)) if hint is not None and zero_points else None
                rec = pred.run(source, det, stored, extra, hint, track_deg or 1.0, zp, defects)
                sol = rec.get("solution", {})
                previous = quaternion_to_matrix(sol["quaternion_wxyz"]) if sol.get("status") == "solved" else None
                if previous is not None and sol.get("zero_point") is not None:
                    zero_points.append(float(sol["zero_point"]))
                rec["total_ms"] = (time.perf_counter() - t0) * 1e3
                diffs = {
                    **pred.config_differences,
                    **(differences.get(source.rsplit("#", 1)[0], {}) if img is None else {}),
                }
                if diffs:
                    rec["config_differences"] = diffs
                if rec["status"] == "no_detections":
                    err(f"fusion predict: {source}: {rec['reason']}")
                if overlay_dir:
                    name = Path(source.replace("#", "_")).name
                    overlay(Path(overlay_dir) / f"{Path(name).stem}.png", img if img is not None else stored, det, rec)
            except FrameError as exc:
                failed += 1
                previous = None
                rec = {"frame": source, "error": str(exc)}
                err(f"fusion predict: {exc}")
            records.append(rec)
            line = dumps_json(rec)
            (sink.write(line + "\n") if sink else log(line))
    return records, failed


def _dataset_differences(frames: list[str], pred: Predictor, warn) -> dict[str, dict]:
    """Per skygen dataset folder among ``frames``: its frame settings unlike the checkpoint's training data
    (one WARNING line each on ``warn``); only those that differ are listed."""
    out: dict[str, dict] = {}
    if pred.checkpoint is None:
        return out
    from skygen.datasets.shards import open_dataset

    for p in frames:
        path = Path(p)
        if path.is_dir() and (path / "manifest.json").exists() and str(path) not in out:
            with open_dataset(path) as ds:
                diffs = pred.check_frame_settings(dict(ds.config), str(path), warn)
            if diffs:
                out[str(path)] = diffs
    return out


def _camera_of_first_frame(frames: list[str], fov_range, channel: str = "luminance") -> dict:
    """Config data of a camera the size of the first readable frame, its field the middle of ``fov_range``
    (``--fov-range`` without ``--camera``: the field is searched; pixel pitch is irrelevant to solving)."""
    for _, img, _, _, error in iter_inputs(frames, 1, channel):
        if img is not None:
            h, w = img.shape
            return {
                "camera": {
                    "width_px": int(w),
                    "height_px": int(h),
                    "pixel_pitch_um": 5.5,
                    "fov_deg": 0.5 * (fov_range[0] + fov_range[1]),
                }
            }
    raise FrameError(
        "--fov-range without --camera takes the sensor size from the first frame, but no frame could be read"
    )
