"""The fine stage's tracking mode: an attitude hint, an identification weighed by a likelihood.

Called by :meth:`fusion.solve.fine.CoarseToFineSolver.solve` (through ``_track``) when a hint is given;
it uses the solver's catalogue cuts, tolerances and confidence bars.

**Tracking** (``CoarseToFineSolver.solve(..., hint=M, hint_sigma_deg=s)``; :func:`track`, scored by
:func:`fusion.solve.match.track_hypotheses`; two detections suffice). Each detection's direction is
predicted by the hint; its candidates are the catalogue cut's stars within 3 s of that (a rotation by an angle
moves no direction farther), plus what the focal tolerance leaves uncertain off-axis (a cone query, no
whole-sky pair search). Every pair of candidates of two of the brightest four detections is an identification
(TRIAD at the focal factor its separation implies), the other detections matched where it puts them, and
each is weighed by a likelihood against "no identification" (each term a density ratio):

* the hint's prior: an isotropic Gaussian (1-sigma s) on the rotation from the hint to the attitude;
* the separation: the catalogue pair's against the detections' over the focal range 1 +- focal_tol (uniform),
  blurred by ``TRACK_CENTROID_PX`` of centroid error; each further detection matched: its position density
  against a uniform one over the field (the chance-star density of the lost-in-space E_false);
* magnitudes: the catalogue magnitudes against the instrumental ones about a fitted zero point
  (``TRACK_MAG_SIGMA``), against a coincidental spread of ``TRACK_MAG_SPREAD``; with ``hint_zero_point`` (the
  zero point earlier frames measured, ``Solution.extra["zero_point"]``) the fitted zero point is also weighed
  against it (``TRACK_ZP_SIGMA``), so that the magnitude difference a fitted zero point spends counts too:
  two stars of the right separation but the wrong brightness no longer pass; and every bright-tier star
  the attitude puts on the sensor, more than ``TRACK_MAG_MARGIN`` brighter than its faintest matched star,
  without a detection, costs a factor ``TRACK_MISS`` (measured: 14 of 105 such stars at the true attitude);
* each detection is no catalogue star with prior ``TRACK_FALSE_DETECTION`` (hot pixels are 4.5 % of the two
  brightest detections of rendered frames): the "no identification" hypothesis (at most one star) keeps
  that mass; and the hint may have missed the stars altogether (prior ``TRACK_HINT_MISS``: a slew, a lost
  track), which leaves the detections as uniform over the hint's field as no identification does, so that
  mass joins it. Measured with ``benchmarks/tracking_calibration.py`` (the detections of another frame given
  with this frame's hint).

The false-match probability is the posterior mass of everything but the best identification (identifications
within ``TRACK_SAME_DEG`` of its attitude count with it), the null included; the best one is returned where
that is at most ``1 - tracking_unverified_confidence`` (1e-3; ``extra["log_evidence"]``: the best identification's
log weight against "no identification"), with its own least-squares attitude (no
tetra3rs verification: it does not know the hint and rejects most matches of three stars). The constants are
measured (above) and then rounded towards less confidence. This replaces the earlier rule (an unverified
E_false below 1e-3 in a 3-sigma region, three stars at least): 85 -> 92 % at N = 3 and 0 -> 78 % at N = 2
with a 2 deg hint, none wrong (data/track300, 300 frames). The covariance is that of the matched stars
(:func:`fusion.solve.base.attitude_covariance`, at least ``TRACK_COV_CENTROID_PX`` per axis for three stars
or fewer): two stars leave the rotation about their mean direction weak, the roll for a pair about the
centre, and a pair too close to fix the roll to ``TRACK_MAX_ROLL_SIGMA_DEG`` is refused. A hint whose
3-sigma region misses the truth can only give a refusal or an attitude near the hint.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from .base import (
    HINT_RADIUS_SIGMAS,
    Detections,
    Refusal,
    Solution,
    attitude_covariance,
    solution_from_matrix,
)
from .fine import TRACKING
from .match import refine_track, track_hypotheses

# --------------------------------------------------------------------------- tracking (an attitude hint)
# The model behind track (module docstring, "Tracking"); each constant errs on the side of
# less confidence where it was measured (results on data/track300, 300 rendered test frames, seed 11), except
# TRACK_FALSE_DETECTION, where the larger value is the less cautious one (see there):
TRACK_FALSE_DETECTION = 0.05  # prior chance that a detection is no star of the catalogue cut (a hot pixel, a
#   cosmic ray, a star beyond the cut): 4.5 % of the two brightest detections of the rendered frames are hot pixels.
#   Not rounded up: a larger value makes a detection left unmatched cheap, which favours partial chance matches
#   near a wrong hint (data/track300, 2-deg hint, with the zero point and known defects, another frame's
#   detections: wrong answers at p <= 1e-3 with 0.1 -> 0.05: N = 2 28 -> 33, N = 3 33 -> 25, N = 4 15 -> 4,
#   N = 6 5 -> 2, and one at p <= 1e-6 -> none; the clean frames answered alike. benchmarks/tracking_calibration.py
#   --false-detection-prior 0.1, results/calibration/tracking/s11-hint2-zp-defects{-eps0.1,})
TRACK_MISS = 0.2  # chance that a catalogue star clearly brighter than a detected one (TRACK_MAG_MARGIN) and inside
#   the sensor (TRACK_EDGE_PX) has no detection of its own: each such star multiplies a hypothesis by this
TRACK_MAG_MARGIN = 1.0  # magnitudes: "clearly brighter" (catalogue vs instrumental scatter, colour, variability)
TRACK_EDGE_PX = 10.0  # a star this close to the sensor's edge may be cut off: never counted as missed
TRACK_MAG_SIGMA = 0.3  # scatter (mag) of a detection's instrumental magnitude about its star's, after the zero point
TRACK_MAG_SPREAD = 3.0  # the range (mag) a coincidental star's magnitude difference spreads over: null density 1/3
TRACK_CENTROID_PX = 0.5  # per-axis centroid error (px) the separation and position likelihoods assume
TRACK_COV_CENTROID_PX = 0.25  # the per-axis centroid error a covariance of three stars or fewer assumes (they fit too
#   well to measure it): 0.15 px rms measured (rendered detections against the catalogue at the true attitude)
TRACK_SAME_DEG = 0.1  # hypotheses within this rotation of the best one identify the same attitude
TRACK_HINT_MISS = 0.1  # prior chance that the hint missed the stars (a slew, a lost track): the detections are then
#   stars elsewhere, as uniform over the hint's field as no identification. Chosen on data/track300
#   (benchmarks/tracking_calibration.py --foreign-pairs 30, results/calibration/tracking): detections of another
#   frame with this frame's 2-deg hint, wrong answers at p <= 1e-3 in 9,000 attempts without -> with it: N = 6
#   172 -> 5 (4 -> 0 at p <= 1e-6), N = 4 159 -> 22, N = 3 122 -> 47, N = 2 83 -> 68 (two detections' "at most
#   one star" mass is already 0.19); the clean frames lose 0-1 point. Still overconfident there (see the results)
TRACK_ZP_SIGMA = 0.25  # 1-sigma (mag) of a known zero point (hint_zero_point: earlier frames') about the one a
#   frame's brightest stars give: from frame to frame the zero point scatters 0.09 mag on data/track300 (fusion
#   benchmark's tracking_zero_point_scatter), and two or three stars add their own scatter and their saturated
#   cores (a bright star's flux is underestimated): 0.25 covers both
TRACK_ANCHORS = 4  # anchor pairs among the brightest this many detections
#: the work budget of one tracking solve: candidate pairs of its anchor detections, counted before any is scored (a
#: count, so the same refusal on every machine). A wide hint on a dense catalogue holds very many: before this
#: budget a 5 deg hint took 6 s a solve on a 1.1 deg Gaia camera and 17 s on a 2.6 deg one (results/real-frames/
#: tracking), where the fitted Blackfly's took 70 ms
TRACK_MAX_PAIRS = 20_000_000
TRACK_MAX_ROLL_SIGMA_DEG = 0.25  # a pair this close fixes the roll too loosely to return (covariance, 1 sigma):
#   the 1-deg roll bound of a correct answer is 4 sigma away. Not looser: a saturated star's centroid can be off by
#   a pixel or more (data/track300-s23, 0.5-deg hint: two answers reported at 0.30 deg erred by 1.1-1.2 deg in roll)


def track(
    solver,
    detections: Detections,
    camera,
    hint: np.ndarray,
    sigma_deg: float,
    t0: float,
    zero_point: float | None = None,
) -> Solution | Refusal:
    """Tracking with an attitude hint: every identification of the brightest detections by catalogue stars
    near their predicted directions, weighed by a likelihood (module docstring); the best one
    if the posterior mass of every other (and of "no identification") is at most
    ``1 - solver.tracking_unverified_confidence``. ``solver``: the :class:`~fusion.solve.fine.CoarseToFineSolver`
    whose catalogue cuts and tolerances it uses; ``t0``: the solve's ``time.perf_counter()`` start."""

    def refuse(reason: str, status: str, extra: dict | None = None) -> Refusal:
        return Refusal(reason, solver.name, (time.perf_counter() - t0) * 1e3, extra or {}, status)

    tier, bright = solver.tiers[0], solver.tiers[-1]
    n = len(detections)
    u = camera.unproject(detections.x_px, detections.y_px)
    t = u[:, :2] / u[:, 2:3]
    s, tol = solver.focal_tol, solver.tol_rad
    sig = math.radians(sigma_deg)
    m_hint = np.asarray(hint, np.float64)
    sig_c = TRACK_CENTROID_PX / camera.f_px  # centroid error per axis (rad)
    log_eps, log_1eps = math.log(TRACK_FALSE_DETECTION), math.log1p(-TRACK_FALSE_DETECTION)
    # the solid angle of the field, the density a detection that is no catalogue star has (uniform over it)
    omega = solver._fov_sr
    na = min(n, TRACK_ANCHORS)
    # each detection's catalogue candidates: within 3 sigma of its predicted direction (a rotation by an angle
    # moves no direction farther), plus what the focal length leaves uncertain at its distance from the centre
    off = np.arctan(np.hypot(t[:, 0], t[:, 1]))
    radius = np.minimum(math.pi, HINT_RADIUS_SIGMAS * sig + 2 * tol + s * off)
    cand = tier.tree.query_ball_point(u @ m_hint.T, 2 * np.sin(radius / 2))
    cand_offs = np.zeros(n + 1, np.int64)
    cand_offs[1:] = np.cumsum([len(c) for c in cand])
    cand_rows = np.concatenate([np.asarray(c, np.int64) for c in cand])
    # the bright stars around the hint's field: those a hypothesis must explain (TRACK_MISS)
    reach = solver.half_diag_rad * (1 + s) + HINT_RADIUS_SIGMAS * sig
    sizes = np.diff(cand_offs)[:na]
    pairs = int((sizes.sum() ** 2 - (sizes**2).sum()) // 2)  # sum over anchor pairs i < j of |cand_i| |cand_j|
    if pairs > TRACK_MAX_PAIRS:
        return refuse(
            f"tracking: the hint's region holds {pairs:,} candidate pairs for the brightest {na} detections, over the "
            f"budget of {TRACK_MAX_PAIRS:,} (a hint of {sigma_deg:g} deg on this dense a catalogue): a tighter hint, "
            "or lost in space",
            "budget_exhausted",
            {"hypotheses": 0, "candidate_pairs": pairs, "region": TRACKING, "region_probability": 1.0},
        )
    near = np.asarray(bright.tree.query_ball_point(m_hint[:, 2], 2 * math.sin(min(math.pi, reach) / 2)), np.int64)
    flux = np.asarray(detections.flux_adu, np.float64)
    inst = -2.5 * np.log10(np.maximum(flux, 1e-12))
    sat = np.zeros(n, bool) if detections.saturated is None else np.asarray(detections.saturated, bool)
    phot = bool(np.all(flux > 0))
    cam = np.array(
        [camera.f_px, camera.fy_px, camera.cx_px, camera.cy_px, camera.k1, camera.k2, camera.k3, camera.p1]
        + [camera.p2, camera.width_px, camera.height_px, TRACK_EDGE_PX],
        np.float64,
    )
    consts = np.array(
        [
            log_eps,
            log_1eps,
            math.log(TRACK_MISS),
            math.log1p(-TRACK_MISS),
            TRACK_MAG_MARGIN,
            TRACK_MAG_SIGMA,
            math.log(TRACK_MAG_SPREAD / (TRACK_MAG_SIGMA * math.sqrt(2 * math.pi))),
            float(zero_point) if zero_point is not None else 0.0,
            TRACK_ZP_SIGMA if zero_point is not None else 0.0,
        ]
    )
    tc = np.ascontiguousarray(t)
    near_vec, near_mag, near_row = bright.vec[near], bright.mag[near], solver._bright_rows[near]
    log_omega = math.log(omega)
    found = []
    tried = 0
    floor = -math.inf  # every identification 30 below the best is dropped (below): track_hypotheses skips them early
    for i in range(na):
        for j in range(i + 1, na):
            a_rows, b_rows = cand_rows[cand_offs[i] : cand_offs[i + 1]], cand_rows[cand_offs[j] : cand_offs[j + 1]]
            if not len(a_rows) or not len(b_rows):
                continue
            logw, rot, k, cats = track_hypotheses(
                tc, i, j, a_rows, b_rows, cand_offs, cand_rows, tier.vec, tier.mag, m_hint, sig, s, tol, sig_c,
                log_omega, near_vec, near_mag, near_row, cam, inst, sat, phot,
                consts, floor,
            )  # fmt: skip
            tried += len(logw)
            if len(logw):
                found.append((logw, cats, rot, k))
                floor = max(floor, float(logw.max()) - 30.0)
    # no identification: the hint missed the stars (TRACK_HINT_MISS), or at most one detection is a catalogue star
    # (one star alone leaves the attitude free); either way the detections are uniform over the hint's field
    eps, q = TRACK_FALSE_DETECTION, TRACK_HINT_MISS
    log_null = math.log(q + (1 - q) * (eps**n + n * (1 - eps) * eps ** (n - 1)))
    extra = {"hypotheses": tried, "region": TRACKING, "region_probability": 1.0}
    if not found:
        return refuse("no catalogue pair near the hint matches the detections", "no_pattern", extra)
    lw = np.concatenate([x[0] for x in found])
    cats = np.concatenate([x[1] for x in found])
    rots = np.concatenate([x[2] for x in found])
    ks = np.concatenate([x[3] for x in found])
    # the same identification (the same matched row per detection) from several anchor pairs counts once, at
    # its best weight; one below e^-30 of the best changes no probability this solver states
    order = np.argsort(-lw, kind="stable")
    order = order[lw[order] > lw[order[0]] - 30.0]
    rows = cats[order]  # each distinct row's first place in the weight order (a stable lexicographic sort)
    srt = np.lexsort(rows.T[::-1])
    lead = np.ones(len(srt), bool)
    lead[1:] = np.any(rows[srt[1:]] != rows[srt[:-1]], axis=1)
    first = srt[lead]
    keep = order[np.sort(first)]
    lw, cats, rots, ks = lw[keep], cats[keep], rots[keep], ks[keep]
    best = 0  # keep is in descending weight
    top = lw[best]
    cos_same = math.cos(math.radians(TRACK_SAME_DEG))
    same = (rots.reshape(-1, 9) @ rots[best].ravel() - 1) / 2 >= cos_same
    # in logs: a hint far off leaves every weight far below the null's
    log_total = np.logaddexp(np.logaddexp.reduce(lw), log_null)
    p_false = float(min(1.0, max(0.0, -np.expm1(np.logaddexp.reduce(lw[same]) - log_total))))
    w = np.exp(lw - top)
    conf = 1.0 - p_false
    extra["log_evidence"] = float(top - log_null)  # the best identification against "no identification" (log)
    if conf < solver.tracking_unverified_confidence:
        runner = np.flatnonzero(~same)
        why = (
            f"{len(runner)} other identification(s) near the hint"
            if len(runner) and math.log(w[runner].max()) + top + math.log(1e3) > log_null
            else "no identification at all (a detection that is no catalogue star)"
        )
        return refuse(
            f"tracking: the best identification has false-match probability {p_false:.3g} > "
            f"{1 - solver.tracking_unverified_confidence:.3g} (most of the rest: {why})",
            "weak_evidence" if len(runner) else "not_verified",
            extra,
        )
    rot, k = rots[best], float(ks[best])
    det_rows = np.flatnonzero(cats[best] >= 0)
    cat_rows = cats[best][det_rows]
    # the least-squares rotation of the identified stars and, from three on, the focal factor (Umeyama's scale
    # of the tangent-plane coordinates, within 1 +- s): two passes, the identification is not revisited
    passes = 2 if len(det_rows) >= 3 and s > 0 else 1
    rot, k, u_det, rms_rad = refine_track(np.ascontiguousarray(t[det_rows]), tier.vec[cat_rows], k, s, passes)
    rms_arcsec = math.degrees(rms_rad) * 3600
    cam_k = dataclasses.replace(camera, f_px=camera.f_px * k) if k != 1.0 else camera
    # the covariance assumes at least the model's centroid error where the stars are too few to measure it
    # (two stars and a free focal length fit exactly)
    floor = TRACK_COV_CENTROID_PX * cam_k.pixel_scale_arcsec if len(det_rows) <= 3 else 0.0
    # (three stars or fewer: the plain estimate, the floor already makes their 1 sigma hold 97-99 %; from four on as
    # lost in space: the Student scale, and the focal factor fitted from three on as a fourth parameter)
    few = len(det_rows) <= 3
    cov = attitude_covariance(
        u_det,
        max(rms_arcsec, floor),
        cam_k.pixel_scale_arcsec,
        student=not few,
        scale_fitted=passes == 2,
        floor_px=cam_k.centroid_sigma_px,
        shared_px=cam_k.shared_sigma_px,
    )
    if math.sqrt(cov[2, 2]) / 3600 > TRACK_MAX_ROLL_SIGMA_DEG:
        return refuse(
            f"tracking: the matched stars fix the roll only to {math.sqrt(cov[2, 2]) / 3600:.2f} deg (1 sigma) "
            f"> {TRACK_MAX_ROLL_SIGMA_DEG} deg: too close together",
            "weak_evidence",
            extra,
        )
    extra.update(
        {
            "refined_by": "own least squares",
            "focal_factor": k,
            "fov_deg": list(cam_k.fov_deg),
            "evidence": "hint prior, geometry and photometry" if phot else "hint prior and geometry",
            "identifications": len(lw),
        }
    )
    if phot:  # as fine.magnitude_scatter and base.photometric_zero_point, inline (every flux is positive)
        d = tier.mag[cat_rows] - inst[det_rows]
        if len(d) >= 2:
            extra["magnitude_scatter"] = float(d.std(ddof=1))
        extra["zero_point"] = float(d.mean())
    if zero_point is not None:
        extra["hint_zero_point"] = float(zero_point)
    return solution_from_matrix(
        rot,
        matched=np.column_stack([det_rows, tier.ids[cat_rows]]),
        residual_arcsec=rms_arcsec,
        confidence=conf,
        solver=solver.name,
        time_ms=(time.perf_counter() - t0) * 1e3,
        extra=extra,
        false_match_probability=p_false,
        covariance_matrix_arcsec2=cov,
    )
