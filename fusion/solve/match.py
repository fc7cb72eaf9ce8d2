"""The fine stage's inner loops, compiled with numba: score every catalogue pair hypothesis of one detection pair.

For an anchor pair of detections (i, j) and every catalogue pair (A, B) of the pair index whose
separation matches (both orders, A in the searched region), the hypothesis "i is A and j is B"
fixes a rotation (TRIAD) and, with a focal length known to ±s, a focal factor. Its score is the
number of detections that land within their tolerance of a catalogue star: i itself, j when B
lies within its tolerance of where the rotation puts j, and every other detection k for which a
star C does. The rotation is computed only for hypotheses where some k can match, and C is found
without projecting k into the sky first: a star C within ``tol_k`` of where k lands satisfies
``|sep(A, C) - d_ik| <= tol_k`` and ``|sep(B, C) - d_jk| <= delta + tol_k`` (triangle inequality;
``delta`` is how far the rotation puts j from B), so the candidates C are A's partners in the
pair-index range of ``d_ik`` (:func:`partner_table`), and the positional test decides for the few
that pass both distance tests. The scores are exactly those of projecting every detection and
searching the nearest star (the earlier implementation), except that j counts only through B.

The caller's E_false bar gives each hypothesis the least score it could still be accepted with; scoring
stops at the detection that puts it out of reach (:func:`anchor_hypotheses`, "Early rejection"). The
focal-length pass, whose tolerances are wide, finds C through a cube-map grid of the sky instead
(:func:`sky_grid`): the same matches.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _star_offsets(lo: int, hi: int, first, second, n_stars: int):
    """(S + 1,) offsets of a table of pair-index rows ``[lo, hi)`` keyed on either star (CSR: star a's entries at
    ``offs[a]:offs[a + 1]``)."""
    offs = np.zeros(n_stars + 1, np.int64)
    for q in range(lo, hi):
        offs[first[q] + 1] += 1
        offs[second[q] + 1] += 1
    for a in range(n_stars):
        offs[a + 1] += offs[a]
    return offs


@njit(cache=True)
def partner_table(lo: int, hi: int, first, second, sep, n_stars: int):
    """(offsets (S + 1,), partner, separation) of pair-index rows ``[lo, hi)``, keyed on either star; each
    star's partners in ascending separation (the pair index's order), which :func:`anchor_hypotheses` relies on."""
    offs = _star_offsets(lo, hi, first, second, n_stars)
    partner = np.empty(offs[n_stars], np.int32)
    psep = np.empty(offs[n_stars], np.float64)
    fill = offs[:-1].copy()
    for q in range(lo, hi):
        a, b = first[q], second[q]
        partner[fill[a]] = b
        psep[fill[a]] = sep[q]
        fill[a] += 1
        partner[fill[b]] = a
        psep[fill[b]] = sep[q]
        fill[b] += 1
    return offs, partner, psep


@njit(cache=True)
def window_codes(lo: int, hi: int, first, second, n_stars: int):
    """(offsets (S + 1,), codes) of pair-index rows ``[lo, hi)`` keyed on the star a hypothesis anchors first (A):
    ``2 q`` where it is ``first[q]``, ``2 q + 1`` where it is ``second[q]`` -- the (row, orientation) order in which
    :func:`anchor_hypotheses` visits hypotheses; each star's codes ascending."""
    offs = _star_offsets(lo, hi, first, second, n_stars)
    codes = np.empty(offs[n_stars], np.int64)
    fill = offs[:-1].copy()
    for q in range(lo, hi):
        a, b = first[q], second[q]
        codes[fill[a]] = 2 * q
        fill[a] += 1
        codes[fill[b]] = 2 * q + 1
        fill[b] += 1
    return offs, codes


@njit(cache=True)
def region_codes(offs, codes, rows):
    """The codes (:func:`window_codes`) whose star A is one of ``rows`` (a region's stars), ascending: the
    hypotheses of the window :func:`anchor_hypotheses` would visit with A in the region, in its order."""
    total = 0
    for a in rows:
        total += offs[a + 1] - offs[a]
    out = np.empty(total, np.int64)
    m = 0
    for a in rows:
        for p in range(offs[a], offs[a + 1]):
            out[m] = codes[p]
            m += 1
    return np.sort(out)


@njit(cache=True, inline="always")
def _unit(tx: float, ty: float, kf: float):
    x, y = tx / kf, ty / kf
    r = math.sqrt(x * x + y * y + 1.0)
    return x / r, y / r, 1.0 / r


@njit(cache=True, inline="always")
def _angle(ax, ay, az, bx, by, bz) -> float:
    c = ax * bx + ay * by + az * bz
    return math.acos(min(1.0, max(-1.0, c)))


@njit(cache=True)
def _frame(a, b):
    """Columns a, n = a x b / |a x b|, a x n."""
    n = np.cross(a, b)
    n /= np.linalg.norm(n)
    f = np.empty((3, 3))
    f[:, 0] = a
    f[:, 1] = n
    f[:, 2] = np.cross(a, n)
    return f


