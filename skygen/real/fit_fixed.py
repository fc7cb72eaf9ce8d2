"""Light fixed on the sensor, found in real frames: ``sensor.fixed_sources`` for ``skygen fit-camera``.

A glow at the sensor's edge (amplifier glow, a light leak) or a bright defect stays at the same pixels while
the stars move with the attitude. In the frames it is a detection no catalogue star explains, at about the
same place (within :data:`FIXED_RADIUS_PX`: a glow's centroid wanders with the noise) in frames of several
pointings. Random uncatalogued sources (stars fainter than the catalogue, particle hits) also fall near a
given place now and then; a place counts only where the frames' other pointings put an unexplained
detection within the radius more often than their own density of such detections allows at a Poisson
chance of :data:`FIXED_CHANCE` (the test of the solver's defect regions, ``fusion.solve.defects``), and from
at least :data:`FIXED_MIN_POINTINGS` pointings. Sharp detections (a hot pixel, a particle hit) are left to the
sensor's hot-pixel and cosmic-ray terms.

Each source found is one round Gaussian: its position the median of its detections' (per frame, the
flux-weighted centre of its fragments: an extended glow can be detected in pieces), its width from the detected
flux per frame (the fragments' sum) and peak (a Gaussian's peak is flux / (2 pi sigma^2)). A Gaussian's light
below the detection threshold is not detected, so the fit renders it, measures it as the frames were measured
(:func:`detected_near`) and scales its light until the renders detect what the frames do (within 10 %, at most
three more renders)
(``skygen.real.fit_render.fit_model_terms``); the fitted camera renders it in every frame
(``skygen.render.frame.Renderer.deposit_fixed``).
"""

from __future__ import annotations

import math

import numpy as np

FIXED_RADIUS_PX = 8.0  # detections this close to one another are one fixed source (a glow wanders by a few px)
FIXED_MIN_POINTINGS = 3  # ... seen from at least this many pointings
FIXED_CHANCE = 1e-4  # ... more often than the frames' own unexplained detections fall there by chance (per
#   detection tested: with ~100 unexplained detections in a fit, about one chance source in a hundred fits; four
#   pointings that all show a glow reach ~3e-5 at a typical density, 1e-6 would need six)
FIXED_MAX_SHARPNESS = 2.0  # a detection whose peak holds more of its flux than this times the frame's catalogue
#   stars' (median) is a hot pixel or a particle hit: the sensor's hot-pixel and cosmic-ray terms model those
#   (corruptions.hotpixels, corruptions.cosmic_rays), not a fixed source
POINTING_SEPARATION_DEG = 1.0  # frames whose boresights lie closer than this are one pointing (a staring camera)


def pointings(boresights: list, separation_deg: float = POINTING_SEPARATION_DEG) -> np.ndarray:
    """A pointing id per frame: frames whose boresight (unit vectors, ICRS) lies within ``separation_deg`` of
    an earlier pointing's first frame share its id."""
    ids, firsts = [], []
    c = math.cos(math.radians(separation_deg))
    for b in boresights:
        b = np.asarray(b, np.float64)
        hit = next((i for i, f in enumerate(firsts) if float(f @ b) >= c), None)
        if hit is None:
            firsts.append(b)
            hit = len(firsts) - 1
        ids.append(hit)
    return np.asarray(ids, np.int64)


