"""Frames rendered directly at the stored resolution: a binned sensor.

``Renderer.render`` draws every full-resolution pixel (1024 x 1024 by default) and then
area-averages the uint16 frame to the stored size (``Renderer.downsample``, OpenCV
``INTER_AREA``). :class:`BinnedRenderer` draws the *stored* pixels of the same
:class:`skygen.render.Scene` directly, with the distribution render-then-downsample gives
them. What follows is the derivation; ``tests/test_stream_binned.py`` checks it.

What render-then-downsample stores
    Stored pixel ``b`` covers the ``n = s x s`` sensor pixels ``p`` of one ``s x s`` block
    (``u = (x + 0.5) / s - 0.5``, :mod:`skygen.conventions`). Each sensor pixel reads
    ``a_p = clip(k_p + o_p, 0, 2^bits - 1)`` with ``k_p = floor(x_p)``,
    ``x_p = (e_p + n_p) / g``, ``e_p ~ Poisson(lam_p) + c_p`` (``lam_p``: dark + sky (+ stray
    light) + PRNU x star light + hot-pixel dark current, 0 for a dead pixel; ``c_p``: cosmic-ray
    charge), ``n_p ~ N(0, sigma_read)``, ``o_p`` the static bias + FPN offset
    (:mod:`skygen.sensor`). ``INTER_AREA`` at an integer factor stores the block sum
    ``A_b = sum_p a_p`` divided by ``n`` and rounded: half to even for ``s = 4, 8``, half up
    for ``s = 2`` (OpenCV's code paths differ; :func:`area_rounding` finds the rule by asking
    OpenCV once, and refuses a factor it cannot reproduce). So the stored value is a
    function of the block sum alone, and it is the block sum we draw.

Block sums (no clipping, no full well reached)
    ``A_b = S_b + O_b`` with ``O_b = sum_p o_p`` static and ``S_b = sum_p k_p``.

    * Background-only blocks (uniform dark + sky, no star, hot, dead pixel or cosmic ray):
      the ``k_p`` are i.i.d. with the per-pixel distribution of the renderer's own
      ``fast`` sampler (:class:`skygen.sensor.BackgroundSampler`), so ``S_b`` has its
      ``n``-fold convolution, computed once and drawn from the same 2^-32 table. Exact.
    * Every other block (stars, hot and dead pixels, cosmic rays, a non-uniform
      background): with ``U`` uniform on [0, 1), ``P(floor(x) = k) = f_{x - U}(k)`` for any
      continuous ``x``. The sum of ``n`` such integers therefore has the pmf of
      ``sum_p (x_p - U_p)`` sampled at the integers up to aliasing terms, and
      ``P(floor(Y - (U_1 + ... + U_{n-1})) = k) = f_{Y - U_1 - ... - U_n}(k)``. Hence::

          S_b  =d  floor( (Poisson(Lambda_b) + C_b + N(0, n sigma_read^2)) / g  -  IH_{n-1} )

      with ``Lambda_b = sum_p lam_p`` (Poisson of the sum = sum of the Poissons),
      ``C_b = sum_p c_p``, read noise summed over the ``n`` pixels (dead ones too) and
      ``IH_{n-1}`` a sum of ``n - 1`` independent uniforms (the quantisation of ``n``
      separate ADC conversions). The aliasing the sampling argument neglects is bounded by
      the characteristic function of the per-pixel read noise in ADU away from the
      origin: at most ``n exp(-2 pi^2 (sigma_read / g)^2 (n - 1) / n)`` (6e-18 for the
      default sensor, sigma_read / g = 1.5). :func:`unsupported_reason` refuses a sensor
      where this bound exceeds 1e-12 (little read noise per ADU: the quantisation of each
      pixel is then visible in the sum and only per-pixel draws are exact).
    * Blocks where any pixel could reach the full well or the ADC top (bright stars, strong
      hot pixels, cosmic-ray cores), extended along the columns as far as blooming can
      spill: every sensor pixel of those blocks is drawn as :func:`skygen.sensor.read_out`
      draws it (Poisson, charge, dead pixels, blooming onto the pixels the full renderer
      draws exactly, full well, read noise, ADC, clipping), then summed. Exact.

The PSF is integrated over each sensor pixel by the renderer's own stamp code (so over
the large pixel by summation), PRNU weights it per sensor pixel, and a star lands in the
stored pixel that contains its full-resolution position: the same frame index gives the
same stars at the same stored positions as render-then-downsample.

What is not reproduced (and so refused by :func:`unsupported_reason`, the stream then
falls back to render-then-downsample): a stored width that does not divide the sensor by
an integer factor, a rounding rule OpenCV does not follow at that factor, too little
read noise per ADU (above), an offset so low that a pixel could clip at 0 ADU.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numba import njit

from .psf import gaussian_radius_px, stamp, streak
from .sensor import BackgroundSampler, background_sampler, bloom

ALIAS_BOUND = 1e-12      # largest tolerated aliasing of the block-sum model (see module doc)
_SQRT2 = math.sqrt(2.0)


# ---------------------------------------------------------------------------------- checks
def aliasing_bound(read_noise_e: float, gain_e_per_adu: float, n: int) -> float:
    """Upper bound on the error of the block-sum model (characteristic-function terms)."""
    if n <= 1:
        return 0.0
    s = read_noise_e / gain_e_per_adu
    return float(n * np.exp(-2.0 * np.pi ** 2 * s * s * (n - 1) / n))


def area_rounding(factor: int) -> str | None:
    """How ``cv2.resize(INTER_AREA)`` rounds a uint16 block mean at ``factor``: ``"half_up"``,
    ``"half_even"``, or None if neither rule reproduces it exactly."""
    n = factor * factor
    rng = np.random.default_rng(0)
    a = rng.integers(0, 4096, (64 * factor, 64 * factor)).astype(np.uint16)
    # force every residue (ties included) to occur
    a[::factor, ::factor] = (np.arange(64 * 64) % n).reshape(64, 64) + 1000
    out = cv2.resize(a, (64, 64), interpolation=cv2.INTER_AREA).astype(np.int64)
    total = a.reshape(64, factor, 64, factor).sum((1, 3)).astype(np.int64)
    for rule in ("half_even", "half_up"):
        if np.array_equal(round_block_sums(total, n, rule), out):
            return rule
    return None


def round_block_sums(total: np.ndarray, n: int, rule: str) -> np.ndarray:
    """Block sums (int) -> stored values, as ``INTER_AREA`` rounds ``total / n``."""
    if rule == "half_up":
        return (total + n // 2) // n
    q, r = np.divmod(total, n)
    return q + (2 * r > n) + ((2 * r == n) & (q % 2 == 1))


def unsupported_reason(renderer) -> str | None:
    """Why :class:`BinnedRenderer` cannot reproduce ``renderer``'s stored frames exactly, or None."""
    cfg = renderer.cfg
    s, cam = cfg.sensor, cfg.camera
    f = renderer.factor
    if cam.width_px % cfg.output.image_size_px or cam.height_px % max(f, 1) or f < 1:
        return (f"stored size {cfg.output.image_size_px} is not an integer binning of the "
                f"{cam.width_px} x {cam.height_px} sensor")
    if f == 1:
        return None
    if area_rounding(f) is None:
        return f"OpenCV's INTER_AREA rounding at factor {f} is not one this renderer reproduces"
    sigma = float(np.hypot(s.read_noise_e, renderer.levels["read_noise"]))
    bound = aliasing_bound(sigma, s.gain_e_per_adu, f * f)
    if bound > ALIAS_BOUND:
        return (f"read noise {sigma:g} e- is {sigma / s.gain_e_per_adu:.2f} ADU: the per-pixel quantisation "
                f"shows in a {f}x{f} sum (model error bound {bound:.1e} > {ALIAS_BOUND:g})")
    low = int(renderer.maps.offset_adu.min())
    if low * s.gain_e_per_adu < 12 * sigma + 1:
        return f"the lowest pixel offset ({low} ADU) lets read noise clip pixels at 0 ADU"
    bg = renderer.background_e
    top = min(s.full_well_e, s.gain_e_per_adu * (2 ** s.bit_depth - 1 - int(renderer.maps.offset_adu.max())))
    if bg + 12 * np.sqrt(bg) + 12 * sigma >= top:
        return f"the background ({bg:.4g} e-/px) reaches the full well or the ADC top"
    return None


