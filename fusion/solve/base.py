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
    its false-positive probability); ``status`` = ``"solved"``. :class:`Refusal` — the solver
    declines, with a reason and a ``status`` code. A wrong attitude is worse than a refusal: the
    benchmark counts them separately.

The certificate of a solution
    ``false_match_probability`` — the solver's own probability that the identification is a
    coincidence (the fine stage: its expected number of coincidental hypotheses E_false, so
    ``confidence = 1 - E_false``; tetra3rs: its ``probability``, the false-positive probability of
    its verification). ``None`` where a solver gives none.

    ``covariance_arcsec`` — 1-sigma attitude uncertainty ``[sigma_x, sigma_y, sigma_roll]``
    (arcseconds): the small rotation taking the true attitude to the returned one, as a rotation
    vector in the camera frame (x, y: about the camera's +x and +y axes, i.e. the boresight moving
    along image -y and +x; roll: about the boresight, +z), and ``covariance_matrix_arcsec2`` its
    full 3 x 3 covariance (arcsec^2). From the matched stars alone (:func:`attitude_covariance`):
    with ``v_i`` the matched detections' unit vectors in the camera frame and sigma the per-axis
    angular centroid error,

        C = sigma^2 * (sum_i (I - v_i v_i^T))^-1,
        sigma^2 = max(k_nu^2 * n * rms^2 / nu, sigma_floor^2),   nu = 2n - p

    (each star constrains the two directions perpendicular to itself; ``rms`` the matched stars'
    rms residual angle after the fit, 2n measurements less the p fitted parameters: 3 angles, and a
    fourth where the focal length was fitted to the same stars, as the fine stage does from three stars
    on -- then C is the rotation's block of the four-parameter fit's inverse information, larger across
    the boresight wherever the stars lie off it, since a scale error moves them the way a turn does;
    ``sigma_floor`` the camera's pixel scale times ``CENTROID_FLOOR_PX``, so three stars that happen to
    fit perfectly do not claim a perfect attitude, or times the real camera's measured centroid error where
    ``skygen fit-camera`` wrote one, ``camera.centroid_sigma_px``). sigma is estimated from the same few residuals, so
    an error divided by it follows Student's t with nu degrees of freedom, not a Gaussian: k_nu
    (:func:`student_scale`) puts the t's 1 and 2 sigma nearest the Gaussian 68 / 95 % (four stars and a
    fitted focal length, nu = 4: k = 1.25, 72 / 93 %; without it 63 / 88 %). Near the boresight this is
    sigma_x = sigma_y ~ sigma / sqrt(n) and sigma_roll ~ sigma / (sqrt(n) * rho_rms), rho_rms the
    matched stars' rms distance from their own centroid (radians). It assumes the matches are right
    and the centroid errors independent; ``fusion benchmark`` reports how often the true error lies
    within 1 and 2 sigma (coverage). Errors the stars of one frame share do not average down: on a camera
    ``skygen fit-camera`` measured them on (``camera.shared_sigma_px``) C gains (shared x pixel scale)^2 on
    each cross-boresight axis.

Refusal status codes (:data:`REFUSAL_STATUSES`)
    ``too_few_stars`` fewer detections than the method needs (or none); ``no_pattern`` no catalogue
    pattern matches the detections where the solver searched; ``budget_exhausted`` the solver's
    work budget ran out before a decision (the fine stage: ``max_hypotheses``, a count, so the same
    on every machine; tetra3rs: its timeout); ``ambiguous`` several attitudes explain the
    detections equally well; ``weak_evidence`` a best candidate whose chance of being a coincidence
    is too high (or that no candidate could reach the bar any more); ``not_verified`` a candidate
    that verification rejected (tetra3rs tracking did not confirm it, a mismatched star pulled the
    refined attitude off, a mirror image); ``invalid_input`` nothing could be searched (a
    degenerate camera model); ``other`` a solver that gives no code (the default, for solvers
    written before the codes).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import ClassVar, Protocol, runtime_checkable

import numpy as np

from skygen.sky.attitude import matrix_to_quaternion, matrix_to_radec_roll, quaternion_to_matrix


