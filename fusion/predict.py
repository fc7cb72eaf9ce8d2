"""``fusion predict``: a user's own frames -> detections, the model's regions, optionally a full attitude.

    fusion predict FRAME... --checkpoint CK [--solve] [--overlay DIR] [--top-k 3] [--out FILE.jsonl]
                            [--search fine|coarse] [--search-k N] [--focal-tol 0.02]
    fusion predict FRAME... --camera configs/cameras/NAME.yaml --solve      # no model: tetra3rs only

Frames: PNG, TIFF (8 or 16 bit), FITS (the first HDU with 2-D data), ``.npy`` (2-D array) files,
or a skygen dataset folder (its stored detections and images; ``--max-frames``). Each frame
must be one full-resolution sensor read-out of the checkpoint's (or ``--camera``'s) camera,
rows = height, in ADU or any linear unit.

Per frame:

1. detection: skygen's detector (:func:`skygen.detect.detect`) with the camera's detection
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
   reported as ``focal_factor`` / ``fov_deg``); ``--lis-first`` tries tetra3rs lost-in-space
   first and the learned path only where it refuses; without a checkpoint, tetra3rs lost-in-space. A full attitude
   (quaternion, RA/Dec/roll in skygen's conventions, matched catalog stars, residual,
   confidence) or an explicit refusal with its reason.

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

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from skygen.camera import Camera
from skygen.config import build_config as build_render_config
from skygen.config import load_config as load_render_config
from skygen.detect import detect

from .errors import ConfigError, FusionError
from .solvers.base import Detections

FRAME_SUFFIXES = (".png", ".tif", ".tiff", ".fits", ".fit", ".fts", ".npy")


class FrameError(FusionError):
    """A frame file cannot be used (unreadable, empty, colour, wrong size)."""


def read_frame(path: str | Path) -> np.ndarray:
    """A 2-D image from PNG/TIFF (8/16 bit), FITS or .npy; FrameError with the reason otherwise."""
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise FrameError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise FrameError(f"{path}: empty file")
    if suffix not in FRAME_SUFFIXES:
        raise FrameError(f"{path}: unsupported file type {suffix or '(none)'}; give {', '.join(FRAME_SUFFIXES)}")
    try:
        if suffix == ".npy":
            img = np.load(path, allow_pickle=False)
        elif suffix in (".fits", ".fit", ".fts"):
            from astropy.io import fits
            with fits.open(path, memmap=False) as hdul:
                img = next((h.data for h in hdul if h.data is not None and np.ndim(h.data) >= 2), None)
            if img is None:
                raise FrameError(f"{path}: no image HDU with 2-D data")
        else:
            import cv2
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise FrameError(f"{path}: not a readable {suffix[1:].upper()} image")
            if img.ndim == 3 and img.shape[2] in (3, 4):
                img = img[:, :, :3]
                if np.array_equal(img[:, :, 0], img[:, :, 1]) and np.array_equal(img[:, :, 0], img[:, :, 2]):
                    img = img[:, :, 0]           # grey stored as RGB: one channel
    except FrameError:
        raise
    except Exception as exc:                      # decoders raise many types for damaged files
        raise FrameError(f"{path}: unreadable ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[0] == 1:
        img = img[0]
    if img.ndim != 2:
        raise FrameError(f"{path}: colour or multi-plane image (shape {img.shape}); give one monochrome "
                         "sensor read-out")
    if img.size == 0:
        raise FrameError(f"{path}: image has no pixels")
    if not np.issubdtype(img.dtype, np.number):
        raise FrameError(f"{path}: pixel type {img.dtype} is not numeric")
    return img.astype(np.float32)


class Predictor:
    """Detector + (optional) region prior + (optional) solver for one camera."""

    def __init__(self, checkpoint: str | Path | None = None, *, camera: str | Path | None = None,
                 dataset: str | Path | None = None, solve: bool = False, top_k: int = 3, detector: str = "skygen",
                 search: str = "fine", search_k: int | None = None, focal_tol: float = 0.02,
                 background_box: int = 0, lis_first: bool = False, log=None):
        from .solvers.priors import load_prior
        if (checkpoint is None) == (camera is None):
            raise ConfigError("give --checkpoint CK (a trained model: its own camera) or --camera FILE.yaml "
                              "(tetra3rs only), exactly one of them")
        render_config = None
        if dataset is not None:
            from skygen.io import open_dataset
            with open_dataset(dataset) as ds:
                render_config = dict(ds.config)
        if camera is not None:
            from skygen.config import config_dict
            render_config = config_dict(load_render_config(camera))
        self.prior = load_prior(checkpoint, render_config) if checkpoint is not None else None
        if self.prior is not None:
            render_config = self.prior.render_config
        self.cfg = build_render_config(render_config)
        self.camera = Camera.from_config(self.cfg.camera)
        self.factor = self.cfg.camera.width_px // self.cfg.output.image_size_px
        self.top_k, self.detector = top_k, detector
        if detector == "tetra3rs" and self.prior is not None:
            raise ConfigError("--detector tetra3rs: the model was trained on skygen's detector; use it only "
                              "without --checkpoint")
        if background_box and background_box < 8:
            raise ConfigError(f"--background-box {background_box}: 0 (one background per frame) or a box of at "
                              "least 8 px, e.g. 64")
        self.background_box = int(background_box)
        check_search_options(focal_tol, search_k)
        self.solver, self.search_level = None, None
        if solve:
            from .solvers.coarse_fine import CoarseToFineSolver
            from .solvers.tetra import Tetra3Solver
            tetra = Tetra3Solver(self.camera, log=log)
            if self.prior is not None:
                search_prior = self.prior.at_level(search) if hasattr(self.prior, "at_level") else self.prior
                self.search_level = getattr(search_prior, "level", "coarse")
                self.solver = CoarseToFineSolver(tetra, search_prior, name="learned+fine", focal_tol=focal_tol,
                                                 top_k=search_k or default_search_k(self.search_level))
                if lis_first:
                    from .solvers.base import FallbackSolver
                    self.solver = FallbackSolver(tetra, self.solver)
            else:
                self.solver = tetra

    def check_shape(self, img: np.ndarray, source: str) -> None:
        want = (self.cfg.camera.height_px, self.cfg.camera.width_px)
        if img.shape != want:
            raise FrameError(f"{source}: frame is {img.shape[1]} x {img.shape[0]} px but the camera is "
                             f"{want[1]} x {want[0]} px (width x height); give full-resolution frames of that camera")

    def detect(self, img: np.ndarray) -> tuple[Detections, float, float]:
        d = self.cfg.detection
        if self.detector == "tetra3rs":
            # tetra3rs's extractor (local background, matched filter): centroids relative to the image centre;
            # skygen pixel = centroid + (size - 1) / 2 (checked against rendered true positions to 0.004 px)
            import tetra3rs
            res = tetra3rs.extract_centroids(np.ascontiguousarray(img, np.float32),
                                             sigma_threshold=d.threshold_sigma, min_pixels=d.min_area_px,
                                             max_centroids=d.max_detections)
            c = res.centroids
            h, w = img.shape
            table = {"x_px": np.array([p.x for p in c]) + (w - 1) / 2, "y_px": np.array([p.y for p in c]) + (h - 1) / 2,
                     "flux_adu": np.array([p.brightness or 0.0 for p in c])}
            return Detections.from_table(table), float(res.background_mean), float(res.background_sigma)
        det, bg, sigma = detect(img, d.threshold_sigma, d.min_area_px, d.max_detections, self.background_box)
        return Detections.from_table(det), bg, sigma

    def stored_image(self, img: np.ndarray) -> np.ndarray:
        import cv2
        if self.factor == 1:
            return img
        h, w = img.shape
        return cv2.resize(img, (w // self.factor, h // self.factor), interpolation=cv2.INTER_AREA)

    def run(self, source: str, det: Detections, stored: np.ndarray | None, extra: dict) -> dict:
        rec = {"frame": source, **extra, "n_detections": len(det),
               "detections": [[round(float(x), 3), round(float(y), 3), round(float(f), 1)]
                              for x, y, f in zip(det.x_px, det.y_px, det.flux_adu)]}
        probs = search_probs = None
        if self.prior is not None:
            t0 = time.perf_counter()
            if hasattr(self.prior, "both"):
                probs, fine = self.prior.both(det, stored)
            else:
                probs, fine = self.prior.probabilities(det, stored), None
            search_probs = fine if self.solver is not None and self.search_level == "fine" else probs
            rec["model_ms"] = (time.perf_counter() - t0) * 1e3
            order = np.argsort(-probs, kind="stable")[: self.top_k]
            c = self.prior.centroids
            rec["regions"] = [{"rank": r + 1, "region": int(k), "probability": float(probs[k]),
                               "ra_deg": float(np.degrees(np.arctan2(c[k, 1], c[k, 0])) % 360),
                               "dec_deg": float(np.degrees(np.arcsin(np.clip(c[k, 2], -1, 1))))}
                              for r, k in enumerate(order)]
        if self.solver is not None:
            kw = {"probabilities": search_probs} if search_probs is not None else {}
            res = self.solver.solve(det, self.camera, stored, **kw)
            rec["solution"] = res.to_dict()
        return rec


def add_search_arguments(p: argparse.ArgumentParser, k_flag: str = "--search-k") -> None:
    """The coarse-to-fine options shared by ``fusion predict --solve`` and ``fusion benchmark``."""
    p.add_argument("--search", choices=("fine", "coarse"), default="fine",
                   help="coarse-to-fine stage: search the model's fine regions (default; a few degrees each, for "
                        "checkpoints trained with labels.fine_k, else its K regions) or its K regions")
    p.add_argument(k_flag, dest="search_k", type=int, metavar="K",
                   help="coarse-to-fine stage: regions searched, most probable first (default 20 fine regions or "
                        "3 coarse ones)")
    p.add_argument("--focal-tol", type=float, default=0.02,
                   help="coarse-to-fine stage: relative focal-length uncertainty it fits within (default 0.02; "
                        "0 = the camera's nominal focal length exactly)")


def check_search_options(focal_tol: float, search_k: int | None, k_flag: str = "--search-k") -> None:
    if not 0.0 <= focal_tol < 0.2:
        raise ConfigError(f"--focal-tol {focal_tol}: a relative focal-length uncertainty in [0, 0.2), e.g. 0.02")
    if search_k is not None and search_k < 1:
        raise ConfigError(f"{k_flag} {search_k}: search at least 1 region")


def default_search_k(level: str) -> int:
    """Regions the fine stage searches by default: 20 fine regions (~2 % of the sky at fine_k = 1000) or 3 of K."""
    return 20 if level == "fine" else 3


def iter_inputs(paths: list[str], max_frames: int | None):
    """(source name, full image or None, detections table or None, stored image or None, error) per frame."""
    for p in paths:
        path = Path(p)
        if path.is_dir() and (path / "manifest.json").exists():
            from skygen.io import open_dataset
            with open_dataset(path) as ds:
                for pos in range(len(ds) if max_frames is None else min(max_frames, len(ds))):
                    yield f"{path}#{int(ds.frames['index'][pos])}", None, ds.detections(pos), ds.image(pos), None
            continue
        try:
            yield str(path), read_frame(path), None, None, None
        except FrameError as exc:
            yield str(path), None, None, None, str(exc)


def overlay(path: Path, img: np.ndarray, det: Detections, rec: dict) -> None:
    """The frame (log-stretched to 8 bit) with numbered detections; matched ones green."""
    import cv2
    from .checkpoint import atomic_write_bytes
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
        text = (f"RA {sol['ra_deg']:.3f} Dec {sol['dec_deg']:.3f} roll {sol['roll_deg']:.2f}  "
                f"{sol['n_matched']} matched, {sol['residual_arcsec']:.1f}\" rms")
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


def predict(frames: list[str], checkpoint=None, *, camera=None, dataset=None, solve=False, top_k=3,
            detector="skygen", overlay_dir=None, out=None, max_frames=None, log=print,
            err=None, search="fine", search_k=None, focal_tol=0.02, background_box=0,
            lis_first=False) -> tuple[list[dict], int]:
    """Run the pipeline on every frame; returns (records, number of failed frames)."""
    err = err or (lambda m: print(m, file=sys.stderr))
    pred = Predictor(checkpoint, camera=camera, dataset=dataset, solve=solve, top_k=top_k, detector=detector,
                     search=search, search_k=search_k, focal_tol=focal_tol, background_box=background_box,
                     lis_first=lis_first, log=lambda m: err(m))
    sink = open(out, "w") if out else None
    if overlay_dir:
        Path(overlay_dir).mkdir(parents=True, exist_ok=True)
    records, failed = [], 0
    try:
        for source, img, table, stored, error in iter_inputs(frames, max_frames):
            t0 = time.perf_counter()
            try:
                if error:
                    raise FrameError(error)
                if img is not None:
                    pred.check_shape(img, source)
                    det, bg, sigma = pred.detect(img)
                    stored = pred.stored_image(img)
                    extra = {"shape": [int(img.shape[0]), int(img.shape[1])], "background_adu": bg, "noise_adu": sigma}
                else:
                    det, extra = Detections.from_table(table), {"detections_from": "dataset"}
                rec = pred.run(source, det, stored, extra)
                rec["total_ms"] = (time.perf_counter() - t0) * 1e3
                if overlay_dir:
                    name = Path(source.replace("#", "_")).name
                    overlay(Path(overlay_dir) / f"{Path(name).stem}.png", img if img is not None else stored, det, rec)
            except FrameError as exc:
                failed += 1
                rec = {"frame": source, "error": str(exc)}
                err(f"fusion predict: {exc}")
            records.append(rec)
            line = json.dumps(rec, default=float)
            (sink.write(line + "\n") if sink else log(line))
    finally:
        if sink:
            sink.close()
    return records, failed


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("frames", nargs="+", metavar="FRAME",
                   help="image files (.png, .tif/.tiff 8/16-bit, .fits, .npy) or skygen dataset folders")
    p.add_argument("--checkpoint", help="a fusion checkpoint (best.pt): its camera, detector and model")
    p.add_argument("--camera", help="a skygen camera preset (configs/cameras/*.yaml) when no checkpoint is given")
    p.add_argument("--dataset", help="the training dataset of a checkpoint written before checkpoints carried "
                                     "their camera")
    p.add_argument("--solve", action="store_true", help="return a full attitude (or a refusal): the model's regions "
                   "as prior of the fine stage; tetra3rs lost-in-space without a checkpoint")
    p.add_argument("--top-k", type=int, default=3, help="regions (of the model's K) reported (default 3)")
    add_search_arguments(p)
    p.add_argument("--overlay", metavar="DIR", help="write DIR/<frame>.png with the detections drawn")
    p.add_argument("--out", metavar="FILE.jsonl", help="write the JSON lines here instead of stdout")
    p.add_argument("--max-frames", type=int, help="dataset inputs: only the first N frames")
    p.add_argument("--lis-first", action="store_true",
                   help="--solve with a checkpoint: try tetra3rs lost-in-space first (~0.1 ms; enough with 8+ clean "
                        "stars) and the learned prior's fine stage only where it refuses; `solver` says which answered")
    p.add_argument("--background-box", type=int, default=0, metavar="PX",
                   help="skygen detector: background per PX x PX box (e.g. 64; for ground frames with sky glow or "
                        "gradients) instead of one level per frame (default 0, as the renders and the training)")
    p.add_argument("--detector", choices=("skygen", "tetra3rs"), default="skygen",
                   help="skygen (default; what models are trained on) or tetra3rs's extractor (local background, "
                        "matched filter: more stars on ground frames with sky gradients; without --checkpoint only)")


def run(args: argparse.Namespace) -> int:
    _, failed = predict(args.frames, args.checkpoint, camera=args.camera, dataset=args.dataset, solve=args.solve,
                        top_k=args.top_k, detector=args.detector, overlay_dir=args.overlay, out=args.out,
                        max_frames=args.max_frames, search=args.search, search_k=args.search_k,
                        focal_tol=args.focal_tol, background_box=args.background_box, lis_first=args.lis_first)
    return 1 if failed else 0