def find(unexplained: list, boresights: list, width_px: int, height_px: int) -> list:
    """Fixed sources in frames: ``unexplained`` one dict per frame (``x_px``, ``y_px``, ``flux_adu``,
    ``peak_adu`` of the detections no catalogue star explains, and ``star_share``: the median peak / flux of its
    catalogue stars, or NaN), ``boresights`` each frame's (unit vector).
    Returns [{x_px, y_px, flux_adu, sigma_px, frames, pointings}], brightest first."""
    from scipy.spatial import cKDTree
    from scipy.stats import poisson

    pid = pointings(boresights)
    cols = {k: [] for k in ("x_px", "y_px", "flux_adu", "peak_adu")}
    frame, point, limit = [], [], []
    for f, u in enumerate(unexplained):
        n = len(u["x_px"])
        for k in cols:
            cols[k].append(np.asarray(u[k], np.float64))
        frame.append(np.full(n, f))
        point.append(np.full(n, pid[f]))
        share = float(u.get("star_share", np.nan))
        limit.append(np.full(n, FIXED_MAX_SHARPNESS * share if np.isfinite(share) else 1.0))
    if not frame or not sum(len(f) for f in frame):
        return []
    x, y, flux, peak = (np.concatenate(cols[k]) for k in ("x_px", "y_px", "flux_adu", "peak_adu"))
    frame, point, limit = np.concatenate(frame), np.concatenate(point), np.concatenate(limit)
    spread = (flux > 0) & (peak <= limit * np.maximum(flux, 1e-9))  # no sharper than the frame's stars allow
    n_pointings = int(pid.max()) + 1
    if n_pointings < FIXED_MIN_POINTINGS:
        return []
    area = float(width_px * height_px)
    disc = math.pi * FIXED_RADIUS_PX**2
    per_pointing = np.bincount(point, minlength=n_pointings)
    # the chance that pointing p has an unexplained detection within the radius of a given place
    q = 1.0 - np.exp(-per_pointing * disc / area)
    tree = cKDTree(np.column_stack([x, y]))
    near = tree.query_ball_point(np.column_stack([x, y]), FIXED_RADIUS_PX)
    flagged = np.zeros(len(x), bool)
    for m, idx in enumerate(near):
        if not spread[m]:
            continue
        idx = [i for i in idx if spread[i]]
        others = set(point[idx].tolist()) - {int(point[m])}
        if len(others) + 1 < FIXED_MIN_POINTINGS:
            continue
        mu = float(q.sum() - q[point[m]])
        flagged[m] = poisson.sf(len(others) - 1, mu) < FIXED_CHANCE
    if not flagged.any():
        return []
    # one source per group of flagged detections linked within the radius
    sel = np.flatnonzero(flagged)
    parent = {int(i): int(i) for i in sel}

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in sel:
        for j in near[i]:
            if flagged[j]:  # (flagged ones are spread)
                parent[root(int(i))] = root(int(j))
    groups: dict = {}
    for i in sel:
        groups.setdefault(root(int(i)), []).append(int(i))
    out = []
    for members in groups.values():
        m = np.asarray(members)
        if len(set(point[m].tolist())) < FIXED_MIN_POINTINGS:
            continue
        # per frame: an extended glow may be detected as a few fragments; its light is their sum, its place their
        # flux-weighted centre, its peak the highest of theirs
        per = []
        for f in sorted(set(frame[m].tolist())):
            k = m[frame[m] == f]
            w = np.maximum(flux[k], 0.0)
            tot = float(w.sum())
            cx = float(np.average(x[k], weights=w)) if tot > 0 else float(np.mean(x[k]))
            cy = float(np.average(y[k], weights=w)) if tot > 0 else float(np.mean(y[k]))
            per.append((cx, cy, tot, float(peak[k].max())))
        cx, cy, tot, pk = (np.array(v) for v in zip(*per))
        fl, top = float(np.median(tot)), max(float(np.median(pk)), 1e-9)
        out.append(
            {
                "x_px": float(np.median(cx)),
                "y_px": float(np.median(cy)),
                "flux_adu": fl,  # detected, per frame (median): what renders of it must detect
                "peak_adu": top,
                "sigma_px": float(np.clip(math.sqrt(max(fl, 0.0) / (2 * math.pi * top)), 0.5, 20.0)),
                "frames": int(len(per)),
                "pointings": int(len(set(point[m].tolist()))),
            }
        )
    return sorted(out, key=lambda s: -s["flux_adu"])


def detected_near(x: np.ndarray, y: np.ndarray, flux: np.ndarray, sources) -> list:
    """The detected flux within :data:`FIXED_RADIUS_PX` of each source's place (``sources``: (x, y, ...) rows),
    summed: how a frame shows each one, measured as :func:`find` measures the real frames."""
    x, y, flux = (np.asarray(a, np.float64) for a in (x, y, flux))
    return [float(flux[np.hypot(x - s[0], y - s[1]) <= FIXED_RADIUS_PX].sum()) for s in sources]


def near_any(x: np.ndarray, y: np.ndarray, sources: list) -> np.ndarray:
    """Flags: a detection within :data:`FIXED_RADIUS_PX` of one of ``sources``."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    out = np.zeros(len(x), bool)
    for s in sources:
        out |= np.hypot(x - s["x_px"], y - s["y_px"]) <= FIXED_RADIUS_PX
    return out