@dataclass(frozen=True)
class Detections:
    """Detected star centroids of one frame, brightest first.

    ``x_px``/``y_px`` in full-resolution sensor pixels (skygen convention, see module
    docstring); ``flux_adu`` summed background-subtracted signal, ADU. ``saturated`` (optional, bool): detections
    whose brightest pixel reaches the top of the frame's range (:func:`fusion.solve.predict.saturated_rows`),
    whose flux is then only a lower bound (tracking's photometry reads it so); None: not known.
    """

    x_px: np.ndarray
    y_px: np.ndarray
    flux_adu: np.ndarray
    saturated: np.ndarray | None = None

    @classmethod
    def from_table(cls, det: dict) -> "Detections":
        """From a skygen detection table (dict of arrays; ``saturated`` read where it has one), sorted brightest
        first (stable)."""
        flux = np.asarray(det["flux_adu"], np.float64)
        order = np.argsort(-flux, kind="stable")
        sat = det.get("saturated")
        return cls(
            np.asarray(det["x_px"], np.float64)[order],
            np.asarray(det["y_px"], np.float64)[order],
            flux[order],
            None if sat is None else np.asarray(sat, bool)[order],
        )

    def __len__(self) -> int:
        return len(self.x_px)

    def take(self, rows) -> "Detections":
        """The detections ``rows`` (indices or a mask), in that order, with everything they carry."""
        sat = None if self.saturated is None else self.saturated[rows]
        return Detections(self.x_px[rows], self.y_px[rows], self.flux_adu[rows], sat)

    def brightest(self, n: int) -> "Detections":
        return self.take(slice(0, n))


REFUSAL_STATUSES: dict[str, str] = {
    "too_few_stars": "fewer detections than the method needs (or none)",
    "no_pattern": "no catalogue pattern matches the detections where the solver searched",
    "budget_exhausted": "the work budget ran out before a decision",
    "ambiguous": "several attitudes explain the detections equally well",
    "weak_evidence": "the best candidate's chance of being a coincidence is too high",
    "not_verified": "verification rejected the candidate",
    "invalid_input": "nothing could be searched (a degenerate camera model)",
    "other": "the solver gives no code",
}
HINT_RADIUS_SIGMAS = 3.0  # tracking: a hint with 1-sigma error s leaves the attitudes within 3 s of it
CENTROID_FLOOR_PX = 0.03  # the smallest per-axis centroid error an attitude covariance assumes (pixels)


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
    false_match_probability: float | None = None  # see the module docstring
    covariance_matrix_arcsec2: np.ndarray | None = None  # (3, 3), camera-frame rotation vector (x, y, roll)
    status: ClassVar[str] = "solved"

    @property
    def n_matched(self) -> int:
        return len(self.matched)

    @property
    def matrix(self) -> np.ndarray:
        return quaternion_to_matrix(self.quaternion)

    @property
    def covariance_arcsec(self) -> np.ndarray | None:
        """1-sigma ``[x, y, roll]`` (arcsec): the square roots of the covariance's diagonal."""
        c = self.covariance_matrix_arcsec2
        return None if c is None else np.sqrt(np.diag(c))

    def to_dict(self) -> dict:
        cov = self.covariance_matrix_arcsec2
        return {
            "status": self.status,
            "solver": self.solver,
            "quaternion_wxyz": [float(v) for v in self.quaternion],
            "ra_deg": self.ra_deg,
            "dec_deg": self.dec_deg,
            "roll_deg": self.roll_deg,
            "n_matched": self.n_matched,
            "matched": self.matched.tolist(),
            "residual_arcsec": self.residual_arcsec,
            "confidence": self.confidence,
            "false_match_probability": self.false_match_probability,
            "covariance_arcsec": None if cov is None else [float(v) for v in np.sqrt(np.diag(cov))],
            "covariance_matrix_arcsec2": None if cov is None else np.asarray(cov, float).tolist(),
            "time_ms": self.time_ms,
            **self.extra,
        }


