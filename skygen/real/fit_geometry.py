"""Geometry of ``skygen fit-camera``: lost-in-space solutions, catalogue matches and the joint camera fit.

Per frame: tetra3rs lost-in-space (:mod:`skygen.real.platesolve`) on the brightest detections, from a
start camera (a camera file) or from a field-of-view range (the field searched); then every
detection is paired with the nearest skygen catalogue star (Hipparcos-2, propagated to the
epoch) projected through the solution, within ``match_radius_px``.

Joint fit (:func:`fit_geometry`): ``scipy.optimize.least_squares`` over all solved frames at once,
residuals in pixels (projected catalogue star − detected centroid, x and y), parameters: focal
length ``f_px`` (pixel widths), ``pixel_aspect`` (through its logarithm), principal point
(``cx``, ``cy``), radial distortion ``k1`` (and ``k2``), and a small rotation of every frame's
attitude. A term is fitted only when the data can constrain it (:data:`RULES`; principal point and
distortion need several frames and stars spread to the field's edge; ``k2`` needs many stars) and
its 1-sigma uncertainty moves a corner star by less than ``max_corner_sigma_px`` (and, for k1 and k2,
the fitted value is at least twice its uncertainty); otherwise it is fixed (principal point at the sensor centre,
distortion 0) and the reason is recorded. Matches
beyond 3.5 times the robust rms are dropped and the fit repeated (twice), with the matches
re-made from the fitted camera in between.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from skygen.instrument.camera import Camera
from skygen.sky.attitude import matrix_to_radec_roll

RULES = {
    "min_frames_distortion": 2,
    "min_stars_distortion": 30,
    "min_stars_k2": 150,
    "min_edge_fraction": 0.7,
    "max_corner_sigma_px": 0.3,
}
#: the rules of :func:`grow_matches`'s inner stages: distortion fitted from stars short of the corner, its
#: uncertainty there allowed to be large (the next, wider stage refines it; the final fit applies RULES)
GROWING_RULES = {**RULES, "min_edge_fraction": 0.0, "max_corner_sigma_px": 50.0}
#: the stages' reach (share of the centre-to-corner distance matched)
GROWING_REACH = (0.5, 0.7, 0.85, 1.0)
#: a frame takes part in a stage (and takes its attitude from it) only where the stage matches this many of its stars
GROWING_MIN_MATCHES = 4


@dataclass
class FrameSolution:
    """One frame's detections, solution (camera -> ICRS matrix ``R``) and catalogue matches."""

    name: str
    det: dict
    R: np.ndarray | None = None
    fov_deg: float = float("nan")
    reason: str = ""
    det_index: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # matched detections
    star_vec: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # their catalogue directions (ICRS)
    star_mag: np.ndarray = field(default_factory=lambda: np.zeros(0))
    star_bv: np.ndarray = field(default_factory=lambda: np.zeros(0))
    star_hip: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def solved(self) -> bool:
        return self.R is not None


radec_roll = matrix_to_radec_roll  # (ra, dec, roll) degrees of a camera -> ICRS matrix