@njit(cache=True)
def triad(ui, uj, sa, sb):
    """Rotation taking camera vector ``ui`` onto ``sa`` exactly and the ``ui -> uj`` plane onto ``sa -> sb``."""
    return _frame(sa, sb) @ _frame(ui, uj).T


@njit(cache=True)
def _grow(x, cap: int):
    out = np.empty((cap,) + x.shape[1:], x.dtype)
    out[: len(x)] = x
    return out


@njit(cache=True, inline="always")
def _triad_into(r, uix, uiy, uiz, ujx, ujy, ujz, ax, ay, az, bx, by, bz):
    """:func:`triad` written into ``r`` (3, 3) without allocating: the inner loop's rotation."""
    # camera frame: ui, n1 = ui x uj / |ui x uj|, m1 = ui x n1
    nx, ny, nz = uiy * ujz - uiz * ujy, uiz * ujx - uix * ujz, uix * ujy - uiy * ujx
    w = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz = nx * w, ny * w, nz * w
    mx, my, mz = uiy * nz - uiz * ny, uiz * nx - uix * nz, uix * ny - uiy * nx
    # sky frame: a, n2 = a x b / |a x b|, m2 = a x n2
    px, py, pz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    w = 1.0 / math.sqrt(px * px + py * py + pz * pz)
    px, py, pz = px * w, py * w, pz * w
    qx, qy, qz = ay * pz - az * py, az * px - ax * pz, ax * py - ay * px
    # r = [a n2 m2] [ui n1 m1]^T
    r[0, 0] = ax * uix + px * nx + qx * mx
    r[0, 1] = ax * uiy + px * ny + qx * my
    r[0, 2] = ax * uiz + px * nz + qx * mz
    r[1, 0] = ay * uix + py * nx + qy * mx
    r[1, 1] = ay * uiy + py * ny + qy * my
    r[1, 2] = ay * uiz + py * nz + qy * mz
    r[2, 0] = az * uix + pz * nx + qz * mx
    r[2, 1] = az * uiy + pz * ny + qz * my
    r[2, 2] = az * uiz + pz * nz + qz * mz


# --------------------------------------------------------------------------- a grid of the sky (focal pass)
# A cube map: six faces, each a G x G grid of its gnomonic coordinates (u, v) in [-1 - margin, 1 + margin]; a
# star is filed on every face whose extended square holds it. The gnomonic map stretches angles by at most
# 1 + 2 (1 + margin)^2 there (1 / cos^2 of the largest angle from the face centre), and maps the great-circle
# arc between two points to the straight segment between them, so every star within an angle r of a point of
# a face lies in the (u, v) box of half-width that stretch times r around it, on that face.


@njit(cache=True, inline="always")
def _face_uv(x: float, y: float, z: float, f: int):
    """(component along face f's axis, u, v); f = 2 axis + (0 for +, 1 for -)."""
    m = f >> 1
    sg = 1.0 if (f & 1) == 0 else -1.0
    if m == 0:
        c, a, b = sg * x, y, z
    elif m == 1:
        c, a, b = sg * y, x, z
    else:
        c, a, b = sg * z, x, y
    if c <= 0.0:
        return c, 0.0, 0.0
    return c, a / c, b / c


@njit(cache=True)
def sky_grid(vec, margin: float, cell: float):
    """(start (6 G^2 + 1,), the filed stars' vectors (M, 3), their rows of ``vec`` (M,), (G, lowest u, cells per
    unit of u, margin, largest stretch)): every star of ``vec`` filed by cell (see above), cells of about
    ``cell`` in u and v."""
    g = max(1, int(math.ceil((2.0 + 2.0 * margin) / cell)))
    lo = -1.0 - margin
    inv = g / (2.0 + 2.0 * margin)
    nc = 6 * g * g
    cells = np.full((len(vec), 6), -1, np.int64)
    start = np.zeros(nc + 1, np.int64)
    for r in range(len(vec)):
        for f in range(6):
            c, u, v = _face_uv(vec[r, 0], vec[r, 1], vec[r, 2], f)
            if c <= 0.0 or abs(u) > 1.0 + margin or abs(v) > 1.0 + margin:
                continue
            iu = min(g - 1, max(0, int((u - lo) * inv)))
            iv = min(g - 1, max(0, int((v - lo) * inv)))
            cells[r, f] = f * g * g + iu * g + iv
            start[cells[r, f] + 1] += 1
    for q in range(nc):
        start[q + 1] += start[q]
    fill = start[:-1].copy()
    gvec = np.empty((start[nc], 3))
    grow = np.empty(start[nc], np.int32)
    for r in range(len(vec)):
        for f in range(6):
            q = cells[r, f]
            if q >= 0:
                gvec[fill[q]] = vec[r]
                grow[fill[q]] = r
                fill[q] += 1
    par = np.array([g, lo, inv, margin, 1.0 + 2.0 * (1.0 + margin) ** 2 + 1e-6])
    return start, gvec, grow, par


