"""Boresight regions: spherical K-means on the training directions, and the region hierarchy.

A boresight (RA, Dec) becomes the ICRS unit vector ``v = [cos d cos a, cos d sin a, sin d]``
(the same vector skygen stores as ``boresight/unit_vector``). Class k is the spherical
cluster with centroid ``c_k`` (unit vector); a direction belongs to the class of largest
cosine ``v . c_k`` (ties go to the lower index). Centroids are fitted on the training
split only and then frozen; validation and test directions are labelled against them.

Algorithm (:func:`spherical_kmeans`)
    K-Means++ initialisation with the chordal distance ``|v - c|^2 = 2 (1 - v.c)``,
    seeded; then alternate assignment (max cosine) and update (mean of the members,
    re-normalised to unit length). An empty cluster (or one whose members sum to zero)
    is re-seeded with the direction worst served by its current centroid. **Convergence:**
    an iteration in which no assignment changes and no centroid moves by more than
    ``tol_deg``; otherwise stop after ``max_iter`` iterations (``converged=False`` is
    reported). ``n_init`` restarts (seeds ``[seed, r]``) and the one with the largest total
    cosine similarity is kept.

Hierarchy (:class:`Regions`)
    The K regions a model classifies and, optionally, ``fine_k`` finer regions that a model
    can be trained on; ``groups[f]`` is the region of fine region f (the region of its
    centroid). Fine regions (and, for a model trained on a stream, the K regions too) are
    fitted on :func:`sky_directions`, ``SKY_SAMPLES_PER_REGION`` directions per region drawn
    from the render config's attitude distribution with ``labels.seed`` (:func:`skygen.sky.attitude.boresight_sample`),
    never on a dataset's frames: any ``fine_k`` works with any dataset size, and datasets of one
    camera and attitude distribution share the regions. One object owns both levels:
    training fits it, the checkpoint stores it, the model's log-sum-exp head and the fine
    stage's search read it. ``level`` is ``"coarse"`` (the K regions) or ``"fine"``.

Soft targets (:func:`soft_targets`)
    ``q_k ∝ exp(kappa v . c_k)``: a von Mises–Fisher-like spread over the clusters near
    the true direction; kappa in 1/(unit of cosine). For a neighbour whose centroid is
    an angle ``d`` (rad) farther, the weight ratio is ``exp(-kappa (1 - cos d)) ≈ exp(-kappa d^2/2)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, DatasetError


def radec_to_unit(ra_deg, dec_deg) -> np.ndarray:
    """(N, 3) ICRS unit vectors from RA/Dec in degrees."""
    a, d = np.radians(np.asarray(ra_deg, float)), np.radians(np.asarray(dec_deg, float))
    return np.stack([np.cos(d) * np.cos(a), np.cos(d) * np.sin(a), np.sin(d)], axis=-1)


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(n == 0) or not np.all(np.isfinite(v)):
        raise DatasetError("boresight directions contain zero or non-finite vectors; the dataset is damaged")
    return v / n


def assign(v: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """Class of each direction: the centroid of largest cosine (ties: lower index).

    Many centroids (fine regions) go through a k-d tree: for unit vectors the nearest
    centroid in Euclidean distance is the one of largest cosine, and the (N, K) product
    cost the stream's loader worker ~10 ms per batch at K = 1000."""
    v = np.asarray(v, np.float64)
    c = np.asarray(centroids, np.float64)
    if len(c) <= 64 or len(v) == 0:
        return np.argmax(v @ c.T, axis=1).astype(np.int64)
    from scipy.spatial import cKDTree

    return cKDTree(c).query(v.reshape(-1, 3))[1].astype(np.int64).reshape(v.shape[:-1])


def soft_targets(v: np.ndarray, centroids: np.ndarray, kappa: float) -> np.ndarray:
    """(N, K) targets ``q_k ∝ exp(kappa v . c_k)``; rows sum to 1."""
    z = kappa * (np.asarray(v, np.float64) @ np.asarray(centroids, np.float64).T)
    z -= z.max(axis=1, keepdims=True)
    q = np.exp(z)
    return q / q.sum(axis=1, keepdims=True)