def _rotvec(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    t = float(np.linalg.norm(w))
    if t < 1e-15:
        return np.eye(3)
    k = w / t
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def solve_frame(
    db, det: dict, camera: Camera, fov_range, max_stars: int = 64, match_threshold: float = 1e-5
) -> tuple[np.ndarray | None, float, str]:
    """tetra3rs lost-in-space: (camera -> ICRS matrix or None, solved horizontal FOV, refusal reason)."""
    from skygen.real.platesolve import ideal_centroids, tetra3rs

    n = min(len(det["x_px"]), max_stars)
    if n < 4:
        return None, float("nan"), f"too few stars to solve ({n} detections; tetra3rs needs at least 4, better 8+)"
    cents = ideal_centroids(det["x_px"][:n], det["y_px"][:n], det["flux_adu"][:n], camera)
    h_ideal = int(round(camera.height_px * camera.aspect))
    if fov_range is None:
        geo = {"camera_model": tetra3rs().CameraModel(float(camera.f_px), int(camera.width_px), h_ideal)}
    else:
        lo, hi = fov_range
        geo = {
            "fov_estimate_deg": 0.5 * (lo + hi),
            "fov_max_error_deg": 0.5 * (hi - lo),
            "image_width": int(camera.width_px),
            "image_height": h_ideal,
        }
    res = db.solve_from_centroids(
        cents, match_threshold=match_threshold, solve_timeout_ms=5000, max_patterns_checked=1_000_000, **geo
    )
    if not res:
        why = str(res.status)
        hint = " (no match in the field-of-view range?)" if fov_range is not None else ""
        return None, float("nan"), f"no lost-in-space solution from {n} detections ({why}){hint}"
    if res.parity_flip:
        return None, float("nan"), "mirror-image match (parity flip): not a physical attitude"
    return np.asarray(res.rotation_matrix_icrs_to_camera).T.copy(), float(res.fov_deg), ""


def match_catalogue(fs: FrameSolution, camera: Camera, sky, radius_px: float, reach: float = 1.0) -> None:
    """Pair each detection with the nearest catalogue star projected through ``fs.R`` (each star once); with
    ``reach`` < 1 only the detections within that share of the centre-to-corner distance."""
    from scipy.spatial import cKDTree

    idx = sky.cone(fs.R[:, 2], camera.corner_radius_rad() + 0.01)
    v = sky.vectors[idx]
    x, y, front = camera.project(v @ fs.R)
    ok = front & camera.inside(x, y, 2.0)
    idx, v, x, y = idx[ok], v[ok], x[ok], y[ok]
    empty = np.zeros(0, int)
    if len(idx) == 0 or len(fs.det["x_px"]) == 0:
        fs.det_index, fs.star_vec = empty, np.zeros((0, 3))
        fs.star_mag, fs.star_bv, fs.star_hip = np.zeros(0), np.zeros(0), np.zeros(0, np.int64)
        return
    d, j = cKDTree(np.column_stack([x, y])).query(np.column_stack([fs.det["x_px"], fs.det["y_px"]]))
    inner = True
    if reach < 1.0:
        r_max = np.hypot(camera.width_px / 2, camera.height_px * camera.aspect / 2)
        r = np.hypot(fs.det["x_px"] - camera.cx_px, (fs.det["y_px"] - camera.cy_px) * camera.aspect)
        inner = r <= reach * r_max
    good = np.flatnonzero((d <= radius_px) & inner)
    # each catalogue star claimed once: by its nearest detection
    order = good[np.argsort(d[good], kind="stable")]
    _, first = np.unique(j[order], return_index=True)
    keep = np.sort(order[first])
    fs.det_index = keep
    s = j[keep]
    fs.star_vec, fs.star_mag = v[s], sky.table.mag[idx[s]].astype(float)
    fs.star_bv, fs.star_hip = sky.table.bv[idx[s]].astype(float), sky.table.hip[idx[s]]


@dataclass
class GeometryFit:
    camera: Camera
    rotations: list  # fitted camera -> ICRS matrix per solved frame
    fitted: list  # names of the fitted camera terms
    fixed: dict  # term -> reason it was fixed
    sigma: dict  # term -> 1-sigma uncertainty
    residuals: list  # per frame (N, 2) px residuals of the kept matches
    positions: list  # per frame (N, 2) detected px of the kept matches
    keep: list  # per frame boolean mask over the frame's matches
    rms_px: float = float("nan")


TERMS = ("f", "log_aspect", "cx", "cy", "k1", "k2")


def _camera(base: Camera, p: dict) -> Camera:
    return dataclasses.replace(
        base, f_px=p["f"], aspect=float(np.exp(p["log_aspect"])), cx_px=p["cx"], cy_px=p["cy"], k1=p["k1"], k2=p["k2"]
    )


def _residuals(theta, names, fixed_vals, base, frames, masks):
    p = dict(fixed_vals)
    p.update(zip(names, theta[: len(names)]))
    cam = _camera(base, p)
    out = []
    for i, (fs, m) in enumerate(zip(frames, masks)):
        w = theta[len(names) + 3 * i : len(names) + 3 * i + 3]
        R = fs.R @ _rotvec(w)
        x, y, _ = cam.project(fs.star_vec[m] @ R)
        d = fs.det_index[m]
        out.append(np.column_stack([x - fs.det["x_px"][d], y - fs.det["y_px"][d]]).ravel())
    return np.concatenate(out)


def _sparsity(n_terms: int, masks: list):
    """Which parameters each residual depends on: a frame's star residuals on the camera's ``n_terms`` and its
    own three attitude parameters only. With it the finite-difference Jacobian costs n_terms + 3 residual
    evaluations, not n_terms + 3 x frames (100 frames: ~9 instead of ~306 per step)."""
    from scipy.sparse import lil_matrix

    rows = 2 * sum(int(m.sum()) for m in masks)
    out = lil_matrix((rows, n_terms + 3 * len(masks)), dtype=np.int8)
    out[:, :n_terms] = 1
    r = 0
    for i, m in enumerate(masks):
        k = 2 * int(m.sum())
        out[r : r + k, n_terms + 3 * i : n_terms + 3 * i + 3] = 1
        r += k
    return out


def _corner_effect(term: str, cam: Camera) -> float:
    """Pixels a corner star moves per unit change of ``term`` (to turn a sigma into a visible size)."""
    r2 = ((cam.width_px / 2) ** 2 + (cam.height_px * cam.aspect / 2) ** 2) / cam.f_px**2
    r = np.sqrt(r2) * cam.f_px
    return {"f": r / cam.f_px, "log_aspect": cam.height_px / 2, "cx": 1.0, "cy": 1.0, "k1": r * r2, "k2": r * r2 * r2}[
        term
    ]


def residual_cut(rr: np.ndarray) -> float:
    """The radius (px) beyond which a match's residual is left out: 3.5 sigma of the residuals' radii (the median of
    a 2-D Gaussian's radius is 1.1774 sigma), at least 0.5 px."""
    return max(3.5 * float(np.median(rr)) / 1.1774, 0.5)


def fit_geometry(
    frames: list[FrameSolution],
    start: Camera,
    sky,
    radius_px: float,
    rules: dict = RULES,
    log=lambda m: None,
    reach: float = 1.0,
) -> GeometryFit:
    """The joint fit (see module doc) over the solved ``frames``, matched here at ``radius_px`` (``reach``:
    :func:`match_catalogue`)."""
    from scipy.optimize import least_squares

    n_frames = len(frames)
    vals = {
        "f": start.f_px,
        "log_aspect": float(np.log(start.aspect)),
        "cx": start.cx_px,
        "cy": start.cy_px,
        "k1": start.k1,
        "k2": start.k2,
    }
    centre = {"cx": (start.width_px - 1) / 2, "cy": (start.height_px - 1) / 2}
    fixed: dict = {}
    cam = start
    for fs in frames:
        match_catalogue(fs, cam, sky, radius_px, reach)
    n_stars = sum(len(fs.det_index) for fs in frames)
    r_max = np.sqrt(((cam.width_px / 2) ** 2 + (cam.height_px / 2) ** 2))
    edge = (  # how far towards the corner the matched stars reach
        max(
            (
                np.max(np.hypot(fs.det["x_px"][fs.det_index] - cam.cx_px, fs.det["y_px"][fs.det_index] - cam.cy_px))
                for fs in frames
                if len(fs.det_index)
            ),
            default=0.0,
        )
        / r_max
    )
    if n_frames < rules["min_frames_distortion"] or n_stars < rules["min_stars_distortion"]:
        why = (
            f"{n_frames} solved frame(s), {n_stars} matched stars: distortion and principal point need at least "
            f"{rules['min_frames_distortion']} frames and {rules['min_stars_distortion']} stars"
        )
        fixed.update({"k1": why, "k2": why, "cx": why, "cy": why})
    elif edge < rules["min_edge_fraction"]:
        why = f"matched stars reach only {100 * edge:.0f} % of the way to the corner"
        fixed.update({"k1": why, "k2": why, "cx": why, "cy": why})
    elif n_stars < rules["min_stars_k2"]:
        fixed["k2"] = f"{n_stars} matched stars: k2 needs at least {rules['min_stars_k2']}"
    for t in ("cx", "cy"):
        if t in fixed:
            vals[t] = centre[t]
    for t in ("k1", "k2"):
        if t in fixed:
            vals[t] = 0.0
    for attempt in range(4):
        names = [t for t in TERMS if t not in fixed]
        masks = [np.ones(len(fs.det_index), bool) for fs in frames]
        theta = np.concatenate([[vals[t] for t in names], np.zeros(3 * n_frames)])
        for it in range(3):
            res = least_squares(
                _residuals,
                theta,
                args=(names, vals, start, frames, masks),
                x_scale="jac",
                method="trf",
                jac_sparsity=_sparsity(len(names), masks),
            )
            theta = res.x
            r = res.fun.reshape(-1, 2)
            rr = np.hypot(r[:, 0], r[:, 1])
            cut = residual_cut(rr)
            new, pos = [], 0
            for fs, m in zip(frames, masks):
                k = int(m.sum())
                mm = m.copy()
                mm[np.flatnonzero(m)] = rr[pos : pos + k] < cut
                pos += k
                new.append(mm)
            if all((a == b).all() for a, b in zip(new, masks)):
                break
            masks = new
        p = dict(vals)
        p.update(zip(names, theta[: len(names)]))
        # uncertainties from the Jacobian (residual variance from the fit)
        J = res.jac.toarray() if hasattr(res.jac, "toarray") else res.jac
        dof = max(len(res.fun) - len(theta), 1)
        s2 = float(res.fun @ res.fun) / dof
        try:
            cov = np.linalg.inv(J.T @ J) * s2
            sig = {t: float(np.sqrt(max(cov[i, i], 0.0))) for i, t in enumerate(names)}
        except np.linalg.LinAlgError:
            sig = {t: float("inf") for t in names}
        cam = _camera(start, p)
        loose = [
            t
            for t in ("k2", "k1", "cx", "cy")
            if t in sig and sig[t] * _corner_effect(t, cam) > rules["max_corner_sigma_px"]
        ]
        weak = [t for t in ("k2", "k1") if t in sig and abs(p[t]) < 2 * sig[t]]
        if not loose and not weak:
            break
        t = (loose or weak)[0]
        grp = ("cx", "cy") if t in ("cx", "cy") else (t,)
        for g in grp:
            fixed[g] = (
                f"not constrained by these frames: its 1-sigma uncertainty ({sig[t]:.3g}) moves a corner star "
                f"by {sig[t] * _corner_effect(t, cam):.2f} px > {rules['max_corner_sigma_px']} px"
                if loose
                else f"not significant: {p[t]:.3g} +- {sig[t]:.3g} (under 2 sigma); fixed at 0 rather than over-fitted"
            )
            vals[g] = centre[g] if g in centre else 0.0
        log(f"fit-camera: fixing {', '.join(grp)}: {fixed[grp[0]]}")
    rots = [fs.R @ _rotvec(theta[len(names) + 3 * i : len(names) + 3 * i + 3]) for i, fs in enumerate(frames)]
    resid, posn, pos = [], [], 0
    r = res.fun.reshape(-1, 2)
    for fs, m in zip(frames, masks):
        k = int(m.sum())
        resid.append(r[pos : pos + k])
        d = fs.det_index[m]
        posn.append(np.column_stack([fs.det["x_px"][d], fs.det["y_px"][d]]))
        pos += k
    allr = np.concatenate(resid) if resid else np.zeros((0, 2))
    rms = float(np.sqrt(np.mean(np.sum(allr**2, axis=1)))) if len(allr) else float("nan")
    return GeometryFit(cam, rots, names, fixed, sig, resid, posn, masks, rms)


def grow_matches(frames: list[FrameSolution], start: Camera, sky, radius_px: float, reach=GROWING_REACH) -> Camera:
    """A start for the joint fit on a lens whose distortion moves its outer stars beyond the match radius (a wide
    lens: 12 px at half the way to the corner on a 51 deg one, so those stars never match and the distortion is
    never seen): fitted from the centre outwards, matching at ``radius_px`` only the detections within each
    ``reach`` of the centre-to-corner distance (:data:`GROWING_REACH`) under :data:`GROWING_RULES`, each stage's
    camera and attitudes (``fs.R``, updated where the stage matched :data:`GROWING_MIN_MATCHES` of the frame's
    stars; a frame with fewer sits the stage out, and a stage that half the frames would sit out is skipped) the next
    one's start. Returns the last stage's camera."""
    cam = start
    for r in reach:
        # a frame with fewer stars this far in sits the stage out (its attitude unconstrained there), keeping its own
        for fs in frames:
            match_catalogue(fs, cam, sky, radius_px, r)
        used = [fs for fs in frames if len(fs.det_index) >= GROWING_MIN_MATCHES]
        if len(used) < max(1, (len(frames) + 1) // 2):  # too few frames this far in for a camera: the next stage
            continue
        g = fit_geometry(used, cam, sky, radius_px, rules=GROWING_RULES, reach=r)
        for fs, R, res in zip(used, g.rotations, g.residuals):
            if len(res) >= GROWING_MIN_MATCHES:
                fs.R = R
        cam = g.camera
    return cam
