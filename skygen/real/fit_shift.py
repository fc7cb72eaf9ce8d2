"""The brightness-dependent shift of a camera's star images (``camera.bright_shift_px``, ``_x_px``, ``_y_px``), from its
frames.

Some lenses draw a star as an asymmetric image whose tail points away from the centre (coma; lateral colour on a colour
sensor). The detector's threshold centroid then takes in more of the tail the brighter the star, so bright stars are
detected farther out than faint ones at the same place, by more the farther from the centre. No distortion term can
fit that (distortion moves every star at one place alike), and a solver that matches within a few pixels loses
exactly the brightest stars, the ones a few-star solve is given (``benchmarks/centroid_shift.py`` measures it by
magnitude; on the Amalthea camera the brightest stars sit up to 5 px out at the corners).

The model (:meth:`skygen.instrument.camera.Camera.bright_shift`)::

    shift = bright_shift_px * rho * max(q - bright_shift_from, 0)      outward, px

``rho``: distance from the principal point over the distance to the farthest corner; ``q``: log10 of the detection's
flux over the frame's background noise sigma (both ADU: no zero point or exposure needed, the same on every frame of
a camera whatever its exposure).

The fit (:func:`fit_bright_shift`): every detection of the solved frames paired with the catalogue star the fitted
camera puts nearest (within :data:`MATCH_PX`, each the other's nearest, no second star that close, stars no fainter
than the geometry fit matched), and its radial offset regressed on ``rho``, ``rho^3`` (what the distortion left) and
``rho * max(q - q0, 0)`` for a grid of ``q0``, with 3.5 sigma clipping. The shift is kept only where it is
significant (:data:`MIN_T`) and moves the brightest stars at the corner by at least :data:`MIN_CORNER_PX`; otherwise
the camera has none (0) and the fit says so. ``skygen fit-camera`` then fits the geometry again with the detections
moved back (:func:`unshift_frames`), so the distortion is fitted to where the stars are, not to a mix of shifted
bright and unshifted faint ones.

A second part is the same everywhere on the sensor: ``(bright_shift_x_px, bright_shift_y_px) * max(q - q0, 0)``, a
star image whose tail points one way across the whole field (a tilted or decentred lens; a processor's asymmetric
filtering). It moves a few-star solve's bright stars together, so the attitude they give is off from the one every
star gives by more than its covariance says (the RPi HQ frames of githubdoe/skysolve: the brightest five detections
0.2 px off their stars, the faint ones not). :func:`_fit_uniform` fits it to what the radial part leaves of each
pair's offset along x and y, at the radial part's ``q0`` where there is one.
"""

from __future__ import annotations

import numpy as np

#: a detection and a catalogue star this close (px) may be a pair (bright stars sit up to ~7 px out on Amalthea)
MATCH_PX = 8.0
#: the shift is kept where its coefficient is this many standard errors from 0
MIN_T = 5.0
#: ... and where it moves the brightest 5 % of the paired stars at the farthest corner by at least this much (px)
MIN_CORNER_PX = 1.0
#: pairs beyond q0 needed to fit a shift at q0
MIN_BRIGHT = 15
#: the grid of q0 (log10 flux / sigma) the fit tries
FROM_GRID = tuple(np.round(np.arange(0.5, 4.01, 0.25), 2))
CLIP = 3.5
#: a uniform shift is kept where it moves the brightest 5 % of the paired stars by at least this share of the pairs'
#: own centroid scatter per axis: less would not move a few-star attitude beyond its stated error
MIN_UNIFORM_SHARE = 0.5