@njit(cache=True, inline="always")
def _grid_near(x0: float, x1: float, x2: float, cos_r: float, r: float, skip: int, start, gvec, grow, par) -> bool:
    """Is a filed star other than row ``skip`` within angle r (cosine ``cos_r``) of the unit vector x?"""
    ax, ay, az = abs(x0), abs(x1), abs(x2)
    if ax >= ay and ax >= az:
        f = 0 if x0 > 0 else 1
    elif ay >= az:
        f = 2 if x1 > 0 else 3
    else:
        f = 4 if x2 > 0 else 5
    _, u, v = _face_uv(x0, x1, x2, f)
    g, lo, inv, margin, stretch = int(par[0]), par[1], par[2], par[3], par[4]
    w = stretch * r
    if w > margin:
        raise ValueError("sky grid: a tolerance wider than its margin")
    iu0, iu1 = max(0, int((u - w - lo) * inv)), min(g - 1, int((u + w - lo) * inv))
    iv0, iv1 = max(0, int((v - w - lo) * inv)), min(g - 1, int((v + w - lo) * inv))
    for iu in range(iu0, iu1 + 1):
        row = f * g * g + iu * g
        for p in range(start[row + iv0], start[row + iv1 + 1]):
            if grow[p] != skip and x0 * gvec[p, 0] + x1 * gvec[p, 1] + x2 * gvec[p, 2] >= cos_r:
                return True
    return False