def angular_distance_deg(v: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Row-wise angle between unit vectors, degrees: arccos(v . c), clipped to [-1, 1]."""
    cos = np.clip(np.sum(np.asarray(v, np.float64) * np.asarray(c, np.float64), axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


@dataclass(frozen=True)
class KMeansResult:
    centroids: np.ndarray  # (K, 3) unit vectors
    labels: np.ndarray  # (N,) class of each training direction
    n_iter: int
    converged: bool
    total_cosine: float  # sum over directions of the cosine to their centroid (higher is tighter)


def kmeanspp_init(v: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """K-Means++ seeding with the chordal squared distance 2 (1 - v.c)."""
    n = len(v)
    centroids = [v[rng.integers(n)]]
    d2 = 2.0 * (1.0 - v @ centroids[0])
    for _ in range(1, k):
        d2 = np.clip(d2, 0.0, None)
        total = d2.sum()
        j = rng.choice(n, p=d2 / total) if total > 0 else rng.integers(n)
        centroids.append(v[j])
        d2 = np.minimum(d2, 2.0 * (1.0 - v @ v[j]))
    return np.array(centroids)


def _fit_once(v: np.ndarray, k: int, rng: np.random.Generator, max_iter: int, tol_deg: float) -> KMeansResult:
    c = kmeanspp_init(v, k, rng)
    labels = np.full(len(v), -1, np.int64)
    tol_chord = 2.0 * np.sin(np.radians(tol_deg) / 2.0)  # chord length of the tolerance angle
    converged, it = False, 0
    for it in range(1, max_iter + 1):
        new = assign(v, c)
        sums = np.zeros_like(c)
        np.add.at(sums, new, v)
        norms = np.linalg.norm(sums, axis=1)
        new_c = c.copy()
        ok = norms > 1e-12
        new_c[ok] = sums[ok] / norms[ok, None]
        for j in np.flatnonzero(~ok):  # empty or degenerate cluster: re-seed deterministically
            worst = int(np.argmin(np.sum(v * new_c[new], axis=1)))
            new_c[j] = v[worst]
            new[worst] = j
        moved = np.max(np.linalg.norm(new_c - c, axis=1))  # chord, accurate for tiny angles
        stable = np.array_equal(new, labels) and ok.all()
        c, labels = new_c, new
        if stable and moved <= tol_chord:
            converged = True
            break
    labels = assign(v, c)
    total = float(np.sum(v * c[labels]))
    return KMeansResult(c, labels, it, converged, total)


def spherical_kmeans(
    v: np.ndarray, k: int, seed: int = 0, n_init: int = 4, max_iter: int = 300, tol_deg: float = 1e-6
) -> KMeansResult:
    """Fit K unit centroids to unit vectors ``v`` (N, 3). See the module docstring."""
    v = _unit(v)
    n_distinct = len(np.unique(np.round(v, 12), axis=0))
    if n_distinct < k:
        raise DatasetError(
            f"cannot fit labels.k={k} clusters to {n_distinct} distinct training boresights; "
            "render more frames or lower labels.k"
        )
    best = None
    for r in range(n_init):
        res = _fit_once(v, k, np.random.default_rng([seed, r]), max_iter, tol_deg)
        if best is None or res.total_cosine > best.total_cosine + 1e-9:
            best = res
    # a canonical class order (by Dec, then RA of the centroid) so that class ids read sensibly
    order = np.lexsort((np.arctan2(best.centroids[:, 1], best.centroids[:, 0]), -best.centroids[:, 2]))
    c = best.centroids[order]
    return KMeansResult(c, assign(v, c), best.n_iter, best.converged, best.total_cosine)


def class_weights(labels: np.ndarray, k: int, mode: str = "balanced") -> np.ndarray:
    """Per-class alpha: ``balanced`` = N/(K n_c) L1-normalised (sums to 1); ``uniform`` = 1/K.

    A class with no training sample gets the weight of a class with one sample.
    """
    if mode == "uniform":
        return np.full(k, 1.0 / k)
    if mode != "balanced":
        raise ValueError(f"unknown alpha mode {mode!r}")
    counts = np.bincount(np.asarray(labels, np.int64), minlength=k).astype(np.float64)
    alpha = len(labels) / (k * np.maximum(counts, 1.0))
    return alpha / alpha.sum()


LEVELS = ("coarse", "fine")
SKY_SAMPLES_PER_REGION = 20  # sky directions per fitted region (K-means on 20 F directions: ~2 s at F = 1000)
SKY_SAMPLES_MIN = 20_000


def sky_directions(attitude_config, n_regions: int, seed: int) -> np.ndarray:
    """Directions to fit ``n_regions`` regions on: drawn from the attitude distribution, not from a dataset."""
    from skygen.sky.attitude import boresight_sample

    return boresight_sample(attitude_config, max(SKY_SAMPLES_MIN, SKY_SAMPLES_PER_REGION * n_regions), seed)


@dataclass(frozen=True)
class Regions:
    """The K regions (``coarse`` (K, 3) ICRS unit vectors) and, optionally, the fine regions
    (``fine`` (F, 3)) with ``groups`` (F,): the region each fine region belongs to."""

    coarse: np.ndarray
    fine: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "coarse", np.asarray(self.coarse, np.float64))
        if self.fine is not None:
            object.__setattr__(self, "fine", np.asarray(self.fine, np.float64))

    @property
    def k(self) -> int:
        return len(self.coarse)

    @property
    def fine_k(self) -> int | None:
        return None if self.fine is None else len(self.fine)

    @property
    def groups(self) -> np.ndarray | None:
        """(F,) region index of each fine region, or None without fine regions."""
        return None if self.fine is None else assign(self.fine, self.coarse)

    @classmethod
    def fit(
        cls, v: np.ndarray, k: int, *, seed: int = 0, n_init: int = 4, max_iter: int = 300, tol_deg: float = 1e-6
    ) -> tuple["Regions", KMeansResult]:
        """The K regions fitted on directions ``v`` (N, 3); also returns the K-means result."""
        km = spherical_kmeans(v, k, seed, n_init, max_iter, tol_deg)
        return cls(km.centroids), km

    def with_fine(
        self, v: np.ndarray, fine_k: int, *, seed: int = 0, n_init: int = 4, max_iter: int = 300, tol_deg: float = 1e-6
    ) -> "Regions":
        """These regions with ``fine_k`` fine regions fitted on directions ``v`` (the K regions kept)."""
        fine = spherical_kmeans(v, fine_k, seed, n_init, max_iter, tol_deg).centroids
        return Regions(self.coarse, fine).checked()

    def checked(self) -> "Regions":
        """Self, after checking that every region holds at least one fine region (ConfigError otherwise)."""
        if self.fine is not None:
            empty = sorted(set(range(self.k)) - set(self.groups.tolist()))
            if empty:
                raise ConfigError(
                    f"labels.fine_k={self.fine_k}: regions {empty} contain no fine-region centroid; raise labels.fine_k"
                )
        return self

    def has(self, level: str) -> bool:
        return level == "coarse" or (level == "fine" and self.fine is not None)

    def centroids(self, level: str = "coarse") -> np.ndarray:
        if level not in LEVELS:
            raise ValueError(f"level={level!r}: choose one of {LEVELS}")
        return self.fine if level == "fine" and self.fine is not None else self.coarse

    def assign(self, v: np.ndarray, level: str = "coarse") -> np.ndarray:
        """Region (or fine region) index of each direction in ``v``: max cosine."""
        return assign(v, self.centroids(level))
