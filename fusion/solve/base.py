"""The solver interface: detections + camera in, a full attitude or an explicit refusal out.

Any star-identification method (classical, learned, coarse-to-fine, another team's) is
scored by ``fusion benchmark`` on the same inputs if it implements :class:`Solver`::

    class MySolver:
        name = "my-solver"
        def solve(self, detections: Detections, camera: skygen.instrument.camera.Camera,
                  image: numpy.ndarray | None = None) -> Solution | Refusal: ...

Inputs
    ``detections`` — a :class:`Detections` table in skygen's pixel convention
    (full-resolution sensor pixels, the centre of the top-left pixel at (0, 0), +x along
    columns, +y along rows; brightest first). ``camera`` — :class:`skygen.instrument.camera.Camera`
    (focal length in pixels, principal point, Brown-Conrady distortion). ``image`` — the
    stored frame in ADU when the solver wants pixels (learned solvers); classical solvers
    ignore it.

Outputs (conventions of :mod:`skygen.conventions`)
    :class:`Solution` — ``quaternion`` ``[w, x, y, z]`` rotating camera-frame vectors into
    ICRS (w >= 0); ``ra_deg``/``dec_deg`` of the boresight (+z); ``roll_deg`` = position
    angle of image up (-y) from north through east; ``matched`` = (detection row, catalog
    id) pairs; ``residual_arcsec`` = rms angle between matched detections and their
    catalog stars; ``confidence`` in [0, 1] (solver-specific; for tetra3rs ``1 - p`` with p
    its false-positive probability). :class:`Refusal` — the solver declines, with a reason.
    A wrong attitude is worse than a refusal: the benchmark counts them separately.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from skygen.sky.attitude import matrix_to_quaternion, matrix_to_radec_roll, quaternion_to_matrix


@dataclass(frozen=True)
class Detections:
    """Detected star centroids of one frame, brightest first.

    ``x_px``/``y_px`` in full-resolution sensor pixels (skygen convention, see module
    docstring); ``flux_adu`` summed background-subtracted signal, ADU.
    """

    x_px: np.ndarray
    y_px: np.ndarray
    flux_adu: np.ndarray

    @classmethod
    def from_table(cls, det: dict) -> "Detections":
        """From a skygen detection table (dict of arrays), sorted brightest first (stable)."""
        flux = np.asarray(det["flux_adu"], np.float64)
        order = np.argsort(-flux, kind="stable")
        return cls(np.asarray(det["x_px"], np.float64)[order], np.asarray(det["y_px"], np.float64)[order], flux[order])

    def __len__(self) -> int:
        return len(self.x_px)

    def brightest(self, n: int) -> "Detections":
        return Detections(self.x_px[:n], self.y_px[:n], self.flux_adu[:n])


@dataclass(frozen=True)
class Solution:
    quaternion: np.ndarray  # [w, x, y, z], camera -> ICRS, w >= 0
    ra_deg: float
    dec_deg: float
    roll_deg: float
    matched: np.ndarray  # (M, 2) int64: detection row, catalog id
    residual_arcsec: float
    confidence: float
    solver: str
    time_ms: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def n_matched(self) -> int:
        return len(self.matched)

    @property
    def matrix(self) -> np.ndarray:
        return quaternion_to_matrix(self.quaternion)

    def to_dict(self) -> dict:
        return {
            "status": "solved",
            "solver": self.solver,
            "quaternion_wxyz": [float(v) for v in self.quaternion],
            "ra_deg": self.ra_deg,
            "dec_deg": self.dec_deg,
            "roll_deg": self.roll_deg,
            "n_matched": self.n_matched,
            "matched": self.matched.tolist(),
            "residual_arcsec": self.residual_arcsec,
            "confidence": self.confidence,
            "time_ms": self.time_ms,
            **self.extra,
        }


@dataclass(frozen=True)
class Refusal:
    reason: str
    solver: str
    time_ms: float = 0.0
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "status": "refused",
            "solver": self.solver,
            "reason": self.reason,
            "time_ms": self.time_ms,
            **self.extra,
        }


@runtime_checkable
class Solver(Protocol):
    name: str

    def solve(self, detections: Detections, camera, image: np.ndarray | None = None) -> Solution | Refusal: ...


class FallbackSolver:
    """``first`` (e.g. tetra3rs lost-in-space: ~0.1 ms, never wrong in the benchmark), and where it refuses,
    ``second`` (e.g. the coarse-to-fine stage with a learned prior), which alone receives keyword arguments
    such as ``probabilities``. The answer names the solver that gave it; a refusal gives both reasons."""

    def __init__(self, first, second, name: str | None = None):
        self.first, self.second = first, second
        self.name = name or f"{first.name}>{second.name}"

    @property
    def prior(self):
        return getattr(self.second, "prior", None)

    def solve(self, detections: Detections, camera, image: np.ndarray | None = None, **kw) -> Solution | Refusal:
        a = self.first.solve(detections, camera, image)
        if isinstance(a, Solution):
            return a
        b = self.second.solve(detections, camera, image, **kw)
        if isinstance(b, Solution):
            return b
        return Refusal(
            f"{a.solver}: {a.reason}; {b.solver}: {b.reason}", self.name, a.time_ms + b.time_ms, {**a.extra, **b.extra}
        )


# --------------------------------------------------------------------------- attitude helpers
# the inverse of skygen.sky.attitude.attitude_matrix, under the name fusion's solvers have always used
radec_roll_from_matrix = matrix_to_radec_roll


def solution_from_matrix(m: np.ndarray, **kw) -> Solution:
    """A :class:`Solution` from a camera -> ICRS rotation matrix and the remaining fields."""
    ra, dec, roll = radec_roll_from_matrix(m)
    return Solution(matrix_to_quaternion(m), ra, dec, roll, **kw)


def rotation_angle_deg(m_a: np.ndarray, m_b: np.ndarray) -> float:
    """Angle of the rotation taking attitude ``m_a`` to ``m_b`` (degrees): the full attitude error."""
    c = (np.trace(np.asarray(m_a).T @ np.asarray(m_b)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def boresight_error_deg(m_a: np.ndarray, m_b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.asarray(m_a)[:, 2] @ np.asarray(m_b)[:, 2], -1.0, 1.0))))


def roll_error_deg(roll_a: float, roll_b: float) -> float:
    """Smallest absolute difference of two roll angles, degrees in [0, 180]."""
    return float(abs((roll_a - roll_b + 180.0) % 360.0 - 180.0))