@njit(cache=True)
def anchor_hypotheses(
    i: int,
    j: int,
    t,
    lo: int,
    hi: int,
    first,
    second,
    sep,
    vec,
    star_ok,
    s: float,
    tol_n,
    offs,
    partner,
    psep,
    center,
    cos_r: float,
    min_score: int,
    max_tried: int,
    x_axis,
    cos_x: float,
    h0: int,
    h_limit,
    grid_start,
    grid_vec,
    grid_row,
    grid_par,
    by_codes: bool,
    codes,
):
    """Hypotheses of anchor pair (i, j) over pair-index rows ``[lo, hi)``.

    ``t`` (n, 2): detections' tangent-plane coordinates at the nominal focal length; ``tol_n`` (n,):
    each detection's tolerance (rad); ``offs`` (S + 1, n), ``partner``, ``psep``: the partner tables of
    (i, k) for every k (:func:`partner_table`, concatenated, column k; empty for i and j; star-major, so one
    hypothesis reads one row for every k). Returns (tried,
    stars A, stars B, focal factors, scores, rotations, best score, stopped) of the hypotheses with at least
    ``min_score`` matches (and at least the score they need, below) whose boresight lies in the cap
    (``center``, ``cos_r``). ``tried`` counts only hypotheses whose boresight lies in the cap: one outside
    it is never accepted in this region, so it cannot be a false match of this region (and the caps of
    neighbouring regions do not count it twice). At most ``max_tried`` hypotheses are tried (the work budget
    left; ``tried == max_tried`` means it ran out). ``x_axis``, ``cos_x``: a tracking hint also bounds the
    roll: a hypothesis whose camera +x axis lies farther than ``arccos(cos_x)`` from ``x_axis`` (ICRS) is
    outside the region too (``cos_x`` < -1: no bound).

    **Early rejection.** ``h0``: the hypotheses tried before this call (the solve's H so far); ``h_limit``
    (n + 1,): the largest H at which a hypothesis with s matches can still be accepted (the caller's
    E_false bar; -1 where never). The h-th hypothesis of the solve can only be accepted with a score s
    whose ``h_limit[s] >= h``: scoring stops at the first detection after which that score is out of reach
    (each unmatched detection lowers the reachable score by one), and such a hypothesis is not returned.
    Where no score up to n is enough any more (``stopped``: True), the rest of the rows are counted, not scored
    (H only grows: the caller refuses after this pair, having counted what it always counted).
    ``best score``: the highest score any hypothesis reached (where scoring stopped early: so far).

    **The focal pass** (s > 0) with a grid (``grid_*``: :func:`sky_grid` of ``vec``, a margin wide enough for
    every tolerance; an empty ``grid_start`` reads the partner tables instead): its tolerances are wide, so A
    has many partners at the right distance and each would cost a random read; instead each detection k is put
    on the sky and the grid's few stars near it are tested, the same exact test against every star within
    ``tol_n[k]`` but A (the partner tables' candidates are a superset of those): the same scores, in a few
    reads of a compact table. No partner table is needed then.

    **A region's rows** (``by_codes``): ``codes`` (:func:`region_codes`) lists the (row, orientation) pairs of
    ``[lo, hi)`` whose star A is in the region (``star_ok``), in the order the row scan would meet them: the same
    hypotheses in the same order, without scanning the whole separation window for the few of a small region.
    """
    n = t.shape[0]
    ax, ay, az = _unit(t[i, 0], t[i, 1], 1.0)
    bx, by, bz = _unit(t[j, 0], t[j, 1], 1.0)
    d_nom = _angle(ax, ay, az, bx, by, bz)
    cap = 64
    out_a = np.empty(cap, np.int32)
    out_b = np.empty(cap, np.int32)
    out_k = np.empty(cap)
    out_s = np.empty(cap, np.int64)
    out_r = np.empty((cap, 3, 3))
    m = 0
    tried = 0
    best_seen = 0
    stopped = False
    r = np.empty((3, 3))
    u1 = np.empty((n, 3))  # the nominal focal length's unit vectors, and i's and j's separations from them
    d1 = np.empty(n)
    dj1 = np.empty(n)
    cos_t = np.empty(n)  # cosine of each detection's tolerance; and of a hair more, and its sine (the bounds
    cos_w = np.empty(n)  # below are filters before the exact test: rounding must not make them tighter)
    sin_w = np.empty(n)
    for k in range(n):
        u1[k, 0], u1[k, 1], u1[k, 2] = _unit(t[k, 0], t[k, 1], 1.0)
        cos_t[k] = math.cos(tol_n[k])
        cos_w[k], sin_w[k] = math.cos(tol_n[k] + 1e-12), math.sin(tol_n[k] + 1e-12)
    for k in range(n):
        d1[k] = _angle(u1[i, 0], u1[i, 1], u1[i, 2], u1[k, 0], u1[k, 1], u1[k, 2])
        dj1[k] = _angle(u1[j, 0], u1[j, 1], u1[j, 2], u1[k, 0], u1[k, 1], u1[k, 2])
    # strict pass (s = 0): the cosine bounds of sep(B, C) for each k, with the largest |d_ij - sep| of the rows
    # (a looser bound than each hypothesis's own only lets more candidates reach the exact positional test)
    delta_max = 0.0
    if hi > lo:
        delta_max = max(abs(d_nom - sep[lo]), abs(d_nom - sep[hi - 1]))
    lo_b1 = np.empty(n)
    hi_b1 = np.empty(n)
    for k in range(n):
        lo_b1[k] = math.cos(min(math.pi, dj1[k] + delta_max + tol_n[k]))
        hi_b1[k] = math.cos(max(0.0, dj1[k] - delta_max - tol_n[k]))
    need = 0  # the least score the next hypothesis could be accepted with
    uix, uiy, uiz = u1[i, 0], u1[i, 1], u1[i, 2]
    ujx, ujy, ujz = u1[j, 0], u1[j, 1], u1[j, 2]
    d_ij = d_nom
    use_grid = s > 0 and grid_start.shape[0] > 1
    n_visit = codes.shape[0] if by_codes else 2 * (hi - lo)
    for v in range(n_visit):
        if tried >= max_tried:
            break  # (the row scan's two checks: nothing is counted or scored after the budget ran out)
        code = codes[v] if by_codes else 2 * lo + v
        q, orient = code >> 1, code & 1
        a = first[q] if orient == 0 else second[q]
        b = second[q] if orient == 0 else first[q]
        if not star_ok[a]:
            continue
        kf = 1.0
        if s > 0:
            kf = min(1.0 + s, max(1.0 - s, d_nom / max(sep[q], 1e-12)))
            uix, uiy, uiz = _unit(t[i, 0], t[i, 1], kf)
            ujx, ujy, ujz = _unit(t[j, 0], t[j, 1], kf)
            d_ij = _angle(uix, uiy, uiz, ujx, ujy, ujz)
        have_r = cos_r > -1.0  # a region, not the whole sky: place the boresight first
        if have_r:
            _triad_into(
                r, uix, uiy, uiz, ujx, ujy, ujz, vec[a, 0], vec[a, 1], vec[a, 2], vec[b, 0], vec[b, 1], vec[b, 2]
            )
            if r[0, 2] * center[0] + r[1, 2] * center[1] + r[2, 2] * center[2] < cos_r - 1e-12:
                continue  # its boresight lies in another region
            if r[0, 0] * x_axis[0] + r[1, 0] * x_axis[1] + r[2, 0] * x_axis[2] < cos_x - 1e-12:
                continue  # its roll lies outside the hint's
        if tried >= max_tried:
            break  # the budget: a count, so the same answer on every machine
        while need <= n and h_limit[need] < h0 + tried + 1:
            need += 1  # H only grows: so does the score a hypothesis needs
        tried += 1
        if need > n:  # not even every detection matched could be accepted any more: counted, not scored
            stopped = True
            continue
        delta = abs(d_ij - sep[q])
        score = 1 + (1 if delta <= tol_n[j] else 0)
        if s > 0 and not use_grid:
            c_d, s_d = math.cos(delta + 1e-12), math.sin(delta + 1e-12)
        reach = n - 2 + score  # the most this hypothesis can still score
        if reach < need:
            continue
        for k in range(n):
            if k == i or k == j:
                continue
            matched = False
            if use_grid:
                if not have_r:
                    _triad_into(
                        r, uix, uiy, uiz, ujx, ujy, ujz,
                        vec[a, 0], vec[a, 1], vec[a, 2], vec[b, 0], vec[b, 1], vec[b, 2],
                    )  # fmt: skip
                    have_r = True
                ukx, uky, ukz = _unit(t[k, 0], t[k, 1], kf)
                x0 = r[0, 0] * ukx + r[0, 1] * uky + r[0, 2] * ukz
                x1 = r[1, 0] * ukx + r[1, 1] * uky + r[1, 2] * ukz
                x2 = r[2, 0] * ukx + r[2, 1] * uky + r[2, 2] * ukz
                matched = _grid_near(x0, x1, x2, cos_t[k], tol_n[k], a, grid_start, grid_vec, grid_row, grid_par)
                p0 = p1 = 0
            else:
                p0, p1 = offs[a, k], offs[a + 1, k]
            if p0 != p1:  # else no star at the right distance from A: k cannot match
                if s > 0:
                    ukx, uky, ukz = _unit(t[k, 0], t[k, 1], kf)
                    dik = _angle(uix, uiy, uiz, ukx, uky, ukz)
                else:
                    ukx, uky, ukz = u1[k, 0], u1[k, 1], u1[k, 2]
                    dik = d1[k]
                tk = tol_n[k]
                lo_b, hi_b = (-2.0, -2.0) if s > 0 else (lo_b1[k], hi_b1[k])  # cosine bounds of sep(B, C)
                if p1 - p0 > 8:  # a long list (the focal pass's wide windows, a dense field): skip to dik - tk
                    lo_p, hi_p = p0, p1
                    while lo_p < hi_p:
                        mid = (lo_p + hi_p) >> 1
                        if psep[mid] < dik - tk:
                            lo_p = mid + 1
                        else:
                            hi_p = mid
                    p0 = lo_p
                for p in range(p0, p1):  # A's partners, by separation (the pair index's order)
                    if psep[p] < dik - tk:
                        continue
                    if psep[p] > dik + tk:
                        break
                    if lo_b < -1.5:  # the focal pass: cos(d_jk -+ (delta + tk)) on first use, no trigonometry
                        c_jk = min(1.0, ujx * ukx + ujy * uky + ujz * ukz)
                        c_w = c_d * cos_w[k] - s_d * sin_w[k]
                        s_w = s_d * cos_w[k] + c_d * sin_w[k]
                        if c_jk > 0.0 and c_w > 0.0:  # d_jk and delta + tk both below 90 deg: sum formulas
                            s_jk = math.sqrt(max(0.0, 1.0 - c_jk * c_jk))
                            lo_b = c_jk * c_w - s_jk * s_w
                            hi_b = 1.0 if c_jk >= c_w else c_jk * c_w + s_jk * s_w
                        else:
                            djk = _angle(ujx, ujy, ujz, ukx, uky, ukz)
                            lo_b = math.cos(min(math.pi, djk + delta + tk))
                            hi_b = math.cos(max(0.0, djk - delta - tk))
                    c = partner[p]
                    cx, cy, cz = vec[c, 0], vec[c, 1], vec[c, 2]
                    cbc = vec[b, 0] * cx + vec[b, 1] * cy + vec[b, 2] * cz
                    if cbc < lo_b or cbc > hi_b:
                        continue
                    if not have_r:  # whole sky: the rotation only when a partner fits
                        _triad_into(
                            r, uix, uiy, uiz, ujx, ujy, ujz,
                            vec[a, 0], vec[a, 1], vec[a, 2], vec[b, 0], vec[b, 1], vec[b, 2],
                        )  # fmt: skip
                        have_r = True
                    x0 = r[0, 0] * ukx + r[0, 1] * uky + r[0, 2] * ukz
                    x1 = r[1, 0] * ukx + r[1, 1] * uky + r[1, 2] * ukz
                    x2 = r[2, 0] * ukx + r[2, 1] * uky + r[2, 2] * ukz
                    if x0 * cx + x1 * cy + x2 * cz >= cos_t[k]:  # within tk of C
                        matched = True
                        break
            if matched:
                score += 1
            else:
                reach -= 1
                if reach < need:
                    break  # early rejection: the score it needs is out of reach
        if score > best_seen:
            best_seen = score
        if score < min_score or score < need:
            continue
        if not have_r:
            _triad_into(
                r, uix, uiy, uiz, ujx, ujy, ujz, vec[a, 0], vec[a, 1], vec[a, 2], vec[b, 0], vec[b, 1], vec[b, 2]
            )
        if m == cap:  # grow the outputs (rarely: few hypotheses score)
            cap *= 2
            out_a, out_b, out_k = _grow(out_a, cap), _grow(out_b, cap), _grow(out_k, cap)
            out_s, out_r = _grow(out_s, cap), _grow(out_r, cap)
        out_a[m], out_b[m], out_k[m], out_s[m] = a, b, kf, score
        out_r[m] = r
        m += 1
    return tried, out_a[:m], out_b[:m], out_k[:m], out_s[:m], out_r[:m], best_seen, stopped