def shift_rows(frames: list, camera, rotations: list, sky, noise_adu: list, match_px: float = MATCH_PX) -> np.ndarray:
    """Rows (rho, q, radial offset px, ex, ey, dx, dy) of every detection of ``frames`` (raw detections of
    :class:`skygen.real.fit_geometry.FrameSolution`) paired with a catalogue star (see module doc). The offset is
    the star's place less the detection's along the outward line: negative where the frame shows the star farther
    out than ``camera`` puts it; (ex, ey) that line's unit vector and (dx, dy) the star's place less the detection's
    along x and y."""
    from scipy.spatial import cKDTree

    mags = np.concatenate([fs.star_mag for fs in frames if len(fs.star_mag)] or [np.zeros(0)])
    if not len(mags):
        return np.zeros((0, 3))
    faintest = float(np.percentile(mags, 95))
    corner = camera.far_corner_px
    rows = []
    for fs, R, noise in zip(frames, rotations, noise_adu):
        det = fs.det
        x, y = np.asarray(det["x_px"], np.float64), np.asarray(det["y_px"], np.float64)
        if len(x) < 2:
            continue
        sx, sy = _stars_on(camera, R, sky, faintest, match_px)
        if len(sx) < 2:
            continue
        stars = cKDTree(np.column_stack([sx, sy]))
        d2, j2 = stars.query(np.column_stack([x, y]), k=2)
        back = cKDTree(np.column_stack([x, y])).query(np.column_stack([sx, sy]))[1]
        ok = (d2[:, 0] <= match_px) & (d2[:, 1] > match_px) & (back[j2[:, 0]] == np.arange(len(x)))
        k, j = np.flatnonzero(ok), j2[ok, 0]
        ux, uy = sx[j] - camera.cx_px, sy[j] - camera.cy_px
        r = np.hypot(ux, uy)
        ex, ey = ux / np.maximum(r, 1e-9), uy / np.maximum(r, 1e-9)
        dx, dy = sx[j] - x[k], sy[j] - y[k]
        q = np.log10(np.maximum(np.asarray(det["flux_adu"], np.float64)[k], 1e-12) / max(float(noise), 1e-12))
        rows.append(np.column_stack([r / corner, q, dx * ex + dy * ey, ex, ey, dx, dy]))
    return np.concatenate(rows) if rows else np.zeros((0, 7))


