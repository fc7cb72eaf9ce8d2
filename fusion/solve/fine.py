"""The fine stage: a region prior narrows the sky, a few-star identification finds the attitude.

tetra3rs's tracking mode (attitude hint) verifies and refines an attitude only when the
hint is within about half a degree, and a learned region is tens of degrees wide. What
tetra3rs does not do, this module does: **region-restricted hypothesise-and-verify** for few
stars. (The measurements behind each design choice below are in ``results/benchmark/README.md``,
"Why the fine stage is built this way".)

For one region (a cap around a region centroid, :class:`Region`):

1. catalog: tetra3rs's own catalog stars (Gaia DR3 + Hipparcos gap-fill, the stars its
   database verifies with) inside the cap widened by the camera's half-diagonal, the
   brightest ``stars_per_fov`` per field of view (a global magnitude cut; 60). With at most
   ``bright_max_detections`` (3) detections a brighter tier is searched instead,
   ``bright_stars_per_fov`` (12): three bright detections are nearly always among the brightest
   dozen stars of their field, and a chance triangle of three such stars is ~25x rarer (H falls
   with the square of the star count, p with the count), which is what lets a region prior
   identify three stars at all; over the whole sky they still cannot reach the bar;
2. hypotheses: every catalog pair whose separation matches that of two bright detections
   (i, j) within ``tol_px`` (both orders; a range of the catalogue pair index,
   :mod:`fusion.solve.pairs`, built once per camera and catalogue cut and cached on disk) — and, with ``focal_tol`` = s
   > 0, within a focal
   length known only to ±s (a real lens's focal length is off its datasheet value by about
   a percent, which at the edge of a field is several times a 2 px tolerance). Each pair fixes
   a focal-length factor k (catalog separation / detection separation, clipped to 1 ± s) and a
   rotation (TRIAD: detection i onto star a exactly, the i->j direction onto a->b), both
   computed with the detections re-projected at that focal length. All regions are searched at
   the nominal focal length first, and again with ±s only if that finds nothing: the free scale
   costs evidence;
3. score: every detection is mapped to the sky with that rotation and counts if a
   catalog star lies within ``tol_px`` plus what the pair leaves uncertain of the scale
   (``min(s, 2 tol / d_ij)`` times the detection's distance from detection i); a hypothesis
   whose boresight leaves the region is dropped before it is scored or counted (it belongs to another
   region: it could never be accepted here, so it cannot be a false match of this region, and the
   widened catalogue caps of neighbouring regions do not count it twice). The scoring is
   compiled (numba, :mod:`fusion.solve.match`) and finds the candidate stars through the pair
   index rather than by projecting every hypothesis;
4. decision, after each detection pair (so a clear case stops early; by default the pairs with the
   fewest catalogue candidates go first, ``anchor_order="fewest"``: fewer hypotheses to score, and a
   smaller H behind the first decision; ``"brightest"`` keeps the brightest-first order): the best hypothesis
   so far (most matches) must be unique — no other hypothesis with as many matches at an
   attitude more than 0.5° away — and its chance of being a coincidence small:
   ``E_false = H * C(n - 2, s - 2) * p^(s - 2)`` (H hypotheses tried so far, n detections, s
   matches, p the chance that a random sky position has a catalog star within ``tol_px``)
   gives ``confidence = max(0, 1 - E_false)``. Where geometry alone falls short, **photometry** is
   further evidence: if the matched stars' catalogue magnitudes follow the detections'
   instrumental magnitudes (-2.5 log10 flux) to within ``photometric_mag`` (0.5 mag scatter about a
   fitted zero point; true matches pass ~96 % of the time on rendered frames, ``results/benchmark``),
   a coincidence must pass that test too, which random stars of the tier do with chance q (a Monte
   Carlo over the tier's magnitudes against these fluxes, ~0.15-0.25 for 3-4 stars), so
   ``E_false = H * C(..) * p^(s-2) * q``. It only ever adds evidence: a failed test (magnitude
   noise, a variable star) leaves the geometric confidence as it was; below ``min_confidence`` or fewer than
   ``min_matches`` matches: next region, or a refusal. H only grows, so once even ``s = n``
   cannot reach ``min_confidence`` the search stops at once with a refusal (three stars over the
   whole sky: after the first detection pair), and a hypothesis that can no longer reach the score it
   would need is dropped while it is scored ("Work budget and latency bound" below);
   Only the brightest ``max_detections`` (24) are scored (each one costs a partner table per anchor
   star: a real 11° frame with 64 detections built ~60 of them per search); tetra3rs verifies with all;
5. refinement: rotation and focal-length factor fitted to the matched stars (alternating
   Kabsch and the scale of a 2-D similarity between tangent-plane coordinates, k kept within
   1 ± s whichever pass found the hypothesis), re-matched at ``tol_px`` until the matches
   and k stop changing; the same at the camera's own scale (k = 1), kept where it matches more
   (a few stars a pixel off can pull a free scale away from the outer ones); the confidence above
   is recomputed from this tight match count and must still pass;
6. verification: tetra3rs tracking from that attitude (strict hint, 1°, the fitted focal length)
   re-matches every detection against its catalog, tests the match against its own
   false-positive budget and refines the attitude; an attitude that moves any of our matched stars
   beyond ``DISAGREE_FACTOR`` × ``tol_px`` matched other stars and confirms nothing. A candidate
   tetra3rs does not confirm is returned (as the least-squares rotation of our own matches) only if its confidence
   reaches ``unverified_confidence`` (1 - 1e-6); otherwise the next region is searched. Four or five stars are
   rarely confirmed (tetra3rs's own catalogue is denser, its bar its own), so one more piece of evidence counts
   there: **brightness order**. The detections a solver is given are a frame's brightest, so the true attitude's
   matched stars are their field's brightest, where a coincidence's are any of the cut's. Where no more than
   ``ORDER_MISSED`` (1) stars of the full cut on the sensor, brighter than the faintest matched star by
   ``ORDER_MARGIN_MAG`` (1 mag: colour, vignetting, saturation and tone curves reorder stars by less), were missed,
   E_false is multiplied by the chance q that a coincidence's stars do so (:meth:`CoarseToFineSolver._order_q`:
   exact per field for random sets of s stars, over 4,000 random fields of the camera; ~0.003 for four stars on
   11-20 deg cameras, none where a field holds a handful of stars). It reads magnitudes as the photometric test
   does, so it replaces that test's q where smaller rather than multiplying it, and it only ever adds evidence. A
   confirmation whose refined attitude leaves more than ``max_residual_px`` (1.5 px rms) over its
   matched stars and moves our own matches beyond ``tol_px`` took in a star beyond any centroid
   error (a bright star missing from the catalogue tier, matched to a neighbour) and is pulled off
   by it; neither that attitude nor the least-squares fit of our few matches is precise enough to
   return (measured: 0.1-0.2 deg off at N = 4-6), so the region's search goes on.

Regions are tried in order of prior probability (``top_k`` at most; ``few_top_k_factor`` times as many
for three detections), and with ``then_whole_sky`` the whole sky after them (region index -1; the
hypotheses of the prior's regions are counted again there, which only costs confidence; the focal-length pass
then searches the sky alone, not each region again: results/benchmark/work-budget); with
``whole_sky_from`` (the registered ``learned+fine>whole-sky``: :data:`WHOLE_SKY_FROM`), frames of that many
detections or more go to tetra3rs lost in space first and, where it refuses, to the whole sky at once, the prior
not consulted (region index -1) — the prior's coarse
regions, or, for a checkpoint trained with fine regions, its fine regions (a few degrees
across, :meth:`fusion.solve.priors.CheckpointPrior.at_level`), which narrow the search
about ten times more per region searched; the hypothesis count H accumulates, so searching
more regions demands stronger evidence. With ``sky_first_from`` (the registered chain: :data:`SKY_FIRST_FROM`,
4), frames of that many detections and fewer than ``whole_sky_from`` search the whole sky first, as the plain
whole-sky solver does, and only where it refuses the prior's regions (strict pass only: the sky's focal pass held
them), as a search of their own: its own H, the bar learned + fine answers with, so the chain's chance of a wrong
answer is at most the two searches' together (``extra["order"]`` says which answered). The cheaper certain answer
first: at N = 4 the sky answers most frames in ~1.2 ms, the prior's forward and regions cost ~2.2 ms first.
The prior is pluggable: any
:class:`fusion.solve.priors.RegionPrior`, or probabilities passed to
:meth:`CoarseToFineSolver.solve`. Doubtful candidates are :class:`~fusion.solve.base.Refusal`
values (the reason why, and a status code), never strings.

**Work budget and latency bound.** At most ``max_hypotheses`` units of work per solve, every pass and region
together: a hypothesis of the strict pass counts 1, one of the focal-length pass :data:`FOCAL_HYPOTHESIS_COST`
(3: what it costs against a strict one, measured), and with more than :data:`COST_REFERENCE_N` (6) detections
both count :func:`hypothesis_cost` times that ((N - 2) / 4: a hypothesis's time grows with the detections it
scores), so the budget bounds time in either pass and at any N (default:
:data:`MAX_HYPOTHESES` on every camera); where it runs out
without an accepted attitude the answer is a refusal with status ``budget_exhausted`` (``extra``: ``hypotheses``,
the count H, and ``work``, the units spent). A count, not a clock: the same frame gets the same answer on every
machine. The time of a solve is bounded by that count times the cost of one hypothesis (at most one partner scan
per other detection; ``max_detections`` bounds the detections), and both are cut where no answer can come of them:

* E_false only grows with H, so before each hypothesis the search knows the least score it could still be
  accepted with (:meth:`CoarseToFineSolver._h_limit`: the E_false bar per score, with the smallest q
  photometry can give, 1 / :data:`PHOTOMETRIC_SAMPLES`, for subsets and the all-detections q for all);
  scoring a hypothesis stops at the unmatched detection that puts that score out of reach (with four
  detections: at its first), and it is never returned. This drops nothing :meth:`CoarseToFineSolver._decide`
  could accept (the best score and its rivals are all kept), so answers are those of a full scoring;
* where not even every detection matched could pass, nothing more is scored and the search refuses
  (``weak_evidence``) after that detection pair: without photometry, four detections over the whole sky
  stop at about 18,000 hypotheses, not at the budget;
* the compiled loop (:func:`fusion.solve.match.anchor_hypotheses`) reads one row of the partner tables per
  hypothesis (star-major) and computes no trigonometry per candidate star; each anchor detection's tables
  are built once per pass (:meth:`CoarseToFineSolver._partners`); the focal-length pass, whose tolerances
  are several times wider (many candidates per detection, each a random read), puts each detection on the
  sky and tests the stars a cube-map grid files near it (:func:`fusion.solve.match.sky_grid`, built once per
  catalogue cut): the same matches, no partner tables;
* a prior's region does not scan the anchor pair's whole separation window for the rows whose first star lies
  in it: each window's rows are keyed on that star once per solve (:func:`fusion.solve.match.window_codes`) and
  a region's hypotheses listed from its own stars (:func:`fusion.solve.match.region_codes`), in the scan's
  order, so the same ones are tried (results/benchmark/overhead: 1,624 -> 740 ns per hypothesis at N = 4).

Measured (data/tails300, 300 rendered frames, seed 21, whole sky, ``focal_tol`` 0.02, one thread on a shared
2-core machine, before and after back to back: indicative): p99 per solve, refusals included, 175-285 ->
43-52 ms in the N = 4-5, false-star and 1 px centroid-noise cells (the frames refused at the budget or the
evidence bar), 24-62 -> 12-26 ms in the others; medians 6.4-11 -> 4.6-6.2 ms (21 -> 12 at 1 px noise); the
answers, refusal codes and hypothesis counts identical (and on a second seed, data/tails300b). Pure noise
(4-12 uniform detections, 200 sets): mean 311 -> 44 ms, p99 750 -> 117 ms; frames at a focal length 8 % off:
mean 238 -> 32 ms. Then a refusal at the budget cost its 150,000 hypotheses, a focal one ~3x a strict one; with
focal hypotheses counted 3 units of a 200,000 budget (results/benchmark/work-budget: held-out seed 41, 38 cells of
500 frames, one quiet core): the same answers in every cell, p99 over 20 ms in 16 -> 2 cells (2 and 4 px of
centroid noise at N = 6: 20.5, 23.6 ms), e.g. clean N = 4 / 5 17.7 / 29.4 -> 10.5 / 15.3 ms.

**Certificate.** A solution's ``false_match_probability`` is its E_false above with the catalogue's clustering
weighed in (so ``confidence = 1 - E_false``): stars crowd towards the Galaxy, hypotheses (catalogue pairs at the
right separation) crowd there with the density squared, and each further chance match with the density, so k
chance matches are :func:`density_clustering` (``E[rho^(2+k)] / (E[rho^2] E[rho]^k)``, rho over field-sized caps)
times likelier than the mean density says: 1.2 / 1.7 / 2.5 / 4.0 for k = 1-4 on the 20 deg camera's cut. The
bars (``min_confidence``, ``unverified_confidence``) stay on the mean-density E_false they were chosen and tested
on (``extra["false_match_probability_mean_density"]``): the same answers; only the number reported changed
(results/calibration/clustering: with the bars lifted, 1,385 wrong answers against a summed p of 323 before,
533 after). Its covariance is that of :func:`fusion.solve.base.attitude_covariance` from the stars it matched
(tetra3rs's matches where tetra3rs confirmed it).

**Tracking** (``solve(..., hint=M, hint_sigma_deg=s)``): :mod:`fusion.solve.track` (an identification
near the hint weighed by a likelihood; two detections can suffice).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .base import (
    HINT_RADIUS_SIGMAS,
    Detections,
    Refusal,
    Solution,
    attitude_covariance,
    photometric_zero_point,
    rotation_angle_deg,
    solution_from_matrix,
)
from .match import anchor_hypotheses, partner_table, refine_track, region_codes, sky_grid, window_codes
from .pairs import load_or_build

# the work budget per solve (hypotheses, both passes and every region together; one of the focal pass counts
# FOCAL_HYPOTHESIS_COST). Chosen from measurement: on 500 rendered frames x 38 cells (clean N = 3-10, every
# detection-level corruption at N = 4 and 6; data/bench500, seed 11) every correct whole-sky answer came within
# 164,102 units (the costliest: 2 px of centroid noise at N = 6, 130,868 strict + 11,078 focal hypotheses), and only
# 5 of 14,129 correct answers needed the focal pass at all, while refusals spent about a third of their hypotheses
# (and two thirds of their time) there; 200,000 keeps every answer of seed 11 and of a held-out seed (41: the
# costliest 192,032) and bounds a refusal's time by the strict pass's cost. (Until 2026-11-27: 150,000 hypotheses
# of either pass.) The same count on every camera: until 2026-11-28 the default grew with the catalogue cut's pairs
# per separation window (x 5.0 for the fitted Blackfly camera, x 4.0 for skysolve's, x 13.8 for openstartracker's),
# which kept a few hard answers and made refusals 4-14 times longer. On renders of the fitted Blackfly camera
# (300 frames, seed 41, 38 cells) the fixed budget gave the same answers in 35 of 38 cells (1 px of centroid noise at
# N = 6: 81 -> 67 %; 2 px: 8.7 -> 4.3 %; at N = 4 one frame) and p99 over 20 ms in 13 cells instead of 29 (the worst
# 129 -> 38 ms); on the real frames of seven cameras the same answers, skysolve's N = 5 p99 65 -> 18 ms
# (results/benchmark/dense-budget). A hypothesis costs about the same on any camera, so the count bounds the time
# alike, beside the partner tables a denser cut makes longer (~4 ms a solve on the fitted Blackfly's).
MAX_HYPOTHESES = 200_000
# the match tolerance (px) of a camera that does not give its own (camera.match_tol_px, which skygen fit-camera sets
# from how far its frames' brightest detections lie from their stars: skygen.real.fit_shift.match_tolerance)
TOL_PX = 2.0
# what one hypothesis of the focal-length pass costs against one of the strict pass, in the work budget: its wider
# tolerances test each detection on the sky grid (rotation, cube-map lookup) rather than in a partner table. Measured
# (benchmarks/pass_cost.py, data/bench500, whole sky, the compiled loop alone, one core): 41 vs 150 ns per hypothesis
# at N = 4, 83 vs 286 ns at N = 6, so 3: the budget is a count, the same on every machine, that bounds the time too.
FOCAL_HYPOTHESIS_COST = 3
# a hypothesis scores the detections beyond its anchor pair, so its time grows with them: measured per hypothesis
# of refusals (pure noise and other cameras' detection sets, whole sky, one core; results/benchmark/work-per-n)
# about 1 : 1.5 : 2 : 2.5 at N = 6 : 8 : 10 : 12, i.e. in proportion to N - 2. The budget was chosen at N <= 6
# (every correct answer of two seeds' benchmark cells within it), so up to COST_REFERENCE_N detections a hypothesis
# counts 1 and beyond it (N - 2) / (COST_REFERENCE_N - 2): a refusal of many detections then takes about the time
# of one of six, not twice or three times it (hypothesis_cost)
COST_REFERENCE_N = 6
REFERENCE_WINDOW_PAIRS = 7_120.0  # the 20 deg, 1024 px camera (configs/cameras/default-20deg.yaml): 7,113
NO_GRID = (np.zeros(1, np.int64), np.zeros((0, 3)), np.zeros(0, np.int32), np.zeros(5))  # anchor_hypotheses: none
NO_CODES = (False, np.zeros(0, np.int64))  # anchor_hypotheses: scan the rows (no region's list of them)
PHOTOMETRIC_SAMPLES = 4000  # Monte Carlo draws of the photometric q (CoarseToFineSolver._photometric_q): q >= 1 / this
# brightness order (CoarseToFineSolver._order_q): the detections a solver is given are a frame's brightest, so the
# stars of the true attitude are its field's brightest, where a chance match's are any of the catalogue cut's. A
# catalogue star of the full cut inside the sensor (ORDER_EDGE_PX from its edges) and brighter than the faintest
# matched star by more than ORDER_MARGIN_MAG (colour, vignetting, saturation and a tone curve reorder stars by less)
# that no detection matched is "missed"; at most ORDER_MISSED of them (a blend, a double star) and the order holds.
# Its chance q: exact for random sets of s stars of a field, over ORDER_POINTINGS random fields
ORDER_MARGIN_MAG = 1.0
ORDER_MISSED = 1
ORDER_EDGE_PX = 5.0
ORDER_POINTINGS = 4000
ORDER_PREPARED_UP_TO = 8  # the first solve makes q for 3 to this many matched stars; more, when first needed


def tolerance_of(tetra, tol_px: float | None) -> float:
    """The match tolerance (px): ``tol_px`` where given, else the camera's own (``camera.match_tol_px``, which
    skygen fit-camera sets from its frames' brightest detections), else :data:`TOL_PX`."""
    if tol_px is None:
        tol_px = getattr(tetra.camera, "match_tol_px", None) or TOL_PX
    if not tol_px > 0:
        raise ValueError(f"tol_px={tol_px!r}: a positive match tolerance (px)")
    return float(tol_px)


