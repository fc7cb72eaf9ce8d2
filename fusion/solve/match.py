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
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def partner_table(lo: int, hi: int, first, second, sep, n_stars: int):
    """(offsets (S + 1,), partner, separation) of pair-index rows ``[lo, hi)``, keyed on either star."""
    offs = np.zeros(n_stars + 1, np.int64)
    for q in range(lo, hi):
        offs[first[q] + 1] += 1
        offs[second[q] + 1] += 1
    for a in range(n_stars):
        offs[a + 1] += offs[a]
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
):
    """Hypotheses of anchor pair (i, j) over pair-index rows ``[lo, hi)``.

    ``t`` (n, 2): detections' tangent-plane coordinates at the nominal focal length; ``tol_n`` (n,):
    each detection's tolerance (rad); ``offs`` (n, S + 1), ``partner``, ``psep``: the partner tables of
    (i, k) for every k (:func:`partner_table`, concatenated; empty for i and j). Returns (tried,
    stars A, stars B, focal factors, scores, rotations) of the hypotheses with at least ``min_score``
    matches whose boresight lies in the cap (``center``, ``cos_r``). ``tried`` counts only hypotheses
    whose boresight lies in the cap: one outside it is never accepted in this region, so it cannot be
    a false match of this region (and the caps of neighbouring regions do not count it twice). At most
    ``max_tried`` hypotheses are tried (the work budget left; ``tried == max_tried`` means it ran out).
    ``x_axis``, ``cos_x``: a tracking hint also bounds the roll: a hypothesis whose camera +x axis lies
    farther than ``arccos(cos_x)`` from ``x_axis`` (ICRS) is outside the region too (``cos_x`` < -1: no bound).
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
    ui = np.empty(3)
    uj = np.empty(3)
    uk = np.empty(3)
    r = np.empty((3, 3))
    u1 = np.empty((n, 3))  # the nominal focal length's unit vectors, and i's separations from them
    d1 = np.empty(n)
    for k in range(n):
        u1[k, 0], u1[k, 1], u1[k, 2] = _unit(t[k, 0], t[k, 1], 1.0)
    for k in range(n):
        d1[k] = _angle(u1[i, 0], u1[i, 1], u1[i, 2], u1[k, 0], u1[k, 1], u1[k, 2])
    for q in range(lo, hi):
        if tried >= max_tried:
            break
        for orient in range(2):
            a = first[q] if orient == 0 else second[q]
            b = second[q] if orient == 0 else first[q]
            if not star_ok[a]:
                continue
            kf = 1.0
            if s > 0:
                kf = min(1.0 + s, max(1.0 - s, d_nom / max(sep[q], 1e-12)))
            ui[0], ui[1], ui[2] = _unit(t[i, 0], t[i, 1], kf)
            uj[0], uj[1], uj[2] = _unit(t[j, 0], t[j, 1], kf)
            have_r = cos_r > -1.0  # a region, not the whole sky: place the boresight first
            if have_r:
                r = triad(ui, uj, vec[a], vec[b])
                if r[0, 2] * center[0] + r[1, 2] * center[1] + r[2, 2] * center[2] < cos_r - 1e-12:
                    continue  # its boresight lies in another region
                if r[0, 0] * x_axis[0] + r[1, 0] * x_axis[1] + r[2, 0] * x_axis[2] < cos_x - 1e-12:
                    continue  # its roll lies outside the hint's
            if tried >= max_tried:
                break  # the budget: a count, so the same answer on every machine
            tried += 1
            delta = abs(_angle(ui[0], ui[1], ui[2], uj[0], uj[1], uj[2]) - sep[q])
            score = 1 + (1 if delta <= tol_n[j] else 0)
            for k in range(n):
                if k == i or k == j or offs[k, a] == offs[k, a + 1]:
                    continue  # no star at the right distance from A: k cannot match
                if s > 0:
                    uk[0], uk[1], uk[2] = _unit(t[k, 0], t[k, 1], kf)
                    dik = _angle(ui[0], ui[1], ui[2], uk[0], uk[1], uk[2])
                else:
                    uk[0], uk[1], uk[2] = u1[k, 0], u1[k, 1], u1[k, 2]
                    dik = d1[k]
                tk = tol_n[k]
                lo_b = hi_b = -2.0  # cosine bounds of sep(B, C), computed on first use
                for p in range(offs[k, a], offs[k, a + 1]):
                    if abs(psep[p] - dik) > tk:
                        continue
                    if lo_b < -1.5:
                        djk = _angle(uj[0], uj[1], uj[2], uk[0], uk[1], uk[2])
                        lo_b = math.cos(min(math.pi, djk + delta + tk))
                        hi_b = math.cos(max(0.0, djk - delta - tk))
                    c = partner[p]
                    cbc = vec[b, 0] * vec[c, 0] + vec[b, 1] * vec[c, 1] + vec[b, 2] * vec[c, 2]
                    if cbc < lo_b or cbc > hi_b:
                        continue
                    if not have_r:  # whole sky: the rotation only when a partner fits
                        r = triad(ui, uj, vec[a], vec[b])
                        have_r = True
                    x0 = r[0, 0] * uk[0] + r[0, 1] * uk[1] + r[0, 2] * uk[2]
                    x1 = r[1, 0] * uk[0] + r[1, 1] * uk[1] + r[1, 2] * uk[2]
                    x2 = r[2, 0] * uk[0] + r[2, 1] * uk[1] + r[2, 2] * uk[2]
                    if _angle(x0, x1, x2, vec[c, 0], vec[c, 1], vec[c, 2]) <= tk:
                        score += 1
                        break
            if score < min_score:
                continue
            if not have_r:
                r = triad(ui, uj, vec[a], vec[b])
            if m == cap:  # grow the outputs (rarely: few hypotheses score)
                cap *= 2
                out_a, out_b, out_k = _grow(out_a, cap), _grow(out_b, cap), _grow(out_k, cap)
                out_s, out_r = _grow(out_s, cap), _grow(out_r, cap)
            out_a[m], out_b[m], out_k[m], out_s[m] = a, b, kf, score
            out_r[m] = r
            m += 1
    return tried, out_a[:m], out_b[:m], out_k[:m], out_s[:m], out_r[:m]


@njit(cache=True, inline="always")
def _ndtr(x: float) -> float:
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


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
    phot: bool,
    consts,
):
    """Tracking: every hypothesis "detection i is star a, j is star b" (a of ``a_rows``, b of ``b_rows``, rows of the
    catalogue cut ``vec``/``mag``) and its log weight (:meth:`fusion.solve.fine.CoarseToFineSolver._track`).

    ``t`` (n, 2): tangent-plane coordinates at the nominal focal length; ``cand_offs``/``cand_rows``: each
    detection's catalogue candidates (its cone around the hint's prediction); ``m_hint``: the hint (camera ->
    ICRS), 1-sigma ``sig`` (rad); ``s``: the focal-length tolerance; ``tol``: the match tolerance, ``sig_c`` the
    centroid error (rad); ``near_*``: the bright stars around the hint's field (unit vectors, magnitudes, their
    row in the cut); ``cam``: (f, fy, cx, cy, k1, k2, k3, p1, p2, width, height, edge margin) of the camera;
    ``inst``: the detections' instrumental magnitudes; ``consts``: (log eps, log(1 - eps), log miss,
    log(1 - miss), magnitude margin, magnitude sigma, log(spread / (sigma sqrt(2 pi)))). Returns (log weights
    (H,), rotations (H, 3, 3), focal factors (H,), matched rows (H, n), -1 where a detection is unmatched)."""
    n = t.shape[0]
    ui0x, ui0y, ui0z = _unit(t[i, 0], t[i, 1], 1.0)
    uj0x, uj0y, uj0z = _unit(t[j, 0], t[j, 1], 1.0)
    d = _angle(ui0x, ui0y, ui0z, uj0x, uj0y, uj0z)
    sd = math.sqrt(2.0) * sig_c
    if s > 0:
        lo, hi = d / (1 + s), d / (1 - s)
    else:
        lo, hi = d, d
    log_eps, log_1eps, log_miss, log_1miss, margin, mag_sig, log_spread = (
        consts[0],
        consts[1],
        consts[2],
        consts[3],
        consts[4],
        consts[5],
        consts[6],
    )
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
            lw += m * log_1miss + missed * log_miss
            if phot:
                zp = 0.0
                for k in range(n):
                    if row[k] >= 0:
                        zp += mag[row[k]] - inst[k]
                zp /= m
                chi2 = 0.0
                for k in range(n):
                    if row[k] >= 0:
                        chi2 += (mag[row[k]] - inst[k] - zp) ** 2
                lw += -0.5 * chi2 / (mag_sig * mag_sig) + (m - 1) * log_spread
            out_w[h] = lw
            out_r[h] = r
            out_k[h] = kf
            h += 1
    return out_w[:h], out_r[:h], out_k[:h], out_c[:h]
