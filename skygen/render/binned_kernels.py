"""The binned renderer's inner loops (:mod:`skygen.render.binned`), compiled with numba.

Static sensor-size maps are *block-major*: pixel (y, x) at b * s^2 + (y % s) * s + x % s,
b = (y // s) * wb + x // s, so a stored pixel's s^2 sensor pixels are contiguous. A frame's
light lives in *compact* buffers: only the blocks its sources touch get a slot, entry
slot[b] * s^2 + (y % s) * s + x % s, so the per-frame memory is small and read in order.
Randomness: SplitMix64 streams (:func:`_next`, as :mod:`skygen.hashrng`) for uniforms and
numba's generator (seeded by :func:`seed`) for Poisson and Gaussian draws.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_SQRT2 = math.sqrt(2.0)


@njit(cache=True)
def mark_boxes(mark, boxes, f, wb):
    for i in range(len(boxes)):
        ya, yb, xa, xb = boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3]
        if ya < 0:
            continue
        for by in range(ya // f, (yb - 1) // f + 1):
            for bx in range(xa // f, (xb - 1) // f + 1):
                mark[by * wb + bx] = 1


@njit(cache=True)
def slots(mark, slot, blocks):
    """Give every marked block a compact slot (in block order); unmark; return the count."""
    m = 0
    for b in range(len(mark)):
        if mark[b]:
            slot[b] = m
            blocks[m] = b
            m += 1
            mark[b] = 0
        else:
            slot[b] = -1
    return m


@njit(cache=True)
def _add(buf, paint, slot, weight, use_weight, f, wb, yy, xa, xb, vals, v0):
    """Add vals[v0 + (x - xa)] (times the static ``weight`` of the pixel, block-major, when
    ``use_weight``) to row ``yy``, columns [xa, xb), of the compact buffer; return the largest
    unweighted value."""
    n = f * f
    by, ry = yy // f, yy % f
    bx, rx = xa // f, xa % f
    k = slot[by * wb + bx] * n + ry * f + rx
    ks = (by * wb + bx) * n + ry * f + rx
    pk = 0.0
    for xx in range(xa, xb):
        v = vals[v0 + xx - xa]
        buf[k] += v * weight[ks] if use_weight else v
        paint[k] = True
        pk = max(pk, v)
        rx += 1
        if rx == f:
            rx = 0
            bx += 1
            if xx + 1 < xb:
                k = slot[by * wb + bx] * n + ry * f
                ks = (by * wb + bx) * n + ry * f
        else:
            k += 1
            ks += 1
    return pk


@njit(cache=True)
def paint_gauss(buf, paint, slot, weight, xs, ys, flux, radii, sigma, f, h, w):
    """Add Gaussian stamps (exactly as :func:`skygen.instrument.psf.gaussian_stamps`: erf differences,
    normalised to the flux), times the pixels' ``weight`` (PRNU, 0 on dead pixels), into the
    compact buffer; return each stamp's peak pixel (unweighted, as Renderer.deposit sees it)."""
    wb = w // f
    peaks = np.zeros(len(xs))
    row = np.empty(64)
    for i in range(len(xs)):
        r = radii[i]
        n = 2 * r + 1
        x0 = math.floor(xs[i] + 0.5) - r
        y0 = math.floor(ys[i] + 0.5) - r
        ya, xa = max(y0, 0), max(x0, 0)
        yb, xb = min(y0 + n, h), min(x0 + n, w)
        if ya >= yb or xa >= xb:
            continue
        gx = np.empty(n)
        gy = np.empty(n)
        ex0 = math.erf((x0 - 0.5 - xs[i]) / (_SQRT2 * sigma))
        ey0 = math.erf((y0 - 0.5 - ys[i]) / (_SQRT2 * sigma))
        sx = 0.0
        sy = 0.0
        for j in range(n):
            ex1 = math.erf((x0 + j + 0.5 - xs[i]) / (_SQRT2 * sigma))
            ey1 = math.erf((y0 + j + 0.5 - ys[i]) / (_SQRT2 * sigma))
            gx[j] = ex1 - ex0
            gy[j] = ey1 - ey0
            sx += gx[j]
            sy += gy[j]
            ex0 = ex1
            ey0 = ey1
        norm = flux[i] / (sx * sy)
        if len(row) < n:
            row = np.empty(n)
        pk = 0.0
        for yy in range(ya, yb):
            a = gy[yy - y0] * norm
            for xx in range(xa, xb):
                row[xx - xa] = a * gx[xx - x0]
            pk = max(pk, _add(buf, paint, slot, weight, True, f, wb, yy, xa, xb, row, 0))
        peaks[i] = pk
    return peaks