@dataclass(frozen=True)
class Refusal:
    """The solver declines: ``reason`` in words, ``status`` one of :data:`REFUSAL_STATUSES`."""

    reason: str
    solver: str
    time_ms: float = 0.0
    extra: dict = field(default_factory=dict)
    status: str = "other"

    def __post_init__(self):
        if self.status not in REFUSAL_STATUSES:
            raise ValueError(f"Refusal status {self.status!r}: one of {', '.join(REFUSAL_STATUSES)}")

    def to_dict(self) -> dict:
        return {
            "status": "refused",
            "refusal_status": self.status,
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
        track = {k: kw[k] for k in ("hint", "hint_sigma_deg", "hint_zero_point") if kw.get(k) is not None}
        a = self.first.solve(detections, camera, image, **track)  # a tracking hint goes to both
        if isinstance(a, Solution):
            return a
        b = self.second.solve(detections, camera, image, **kw)
        if isinstance(b, Solution):
            return b
        # the status is the second's: it searched last and most (the first's is in the reason)
        return Refusal(
            f"{a.solver}: {a.reason}; {b.solver}: {b.reason}",
            self.name,
            a.time_ms + b.time_ms,
            {**a.extra, **b.extra},
            b.status,
        )


# --------------------------------------------------------------------------- attitude helpers
# the inverse of skygen.sky.attitude.attitude_matrix, under the name fusion's solvers have always used
radec_roll_from_matrix = matrix_to_radec_roll


def solution_from_matrix(m: np.ndarray, **kw) -> Solution:
    """A :class:`Solution` from a camera -> ICRS rotation matrix and the remaining fields."""
    ra, dec, roll = radec_roll_from_matrix(m)
    return Solution(matrix_to_quaternion(m), ra, dec, roll, **kw)


def photometric_zero_point(cat_mag: np.ndarray, flux_adu: np.ndarray) -> float | None:
    """The mean of catalogue magnitude minus instrumental magnitude (-2.5 log10 flux) over matched stars with a
    positive flux (``Solution.extra["zero_point"]``: what tracking's ``hint_zero_point`` takes), or None."""
    mag, flux = np.asarray(cat_mag, np.float64), np.asarray(flux_adu, np.float64)
    ok = (flux > 0) & np.isfinite(mag)
    if not ok.any():
        return None
    return float(np.mean(mag[ok] + 2.5 * np.log10(flux[ok])))


@functools.lru_cache(maxsize=256)
def student_scale(dof: int) -> float:
    """The factor k that makes a sigma estimated from ``dof`` residual degrees of freedom a calibrated one:
    an error divided by it follows Student's t with ``dof`` degrees of freedom, whose tails are heavier than
    a Gaussian's, so no single k gives both the Gaussian 68.27 % within 1 sigma and 95.45 % within 2. k is
    the one whose 1 and 2 sigma miss those by the least, in units of the tolerances a covariance is held to
    (5 and 3 points: issue 37), from the 68.27 % quantile up (three degrees of freedom: 1.35 -> 73 / 93 %;
    five: 1.19 -> 71 / 94 %; 26: 1.03 -> 69 / 95 %; -> 1 for many)."""
    from scipy.special import stdtr, stdtrit  # the t distribution; scipy.special is loaded by the solvers already

    nu = max(int(dof), 1)
    k68 = float(stdtrit(nu, 0.5 * (1.0 + math.erf(1.0 / math.sqrt(2.0)))))
    ks = np.linspace(k68, 2.0 * k68, 2001)
    p1, p2 = 2.0 * stdtr(nu, ks) - 1.0, 2.0 * stdtr(nu, 2.0 * ks) - 1.0
    miss = np.maximum(np.abs(p1 - 0.6827) / 0.05, np.abs(p2 - 0.9545) / 0.03)
    return float(ks[int(np.argmin(miss))])


def attitude_covariance(
    u: np.ndarray,
    residual_arcsec: float,
    pixel_scale_arcsec: float,
    *,
    student: bool = True,
    scale_fitted: bool = False,
    floor_px: float | None = None,
    shared_px: float | None = None,
) -> np.ndarray:
    """The 3 x 3 attitude covariance (arcsec^2) of a rotation fitted to matched stars (module docstring).

    ``u`` (n, 3): the matched detections' unit vectors in the camera frame; ``residual_arcsec``: their rms
    angle from their catalogue stars after the fit; ``pixel_scale_arcsec``: of the camera (the floor of
    the per-axis centroid error is :data:`CENTROID_FLOOR_PX` pixels). ``student``: scale the sigma
    estimated from the residuals by :func:`student_scale` of its degrees of freedom (the default; False
    gives the plain estimate, whose 1 sigma holds less than 68 % for few stars). ``scale_fitted``: the
    focal length was fitted to the same stars (the fine stage's focal factor, from three stars on): a
    fourth parameter, so 2n - 4 degrees of freedom, and the rotation's covariance marginalised over it
    (a scale error moves a star set lying off the boresight the way a cross-boresight turn does).
    ``floor_px``: the camera's measured per-axis centroid error (``camera.centroid_sigma_px``, from
    ``skygen fit-camera``), the floor in place of :data:`CENTROID_FLOOR_PX` where it is larger: a few
    stars' residuals cannot show the errors they share (residual distortion, the catalogue's positions),
    which move the attitude all the same. ``shared_px``: the per-axis error the brightest stars of one real frame
    share (``camera.shared_sigma_px``, from ``skygen fit-camera``): it moves every matched star alike, so it turns
    the attitude across the boresight by that much over the focal length however many stars there are, and is
    added there (x and y, in quadrature; nothing in roll)."""
    u = np.asarray(u, np.float64).reshape(-1, 3)
    n = len(u)
    scale_fitted = scale_fitted and n >= 3
    dof = max(2 * n - (4 if scale_fitted else 3), 1)
    k2 = student_scale(dof) ** 2 if student else 1.0
    floor = CENTROID_FLOOR_PX if floor_px is None else max(floor_px, CENTROID_FLOOR_PX)
    sigma2 = max(k2 * n * residual_arcsec**2 / dof, (floor * pixel_scale_arcsec) ** 2)
    info = n * np.eye(3) - u.T @ u  # sum of (I - v v^T)
    if scale_fitted:
        # d_i = (x z^2, y z^2, -z rho^2) for v_i = (x, y, z), rho^2 = x^2 + y^2: how star i moves per unit of
        # relative focal-length change (radially, perpendicular to it). The information of (rotation, scale)
        # is [[info, b], [b^T, e]] with b = -sum v_i x d_i = (-sum z y, sum z x, 0) and e = sum |d_i|^2 =
        # sum z^2 rho^2; the rotation's marginal information is its Schur complement info - b b^T / e
        z = u[:, 2]
        b = np.array([-np.dot(z, u[:, 1]), np.dot(z, u[:, 0]), 0.0])
        e = float(np.dot(z * z, 1.0 - z * z))
        if e > 0:
            info = info - np.outer(b, b) / e
    try:  # two distinct directions or more make it invertible; pinv for one (or a degenerate set)
        cov = sigma2 * np.linalg.inv(info) if n >= 2 else sigma2 * np.linalg.pinv(info)
    except np.linalg.LinAlgError:
        cov = sigma2 * np.linalg.pinv(info)
    if shared_px:
        cov[0, 0] += (shared_px * pixel_scale_arcsec) ** 2
        cov[1, 1] += (shared_px * pixel_scale_arcsec) ** 2
    return cov


def rotation_vector_deg(m_a: np.ndarray, m_b: np.ndarray) -> np.ndarray:
    """Rotation vector (degrees) of ``m_a^T m_b``: the rotation taking attitude ``m_a`` to ``m_b`` in ``m_a``'s
    camera frame (x, y cross-boresight, z roll), the frame of :attr:`Solution.covariance_matrix_arcsec2`."""
    from scipy.spatial.transform import Rotation

    return np.degrees(Rotation.from_matrix(np.asarray(m_a).T @ np.asarray(m_b)).as_rotvec())


def rotation_angle_deg(m_a: np.ndarray, m_b: np.ndarray) -> float:
    """Angle of the rotation taking attitude ``m_a`` to ``m_b`` (degrees): the full attitude error."""
    c = (np.trace(np.asarray(m_a).T @ np.asarray(m_b)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def boresight_error_deg(m_a: np.ndarray, m_b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.asarray(m_a)[:, 2] @ np.asarray(m_b)[:, 2], -1.0, 1.0))))


def roll_error_deg(roll_a: float, roll_b: float) -> float:
    """Smallest absolute difference of two roll angles, degrees in [0, 180]."""
    return float(abs((roll_a - roll_b + 180.0) % 360.0 - 180.0))