def hypothesis_cost(n: int) -> float:
    """Work-budget units of one strict-pass hypothesis scoring ``n`` detections (a focal-pass one: this times
    :data:`FOCAL_HYPOTHESIS_COST`): 1 up to :data:`COST_REFERENCE_N`, then ``(n - 2) / (COST_REFERENCE_N - 2)``."""
    return max(1.0, (n - 2) / (COST_REFERENCE_N - 2))


#: a refined focal factor this close to the edge of +-focal_tol (as a share of it) is refused: the camera's scale
#: would have to leave the range searched to fit the detections
FOCAL_EDGE = 0.98
# tetra3rs's tracking attitude does not confirm ours where it moves one of our matched stars beyond this many match
# tolerances (_finish): it matched other stars. Three, so that a centroid a pixel or two off (a saturated star, a
# field edge) never turns a confirmation into a refusal
DISAGREE_FACTOR = 3.0
REST_OF_SKY = -1  # Region.index of the sky outside the prior's regions (then_whole_sky)
# the learned chain (learned+fine>whole-sky) from this many detections: tetra3rs lost in space, then the whole sky at
# once, the prior not asked. There the whole sky alone was as often right as the prior's regions first (data/bench500,
# 150 frames, cpu-few prior; results/benchmark/whole-sky-from): N = 6 99 % both, and tetra3rs first made the chain's
# median 0.6 ms clean, 2.3 ms at 0.5 mag of magnitude noise (before: 8.8, 31.2 ms); N = 5 (since 2026-11-27) the same
# % clean and at 0.25 mag, 2 points fewer at 0.1 and 0.5 mag (3 of 150 frames), 8 more at 1 mag, and the chain's p99
# 4-5 times shorter (refused regions no longer precede the sky). At N = 4 the prior adds points (87 against 83 %)
WHOLE_SKY_FROM = 5
# the learned chain from this many detections (and fewer than WHOLE_SKY_FROM): the whole sky first, the prior's
# regions only where it refuses (their own search). Measured (results/benchmark/sky-first, two seeds, 300 frames,
# clean and 16 corrupted cells at N = 4, both orders interleaved in one process): the same answers in every cell;
# medians 2.2-2.9 -> 1.2-1.3 ms clean and within 3 ms in 12 of 16 corrupted cells (4-6 before), slower only where
# the sky refuses most frames (1-4 px of centroid noise, 8 false stars); p99 within 18 ms. At N = 3 the sky answers
# a third of frames, so the prior stays first there
SKY_FIRST_FROM = 4
TRACKING = -2  # Region.index of a tracking hint's region
FEW_TOP_K_FACTOR = 4  # three detections: this many times top_k regions (see solve)