@njit(cache=True)
def paint_patches(buf, paint, slot, weight, use_weight, y0s, x0s, hs, ws, starts, flat, f, h, w):
    """Generic stamps (Moffat, Airy, streaks: weighted like paint_gauss; cosmic-ray charge:
    ``use_weight`` False) into the compact buffer."""
    wb = w // f
    peaks = np.zeros(len(y0s))
    for i in range(len(y0s)):
        y0, x0, ph, pw = y0s[i], x0s[i], hs[i], ws[i]
        ya, xa = max(y0, 0), max(x0, 0)
        yb, xb = min(y0 + ph, h), min(x0 + pw, w)
        if ya >= yb or xa >= xb:
            continue
        pk = 0.0
        for yy in range(ya, yb):
            pk = max(
                pk,
                _add(
                    buf,
                    paint,
                    slot,
                    weight,
                    use_weight,
                    f,
                    wb,
                    yy,
                    xa,
                    xb,
                    flat,
                    starts[i] + (yy - y0) * pw + (xa - x0),
                ),
            )
        peaks[i] = pk
    return peaks


@njit(cache=True)
def _next(state):
    """Next 64-bit output of the SplitMix64 stream ``state[0]`` (as :mod:`skygen.hashrng`)."""
    s = state[0] + np.uint64(0x9E3779B97F4A7C15)
    state[0] = s
    z = (s ^ (s >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=True)
def _uniforms_sum(state, k):
    """Sum of ``k`` independent uniforms on [0, 1) (53-bit, SplitMix64 stream ``state[0]``):
    the quantisation of k separate ADC conversions; faster than k calls of numba's MT19937."""
    acc = 0.0
    for _ in range(k):
        acc += np.float64(_next(state) >> np.uint64(11)) * (1.0 / 9007199254740992.0)
    return acc


@njit(cache=True)
def _poisson(state, lam):
    """Poisson(lam): inversion with one 53-bit uniform below lam = 10 (a block's star photons are
    mostly a fraction of one), numba's PTRS sampler above."""
    if lam >= 10.0:
        return np.random.poisson(lam)
    u = np.float64(_next(state) >> np.uint64(11)) * (1.0 / 9007199254740992.0)
    p = math.exp(-lam)
    cdf = p
    k = 0
    while u >= cdf and k < 200:
        k += 1
        p *= lam / k
        cdf += p
    return k


@njit(cache=True)
def _normal(state):
    """A standard normal draw (Box-Muller on two 53-bit uniforms of the SplitMix64 stream)."""
    u1 = (np.float64(_next(state) >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)
    u2 = np.float64(_next(state) >> np.uint64(11)) * (1.0 / 9007199254740992.0)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


@njit(cache=True)
def _round(total, n, even, max_adu):
    q = total // n
    r = total - q * n
    if 2 * r > n or (2 * r == n and (not even or q % 2 == 1)):
        q += 1
    return min(max(q, 0), max_adu)


@njit(cache=True)
def model_blocks(
    blocks,
    n,
    star,
    charge,
    has_charge,
    live,
    hot_e,
    static_special,
    bg,
    bg_bm,
    use_map,
    sigma,
    g,
    offset_sum,
    limit,
    even,
    max_adu,
    state,
    bg_thr,
    out,
    risky,
    lam_out,
):
    """Stored values of the marked blocks (slot i = ``blocks[i]``) by the block-sum model (module
    doc), drawn from numba's generator (seeded by the caller), written into ``out`` (which
    holds the background-only draw of every block).

    A block of uniform background whose only extra light is starlight (no hot, dead or
    cosmic-ray pixel) first draws its star photons M ~ Poisson(sum of star light): the
    Poisson splits into background + star, so with M = 0 the block *is* a background-only
    block and keeps its table draw; otherwise its electrons are Poisson(background) + M.
    A block where a pixel may reach ``limit`` (full well or ADC top) is flagged in
    ``risky`` (expected electrons in ``lam_out``) for the per-pixel path."""
    sn = sigma * math.sqrt(n)
    for i in range(len(blocks)):
        b = blocks[i]
        bs = b * n  # static maps (block-major)
        bc = i * n  # this frame's compact buffers
        lam_bg = 0.0
        lam_star = 0.0
        chg = 0.0
        top = 0.0
        special = use_map or static_special[b]
        if has_charge:
            for j in range(n):
                if charge[bc + j] > 0:
                    special = True
        if special:
            for j in range(n):
                if live[bs + j]:
                    bk = (bg_bm[bs + j] if use_map else bg) + hot_e[bs + j]
                    v = star[bc + j]
                    c = charge[bc + j] if has_charge else 0.0
                    lam_bg += bk
                    lam_star += v
                    chg += c
                    top = max(top, bk + v + c)
        else:
            vmax = 0.0
            for j in range(n):
                v = star[bc + j]
                lam_star += v
                vmax = max(vmax, v)
            lam_bg = n * bg
            top = bg + vmax
        lam_out[i] = lam_bg + lam_star
        if top + 8.0 * math.sqrt(top) + 8.0 * sigma >= limit:
            risky[i] = True
            continue
        m = _poisson(state, lam_star)
        if m == 0 and not special:
            continue
        if special:
            e_bg = np.random.poisson(lam_bg)
        else:  # Poisson(n * background) from its 2^-32 table
            u = _next(state) >> np.uint64(32)
            lo, hi = 0, len(bg_thr) - 1
            while lo < hi:
                mid = (lo + hi) // 2
                if u < bg_thr[mid]:
                    hi = mid
                else:
                    lo = mid + 1
            e_bg = lo
        t = e_bg + m + chg + sn * _normal(state)
        ih = _uniforms_sum(state, n - 1)
        out[b] = _round(np.int64(math.floor(t / g - ih)) + offset_sum[b], n, even, max_adu)


@njit(cache=True)
def _bloom_column(col, full_well):
    """:func:`skygen.instrument.sensor.bloom` on one column (in place)."""
    h = len(col)
    first, last = -1, -1
    excess = 0.0
    for r in range(h):
        if col[r] > full_well:
            excess += col[r] - full_well
            col[r] = full_well
            if first < 0:
                first = r
            last = r
    if first < 0:
        return
    for direction, start in ((-1, first - 1), (1, last + 1)):
        q = excess / 2.0
        r = start
        while q > 0 and 0 <= r < h:
            take = min(full_well - col[r], q)
            col[r] += take
            q -= take
            r += direction


@njit(cache=True)
def exact_blocks(
    exact,
    slot,
    n,
    f,
    wb,
    h,
    star,
    charge,
    has_charge,
    paint,
    live,
    hot_e,
    static_px,
    bg,
    bg_bm,
    use_map,
    all_on,
    bloom_boxes,
    blooming,
    full_well,
    sigma,
    g,
    offset,
    max_adu,
    even,
    out,
):
    """Blocks drawn pixel by pixel as :func:`skygen.instrument.sensor.read_out` draws them: Poisson,
    cosmic charge, dead pixels, blooming (spilled charge kept only on pixels the full renderer
    draws exactly: source boxes, their blooming extensions, hot and dead pixels; every pixel
    when ``all_on``, i.e. when the full renderer draws every pixel exactly), full well, read
    noise, ADC with offset and clipping; the stored value of each block into ``out``."""
    m = len(exact)
    e = np.zeros(m * n)
    on = np.zeros(m * n, np.bool_)
    ys = np.empty(m * n, np.int64)
    xs = np.empty(m * n, np.int64)
    any_over = False
    for i in range(m):
        b = exact[i]
        sl = slot[b]
        for j in range(n):
            k, bs = i * n + j, b * n + j
            ys[k] = (b // wb) * f + j // f
            xs[k] = (b % wb) * f + j % f
            lam = (bg_bm[bs] if use_map else bg) + hot_e[bs]
            c = 0.0
            if sl >= 0:
                lam += star[sl * n + j]
                on[k] = paint[sl * n + j]
                if has_charge:
                    c = charge[sl * n + j]
            on[k] = on[k] or static_px[bs] or all_on
            for q in range(len(bloom_boxes)):
                if (bloom_boxes[q, 0] <= ys[k] < bloom_boxes[q, 1]) and (
                    bloom_boxes[q, 2] <= xs[k] < bloom_boxes[q, 3]
                ):
                    on[k] = True
            v = np.random.poisson(lam) + c
            if not live[bs]:
                v = 0.0
            e[k] = v
            if v > full_well:
                any_over = True
    if blooming and any_over:
        done = np.zeros(0, np.int64)
        for k in range(m * n):
            if e[k] > full_well and on[k]:
                c = xs[k]
                seen = False
                for d in done:
                    if d == c:
                        seen = True
                if seen:
                    continue
                done = np.append(done, c)
                col = np.zeros(h)
                for k2 in range(m * n):
                    if xs[k2] == c and on[k2]:
                        col[ys[k2]] = e[k2]
                _bloom_column(col, full_well)
                for k2 in range(m * n):
                    if xs[k2] == c and on[k2]:
                        e[k2] = col[ys[k2]]
    for i in range(m):
        total = np.int64(0)
        for j in range(n):
            k = i * n + j
            v = min(e[k], full_well) + sigma * np.random.standard_normal()
            a = np.int64(math.floor(v / g)) + offset[exact[i] * n + j]
            total += min(max(a, 0), max_adu)
        out[exact[i]] = _round(total, n, even, max_adu)


@njit(cache=True)
def seed(seed):
    np.random.seed(seed)


@njit(cache=True)
def background_draw(state, cls, lut8, thr, nthr, vmin, amb):
    """Stored values of background-only blocks: a 32-bit uniform u each (two per SplitMix64
    output), class ``cls[i]`` (its offset sum) resolved by the top byte of u where that
    decides, else by the 32-bit thresholds (the renderer's own table scheme)."""
    out = np.empty(len(cls), np.uint16)
    z = np.uint64(0)
    for i in range(len(cls)):
        c = cls[i]
        if i & 1 == 0:
            z = _next(state)
        u = z & np.uint64(0xFFFFFFFF)
        z = z >> np.uint64(32)
        j = lut8[c, u >> np.uint64(24)]
        if j == amb:
            lo, hi = 0, nthr[c] - 1
            while lo < hi:  # first j with u < thr[c, j]
                mid = (lo + hi) // 2
                if u < thr[c, mid]:
                    hi = mid
                else:
                    lo = mid + 1
            j = lo
        out[i] = vmin[c] + j
    return out