# ---------------------------------------------------------------------------------- kernels
# Sensor-size arrays are kept *block-major*: pixel (y, x) at ((y // s) * wb + x // s) * s^2 +
# (y % s) * s + x % s, so a stored pixel's s^2 sensor pixels are contiguous in memory.
@njit(cache=True)
def _bm(y, x, f, wb):
    return ((y // f) * wb + x // f) * f * f + (y % f) * f + x % f


@njit(cache=True)
def _paint_gauss(buf, mark, paint, xs, ys, flux, radii, sigma, f, h, w):
    """Add Gaussian stamps (exactly as :func:`skygen.psf.gaussian_stamps`) into ``buf``;
    mark their stored blocks in ``mark`` and their pixels in ``paint``; return each stamp's
    clipped box (y0, y1, x0, x1; -1 when off the sensor) and peak pixel."""
    wb = w // f
    boxes = np.full((len(xs), 4), -1, np.int64)
    peaks = np.zeros(len(xs))
    for i in range(len(xs)):
        r = radii[i]
        n = 2 * r + 1
        x0 = int(math.floor(xs[i] + 0.5)) - r
        y0 = int(math.floor(ys[i] + 0.5)) - r
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
        ya, xa = max(y0, 0), max(x0, 0)
        yb, xb = min(y0 + n, h), min(x0 + n, w)
        if ya >= yb or xa >= xb:
            continue
        pk = 0.0
        nn = f * f
        for yy in range(ya, yb):
            row = (yy // f) * wb * nn + (yy % f) * f
            k = row + (xa // f) * nn + xa % f
            rx = xa % f
            gyv = gy[yy - y0] * norm
            for xx in range(xa, xb):
                v = gyv * gx[xx - x0]
                buf[k] += v
                paint[k] = True
                pk = max(pk, v)
                rx += 1
                if rx == f:
                    rx = 0
                    k += nn - f + 1
                else:
                    k += 1
        for by in range(ya // f, (yb - 1) // f + 1):
            for bx in range(xa // f, (xb - 1) // f + 1):
                mark[by * wb + bx] = 1
        boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3] = ya, yb, xa, xb
        peaks[i] = pk
    return boxes, peaks


@njit(cache=True)
def _paint_patches(buf, mark, paint, y0s, x0s, hs, ws, starts, flat, f, h, w):
    """Generic stamps (Moffat, Airy, streaks, cosmic-ray charge) into ``buf``; like _paint_gauss."""
    wb = w // f
    boxes = np.full((len(y0s), 4), -1, np.int64)
    peaks = np.zeros(len(y0s))
    for i in range(len(y0s)):
        y0, x0, ph, pw = y0s[i], x0s[i], hs[i], ws[i]
        ya, xa = max(y0, 0), max(x0, 0)
        yb, xb = min(y0 + ph, h), min(x0 + pw, w)
        if ya >= yb or xa >= xb:
            continue
        pk = 0.0
        for yy in range(ya, yb):
            for xx in range(xa, xb):
                v = flat[starts[i] + (yy - y0) * pw + (xx - x0)]
                k = _bm(yy, xx, f, wb)
                buf[k] += v
                paint[k] = True
                pk = max(pk, v)
        for by in range(ya // f, (yb - 1) // f + 1):
            for bx in range(xa // f, (xb - 1) // f + 1):
                mark[by * wb + bx] = 1
        boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3] = ya, yb, xa, xb
        peaks[i] = pk
    return boxes, peaks


@njit(cache=True)
def _model_blocks(blocks, n, star, charge, has_charge, prnu, live, hot_e, static_special, bg, bg_bm, use_map,
                  sigma, g, offset_sum, limit, even, max_adu, seed, out, risky, lam_out):
    """Stored values of the listed blocks by the block-sum model (module doc), drawn from
    numba's generator seeded with ``seed``, written into ``out`` (which holds the
    background-only draw of every block).

    A block of uniform background whose only extra light is starlight (no hot, dead or
    cosmic-ray pixel) first draws its star photons M ~ Poisson(sum of star light): the
    Poisson splits into background + star, so with M = 0 the block *is* a background-only
    block and keeps its table draw; otherwise its electrons are Poisson(background) + M.
    A block where a pixel may reach ``limit`` (full well or ADC top) is flagged in
    ``risky`` (expected electrons in ``lam_out``) for the per-pixel path. The scratch
    buffers are read, not cleared."""
    np.random.seed(seed)
    sn = sigma * math.sqrt(n)
    for i in range(len(blocks)):
        b = blocks[i]
        base = b * n
        lam_bg = 0.0
        lam_star = 0.0
        chg = 0.0
        top = 0.0
        special = use_map or static_special[b]
        if has_charge:
            for j in range(n):
                if charge[base + j] > 0:
                    special = True
        if special:
            for j in range(n):
                k = base + j
                if live[k]:
                    bk = (bg_bm[k] if use_map else bg) + hot_e[k]
                    v = star[k] * prnu[k]
                    c = charge[k] if has_charge else 0.0
                    lam_bg += bk
                    lam_star += v
                    chg += c
                    top = max(top, bk + v + c)
        else:
            vmax = 0.0
            for j in range(n):
                v = star[base + j] * prnu[base + j]
                lam_star += v
                vmax = max(vmax, v)
            lam_bg = n * bg
            top = bg + vmax
        lam_out[i] = lam_bg + lam_star
        if top + 8.0 * math.sqrt(top) + 8.0 * sigma >= limit:
            risky[i] = True
            continue
        m = np.random.poisson(lam_star)
        if m == 0 and not special:
            continue
        t = np.random.poisson(lam_bg) + m + chg + sn * np.random.standard_normal()
        ih = 0.0
        for _ in range(n - 1):
            ih += np.random.random()
        total = np.int64(math.floor(t / g - ih)) + offset_sum[b]
        q = total // n
        r = total - q * n
        if 2 * r > n or (2 * r == n and (not even or q % 2 == 1)):
            q += 1
        out[b] = min(max(q, 0), max_adu)


@njit(cache=True)
def _background_draw(u32, cls, lut8, thr, nthr, vmin, amb):
    """Stored values of background-only blocks: class ``cls[i]`` (its offset sum) resolved by
    the top byte of ``u32[i]`` where that decides, else by the 32-bit thresholds."""
    out = np.empty(len(u32), np.uint16)
    for i in range(len(u32)):
        c = cls[i]
        u = u32[i]
        j = lut8[c, u >> 24]
        if j == amb:
            lo, hi = 0, nthr[c] - 1
            while lo < hi:                      # first j with u < thr[c, j]
                mid = (lo + hi) // 2
                if u < thr[c, mid]:
                    hi = mid
                else:
                    lo = mid + 1
            j = lo
        out[i] = vmin[c] + j
    return out


@njit(cache=True)
def _clear(blocks, n, star, charge, paint, has_charge):
    for i in range(len(blocks)):
        base = blocks[i] * n
        for j in range(n):
            star[base + j] = 0.0
            paint[base + j] = False
            if has_charge:
                charge[base + j] = 0.0


# ---------------------------------------------------------------------------------- renderer
class BinnedRenderer:
    """Stored-size uint16 frames of a :class:`skygen.render.Renderer`'s scenes (module doc).

    Construct once per process (static maps are binned here). :meth:`image` is a pure
    function of (config, scene, numba version): its draws come from the scene's own
    generator, stage ``"binned_noise"`` (never the full renderer's draws), which also seeds
    numba's generator for the block-sum model."""

    def __init__(self, renderer):
        reason = unsupported_reason(renderer)
        if reason is not None:
            from .errors import ConfigError
            raise ConfigError(f"binned rendering cannot reproduce this config: {reason}")
        self.r = renderer
        cfg = renderer.cfg
        s = cfg.sensor
        self.f = f = renderer.factor
        self.n = n = f * f
        self.rule = area_rounding(f) if f > 1 else "half_up"
        self.sensor_shape = h, w = cfg.camera.height_px, cfg.camera.width_px
        self.shape = hb, wb = (h // f, w // f)
        maps = self.maps = renderer.maps
        bm = self.to_block_major
        self.live = bm(~maps.dead_mask)
        self.prnu = bm(maps.prnu.astype(np.float64))
        self.hot_e = bm(maps.hot_map.astype(np.float64) * s.exposure_s)
        self.offset = bm(maps.offset_adu.astype(np.int64))
        self.offset_sum = self.offset.reshape(-1, n).sum(1)                              # O_b
        self.offset_values, cls = np.unique(self.offset_sum, return_inverse=True)
        self.offset_class = cls.astype(np.int32)
        self.static_px = bm((maps.hot_map > 0) | maps.dead_mask)
        self.static_special = self.static_px.reshape(-1, n).any(1)
        self.static_blocks = np.flatnonzero(self.static_special)
        dy, dx = np.divmod(np.arange(n), f)
        by, bx = np.divmod(np.arange(hb * wb), wb)
        self.px_y = bm(np.repeat(np.arange(h)[:, None], w, 1))            # sensor row of each entry
        self.px_x = bm(np.repeat(np.arange(w)[None, :], h, 0))
        self.max_adu = 2 ** s.bit_depth - 1
        self.off_max = int(maps.offset_adu.max())
        self._star = np.zeros(h * w)             # scratch: expected star electrons per sensor pixel
        self._charge = np.zeros(h * w)           # scratch: cosmic-ray charge per sensor pixel
        self._paint = np.zeros(h * w, bool)      # scratch: pixels the full renderer draws exactly
        self._mark = np.zeros(hb * wb, np.uint8)
        self._tables: dict = {}

    def to_block_major(self, a: np.ndarray) -> np.ndarray:
        """A sensor-size (H, W) array in block-major order (see the kernels' comment)."""
        f, (hb, wb) = self.f, self.shape
        return np.ascontiguousarray(a.reshape(hb, f, wb, f).transpose(0, 2, 1, 3)).reshape(-1)

    # ------------------------------------------------------------------ helpers
    def sigma_e(self) -> float:
        return float(np.hypot(self.r.cfg.sensor.read_noise_e, self.r.levels["read_noise"]))

    def block_sum_pmf(self, lam: float, sigma: float) -> tuple[int, np.ndarray]:
        """(smallest value, pmf) of S_b for a background-only block: the n-fold convolution
        of the renderer's per-pixel distribution."""
        px = background_sampler(round(lam, 9), round(sigma, 9), float(self.r.cfg.sensor.gain_e_per_adu))
        out = np.ones(1)
        for _ in range(self.n):
            out = np.convolve(out, px.pmf)
        keep = np.flatnonzero(out > 1e-300)
        return self.n * int(px.kmin) + int(keep[0]), out[keep[0]:keep[-1] + 1]

    def background_tables(self, lam: float, sigma: float):
        """Per offset class: the stored value's distribution, as the renderer's 2^-32 tables."""
        key = (round(lam, 9), round(sigma, 9))
        if key not in self._tables:
            smin, pmf = self.block_sum_pmf(lam, sigma)
            S = smin + np.arange(len(pmf))
            samplers = []
            for O in self.offset_values:
                v = np.clip(round_block_sums(S + O, self.n, self.rule), 0, self.max_adu)
                vals = np.arange(v.min(), v.max() + 1)
                samplers.append(BackgroundSampler.from_pmf(vals, np.bincount(v - v.min(), weights=pmf)))
            if any(sm.lut8 is None for sm in samplers):
                raise ValueError("stored background too noisy for the 8-bit table")
            L = max(len(sm.thresholds) for sm in samplers)
            thr = np.full((len(samplers), L), 2 ** 32, np.uint64)
            for c, sm in enumerate(samplers):
                thr[c, :len(sm.thresholds)] = sm.thresholds
            self._tables = {key: (np.stack([sm.lut8 for sm in samplers]), thr,
                                  np.array([len(sm.thresholds) for sm in samplers], np.int64),
                                  np.array([sm.kmin for sm in samplers], np.int64))}
        return self._tables[key]

    def _stamps(self, stars: dict):
        """Paint every light source into the scratch buffer; return (boxes, peaks, fluxes)."""
        o = self.r.cfg.optics
        h, w = self.sensor_shape
        flux = np.asarray(stars["electrons"], np.float64)
        if len(flux) == 0:
            return np.zeros((0, 4), np.int64), np.zeros(0), flux
        if stars["paths"] is None and o.psf == "gaussian":
            radii = gaussian_radius_px(flux, o.psf_sigma_px).astype(np.int64)
            boxes, peaks = _paint_gauss(self._star, self._mark, self._paint, np.asarray(stars["x_px"], np.float64),
                                        np.asarray(stars["y_px"], np.float64), flux, radii,
                                        float(o.psf_sigma_px), self.f, h, w)
            return boxes, peaks, flux
        if stars["paths"] is None:
            st = [stamp(float(x), float(y), float(fl), o.psf, o.psf_sigma_px, o.moffat_beta)
                  for x, y, fl in zip(stars["x_px"], stars["y_px"], flux)]
        else:
            st = [streak(xs, ys, float(fl), o.psf, o.psf_sigma_px, o.moffat_beta)
                  for xs, ys, fl in zip(stars["paths"][0], stars["paths"][1], flux)]
        boxes, peaks = self._paint_list(self._star, st)
        return boxes, peaks, flux

    def _paint_list(self, buf, patches):
        h, w = self.sensor_shape
        sizes = np.array([p.size for _, _, p in patches], np.int64)
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        flat = np.concatenate([p.ravel() for _, _, p in patches]).astype(np.float64)
        return _paint_patches(buf, self._mark, self._paint, np.array([p[0] for p in patches], np.int64),
                              np.array([p[1] for p in patches], np.int64),
                              np.array([p[2].shape[0] for p in patches], np.int64),
                              np.array([p[2].shape[1] for p in patches], np.int64), starts, flat, self.f, h, w)

    # ------------------------------------------------------------------ frame
    def image(self, scene, rng: np.random.Generator | None = None) -> np.ndarray:
        """The stored-size uint16 ADU image (h/s, w/s) of ``scene``."""
        from . import corruptions as corr
        r, cfg = self.r, self.r.cfg
        s = cfg.sensor
        f, n, (hb, wb) = self.f, self.n, self.shape
        if rng is None:
            rng = corr.stage_rng(cfg.seed, scene.rng_key, "binned_noise" + r.rng_tag)
        sigma = self.sigma_e()
        g = float(s.gain_e_per_adu)
        bg_map = r.background_map(scene)
        bg_bm = self.to_block_major(bg_map.astype(np.float64)) if bg_map is not None else np.zeros(1)
        # 1. light sources and charge into the sensor-size scratch buffers, their blocks marked
        boxes, peaks, flux = self._stamps(scene.stars)
        bloom_boxes = []
        if s.blooming and len(flux):
            fw = s.full_well_e
            for k in np.flatnonzero((boxes[:, 0] >= 0) & (peaks > 0.5 * fw)):   # as Renderer._deposit extends them
                ya, yb, xa, xb = (int(v) for v in boxes[k])
                extra = int(np.ceil(flux[k] / fw)) + 2
                bloom_boxes.append((max(ya - extra, 0), min(yb + extra, cfg.camera.height_px), xa, xb))
        has_charge = bool(scene.cosmic_rays)
        if has_charge:
            self._paint_list(self._charge, scene.cosmic_rays)
        mark = self._mark
        # 2. background-only blocks: the exact n-fold convolution, per offset class (every block
        #    is drawn; marked ones are overwritten below, so two draws never mix)
        if bg_map is None:
            lut8, thr, nthr, vmin = self.background_tables(float(r.background_e), sigma)
            u32 = rng.bit_generator.random_raw((hb * wb + 1) // 2).view(np.uint32)[:hb * wb]
            out = _background_draw(u32, self.offset_class, lut8, thr, nthr, vmin, 255)
            mark[self.static_blocks] = 1
            blocks = np.flatnonzero(mark)
        else:
            out = np.empty(hb * wb, np.uint16)
            blocks = np.arange(hb * wb)
        mark[:] = 0
        # 3. marked blocks: the block-sum model, unless a pixel may saturate or clip
        limit = min(s.full_well_e, g * (self.max_adu - self.off_max))
        risky = np.zeros(len(blocks), bool)
        lam = np.empty(len(blocks))
        _model_blocks(blocks, n, self._star, self._charge, has_charge, self.prnu, self.live, self.hot_e,
                      self.static_special, float(r.background_e), bg_bm, bg_map is not None, sigma, g,
                      self.offset_sum, limit, self.rule == "half_even", self.max_adu, int(rng.integers(2 ** 32)),
                      out, risky, lam)
        # 4. risky blocks (and as far along their columns as blooming reaches): every sensor
        #    pixel as sensor.read_out draws it
        if risky.any():
            exact = self._exact_region(blocks[risky], lam[risky], bloom_boxes)
            total = self._exact_sums(exact, bloom_boxes, bg_bm if bg_map is not None else None, sigma, rng)
            out[exact] = np.clip(round_block_sums(total, n, self.rule), 0, self.max_adu)
            _clear(exact, n, self._star, self._charge, self._paint, has_charge)
        _clear(blocks, n, self._star, self._charge, self._paint, has_charge)
        return out.reshape(hb, wb)

    def _exact_region(self, risky_blocks: np.ndarray, risky_lam: np.ndarray, bloom_boxes: list) -> np.ndarray:
        """Risky blocks, extended along their columns as far as blooming can carry charge."""
        f, (hb, wb) = self.f, self.shape
        fw = self.r.cfg.sensor.full_well_e
        sel = np.zeros((hb, wb), bool)
        for b, lam in zip(risky_blocks, risky_lam):
            by, bx = divmod(int(b), wb)
            reach = int(np.ceil((lam / fw + 2) / f)) if self.r.cfg.sensor.blooming else 0
            sel[max(by - reach, 0):by + reach + 1, bx] = True
        for ya, yb, xa, xb in bloom_boxes:       # a bloom-capable star: its whole (extended) box
            if sel[ya // f:(yb - 1) // f + 1, xa // f:(xb - 1) // f + 1].any():
                sel[ya // f:(yb - 1) // f + 1, xa // f:(xb - 1) // f + 1] = True
        return np.flatnonzero(sel)

    def _exact_sums(self, exact, bloom_boxes, bg_bm, sigma, rng) -> np.ndarray:
        """Block sums of ``exact`` blocks from per-pixel draws (the model of sensor.read_out)."""
        s = self.r.cfg.sensor
        n = self.n
        h, w = self.sensor_shape
        idx = (exact[:, None] * n + np.arange(n)[None, :]).ravel()      # block-major entries
        yy, xx = self.px_y[idx], self.px_x[idx]
        lam = bg_bm[idx].copy() if bg_bm is not None else np.full(idx.size, float(self.r.background_e))
        lam += self._star[idx] * self.prnu[idx] + self.hot_e[idx]
        e = rng.poisson(lam).astype(np.float64) + self._charge[idx]
        e[~self.live[idx]] = 0.0
        if s.blooming and (e > s.full_well_e).any():
            # charge spills only onto pixels the full renderer draws exactly (its "painted" set)
            on_px = self._paint[idx] | self.static_px[idx]
            for ya, yb, xa, xb in bloom_boxes:
                on_px |= (yy >= ya) & (yy < yb) & (xx >= xa) & (xx < xb)
            cols = np.unique(xx[e > s.full_well_e])
            charge = np.zeros((h, len(cols)))
            col_of = np.full(w, -1)
            col_of[cols] = np.arange(len(cols))
            on = (col_of[xx] >= 0) & on_px
            charge[yy[on], col_of[xx[on]]] = e[on]
            bloom(charge, s.full_well_e)
            e[on] = charge[yy[on], col_of[xx[on]]]
        np.minimum(e, s.full_well_e, out=e)
        if sigma > 0:
            e += sigma * rng.standard_normal(e.size)
        k = np.floor(e / s.gain_e_per_adu).astype(np.int64) + self.offset[idx]
        return np.clip(k, 0, self.max_adu).reshape(len(exact), n).sum(1)


__all__ = ["BinnedRenderer", "unsupported_reason", "area_rounding", "round_block_sums", "aliasing_bound"]