@dataclass(frozen=True)
class Region:
    center: np.ndarray  # (3,) ICRS unit vector
    radius_deg: float  # every boresight of the region lies within this angle of the centre
    probability: float
    index: int  # the prior's region, or REST_OF_SKY (then_whole_sky) or TRACKING (a tracking hint's)
    x_axis: np.ndarray | None = None  # a tracking hint's camera +x (ICRS): the roll is bounded too


def hint_region(hint: np.ndarray, hint_sigma_deg: float) -> Region:
    """The region a tracking hint (camera -> ICRS matrix, 1-sigma ``hint_sigma_deg``) leaves: attitudes within
    ``HINT_RADIUS_SIGMAS`` sigma of it, i.e. boresight and camera +x axis both within that angle of the hint's
    (a rotation by an angle moves no axis farther than that angle)."""
    if not (np.isfinite(hint_sigma_deg) and 0 < hint_sigma_deg <= 60):
        raise ValueError(f"hint_sigma_deg={hint_sigma_deg}: the hint's 1-sigma error, in (0, 60] degrees")
    m = np.asarray(hint, np.float64)
    if m.shape != (3, 3) or not np.abs(m.T @ m - np.eye(3)).max() <= 1e-6 or np.linalg.det(m) < 0:
        raise ValueError("hint: a 3 x 3 rotation matrix (camera -> ICRS), e.g. the previous Solution.matrix")
    radius = min(180.0, HINT_RADIUS_SIGMAS * float(hint_sigma_deg))
    return Region(np.ascontiguousarray(m[:, 2]), radius, 1.0, TRACKING, np.ascontiguousarray(m[:, 0]))


def region_radii_deg(centroids: np.ndarray, n_samples: int = 200_000) -> np.ndarray:
    """Circumradius of each max-cosine (Voronoi) cell on the sphere, from a Fibonacci lattice, degrees."""
    c = np.asarray(centroids, np.float64)
    if len(c) == 1:
        return np.array([180.0])
    k = np.arange(n_samples) + 0.5
    z = 1 - 2 * k / n_samples
    phi = np.pi * (1 + 5**0.5) * k
    r = np.sqrt(1 - z * z)
    v = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    dots = v @ c.T
    lab = np.argmax(dots, axis=1)
    best = dots[np.arange(n_samples), lab]
    radii = np.zeros(len(c))
    np.maximum.at(radii, lab, np.degrees(np.arccos(np.clip(best, -1, 1))))
    spacing = np.degrees(np.sqrt(4 * np.pi / n_samples))  # lattice spacing: the radius is at most this short
    return radii + spacing