def _stars_on(camera, R: np.ndarray, sky, faintest_mag: float, margin_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of the catalogue stars to ``faintest_mag`` that ``camera`` at attitude ``R`` puts on the sensor grown
    by ``margin_px``."""
    from skygen.real.fit_render import projected

    idx, sx, sy = projected(camera, R, sky, margin_px)
    keep = np.asarray(sky.table.mag, np.float64)[idx] <= faintest_mag
    return sx[keep], sy[keep]


def _clipped_fit(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least squares of ``b`` on ``A`` with 3.5 sigma clipping: (coefficients, kept mask, residual rms of the kept)."""
    keep = np.ones(len(b), bool)
    coef = np.zeros(A.shape[1])
    for _ in range(5):
        coef = np.linalg.lstsq(A[keep], b[keep], rcond=None)[0]
        res = b - A @ coef
        s = 1.4826 * float(np.median(np.abs(res[keep] - np.median(res[keep])))) or 1e-9
        new = np.abs(res) <= CLIP * s
        if new.sum() < A.shape[1] + 3 or np.array_equal(new, keep):
            break
        keep = new
    res = b - A @ coef
    return coef, keep, float(np.sqrt(np.mean(res[keep] ** 2)))


def fit_bright_shift(rows: np.ndarray) -> dict:
    """The camera's ``bright_shift_px``, ``bright_shift_from``, ``bright_shift_x_px`` and ``_y_px`` (``px``, ``from``,
    ``x_px``, ``y_px``) from :func:`shift_rows`' rows (see module doc), with what was measured: 0 where no significant
    shift is found, and a ``note`` saying which."""
    rho, q, off = rows[:, 0], rows[:, 1], rows[:, 2]
    out = {"px": 0.0, "from": 1.5, "x_px": 0.0, "y_px": 0.0, "stars": int(len(rows))}
    if len(rows) < 3 * MIN_BRIGHT:
        out["note"] = f"bright-star shift: not measured ({len(rows)} paired stars, fewer than {3 * MIN_BRIGHT})"
        return out
    base = np.column_stack([rho, rho**3])
    _, keep0, rms0 = _clipped_fit(base, off)
    scale = rms0 or 1e-9
    best = None
    for q0 in FROM_GRID:
        excess = np.maximum(q - q0, 0.0)
        if int((excess > 0.3).sum()) < MIN_BRIGHT:
            continue
        A = np.column_stack([base, rho * excess])
        coef, keep, _ = _clipped_fit(A, off)
        res = off - A @ coef
        cost = float(np.sum(np.minimum(res**2, (CLIP * scale) ** 2)))  # one robust cost across the grid
        if best is None or cost < best[0]:
            best = (cost, float(q0), coef, keep, A)
    if best is None:
        out["note"] = "bright-star shift: not measured (too few bright stars)"
        return out
    _, q0, coef, keep, A = best
    res = off - A @ coef
    dof = max(int(keep.sum()) - A.shape[1], 1)
    cov = np.linalg.pinv(A[keep].T @ A[keep]) * float(np.sum(res[keep] ** 2)) / dof
    se = float(np.sqrt(max(cov[2, 2], 0.0)))
    shift = -float(coef[2])  # outward, px per decade at the farthest corner
    top = float(np.percentile(q, 95)) - q0
    corner_px = shift * max(top, 0.0)
    t = abs(shift) / se if se > 0 else float("inf")
    out.update(
        {
            "from": q0,
            "fitted_px": shift,
            "se_px": se,
            "t": t,
            "corner_px_brightest": corner_px,
            "bright_stars": int((q > q0).sum()),
            "rms_px": float(np.sqrt(np.mean(res[keep] ** 2))),
            "rms_px_without": rms0,
        }
    )
    radial = t >= MIN_T and abs(corner_px) >= MIN_CORNER_PX
    # what the radial model leaves of each pair's offset, along x and y: the uniform part is fitted to that (with a
    # significant radial shift taken off even where it is too small to keep: the few bright stars' directions do not
    # average it out)
    significant = t >= MIN_T
    model = A @ coef if significant else base @ np.linalg.lstsq(base[keep0], off[keep0], rcond=None)[0]
    uniform = _fit_uniform(rows, q0 if significant else None, model)
    if radial:
        out["px"] = shift
        out["note"] = (
            f"bright-star shift: detections {shift:+.2f} px farther out per decade of flux / noise beyond "
            f"10^{q0:g}, at the farthest corner ({corner_px:+.1f} px for the brightest 5 % of {len(rows)} paired "
            f"stars; {t:.0f} standard errors): camera.bright_shift_px {shift:.3f}, bright_shift_from {q0:g}"
        )
    else:
        out["note"] = (
            f"bright-star shift: none ({shift:+.2f} ± {se:.2f} px per decade, {corner_px:+.2f} px at the corner for "
            f"the brightest stars; kept from {MIN_T:g} standard errors and {MIN_CORNER_PX:g} px)"
        )
    out["uniform"] = uniform
    if uniform["kept"]:
        out["x_px"], out["y_px"] = uniform["x_px"], uniform["y_px"]
        if not radial:
            out["from"] = uniform["from"]
    out["note"] += "; " + uniform["note"]
    return out


def _fit_uniform(rows: np.ndarray, q0: float | None, radial_model: np.ndarray) -> dict:
    """The uniform part of the shift (``camera.bright_shift_x_px`` / ``_y_px``): each pair's offset along x and y, less
    what the radial model (``radial_model``, px outward per pair) explains, regressed on ``[1, max(q - q0, 0)]`` with
    3.5 sigma clipping, at ``q0`` (the radial shift's, where it has one) or the ``q0`` of :data:`FROM_GRID` that fits
    best. Kept at :data:`MIN_T` standard errors (the two axes together) where it moves the brightest 5 % of the pairs
    by at least :data:`MIN_UNIFORM_SHARE` of the pairs' own scatter per axis."""
    q, ex, ey, dx, dy = rows[:, 1], rows[:, 3], rows[:, 4], rows[:, 5], rows[:, 6]
    rx, ry = dx - ex * radial_model, dy - ey * radial_model
    one = np.ones((len(rows), 1))
    scale = [_clipped_fit(one, r)[2] or 1e-9 for r in (rx, ry)]
    best = None
    for g in (q0,) if q0 is not None else FROM_GRID:
        excess = np.maximum(q - g, 0.0)
        if int((excess > 0.3).sum()) < MIN_BRIGHT:
            continue
        A = np.column_stack([one, excess])
        fits = [_clipped_fit(A, r) for r in (rx, ry)]
        cost = sum(
            float(np.sum(np.minimum((r - A @ c) ** 2, (CLIP * sc) ** 2)))
            for (c, _, _), r, sc in zip(fits, (rx, ry), scale)
        )
        if best is None or cost < best[0]:
            best = (cost, float(g), A, fits)
    if best is None:
        return {"kept": False, "x_px": 0.0, "y_px": 0.0, "note": "uniform shift: not measured (too few bright stars)"}
    _, g, A, fits = best
    b, se, rms = [], [], []
    for (c, keep, _), r in zip(fits, (rx, ry)):
        res = r - A @ c
        dof = max(int(keep.sum()) - 2, 1)
        cov = np.linalg.pinv(A[keep].T @ A[keep]) * float(np.sum(res[keep] ** 2)) / dof
        b.append(-float(c[1]))  # the detection's place less the star's, px per decade
        se.append(float(np.sqrt(max(cov[1, 1], 0.0))) or 1e-12)
        rms.append(float(np.sqrt(np.mean(res[keep] ** 2))))
    t = float(np.hypot(b[0] / se[0], b[1] / se[1]))
    top = float(np.mean(np.maximum(q[q >= np.percentile(q, 95)] - g, 0.0)))  # the brightest 5 %'s mean excess
    moved = float(np.hypot(*b)) * top
    bar = MIN_UNIFORM_SHARE * float(np.mean(rms))
    kept = t >= MIN_T and moved >= bar
    out = {"kept": bool(kept), "from": g, "fitted_x_px": b[0], "fitted_y_px": b[1], "se_px": se, "t": t}
    out.update(
        {"moved_px_brightest": moved, "bar_px": bar, "x_px": b[0] if kept else 0.0, "y_px": b[1] if kept else 0.0}
    )
    size = f"({b[0]:+.3f}, {b[1]:+.3f}) px per decade beyond 10^{g:g}, {moved:.2f} px on the brightest 5 % (mean)"
    out["note"] = (
        f"uniform shift: bright detections moved {size} ({t:.0f} standard errors): camera.bright_shift_x_px "
        f"{b[0]:.3f}, bright_shift_y_px {b[1]:.3f}"
        if kept
        else f"uniform shift: none ({size}, {t:.1f} standard errors; kept from {MIN_T:g} and {bar:.2f} px, "
        f"{MIN_UNIFORM_SHARE:g} of the pairs' scatter)"
    )
    return out


def unshift_frames(frames: list, camera, noise_adu: list) -> list[dict]:
    """Each frame's detections moved back by ``camera``'s shift (:meth:`skygen.instrument.camera.Camera.unshift`) in
    place of its own; returns the raw detections, to put back after the geometry fit."""
    raw = []
    for fs, noise in zip(frames, noise_adu):
        raw.append(fs.det)
        x, y = camera.unshift(fs.det["x_px"], fs.det["y_px"], fs.det["flux_adu"], noise)
        fs.det = {**fs.det, "x_px": x, "y_px": y}
    return raw


#: the detections a few-star solve is given: each frame's brightest this many
BRIGHTEST = 8
#: a bright detection this close to a catalogue star (px, after the shift is taken off) is that star's
BRIGHT_PAIR_PX = 5.0
#: the fine stage's match tolerance is this many times the 95th percentile of those offsets, within TOL_RANGE_PX
TOL_FACTOR = 1.5
#: 2 px (fusion.solve.fine.TOL_PX) is what the rendered benchmarks were tuned at, and a wider window weakened
#: SPEL's evidence (session 29); below 1 px is untested
TOL_RANGE_PX = (1.0, 2.0)


def bright_offsets(frames: list, camera, rotations: list, sky, noise_adu: list, n: int = BRIGHTEST) -> np.ndarray:
    """(dx, dy) px of each frame's ``n`` brightest detections (moved back by ``camera``'s shift) from the catalogue star
    ``camera`` puts nearest, where one lies within :data:`BRIGHT_PAIR_PX`: the centroid errors a few-star solve meets,
    unclipped (a geometry fit's 3.5 sigma cut drops the bright stars that saturate, bloom or blend)."""
    per = bright_offsets_per_frame(frames, camera, rotations, sky, noise_adu, n)
    return np.concatenate(per) if per else np.zeros((0, 2))


def bright_offsets_per_frame(
    frames: list, camera, rotations: list, sky, noise_adu: list, n: int = BRIGHTEST
) -> list[np.ndarray]:
    """:func:`bright_offsets`, one (k, 2) array per frame that has a star on the sensor."""
    from scipy.spatial import cKDTree

    out = []
    for fs, R, noise in zip(frames, rotations, noise_adu):
        det = fs.det
        flux = np.asarray(det["flux_adu"], np.float64)
        sx, sy = _stars_on(camera, R, sky, 9.0, BRIGHT_PAIR_PX)
        if not len(flux) or not len(sx):
            continue
        k = np.argsort(-flux, kind="stable")[:n]
        x, y = camera.unshift(np.asarray(det["x_px"])[k], np.asarray(det["y_px"])[k], flux[k], noise)
        d, j = cKDTree(np.column_stack([sx, sy])).query(np.column_stack([x, y]))
        ok = d <= BRIGHT_PAIR_PX
        out.append(np.column_stack([x[ok] - sx[j[ok]], y[ok] - sy[j[ok]]]))
    return out


#: a frame's brightest stars count towards the shared error where at least this many lie within the match window
SHARED_MIN_STARS = 3


def shared_error(per_frame: list, window_px: float | None) -> dict:
    """The centroid error a frame's brightest stars share (``camera.shared_sigma_px``): each frame's mean offset of
    its brightest detections within ``window_px`` of their stars (:func:`bright_offsets_per_frame`; those a few-star
    solver matches), per axis, in rms over the frames, less what their own scatter leaves in a mean of that many
    stars. A few-star attitude moves with that mean whatever the number of stars, across the boresight, so the
    per-star scatter (``camera.centroid_sigma_px``), which averages down, cannot stand for it. Part of it may be the
    same every frame (``bias_px``: saturated or shifted bright stars, the same stars in every frame of a set); part
    changes from frame to frame. None where fewer than 3 frames hold :data:`SHARED_MIN_STARS` stars, and 0 where the
    means scatter no more than independent errors would."""
    w = BRIGHT_PAIR_PX if window_px is None else float(window_px)
    means, within, counts = [], [], []
    for off in per_frame:
        off = off[np.hypot(off[:, 0], off[:, 1]) <= w] if len(off) else off
        if len(off) < SHARED_MIN_STARS:
            continue
        m = off.mean(0)
        means.append(m)
        within.append(((off - m) ** 2).sum(0) / (len(off) - 1))  # per axis, unbiased
        counts.append(len(off))
    if len(means) < 3:
        return {"px": None, "frames": len(means), "note": f"shared error: not measured ({len(means)} frames)"}
    m = np.array(means)
    f = len(m)
    own = float(np.mean([v.mean() / c for v, c in zip(within, counts)]))  # what independent errors leave in a mean
    bias = m.mean(0)
    # per axis, both axes pooled: the part the same in every frame (its estimate's own noise, own / f, taken off)
    # and the part that changes from frame to frame beyond own; each estimated apart, each at least 0
    same = max(0.0, float(np.mean(bias**2)) - own / f)
    varies = max(0.0, float(np.sum((m - bias) ** 2)) / (2 * (f - 1)) - own)
    px = float(np.sqrt(same + varies))
    return {
        "px": px,
        "frames": f,
        "bias_px": [float(v) for v in bias],
        "same_px": float(np.sqrt(same)),
        "varies_px": float(np.sqrt(varies)),
        "independent_px": float(np.sqrt(own)),
        "note": (
            f"shared error {px:.3f} px per axis: each frame's brightest {int(np.median(counts))} matched detections "
            f"lie on average ({bias[0]:+.3f}, {bias[1]:+.3f}) px off their stars over {f} frames ({np.sqrt(same):.3f} "
            f"px per axis beyond chance), and their mean moves {np.sqrt(varies):.3f} px from frame to frame beyond "
            f"the {np.sqrt(own):.3f} px their own scatter leaves"
        ),
    }


def match_tolerance(offsets: np.ndarray) -> dict:
    """The fine stage's match tolerance for this camera (``camera.match_tol_px``) from :func:`bright_offsets`:
    :data:`TOL_FACTOR` times their radii's 95th percentile, within :data:`TOL_RANGE_PX`; None with fewer than 20."""
    r = np.hypot(offsets[:, 0], offsets[:, 1]) if len(offsets) else np.zeros(0)
    if len(r) < 20:
        return {
            "px": None,
            "stars": int(len(r)),
            "note": f"match tolerance: the solvers' default ({len(r)} bright stars)",
        }
    p95 = float(np.percentile(r, 95))
    tol = float(np.clip(TOL_FACTOR * p95, *TOL_RANGE_PX))
    return {
        "px": tol,
        "stars": int(len(r)),
        "p95_px": p95,
        "rms_px_per_axis": float(np.sqrt(np.mean(offsets**2))),
        "note": (
            f"match tolerance {tol:.2f} px: the brightest {BRIGHTEST} detections of each frame lie within {p95:.2f} px "
            f"of their stars in 95 % of {len(r)} (x {TOL_FACTOR:g}, within {TOL_RANGE_PX[0]:g}-{TOL_RANGE_PX[1]:g} px)"
        ),
    }