@njit(cache=True, inline="always")
def _ndtr(x: float) -> float:
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


@njit(cache=True)
def _photometry(row, n: int, mag, inst, sat, lower_bounds: bool, mag_sig, log_spread, log_mag_norm, zp0, zp_sig):
    """Tracking's photometric log weight of one identification (``row``: each detection's matched star, -1 none):
    the matched stars' catalogue magnitudes against their instrumental ones about a zero point fitted to them,
    each difference beyond the one the zero point spends worth ``log_spread`` less its Gaussian misfit, and the
    fitted zero point held to a known one (``zp0``, 1-sigma ``zp_sig``; 0: none).

    ``lower_bounds``: the saturated detections' (``sat``) fluxes read as lower bounds: the zero point from the others
    (the known one where every matched detection is saturated; -inf where there is none either: no reading), and a
    saturated one's star may be any amount brighter than its flux says but not fainter, a one-sided test worth
    log 2 where it holds (a coincidental star passes it about half the time)."""
    zp = 0.0
    mu = 0
    m = 0
    for k in range(n):
        if row[k] >= 0:
            m += 1
            if not (lower_bounds and sat[k]):
                zp += mag[row[k]] - inst[k]
                mu += 1
    fitted = mu > 0
    if fitted:
        zp /= mu
    elif zp_sig > 0:
        zp = zp0
    else:
        return -np.inf
    chi2 = 0.0
    n_low = 0
    for k in range(n):
        if row[k] >= 0:
            dm = mag[row[k]] - inst[k] - zp
            if lower_bounds and sat[k]:
                dm = max(dm, 0.0)
                n_low += 1
            chi2 += dm * dm
    out = -0.5 * chi2 / (mag_sig * mag_sig) + max(mu - 1, 0) * log_spread + n_low * math.log(2.0)
    if zp_sig > 0 and fitted:
        # the known zero point (earlier frames'): the fitted one's density about it, against the coincidental
        # spread -- the mu-th magnitude difference, which a fitted zero point spends
        tau2 = zp_sig * zp_sig + mag_sig * mag_sig / mu
        out += log_mag_norm - 0.5 * math.log(2 * math.pi * tau2) - 0.5 * (zp - zp0) ** 2 / tau2
    return out