def _unit_at(t: np.ndarray, k) -> np.ndarray:
    """Unit camera vectors of tangent-plane points ``t`` (n, 2) at focal-length factor(s) ``k`` (scalar or (P,))."""
    k = np.asarray(k, np.float64)
    tk = t / k[..., None, None] if k.ndim else t / k
    v = np.concatenate([tk, np.ones(tk.shape[:-1] + (1,))], axis=-1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _angle_at(ti: np.ndarray, tk: np.ndarray, f: float) -> float:
    """Angle between two tangent-plane points seen at focal-length factor ``f``."""
    ax, ay, bx, by = float(ti[0]) / f, float(ti[1]) / f, float(tk[0]) / f, float(tk[1]) / f
    c = (ax * bx + ay * by + 1.0) / math.sqrt((ax * ax + ay * ay + 1.0) * (bx * bx + by * by + 1.0))
    return math.acos(min(1.0, c))


@dataclass
class _Tier:
    """One catalogue cut: the brightest ``stars_per_fov`` stars per field, their index and chance rate."""

    stars_per_fov: float
    vec: np.ndarray
    ids: np.ndarray
    mag: np.ndarray
    tree: cKDTree
    pairs: object
    p_chance: float
    clustering: np.ndarray | None = None  # density_clustering of vec (None: the mean density alone)
    grid: tuple | None = None  # the focal pass's sky grid (fusion.solve.match.sky_grid), None: partner tables
    draws: dict = field(default_factory=dict)  # _photometric_q's magnitude draws, by (samples, detections)


def _focal_grid(vec: np.ndarray, tk_max: float) -> tuple | None:
    """:func:`fusion.solve.match.sky_grid` of ``vec`` for tolerances up to ``tk_max`` (rad): a margin that holds
    every query (stretch x tolerance), cells of about one query's width; None where no margin up to 0.5 does."""
    margin = 0.05
    while (1 + 2 * (1 + margin) ** 2) * tk_max * 1.01 > margin:
        margin *= 1.5
        if margin > 0.5:
            return None
    cell = max((1 + 2 * (1 + margin) ** 2) * tk_max, (2 + 2 * margin) / 512)
    return sky_grid(np.ascontiguousarray(vec), margin, cell)


def magnitude_scatter(mag: np.ndarray, flux: np.ndarray) -> np.ndarray:
    """Scatter (mag) of catalogue magnitudes about the detections' instrumental magnitudes
    -2.5 log10(flux) once their common zero point is removed: the sample standard deviation of
    ``mag - inst`` along the last axis (``mag`` (..., m), ``flux`` (m,))."""
    inst = -2.5 * np.log10(np.maximum(np.asarray(flux, np.float64), 1e-12))
    d = np.asarray(mag, np.float64) - inst
    return np.std(d, axis=-1, ddof=1)


def _chance_sum(p: float, n_det: int, score: int, clustering: np.ndarray | None = None) -> float:
    """P(at least ``score - 2`` of the ``n_det - 2`` other detections land on a star by chance); ``clustering``
    (:func:`density_clustering`): the term of k chance stars weighed by ``clustering[k]`` (1 where not given)."""
    extra = score - 2
    if extra <= 0:
        return 1.0
    w = (lambda k: 1.0) if clustering is None else (lambda k: float(clustering[min(k, len(clustering) - 1)]))
    return sum(w(k) * math.comb(n_det - 2, k) * p**k * (1 - p) ** (n_det - 2 - k) for k in range(extra, n_det - 1))


def density_clustering(vec: np.ndarray, radius_rad: float, k_max: int = 8, pointings: int = 20_000) -> np.ndarray:
    """(k_max + 1,): how much more often k chance matches happen than the sky's mean density says, because the
    catalogue's stars cluster (the Galaxy: fields in the plane hold several times the stars of those at the
    poles). A hypothesis needs a catalogue pair at the detections' separation, so hypotheses fall on a field in
    proportion to its density squared, and each further detection lands on a star with a chance proportional to
    the density there: the expected number of chance matches with k extra stars is
    ``E[rho^(2+k)] / (E[rho^2] E[rho]^k)`` times what the mean density gives (Jensen's inequality: >= 1, growing
    with k). rho: the stars within ``radius_rad`` (the field's) of ``pointings`` fixed pseudo-random directions;
    its moments from the counts' factorial moments (unbiased for a Poisson count about the local density), so
    the count's own shot noise does not inflate them. Deterministic (fixed seed)."""
    rng = np.random.default_rng(0x5EED)
    x = rng.normal(size=(pointings, 3))
    x /= np.linalg.norm(x, axis=1)[:, None]
    counts = cKDTree(vec).query_ball_point(x, 2 * math.sin(radius_rad / 2), return_length=True).astype(np.float64)
    moment = [1.0]  # E[rho^m] by the factorial moments E[c (c - 1) ... (c - m + 1)]
    fall = np.ones_like(counts)
    for m in range(1, k_max + 3):
        fall = fall * np.maximum(counts - (m - 1), 0.0)
        moment.append(float(np.mean(fall)))
    if moment[1] <= 0 or moment[2] <= 0:
        return np.ones(k_max + 1)
    out = np.array([moment[2 + k] / (moment[2] * moment[1] ** k) for k in range(k_max + 1)])
    return np.maximum(out, 1.0)


class CoarseToFineSolver:
    """Region prior -> region-restricted identification -> tetra3rs verification. See the module docstring."""

    def __init__(
        self,
        tetra,
        prior=None,
        *,
        name: str = "coarse-to-fine",
        top_k: int = 3,
        tol_px: float | None = None,
        stars_per_fov: float = 60.0,
        max_pair_detections: int = 5,
        min_matches: int = 3,
        min_confidence: float = 0.99,
        unverified_confidence: float = 1 - 1e-6,
        tracking_unverified_confidence: float = 1 - 1e-3,
        verify_with_tetra3rs: bool = True,
        focal_tol: float = 0.0,
        anchor_order: str = "fewest",
        bright_stars_per_fov: float | None = 12.0,
        bright_max_detections: int = 3,
        photometric_mag: float | None = 0.5,
        max_residual_px: float = 1.5,
        few_top_k_factor: int = FEW_TOP_K_FACTOR,
        then_whole_sky: bool = False,
        whole_sky_from: int | None = None,
        sky_first_from: int | None = None,
        max_detections: int | None = 24,
        max_hypotheses: int | None = None,
        clustering: bool = True,
    ):
        if not 0.0 <= focal_tol < 0.2:
            raise ValueError(f"focal_tol={focal_tol}: the relative focal-length uncertainty must be in [0, 0.2)")
        self.tetra, self.prior, self.name = tetra, prior, name
        tol_px = tolerance_of(tetra, tol_px)
        self.focal_tol = float(focal_tol)
        if anchor_order not in ("fewest", "brightest"):
            raise ValueError(f"anchor_order={anchor_order!r}: 'fewest' or 'brightest'")
        self.anchor_order = anchor_order
        self.top_k, self.tol_px, self.min_matches, self.min_confidence = top_k, tol_px, min_matches, min_confidence
        self.few_top_k_factor = int(few_top_k_factor)
        self.then_whole_sky = bool(then_whole_sky)
        if whole_sky_from is not None and (not then_whole_sky or whole_sky_from < 3):
            raise ValueError(f"whole_sky_from={whole_sky_from!r}: at least 3 detections, and only with then_whole_sky")
        self.whole_sky_from = whole_sky_from
        if sky_first_from is not None and (
            not then_whole_sky
            or sky_first_from < 3
            or (whole_sky_from is not None and sky_first_from >= whole_sky_from)
        ):
            raise ValueError(
                f"sky_first_from={sky_first_from!r}: at least 3 detections, fewer than whole_sky_from "
                f"({whole_sky_from}), and only with then_whole_sky"
            )
        self.sky_first_from = sky_first_from
        self._strict_only = False  # the prior's regions after the sky (sky_first_from): the sky's focal pass held them
        if max_detections is not None and max_detections < 3:
            raise ValueError(f"max_detections={max_detections}: at least 3, or None (all)")
        self.max_detections = max_detections
        if max_hypotheses is not None and (
            isinstance(max_hypotheses, bool) or not isinstance(max_hypotheses, int) or max_hypotheses < 1
        ):
            raise ValueError(f"max_hypotheses={max_hypotheses!r}: a positive number of hypotheses per solve, or None")
        self.max_pair_detections, self.verify = max_pair_detections, verify_with_tetra3rs
        self.unverified_confidence = unverified_confidence
        self.tracking_unverified_confidence = tracking_unverified_confidence
        self.bright_max_detections = int(bright_max_detections)
        if photometric_mag is not None and not photometric_mag > 0:
            raise ValueError(f"photometric_mag={photometric_mag}: a positive magnitude scatter, or None (off)")
        self.photometric_mag = photometric_mag
        self.clustering = bool(clustering)  # E_false weighs chance matches by the catalogue's clustering
        if not max_residual_px > 0:
            raise ValueError(f"max_residual_px={max_residual_px}: a positive residual (px)")
        self.max_residual_px = float(max_residual_px)
        cam = tetra.camera
        db = tetra.db
        stars = [db.get_star(i) for i in range(db.num_stars)]
        ra = np.radians([s.ra_deg for s in stars])
        dec = np.radians([s.dec_deg for s in stars])
        mag = np.array([s.magnitude for s in stars])
        ids = np.array([s.id for s in stars], np.int64)
        fov_sr = 4 * math.atan(
            cam.width_px * cam.height_px / (2 * cam.f_px * math.hypot(cam.width_px, cam.height_px, 2 * cam.f_px))
        )  # solid angle of the rectangular pinhole field
        self._fov_sr = fov_sr
        self.tol_rad = tol_px / cam.f_px
        self.half_diag_rad = math.atan(math.hypot(cam.width_px, cam.height_px) / 2 / cam.f_px)
        # every catalog pair closer than the field's diagonal (at the longest focal length searched), by separation
        max_sep = (2 * self.half_diag_rad + 2 * self.tol_rad) * (1 + self.focal_tol)
        unit = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=1)
        order = np.argsort(mag, kind="stable")
        self.tiers = []
        for spf in (stars_per_fov,) + ((bright_stars_per_fov,) if bright_stars_per_fov else ()):
            keep = order[: int(min(len(stars), spf * 4 * math.pi / fov_sr))]
            vec = unit[keep]
            self.tiers.append(
                _Tier(
                    spf,
                    vec,
                    ids[keep],
                    mag[keep],
                    cKDTree(vec),
                    load_or_build(vec, max_sep, getattr(tetra, "db_folder", None), getattr(tetra, "log", None)),
                    # chance that a random direction has a catalog star within tol
                    min(1.0, len(vec) / (4 * math.pi) * math.pi * self.tol_rad**2),
                    density_clustering(vec, self.half_diag_rad) if self.clustering else None,
                )
            )
        if self.focal_tol > 0:
            # the focal pass's widest tolerance: tol + focal_tol times the farthest two detections can be apart
            far = 2.5 * math.tan(self.half_diag_rad)  # (and a margin: distortion, detections off the corners)
            for tier in self.tiers:
                tier.grid = _focal_grid(tier.vec, self.tol_rad + self.focal_tol * far)
        row_of = {int(x): r for r, x in enumerate(self.tiers[0].ids)}
        self._bright_rows = np.array([row_of.get(int(x), -1) for x in self.tiers[-1].ids], np.int64)
        # _order_q's random fields ("fields": their stars' magnitudes) and its q by matched stars: made once, filled in
        # place (the object's attributes stay as they are: one solver serves interleaved solves)
        self._order_cache: dict = {}
        self.radii = None if prior is None else region_radii_deg(prior.centroids)
        # the catalogue cut's pairs per separation window, relative to the 20 deg camera's (what makes a denser cut try
        # more hypotheses for the same frame; the budget does not follow it: see MAX_HYPOTHESES)
        self.window_density = len(self.tiers[0].pairs.sep) * 4 * self.tol_rad / max_sep / REFERENCE_WINDOW_PAIRS
        self.max_hypotheses = MAX_HYPOTHESES if max_hypotheses is None else max_hypotheses

    # ---------------------------------------------------------------- regions
    def regions(self, probs: np.ndarray | None, centroids: np.ndarray | None, top_k: int | None = None) -> list[Region]:
        if probs is None:
            return [Region(np.array([0.0, 0.0, 1.0]), 180.0, 1.0, 0)]
        radii = (
            self.radii if self.radii is not None and len(self.radii) == len(centroids) else region_radii_deg(centroids)
        )
        order = np.argsort(-np.asarray(probs), kind="stable")[: top_k or self.top_k]
        return [Region(np.asarray(centroids[k], np.float64), float(radii[k]), float(probs[k]), int(k)) for k in order]

    # ---------------------------------------------------------------- search
    def _hypotheses(
        self, tier: _Tier, u: np.ndarray, region: Region, s: float, tables: dict, budget: int, h0: int, h_limit
    ):
        """Per pair of bright detections: (rotations, focal factors, match counts, hypotheses tried, best score,
        stopped) of the hypotheses in ``region`` with at least 3 matches and the matches they need to be
        accepted (:func:`fusion.solve.match.anchor_hypotheses`; ``h0``: the solve's hypotheses before these,
        ``h_limit``: :meth:`_h_limit`, read afresh for every pair), at most ``budget`` hypotheses in all (the
        last pair's are cut short where it runs out)."""
        idx = tier.pairs
        cap = np.radians(region.radius_deg) + (self.half_diag_rad + self.tol_rad) * (1 + self.focal_tol)
        star_ok = (tier.vec @ region.center >= math.cos(cap)) if cap < math.pi else np.ones(len(tier.vec), bool)
        cos_r = math.cos(math.radians(region.radius_deg))
        t, anchors = self._anchors(tier, u, s, tables)
        # a region's stars A: its hypotheses listed from them (the rows of each window keyed on A, built once per
        # solve), not found by scanning the window's rows for the few whose A lies in it
        rows = np.flatnonzero(star_ok) if cap < math.pi else None
        for i, j, lo, hi, tol_n, grid in anchors:
            offs, partner, psep = self._partners(tier, i, j, t, s, tables, grid is None)
            codes = NO_CODES
            if rows is not None:
                key = ("window", lo, hi)
                if key not in tables:
                    tables[key] = window_codes(lo, hi, idx.first, idx.second, len(tier.vec))
                codes = (True, region_codes(*tables[key], rows))
            tried, _, _, ks, scores, rots, best, stopped = anchor_hypotheses(
                i,
                j,
                t,
                lo,
                hi,
                idx.first,
                idx.second,
                idx.sep,
                tier.vec,
                star_ok,
                s,
                tol_n,
                offs,
                partner,
                psep,
                region.center,
                cos_r,
                3,
                budget,
                region.center if region.x_axis is None else region.x_axis,
                -2.0 if region.x_axis is None else cos_r,
                h0,
                h_limit,
                *(grid or NO_GRID),
                *codes,
            )
            budget -= tried
            h0 += tried
            yield rots, ks, scores, tried, best, stopped

    def _anchors(self, tier: _Tier, u: np.ndarray, s: float, tables: dict) -> tuple[np.ndarray, list]:
        """(tangent-plane coordinates of the detections at the nominal focal length, the anchor pairs to search in
        order: (i, j, catalogue pair range lo, hi, each detection's tolerance, the sky grid or None)) of one pass:
        they depend on the detections and the pass, not on the region, so they are built once per solve
        (``tables``; a learned prior's 80 regions at N = 3 had rebuilt them 80 times)."""
        key = ("anchors", s)
        if key in tables:
            return tables[key]
        idx, tol = tier.pairs, self.tol_rad
        n = len(u)
        m = min(n, self.max_pair_detections)
        t = np.ascontiguousarray(u[:, :2] / u[:, 2:3])
        pairs = []
        for i in range(m):
            for j in range(i + 1, m):
                d = math.acos(min(1.0, float(u[i] @ u[j])))
                lo, hi = idx.range(d / (1 + s) - 2 * tol, d / (1 - s) + 2 * tol)
                pairs.append((hi - lo, i, j, d, lo, hi))
        if self.anchor_order == "fewest":
            pairs.sort()
        anchors = []
        for _, i, j, d, lo, hi in pairs:
            if hi <= lo:
                continue
            if s > 0:  # what the pair leaves uncertain of the scale, times the distance from detection i
                tol_n = tol + min(s, 2 * tol / max(d, 1e-12)) * np.hypot(*(t - t[i]).T)
            else:
                tol_n = np.full(n, tol)
            # the focal pass reads the sky grid where its margin holds every tolerance (else the partner tables)
            grid = tier.grid if s > 0 and tier.grid is not None else None
            if grid is not None and float(np.max(tol_n)) * grid[3][4] > grid[3][3]:
                grid = None
            anchors.append((i, j, lo, hi, tol_n, grid))
        tables[key] = t, anchors
        return tables[key]

    def _partners(self, tier: _Tier, i: int, j: int, t: np.ndarray, s: float, tables: dict, needed: bool = True):
        """The partner tables of detection pairs (i, k) for every k but i, concatenated (see
        :func:`fusion.solve.match.partner_table`; :func:`~fusion.solve.match.anchor_hypotheses` skips j's);
        built once per solve, anchor detection i and pass, whatever the number of regions and of partners j
        searched (``tables``). ``needed`` False (the focal pass reads the sky grid): empty ones."""
        n = len(t)
        if not needed:
            return np.zeros((1, n), np.int64), np.zeros(0, np.int32), np.zeros(0)
        key = ("i", i, s)
        if key in tables:
            return tables[key]
        idx, tol, n_stars = tier.pairs, self.tol_rad, len(tier.vec)
        offs = np.zeros((n_stars + 1, n), np.int64)  # star-major: a hypothesis reads one row
        parts, seps, base = [], [], 0
        for k in range(n):
            if k == i:
                continue
            # the separation of i and k over the focal factors 1 -s .. 1 + s, widened by k's largest tolerance
            near = [_angle_at(t[i], t[k], f) for f in (1 + s, 1 - s)]
            tk = tol + s * math.hypot(t[k, 0] - t[i, 0], t[k, 1] - t[i, 1])
            lo, hi = idx.range(min(near) - tk, max(near) + tk)
            # the window is symmetric in i and k: (k, i)'s table, where anchor k built it, is this one
            pkey = ("partner", lo, hi)
            if pkey not in tables:
                tables[pkey] = partner_table(lo, hi, idx.first, idx.second, idx.sep, n_stars)
            o, p, q = tables[pkey]
            offs[:, k] = o + base
            parts.append(p)
            seps.append(q)
            base += len(p)
        partner = np.concatenate(parts) if parts else np.zeros(0, np.int32)
        psep = np.concatenate(seps) if seps else np.zeros(0)
        tables[key] = offs, partner, psep
        return tables[key]

    def _matches(self, tier: _Tier, rot: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dist, idx = tier.tree.query(u @ rot.T, distance_upper_bound=2 * math.sin(self.tol_rad / 2))
        ok = np.isfinite(dist)
        return np.flatnonzero(ok), idx[ok]

    def expected_false(
        self,
        n_hypotheses: int,
        n_det: int,
        score: int,
        q: float = 1.0,
        tier: _Tier | None = None,
        clustered: bool = False,
    ) -> float:
        """E_false: the expected number of coincidental hypotheses with ``score`` or more matches (see module
        doc), with the chance rate of the catalogue tier being searched; ``q``: the chance that a coincidental
        match also passes the photometric test (1: not tested); ``clustered``: k chance matches weighed by the tier's
        :func:`density_clustering` (what a solution reports; the bars are on the mean density's). Infinite for two
        matches or fewer."""
        tier = tier or self.tiers[0]
        if score - 2 <= 0:
            return math.inf
        clustering = tier.clustering if clustered else None
        return float(n_hypotheses * _chance_sum(tier.p_chance, n_det, score, clustering) * q)

    def confidence(self, n_hypotheses: int, n_det: int, score: int, q: float = 1.0, tier: _Tier | None = None) -> float:
        """``max(0, 1 - E_false)`` (:meth:`expected_false`)."""
        return float(max(0.0, 1.0 - self.expected_false(n_hypotheses, n_det, score, q, tier)))

    def _h_limit(self, tier: _Tier, flux: np.ndarray, n: int, q_all: float | None = None) -> np.ndarray:
        """(n + 1,): the largest H at which a hypothesis with s matches can still be accepted
        (``expected_false(H, n, s, q) <= 1 - min_confidence``), -1 where never (s < 3 or below ``min_matches``).
        A hypothesis accepted at H was tried at H or before, so one tried later than ``h_limit[s]`` with fewer
        than s + 1 matches can be dropped: it could never pass :meth:`_decide` (which, H only growing, never
        revisits a smaller H). Photometry can lower E_false by q, so where it could apply the limit assumes the
        smallest q :meth:`_photometric_q` can return (:data:`PHOTOMETRIC_SAMPLES` of them: 1 / samples) for a
        subset of the detections, and ``q_all`` (the value of all n, once computed) for all n: the same bound
        the search's stop after each detection pair uses."""
        bar = 1.0 - self.min_confidence
        phot = self.photometric_mag is not None and n >= 3 and bool(np.all(flux > 0))
        out = np.full(n + 1, -1.0)
        for s in range(max(3, self.min_matches), n + 1):
            q = (q_all if q_all is not None and s == n else 1.0 / PHOTOMETRIC_SAMPLES) if phot else 1.0
            e1 = self.expected_false(1, n, s, q, tier=tier)  # E_false per hypothesis
            out[s] = bar / e1 * (1 + 1e-9) if e1 > 0 else math.inf
        return out

    # ---------------------------------------------------------------- photometry
    def _photometric_q(self, tier: _Tier, flux: np.ndarray, samples: int = PHOTOMETRIC_SAMPLES) -> float:
        """Chance that random stars of the tier, one per detection of ``flux``, pass the photometric test
        against these detections: a Monte Carlo over the tier's magnitudes (fixed seed), plus two
        standard errors and 1/samples, so the bound errs on the side of less confidence."""
        if self.photometric_mag is None or len(flux) < 3 or np.any(flux <= 0):
            return 1.0
        m = len(flux)
        draw = tier.draws.get((samples, m))
        if draw is None:  # the same draws for every call with m detections: kept, centred, with their squares summed
            rng = np.random.default_rng(0x9407)
            mags = np.asarray(tier.mag[rng.integers(0, len(tier.mag), (samples, m))], np.float64)
            centred = mags - mags.mean(axis=1, keepdims=True)
            draw = tier.draws[(samples, m)] = (centred, np.einsum("ij,ij->i", centred, centred))
        centred, ss = draw
        # magnitude_scatter of every draw, as a variance: sum((a - b - mean)^2) = S_aa - 2 S_ab + S_bb
        inst = -2.5 * np.log10(np.asarray(flux, np.float64))
        b = inst - inst.mean()
        var = (ss - 2.0 * (centred @ b) + b @ b) / (m - 1)
        q = float(np.mean(var <= self.photometric_mag**2))
        return min(1.0, q + 2 * math.sqrt(q * (1 - q) / samples) + 1.0 / samples)

    def _photometric_pass(self, tier: _Tier, cat_rows: np.ndarray, det_rows: np.ndarray, flux: np.ndarray) -> bool:
        """Do the matched stars' catalogue magnitudes follow the detections' fluxes within
        ``photometric_mag`` (after a common zero point)? At least three matched stars with positive flux."""
        if self.photometric_mag is None or len(det_rows) < 3 or np.any(flux[det_rows] <= 0):
            return False
        return bool(magnitude_scatter(tier.mag[cat_rows], flux[det_rows]) <= self.photometric_mag)

    # ---------------------------------------------------------------- brightness order
    def _field_mags(self, rot: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray]:
        """(ids, magnitudes) of the full cut's stars that attitude ``rot`` (camera -> ICRS) puts on ``camera``'s
        sensor, :data:`ORDER_EDGE_PX` inside its edges."""
        tier = self.tiers[0]
        rows = np.asarray(tier.tree.query_ball_point(rot[:, 2], 2 * math.sin(1.05 * self.half_diag_rad / 2)), np.int64)
        if not len(rows):
            return np.zeros(0, np.int64), np.zeros(0)
        x, y, front = camera.project(tier.vec[rows] @ rot)
        rows = rows[front & camera.inside(x, y, -ORDER_EDGE_PX)]
        return tier.ids[rows], tier.mag[rows]

    def _order_holds(self, tier: _Tier, rot: np.ndarray, camera, cat_rows: np.ndarray) -> bool:
        """Are the matched stars (``cat_rows`` of ``tier``) their field's brightest: at most :data:`ORDER_MISSED`
        unmatched stars of the full cut on the sensor brighter than the faintest of them by
        :data:`ORDER_MARGIN_MAG`?"""
        ids, mags = self._field_mags(rot, camera)
        faint = float(np.max(tier.mag[cat_rows]))
        missed = (mags < faint - ORDER_MARGIN_MAG) & ~np.isin(ids, tier.ids[cat_rows])
        return int(missed.sum()) <= ORDER_MISSED

    def _random_fields(self) -> np.ndarray:
        """(:data:`ORDER_POINTINGS`, most stars in one): the magnitudes, sorted, of the full cut's stars on the nominal
        camera's sensor (:data:`ORDER_EDGE_PX` inside) at as many random attitudes (fixed seed), padded with inf:
        :meth:`_order_q`'s fields."""
        from scipy.spatial.transform import Rotation

        rots = Rotation.random(ORDER_POINTINGS, random_state=0x0D0E).as_matrix()
        fields = [np.sort(self._field_mags(rot, self.tetra.camera)[1]) for rot in rots]
        out = np.full((len(fields), max(1, max(len(f) for f in fields))), np.inf)
        for i, f in enumerate(fields):
            out[i, : len(f)] = f
        return out

    def _order_q(self, s: int) -> float:
        """Chance that ``s`` stars matched by coincidence pass :meth:`_order_holds`: a coincidence picks its stars
        with no regard to their brightness, so for a field of n stars (magnitudes sorted, m_1 the brightest) and a
        set of s of them drawn at random, the faintest drawn is the j-th with chance C(j - 1, s - 1) / C(n, s), and
        the other s - 1 are drawn from the j - 1 brighter ones: how many of the b_j stars brighter than m_j by
        :data:`ORDER_MARGIN_MAG` they take is hypergeometric, and the order holds where it is at least
        b_j - :data:`ORDER_MISSED`. Exact per field, averaged over :data:`ORDER_POINTINGS` random attitudes of the
        nominal camera (fixed seed), plus two standard errors of that mean and one over the pointings. Attitudes are
        drawn uniformly, though coincidences crowd where stars do (:func:`density_clustering`): there a field holds
        more bright stars to miss, so the uniform draw errs on the side of a larger q. Fields with fewer than ``s``
        stars cannot hold such a match and are not counted."""
        from scipy.special import gammaln

        cache = self._order_cache
        if s in cache:
            return cache[s]
        if "fields" not in cache:
            cache["fields"] = self._random_fields()
        mags = cache["fields"]
        n = np.sum(np.isfinite(mags), axis=1)
        mags, n = mags[n >= s], n[n >= s]
        q, sd = 1.0, 0.0
        if len(mags):
            j = np.arange(1, mags.shape[1] + 1)[None, :]  # the faintest drawn star's rank, 1-based
            ok = (j >= s) & (j <= n[:, None])
            # b_j: the stars brighter than the j-th by the margin (rows sorted: one search over the rows laid end to
            # end, each offset past the last)
            finite = np.where(np.isfinite(mags), mags, 1e3)
            offset = 1e4 * np.arange(len(mags))[:, None]
            flat = (finite + offset).ravel()
            b = np.searchsorted(flat, (finite - ORDER_MARGIN_MAG + offset).ravel()).reshape(mags.shape)
            b = b - mags.shape[1] * np.arange(len(mags))[:, None]

            lf = gammaln(np.arange(mags.shape[1] + 2) + 1.0)  # log k!

            def lcomb(a, k):  # log C(a, k) for 0 <= k <= a (else anything: masked)
                a, k = np.clip(a, 0, len(lf) - 1), np.clip(k, 0, None)
                return lf[a] - lf[np.minimum(k, a)] - lf[np.clip(a - k, 0, None)]

            # only where the s - 1 others can take all but ORDER_MISSED of the b_j is there anything to add
            rows, cols = np.nonzero(ok & (b <= s - 1 + ORDER_MISSED))
            pop, b = cols, b[rows, cols]  # j - 1 (cols are 0-based ranks)
            w = np.exp(lcomb(pop, s - 1) - lcomb(n[rows], s))
            p = np.zeros(len(rows))
            for x in range(s):
                valid = (x <= b) & (s - 1 - x <= pop - b) & (x >= b - ORDER_MISSED)
                p += np.where(valid, np.exp(lcomb(b, x) + lcomb(pop - b, s - 1 - x) - lcomb(pop, s - 1)), 0.0)
            per_field = np.bincount(rows, weights=w * p, minlength=len(mags))
            q, sd = float(np.mean(per_field)), float(np.std(per_field) / math.sqrt(len(per_field)))
            q = min(1.0, q + 2 * sd + 1.0 / len(per_field))
        cache[s] = q
        return q

    def _decide(
        self,
        tier: _Tier,
        rots: np.ndarray,
        ks: np.ndarray,
        scores: np.ndarray,
        tried: int,
        u: np.ndarray,
        flux: np.ndarray,
    ) -> int | Refusal:
        """Index of the accepted hypothesis, or a refusal saying why none is accepted yet. Geometry alone
        decides where it can; where it cannot, catalogue magnitudes that follow the detected fluxes
        (:meth:`_photometric_pass`) are further evidence: a coincidental match passes that test only
        with chance q (:meth:`_photometric_q`), so its expected number shrinks by q."""
        n = len(u)
        best = int(np.argmax(scores))
        s = int(scores[best])
        rivals = np.flatnonzero(scores == s)
        if any(rotation_angle_deg(rots[best], rots[k]) > 0.5 for k in rivals):
            return Refusal(f"ambiguous: several attitudes match {s} of {n} detections", self.name, status="ambiguous")
        conf = self.confidence(tried, n, s, tier=tier)
        if s >= self.min_matches and conf < self.min_confidence and self.photometric_mag is not None:
            det_rows, cat_rows = self._matches(tier, rots[best], _unit_at(u[:, :2] / u[:, 2:3], ks[best]))
            if self._photometric_pass(tier, cat_rows, det_rows, flux):
                conf = self.confidence(tried, n, s, self._photometric_q(tier, flux[det_rows]), tier=tier)
        if s < self.min_matches or conf < self.min_confidence:
            return Refusal(
                f"weak evidence: {s} of {n} detections matched, confidence {conf:.3g}",
                self.name,
                status="weak_evidence",
            )
        return best

    def solve(
        self,
        detections: Detections,
        camera=None,
        image=None,
        probabilities: np.ndarray | None = None,
        hint: np.ndarray | None = None,
        hint_sigma_deg: float = 1.0,
        hint_zero_point: float | None = None,
    ) -> Solution | Refusal:
        """An attitude or a refusal (module docstring). ``probabilities``: the regions' prior (default: the
        solver's prior's). ``hint``: tracking; a camera -> ICRS matrix (the previous frame's
        :attr:`Solution.matrix`) with 1-sigma error ``hint_sigma_deg``: the one region searched is every
        attitude within 3 sigma of it (:func:`hint_region`), the prior is not consulted, and the identification
        is weighed by a likelihood (module docstring, "Tracking"): two stars can suffice. ``hint_zero_point``
        (tracking only): the photometric zero point the previous frame measured (its solution's
        ``extra["zero_point"]``, catalogue magnitude minus -2.5 log10 flux), which the likelihood then holds each
        identification's to."""
        if self.verify and "fields" not in self._order_cache:
            # the brightness order's chances, made once (~0.5-1 s) on the first solve rather than inside a later
            # one's time: benchmarks' untimed warm-up solves take it
            for s in range(3, ORDER_PREPARED_UP_TO + 1):
                self._order_q(s)
        t0 = time.perf_counter()
        tracking = hint_region(hint, hint_sigma_deg) if hint is not None else None
        if hint_zero_point is not None and not np.isfinite(hint_zero_point):
            raise ValueError(f"hint_zero_point={hint_zero_point}: a finite magnitude (the previous frame's zero point)")
        camera = camera or self.tetra.camera

        def ms():
            return (time.perf_counter() - t0) * 1e3

        if tracking is not None:
            if len(detections) < 2:
                return Refusal(f"too few detections ({len(detections)})", self.name, ms(), status="too_few_stars")
            if self.max_detections is not None and len(detections) > self.max_detections:
                detections = detections.brightest(self.max_detections)
            return self._track(detections, camera, hint, hint_sigma_deg, t0, hint_zero_point)
        if len(detections) < 3:
            return Refusal(f"too few detections ({len(detections)})", self.name, ms(), status="too_few_stars")
        # the brightest max_detections identify; tetra3rs verifies with all of them. Each detection scored costs a
        # partner table per anchor star (a real 11 deg frame with 64 detections: ~60 of them per search)
        every = detections
        if self.max_detections is not None and len(detections) > self.max_detections:
            detections = detections.brightest(self.max_detections)
        if (
            self.sky_first_from is not None
            and self.prior is not None
            and len(detections) >= self.sky_first_from
            and (self.whole_sky_from is None or len(detections) < self.whole_sky_from)
        ):  # the regions' probabilities, where given (fusion predict reports them first), serve the second search
            return self._sky_then_regions(every, camera, image, t0, probabilities)
        centroids = None
        # from whole_sky_from detections on, the whole sky is searched at once (measured the cheaper certain
        # answer there: the prior's regions first only cost time, and magnitude noise misleads them)
        sky_first = self.whole_sky_from is not None and len(detections) >= self.whole_sky_from
        if sky_first:
            # cheapest first: tetra3rs lost in space (0.1-0.8 ms median, never wrong lost in space in our benchmarks;
            # 70 % of six-star frames, 99 % of eight-star ones), then the whole sky where it refuses
            first = self.tetra.solve(every, camera)
            if isinstance(first, Solution):
                return first
            probabilities = None
        elif probabilities is None and self.prior is not None:
            probabilities = self.prior.probabilities(detections, image)
        if probabilities is not None:
            centroids = self.prior.centroids if self.prior is not None else None
            if centroids is None:
                raise ValueError("probabilities given but the solver has no prior with centroids")
        u = camera.unproject(detections.x_px, detections.y_px)
        n = len(u)
        flux = np.asarray(detections.flux_adu, np.float64)
        # three detections: the bright tier (a chance triangle needs three bright stars, so H and p both
        # shrink); more: the full cut, where four or more stars leave few look-alikes anyway
        tier = self.tiers[-1] if n <= self.bright_max_detections else self.tiers[0]
        tried = 0
        last = Refusal("no catalog pair matches the detections in the prior's regions", self.name, status="no_pattern")
        # strict first (the nominal focal length, every region), then within +-focal_tol: a wider
        # search finds more coincidences, so it runs only where the strict one found nothing,
        # and the hypotheses of both count towards H
        passes = (0.0, self.focal_tol) if self.focal_tol > 0 and not self._strict_only else (0.0,)
        # three detections: a prior ranks the true region lower, and each region's search is cheap and counts
        # only its own hypotheses, so it searches few_top_k_factor times as many (20 -> 80 fine regions:
        # 47 -> 51 % at N = 3 on results/benchmark's frames, the true region's own rate)
        few = n <= self.bright_max_detections
        regions = self.regions(probabilities, centroids, self.top_k * self.few_top_k_factor if few else None)
        if sky_first:
            regions = [Region(np.array([0.0, 0.0, 1.0]), 180.0, 0.0, REST_OF_SKY)]
        elif self.then_whole_sky and probabilities is not None:
            # where the prior's regions refuse (a prior misled by noisy magnitudes, say), the rest of the sky;
            # H keeps counting (the prior's regions are counted again inside it: conservative)
            regions.append(Region(np.array([0.0, 0.0, 1.0]), 180.0, 0.0, REST_OF_SKY))
        tables: dict = {}
        q_all = None
        # the largest H at which each score can still be accepted: a hypothesis that cannot reach the score it
        # needs is dropped at its first detection too many unmatched, and the search stops where no score can
        h_limit = self._h_limit(tier, flux, n)
        best_seen = 0
        # the budget's units: a strict hypothesis hypothesis_cost(n) (1 up to six detections), a focal one
        # FOCAL_HYPOTHESIS_COST times that (tried: H, the count)
        work = 0.0
        per_hypothesis = hypothesis_cost(n)
        # where the prior's regions end with the rest of the sky, the focal pass searches that alone (it holds the
        # regions): a region's focal pass scans the whole +-focal_tol separation window for a few stars in it (~2,400
        # ns per hypothesis it counts, against ~150 over the sky), and none of 1,744 correct learned-chain answers came
        # from any focal pass on data/bench500 (benchmarks/pass_cost.py, results/benchmark/work-budget)
        sky_focal_only = len(regions) > 1 and regions[-1].index == REST_OF_SKY
        for s in passes:
            cost = per_hypothesis * (1 if s == 0 else FOCAL_HYPOTHESIS_COST)
            for region in regions:
                if s > 0 and sky_focal_only and region.index != REST_OF_SKY:
                    continue
                rots, ks, scores = np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0, np.int64)
                # sequential: decide after every detection pair, with H = every hypothesis tried so far
                for r, k, sc, t, best, stopped in self._hypotheses(
                    tier, u, region, s, tables, int((self.max_hypotheses - work) // cost), tried, h_limit
                ):
                    tried += t
                    work += t * cost
                    best_seen = max(best_seen, best)
                    best_possible = self.confidence(tried, n, n, tier=tier)
                    if best_possible < self.min_confidence and self.photometric_mag is not None:
                        if q_all is None:  # photometry's best case: every detection matched and passing
                            q_all = self._photometric_q(tier, flux)
                            h_limit[n] = min(h_limit[n], self._h_limit(tier, flux, n, q_all)[n])
                        best_possible = self.confidence(tried, n, n, q_all, tier=tier)
                    if stopped or best_possible < self.min_confidence:
                        # H only grows: not even all n detections matched could pass any more, so stop here
                        return Refusal(
                            f"the evidence cannot reach the confidence bar: after {tried} hypotheses even "
                            f"{n} of {n} detections matched would give confidence {best_possible:.3g} "
                            f"< {self.min_confidence}",
                            self.name,
                            ms(),
                            {"hypotheses": tried, "work": round(work, 1)},
                            "weak_evidence",
                        )
                    doubtful = False
                    if len(sc):
                        rots, ks = np.concatenate([rots, r]), np.concatenate([ks, k])
                        scores = np.concatenate([scores, sc])
                        verdict = self._decide(tier, rots, ks, scores, tried, u, flux)
                        if isinstance(verdict, int):
                            sol = self._finish(
                                tier, rots[verdict], float(ks[verdict]), u, detections, camera, region, tried, t0, every
                            )
                            if isinstance(sol, Solution):
                                return sol
                            last, doubtful = sol, True
                        else:
                            last = verdict
                    elif best_seen >= self.min_matches and last.status == "no_pattern":
                        # candidates matched, but too few for the confidence bar at this H (dropped early)
                        last = Refusal(
                            f"weak evidence: at most {best_seen} of {n} detections matched, fewer than the "
                            f"confidence bar needs after {tried} hypotheses",
                            self.name,
                            status="weak_evidence",
                        )
                    if self.max_hypotheses - work < cost:
                        # the work budget: a count of hypotheses, so the same answer on every machine
                        return Refusal(
                            f"work budget exhausted: {tried} hypotheses ({work:.0f} of max_hypotheses="
                            f"{self.max_hypotheses} units, one hypothesis of {n} detections counting "
                            f"{per_hypothesis:g}, of the focal pass {FOCAL_HYPOTHESIS_COST} times that) without an "
                            f"accepted attitude; last: {last.reason}",
                            self.name,
                            ms(),
                            {"hypotheses": tried, "work": round(work, 1)},
                            "budget_exhausted",
                        )
                    if doubtful:
                        break  # this pass's best is doubtful: go on
        return Refusal(last.reason, self.name, ms(), {"hypotheses": tried, "work": round(work, 1)}, last.status)

    def _stages(self):
        """(the whole sky alone, the prior's regions alone): shallow copies of this solver, made afresh each solve
        (a few microseconds), so that settings changed on it since (a relaxed bar, a budget) hold in both."""
        import copy

        sky, regions = copy.copy(self), copy.copy(self)
        for stage in (sky, regions):
            stage.then_whole_sky, stage.whole_sky_from, stage.sky_first_from = False, None, None
        sky.prior, sky.radii = None, None
        # the regions lie inside the sky, whose focal pass has searched them already; a region's own focal pass
        # scans the whole +-focal_tol separation window for its few stars (see sky_focal_only in solve)
        regions._strict_only = True
        return sky, regions

    def _sky_then_regions(self, detections: Detections, camera, image, t0: float, probabilities=None):
        """``sky_first_from``: the whole sky (one search, the budget), then, where it refuses, the prior's regions
        (``probabilities``, else the prior's; a search of their own: its own H and budget). The answer's
        ``extra["order"]`` says which answered."""
        sky, regions = self._stages()
        a = sky.solve(detections, camera)
        if isinstance(a, Solution):
            extra = {**a.extra, "region": REST_OF_SKY, "region_probability": 0.0, "order": "sky first"}
            return dataclasses.replace(a, time_ms=(time.perf_counter() - t0) * 1e3, extra=extra)
        b = regions.solve(detections, camera, image, probabilities=probabilities)
        ms = (time.perf_counter() - t0) * 1e3
        if isinstance(b, Solution):
            extra = {**b.extra, "order": "prior's regions after the sky", "sky_hypotheses": a.extra.get("hypotheses")}
            return dataclasses.replace(b, time_ms=ms, extra=extra)
        work = {k: a.extra.get(k, 0) + b.extra.get(k, 0) for k in ("hypotheses", "work")}
        # the status is the sky's where it ran out of budget (the prior's few regions rarely do), else the regions'
        status = a.status if a.status == "budget_exhausted" else b.status
        return Refusal(f"whole sky: {a.reason}; the prior's regions: {b.reason}", self.name, ms, work, status)

    def _track(self, detections: Detections, camera, hint: np.ndarray, sigma_deg: float, t0: float, zero_point=None):
        """Tracking with an attitude hint: :func:`fusion.solve.track.track`."""
        from .track import track  # imports this module: here, not at the top

        return track(self, detections, camera, hint, sigma_deg, t0, zero_point)

    def refine(self, tier: _Tier, rot: np.ndarray, k: float, u: np.ndarray, s: float, iterations: int = 20):
        """Rotation and focal factor fitted to the stars matched within ``tol_px``: (rot, k, det rows, cat rows, unit
        vectors at k, whether k was fitted).

        Iterated to convergence: a scale error leaves the outer stars unmatched at first, and each
        fit with the inner ones brings more of them within the tolerance. With a free scale (``s`` > 0) the same is
        done at the camera's own scale (k = 1) too, and the fit that matches more detections is kept (the free one
        where they tie): three or four stars whose centroids err by a pixel or two (a saturated star, a field edge
        the distortion model leaves off) can pull a free scale by a few tenths of a percent, far enough to trade
        the outer stars for a chance neighbour near the centre (a real 26 deg camera: 5 of 8 detections with the
        scale free, 6 of 8 at its own, results/real-frames/refine-scale). A free scale that ends at the edge of its
        range is returned as it is: the caller refuses it (frames of another lens), whatever the camera's own scale
        would match (the adversarial 'focal' family: 4 of 4 such answers wrong, 5-7 % off the camera's scale)."""
        free = self._refine(tier, rot, k, u, s, iterations)
        if s <= 0 or abs(free[1] - 1.0) >= FOCAL_EDGE * s:
            return (*free, s > 0)
        own = self._refine(tier, rot, 1.0, u, 0.0, iterations)
        if len(own[2]) > len(free[2]):
            return (*own, False)
        return (*free, True)

    def _refine(self, tier: _Tier, rot: np.ndarray, k: float, u: np.ndarray, s: float, iterations: int):
        """:meth:`refine`'s iterations at one scale freedom ``s`` (0: k held)."""
        t = u[:, :2] / u[:, 2:3]
        previous = None
        for _ in range(iterations):
            uk = _unit_at(t, k)
            det_rows, cat_rows = self._matches(tier, rot, uk)
            if len(det_rows) < 2:
                break
            # Kabsch's rotation at k, then (three stars on, s > 0) the scale of the 2-D similarity (Umeyama) from
            # the matched stars' tangent-plane coordinates to the detections' (t = k g up to a small shift and
            # turn): free of the rotation's own error, which a plain t = k g fit absorbs, so it converges in a few
            # iterations; one pass of tracking's compiled fit (a tenth of numpy's time on three by three)
            rot, k_new, _, _ = refine_track(t[det_rows], tier.vec[cat_rows], k, s, 1)
            k_new = float(k_new)
            converged = previous is not None and np.array_equal(previous, det_rows) and abs(k_new - k) < 1e-6
            k, previous = k_new, det_rows
            if converged:
                break
        uk = _unit_at(t, k)
        det_rows, cat_rows = self._matches(tier, rot, uk)
        return rot, k, det_rows, cat_rows, uk

    def _pulled_off(
        self,
        tier: _Tier,
        matrix: np.ndarray,
        uk: np.ndarray,
        det_rows: np.ndarray,
        cat_rows: np.ndarray,
        factor: float = 1.0,
    ) -> bool:
        """Does attitude ``matrix`` move any of our matched stars beyond ``factor`` x ``tol_px`` of its catalogue
        star?"""
        cos = np.sum((uk[det_rows] @ np.asarray(matrix).T) * tier.vec[cat_rows], axis=1)
        return bool(np.any(np.arccos(np.clip(cos, -1, 1)) > factor * self.tol_rad))

    def _finish(self, tier: _Tier, rot, k, u, detections, camera, region, tried, t0, every=None) -> Solution | Refusal:
        # the focal factor is fitted within +-focal_tol whichever pass found the hypothesis: a strict-pass
        # match of the central stars still leaves the outer ones (and the attitude) biased by a wrong scale
        rot, k, det_rows, cat_rows, uk, k_fitted = self.refine(tier, rot, k, u, self.focal_tol)
        if self.focal_tol > 0 and abs(k - 1.0) >= FOCAL_EDGE * self.focal_tol:
            # the scale wants to leave the range searched: the camera does not fit these detections (another lens
            # or camera; the adversarial calibration's 'focal' family: 3 wrong attitudes in 100,000 attempts, all
            # at this edge, one reported at p = 2e-8). Clean frames fit within 0.2 % of their camera.
            return Refusal(
                f"the focal length fits only at the edge of the +-{100 * self.focal_tol:.0f} % searched "
                f"(factor {k:.4f}): frames of another lens or camera?",
                self.name,
                {"focal_factor": k},
                status="not_verified",
            )
        score = len(det_rows)
        e_false = self.expected_false(tried, len(u), score, tier=tier)
        conf = max(0.0, 1.0 - e_false)
        flux = np.asarray(detections.flux_adu, np.float64)
        evidence = "geometry"
        q = 1.0
        if (
            score >= self.min_matches
            and conf < self.unverified_confidence
            and self._photometric_pass(tier, cat_rows, det_rows, flux)
        ):
            q_p = self._photometric_q(tier, flux[det_rows])
            e_p = self.expected_false(tried, len(u), score, q_p, tier=tier)
            if e_p < e_false:
                e_false, conf, evidence, q = e_p, max(0.0, 1.0 - e_p), "geometry and photometry", q_p
        if score < self.min_matches or conf < self.min_confidence:
            return Refusal(
                f"weak evidence after refinement: {score} of {len(u)} detections matched, confidence {conf:.3g}",
                self.name,
                status="weak_evidence",
            )
        cam_k = dataclasses.replace(camera, f_px=camera.f_px * k) if k != 1.0 else camera
        scale_fitted = k_fitted and len(det_rows) >= 3  # refine fitted k to these stars: the covariance's fourth
        # parameter
        # the bars above are on E_false at the sky's mean density (as measured and chosen); the solution reports the
        # probability with the catalogue's clustering (density_clustering: the same count, more chance matches
        # where stars crowd), the better-calibrated number (results/calibration/clustering)
        e_mean = e_false
        if self.clustering:
            e_false = self.expected_false(tried, len(u), score, q, tier=tier, clustered=True)
            conf = max(0.0, 1.0 - e_false)
        extra = {
            "region": region.index,
            "region_probability": region.probability,
            "hypotheses": tried,
            "refined_by": "own least squares",
            "focal_factor": k,
            "fov_deg": list(cam_k.fov_deg),
            "evidence": evidence,
            "false_match_probability_mean_density": min(1.0, e_mean),
        }
        if len(det_rows) >= 2:
            extra["magnitude_scatter"] = float(magnitude_scatter(tier.mag[cat_rows], flux[det_rows]))
        zp = photometric_zero_point(tier.mag[cat_rows], flux[det_rows])
        if zp is not None:
            extra["zero_point"] = zp
        if self.verify:
            # 1 deg: the few matched stars of a tight group (a cluster, a close pair) can fix the roll only
            # to about a degree; tetra3rs re-matches every detection within that and refines
            res = self.tetra.solve_with_hint(
                every if every is not None else detections, cam_k, rot, 1.0, name=self.name, covariance=not scale_fitted
            )
            # a confirmation is an attitude near ours that keeps our matched stars: one that puts any of them beyond
            # DISAGREE_FACTOR x tol_px matched other stars (an adversarial set with a false star: our 4 matches right,
            # tetra3rs's 3 within 0.3 px rms but 0.97 deg off, one of ours then 10 px away; results/real-frames/
            # refine-scale), and our own answer stands alone (the unverified bar below)
            confirmed = (
                isinstance(res, Solution)
                and rotation_angle_deg(res.matrix, rot) < 2.0
                and not self._pulled_off(tier, res.matrix, uk, det_rows, cat_rows, DISAGREE_FACTOR)
            )
            resid_px = res.residual_arcsec / cam_k.pixel_scale_arcsec if confirmed else 0.0
            if (
                confirmed
                and resid_px > self.max_residual_px
                and self._pulled_off(tier, res.matrix, uk, det_rows, cat_rows)
            ):
                # confirmed, but tetra3rs's refinement took in a star beyond any centroid error (a bright
                # star missing from the tier, matched to a neighbour) and is pulled off by it, so far that
                # our own matches no longer fit; their own least squares is no better (few stars, and the
                # same doubt): neither attitude can be trusted to the precision a solution promises
                return Refusal(
                    f"tetra3rs confirmed the stars, but its attitude leaves {resid_px:.2f} px rms and moves "
                    f"our matched stars beyond {self.tol_px} px: a mismatched star; no trustworthy attitude",
                    self.name,
                    status="not_verified",
                )
            if confirmed:
                extra["refined_by"] = "tetra3rs tracking"
                if scale_fitted:  # tetra3rs fitted the turn alone, at the focal length our stars fitted
                    dets = every if every is not None else detections
                    rows = res.matched[:, 0]
                    u_t = cam_k.unproject(dets.x_px[rows], dets.y_px[rows])
                    res = dataclasses.replace(
                        res,
                        covariance_matrix_arcsec2=attitude_covariance(
                            u_t,
                            res.residual_arcsec,
                            cam_k.pixel_scale_arcsec,
                            scale_fitted=True,
                            floor_px=cam_k.centroid_sigma_px,
                            shared_px=cam_k.shared_sigma_px,
                        ),
                    )
                extra["false_positive_probability"] = res.extra.get("false_positive_probability")
                extra["fov_deg"] = [res.extra.get("fov_deg", cam_k.fov_deg[0]), cam_k.fov_deg[1]]
                return dataclasses.replace(
                    res,
                    confidence=conf,
                    solver=self.name,
                    time_ms=(time.perf_counter() - t0) * 1e3,
                    extra=extra,
                    false_match_probability=min(1.0, e_false),
                )  # tetra3rs's attitude and its covariance (from every star it matched)
            elif max(0.0, 1.0 - e_mean) < self.unverified_confidence:  # the bar is on the mean-density E_false
                # unconfirmed (tetra3rs cannot verify four or five stars on its own denser catalogue): the stars'
                # brightness order is further evidence where they are their field's brightest. It replaces the
                # photometric q where stronger (the two read the same magnitudes: not multiplied). The field is looked
                # at only where its q could bring E_false under the bar
                q_o = self._order_q(score)
                if (
                    q_o < q
                    and e_mean * q_o / q <= 1.0 - self.unverified_confidence
                    and self._order_holds(tier, rot, cam_k, cat_rows)
                ):
                    scale = q_o / q
                    e_mean, e_false, q = e_mean * scale, e_false * scale, q_o
                    conf = max(0.0, 1.0 - e_false)
                    extra["evidence"] = evidence = "geometry and brightness order"
                    extra["false_match_probability_mean_density"] = min(1.0, e_mean)
                if max(0.0, 1.0 - e_mean) < self.unverified_confidence:
                    return Refusal(
                        "best candidate not confirmed by tetra3rs tracking and evidence below the unverified bar",
                        self.name,
                        status="not_verified",
                    )
        resid = np.arccos(np.clip(np.sum((uk[det_rows] @ rot.T) * tier.vec[cat_rows], axis=1), -1, 1))
        rms_arcsec = float(np.degrees(np.sqrt(np.mean(resid**2))) * 3600)
        return solution_from_matrix(
            rot,
            matched=np.column_stack([det_rows, tier.ids[cat_rows]]),
            residual_arcsec=rms_arcsec,
            confidence=conf,
            solver=self.name,
            time_ms=(time.perf_counter() - t0) * 1e3,
            extra=extra,
            false_match_probability=min(1.0, e_false),
            covariance_matrix_arcsec2=attitude_covariance(
                uk[det_rows],
                rms_arcsec,
                cam_k.pixel_scale_arcsec,
                scale_fitted=scale_fitted,
                floor_px=cam_k.centroid_sigma_px,
                shared_px=cam_k.shared_sigma_px,
            ),
        )
