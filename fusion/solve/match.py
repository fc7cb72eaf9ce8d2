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