@njit(cache=True)
def track_hypotheses(
    t,
    i: int,
    j: int,
    a_rows,
    b_rows,
    cand_offs,
    cand_rows,
    vec,
    mag,
    m_hint,
    sig: float,
    s: float,
    tol: float,
    sig_c: float,
    log_omega: float,
    near_vec,
    near_mag,
    near_row,
    cam,
    inst,
    sat,
    phot: bool,
    consts,
    floor: float = -np.inf,
):
    """Tracking: every hypothesis "detection i is star a, j is star b" (a of ``a_rows``, b of ``b_rows``, rows of the
    catalogue cut ``vec``/``mag``) and its log weight (:func:`fusion.solve.track.track`).

    ``t`` (n, 2): tangent-plane coordinates at the nominal focal length; ``cand_offs``/``cand_rows``: each
    detection's catalogue candidates (its cone around the hint's prediction); ``m_hint``: the hint (camera ->
    ICRS), 1-sigma ``sig`` (rad); ``s``: the focal-length tolerance; ``tol``: the match tolerance, ``sig_c`` the
    centroid error (rad); ``near_*``: the bright stars around the hint's field (unit vectors, magnitudes, their
    row in the cut); ``cam``: (f, fy, cx, cy, k1, k2, k3, p1, p2, width, height, edge margin) of the camera;
    ``inst``: the detections' instrumental magnitudes, ``sat`` (n,) which are saturated (the photometry is then
    the mixture of two readings, :func:`_photometry`: as measured, and their fluxes as lower bounds);
    ``consts``: (log eps, log(1 - eps), log miss,
    log(1 - miss), magnitude margin, magnitude sigma, log(spread / (sigma sqrt(2 pi))), known zero point (mag),
    its 1-sigma (0: unknown, fitted per hypothesis)); ``floor``: a log weight at or below which a hypothesis is
    dropped (:func:`fusion.solve.track.track` drops every one 30 below the best: the best of earlier calls less
    30), decided before its costliest term, the bright stars it leaves unexplained, which can only lower its
    weight; the best of this call raises it too. Returns (log weights (H,), rotations (H, 3, 3), focal factors
    (H,), matched rows (H, n), -1 where a detection is unmatched) of the hypotheses kept."""
    n = t.shape[0]
    ui0x, ui0y, ui0z = _unit(t[i, 0], t[i, 1], 1.0)
    uj0x, uj0y, uj0z = _unit(t[j, 0], t[j, 1], 1.0)
    d = _angle(ui0x, ui0y, ui0z, uj0x, uj0y, uj0z)
    sd = math.sqrt(2.0) * sig_c
    if s > 0:
        lo, hi = d / (1 + s), d / (1 - s)
    else:
        lo, hi = d, d
    log_eps, log_1eps, log_miss, log_1miss, margin, mag_sig, log_spread, zp0, zp_sig = (
        consts[0],
        consts[1],
        consts[2],
        consts[3],
        consts[4],
        consts[5],
        consts[6],
        consts[7],
        consts[8],
    )
    log_mag_norm = log_spread + 0.5 * math.log(2 * math.pi * mag_sig * mag_sig)  # log(spread)
    base = -1.5 * math.log(2 * math.pi * sig * sig) - math.log(max(math.sin(d), 1e-12)) + 2 * log_omega
    cap = max(16, len(a_rows) * 4)
    out_w = np.empty(cap)
    out_r = np.empty((cap, 3, 3))
    out_k = np.empty(cap)
    out_c = np.empty((cap, n), np.int64)
    h = 0
    ui = np.empty(3)
    uj = np.empty(3)
    uk = np.empty(n * 3).reshape(n, 3)
    dist_i = np.empty(n)
    for k in range(n):
        dist_i[k] = math.hypot(t[k, 0] - t[i, 0], t[k, 1] - t[i, 1])
    f, fy, cx, cy, k1, k2, k3, p1, p2, width, height, edge = (
        cam[0],
        cam[1],
        cam[2],
        cam[3],
        cam[4],
        cam[5],
        cam[6],
        cam[7],
        cam[8],
        cam[9],
        cam[10],
        cam[11],
    )
    for ia in range(len(a_rows)):
        a = a_rows[ia]
        for ib in range(len(b_rows)):
            b = b_rows[ib]
            cd = vec[a, 0] * vec[b, 0] + vec[a, 1] * vec[b, 1] + vec[a, 2] * vec[b, 2]
            sep = math.acos(min(1.0, max(-1.0, cd)))
            if sep < 2 * tol or sep < lo - 7 * sd or sep > hi + 7 * sd:
                continue  # one star for both detections, or a separation the focal range cannot explain
            if s > 0:
                lik = (_ndtr((hi - sep) / sd) - _ndtr((lo - sep) / sd)) / (hi - lo)
                kf = min(1.0 + s, max(1.0 - s, d / sep))
            else:
                lik = math.exp(-0.5 * ((sep - d) / sd) ** 2) / (sd * math.sqrt(2 * math.pi))
                kf = 1.0
            if lik <= 1e-300:
                continue
            for k in range(n):
                uk[k, 0], uk[k, 1], uk[k, 2] = _unit(t[k, 0], t[k, 1], kf)
            ui[:] = uk[i]
            uj[:] = uk[j]
            r = triad(ui, uj, vec[a], vec[b])
            tr = 0.0
            for p in range(3):
                for q in range(3):
                    tr += m_hint[p, q] * r[p, q]
            theta = math.acos(min(1.0, max(-1.0, (tr - 1.0) / 2.0)))
            lw = base - 0.5 * (theta / sig) ** 2 + math.log(lik)
            if h == cap:
                cap *= 2
                out_w, out_k, out_r, out_c = _grow(out_w, cap), _grow(out_k, cap), _grow(out_r, cap), _grow(out_c, cap)
            row = out_c[h]
            row[:] = -1
            row[i], row[j] = a, b
            m = 2
            for k in range(n):
                if k == i or k == j:
                    continue
                x0 = r[0, 0] * uk[k, 0] + r[0, 1] * uk[k, 1] + r[0, 2] * uk[k, 2]
                x1 = r[1, 0] * uk[k, 0] + r[1, 1] * uk[k, 1] + r[1, 2] * uk[k, 2]
                x2 = r[2, 0] * uk[k, 0] + r[2, 1] * uk[k, 1] + r[2, 2] * uk[k, 2]
                slack = min(s, 2 * tol / max(d, 1e-12)) * dist_i[k] if s > 0 else 0.0
                tk = tol + slack
                best, best_c = tk, -1
                for p in range(cand_offs[k], cand_offs[k + 1]):
                    c = cand_rows[p]
                    if c == a or c == b:
                        continue
                    ang = _angle(x0, x1, x2, vec[c, 0], vec[c, 1], vec[c, 2])
                    if ang <= best:
                        best, best_c = ang, c
                if best_c >= 0:
                    dup = False
                    for q in range(n):
                        if row[q] == best_c:
                            dup = True
                    if dup:
                        continue
                    sp2 = sig_c * sig_c + slack * slack  # the centroid, and the scale the pair leaves uncertain
                    lw += log_omega - math.log(2 * math.pi * sp2) - 0.5 * best * best / sp2
                    row[k] = best_c
                    m += 1
            lw += m * log_1eps + (n - m) * log_eps
            # the photometric terms (added below, after the misses, as always): with the misses' most favourable
            # value (none missed), an upper bound of the final weight
            phot_t = 0.0
            if phot:
                # two readings of the magnitudes (_photometry), where a matched detection is saturated: as measured,
                # and its flux as a lower bound; neither known to hold for a camera, so their mixture at 1/2 each
                # (its expectation over coincidental stars is still at most 1)
                phot_t = _photometry(row, n, mag, inst, sat, False, mag_sig, log_spread, log_mag_norm, zp0, zp_sig)
                n_sat = 0
                for k in range(n):
                    if row[k] >= 0 and sat[k]:
                        n_sat += 1
                if n_sat > 0:
                    low = _photometry(row, n, mag, inst, sat, True, mag_sig, log_spread, log_mag_norm, zp0, zp_sig)
                    if low > -np.inf:
                        phot_t = max(phot_t, low) + math.log(0.5 + 0.5 * math.exp(-abs(phot_t - low)))
            if lw + m * log_1miss + phot_t < floor - 1e-9:
                continue  # below the floor whatever it misses: dropped (its row is overwritten by the next)
            faint = -1e30
            for k in range(n):
                if row[k] >= 0 and mag[row[k]] > faint:
                    faint = mag[row[k]]
            # the bright stars this attitude puts on the sensor, clearly brighter than its faintest matched star,
            # that no detection explains
            missed = 0
            for q in range(len(near_mag)):
                if near_mag[q] >= faint - margin:
                    continue
                explained = False
                for k in range(n):
                    if row[k] == near_row[q]:
                        explained = True
                if explained:
                    continue
                vx = r[0, 0] * near_vec[q, 0] + r[1, 0] * near_vec[q, 1] + r[2, 0] * near_vec[q, 2]
                vy = r[0, 1] * near_vec[q, 0] + r[1, 1] * near_vec[q, 1] + r[2, 1] * near_vec[q, 2]
                vz = r[0, 2] * near_vec[q, 0] + r[1, 2] * near_vec[q, 1] + r[2, 2] * near_vec[q, 2]
                if vz <= 1e-9:
                    continue
                x, y = kf * vx / vz, kf * vy / vz
                r2 = x * x + y * y
                rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
                xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
                yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
                px, py = cx + f * xd, cy + fy * yd
                if px >= -0.5 + edge and px < width - 0.5 - edge and py >= -0.5 + edge and py < height - 0.5 - edge:
                    missed += 1
            lw += m * log_1miss + missed * log_miss + phot_t
            if lw - 30.0 > floor:
                floor = lw - 30.0
            out_w[h] = lw
            out_r[h] = r
            out_k[h] = kf
            h += 1
    return out_w[:h], out_r[:h], out_k[:h], out_c[:h]


