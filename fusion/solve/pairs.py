"""The catalogue pair index of the fine stage: every star pair of a camera's catalogue cut, by separation.

Built once per (catalogue stars, largest separation) and cached on disk beside the tetra3rs
database (``$SKYGEN_CACHE`` (or the legacy ``$FUSION_CACHE``), else ``~/.cache/skygen``, folder ``pairs/``): unordered
pairs
``(first[q], second[q])`` (``first < second``, rows of the catalogue cut) with their angular
separation ``sep[q]`` in radians, sorted ascending, for every pair closer than ``max_sep``. The
candidates of a detection pair are a range of it, found by binary search (:meth:`PairIndex.range`):
an equivalent of Mortari's k-vector, ``O(log P)`` instead of ``O(1)``, about a microsecond at a
million pairs. Regions restrict the *first* star of a candidate by a mask over stars, so no
per-region table is ever built.

The cache file holds a format name, a version and a key (a digest of the star vectors and
``max_sep``); a file for another catalogue cut or camera is never used (its key differs, it
has another name), and a file that does not read or does not match its key is rebuilt with one
line saying so.
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skygen.runtime import atomic_path

FORMAT = "fusion-pair-index"
VERSION = 1


@dataclass(frozen=True)
class PairIndex:
    first: np.ndarray  # (P,) int32, row of the first star (first < second)
    second: np.ndarray  # (P,) int32
    sep: np.ndarray  # (P,) float64, radians, ascending
    key: str

    def __len__(self) -> int:
        return len(self.sep)

    def range(self, lo_rad: float, hi_rad: float) -> tuple[int, int]:
        """Rows ``[start, stop)`` of the pairs with ``lo_rad <= sep <= hi_rad``."""
        return int(np.searchsorted(self.sep, lo_rad, "left")), int(np.searchsorted(self.sep, hi_rad, "right"))


def index_key(vec: np.ndarray, max_sep_rad: float) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(np.round(np.asarray(vec, np.float64), 12)).tobytes())
    h.update(f"{FORMAT}/{VERSION}/{max_sep_rad:.12g}".encode())
    return h.hexdigest()[:20]


def build_index(vec: np.ndarray, max_sep_rad: float) -> PairIndex:
    """Every unordered pair of unit vectors ``vec`` (N, 3) closer than ``max_sep_rad``, sorted by separation."""
    from scipy.spatial import cKDTree

    vec = np.asarray(vec, np.float64)
    pairs = cKDTree(vec).query_pairs(2 * math.sin(max_sep_rad / 2), output_type="ndarray").astype(np.int32)
    pairs.sort(axis=1)
    sep = np.arccos(np.clip(np.einsum("ij,ij->i", vec[pairs[:, 0]], vec[pairs[:, 1]]), -1.0, 1.0))
    order = np.lexsort((pairs[:, 1], pairs[:, 0], sep))  # by separation, ties in a fixed order
    return PairIndex(
        np.ascontiguousarray(pairs[order, 0]),
        np.ascontiguousarray(pairs[order, 1]),
        np.ascontiguousarray(sep[order]),
        index_key(vec, max_sep_rad),
    )


def load_or_build(vec: np.ndarray, max_sep_rad: float, folder: str | Path | None = None, log=None) -> PairIndex:
    """The pair index of ``vec``: from the disk cache when it holds this key, else built and cached."""
    from .tetra import cache_dir

    key = index_key(vec, max_sep_rad)
    path = Path(folder or cache_dir() / "pairs") / f"pairs-{key}.npz"
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["format"]) == FORMAT and int(z["version"]) == VERSION and str(z["key"]) == key:
                    return PairIndex(z["first"], z["second"], z["sep"], key)
            reason = "written for another format, version or catalogue"
        except Exception as exc:  # a damaged file: numpy/zipfile raise many types
            reason = f"unreadable ({type(exc).__name__})"
        if log:
            log(f"fine stage: pair index {path} is {reason}; rebuilding it")
    t0 = time.perf_counter()
    index = build_index(vec, max_sep_rad)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez(
                tmp, format=FORMAT, version=VERSION, key=key, first=index.first, second=index.second, sep=index.sep
            )
    except OSError as exc:  # a read-only cache is no reason to fail: the index is in memory
        if log:
            log(f"fine stage: could not cache the pair index in {path.parent} ({exc.strerror or exc})")
    if log:
        log(
            f"fine stage: built the pair index ({len(index):,} pairs of {len(vec):,} stars) in "
            f"{time.perf_counter() - t0:.1f} s -> {path}"
        )
    return index