@njit(cache=True)
def refine_track(t, vec, k: float, s: float, passes: int):
    """The least-squares attitude of an identification (tracking's, :func:`fusion.solve.track.track`, and one pass
    per iteration of the fine stage's ``refine``): ``t`` (m, 2)
    the matched detections' tangent-plane coordinates, ``vec`` (m, 3) their catalogue stars. Per pass: Kabsch's
    rotation at focal factor ``k``, then (three stars or more, ``s`` > 0) Umeyama's scale of the tangent-plane
    coordinates, clipped to 1 +- s. Returns (rotation camera -> ICRS, k, the unit vectors at k (m, 3), rms
    residual angle (rad))."""
    m = t.shape[0]
    uk = np.empty((m, 3))
    rot = np.eye(3)
    for it in range(passes):
        for r in range(m):
            uk[r, 0], uk[r, 1], uk[r, 2] = _unit(t[r, 0], t[r, 1], k)
        h = uk.T @ vec
        uu, _, vt = np.linalg.svd(h)
        d = 1.0 if np.linalg.det(vt.T @ uu.T) >= 0 else -1.0
        dd = np.eye(3)
        dd[2, 2] = d
        rot = vt.T @ dd @ uu.T
        if m >= 3 and s > 0:
            c = vec @ rot
            g = np.empty((m, 2))
            for r in range(m):
                g[r, 0], g[r, 1] = c[r, 0] / c[r, 2], c[r, 1] / c[r, 2]
            gm0, gm1, tm0, tm1 = g[:, 0].mean(), g[:, 1].mean(), t[:, 0].mean(), t[:, 1].mean()
            mm = np.zeros((2, 2))
            ss = 0.0
            for r in range(m):
                a0, a1, b0, b1 = g[r, 0] - gm0, g[r, 1] - gm1, t[r, 0] - tm0, t[r, 1] - tm1
                mm[0, 0] += a0 * b0
                mm[0, 1] += a0 * b1
                mm[1, 0] += a1 * b0
                mm[1, 1] += a1 * b1
                ss += a0 * a0 + a1 * a1
            sv = np.linalg.svd(mm)[1]
            det = mm[0, 0] * mm[1, 1] - mm[0, 1] * mm[1, 0]
            flip = 1.0 if det >= 0 else -1.0
            k = min(1.0 + s, max(1.0 - s, (sv[0] + flip * sv[1]) / ss))
    for r in range(m):
        uk[r, 0], uk[r, 1], uk[r, 2] = _unit(t[r, 0], t[r, 1], k)
    acc = 0.0
    for r in range(m):
        x0 = rot[0, 0] * uk[r, 0] + rot[0, 1] * uk[r, 1] + rot[0, 2] * uk[r, 2]
        x1 = rot[1, 0] * uk[r, 0] + rot[1, 1] * uk[r, 1] + rot[1, 2] * uk[r, 2]
        x2 = rot[2, 0] * uk[r, 0] + rot[2, 1] * uk[r, 1] + rot[2, 2] * uk[r, 2]
        a = _angle(x0, x1, x2, vec[r, 0], vec[r, 1], vec[r, 2])
        acc += a * a
    return rot, k, uk, math.sqrt(acc / m)
