"""Frames rendered directly at the stored resolution: a binned sensor.

``Renderer.render`` draws every full-resolution pixel (1024 x 1024 by default) and then
area-averages the uint16 frame to the stored size (``Renderer.downsample``, OpenCV
``INTER_AREA``). :class:`BinnedRenderer` draws the *stored* pixels of the same
:class:`skygen.render.frame.Scene` directly, with the distribution render-then-downsample gives
them. What follows is the derivation; ``tests/test_stream_binned.py`` checks it.

What render-then-downsample stores
    Stored pixel ``b`` covers the ``n = s x s`` sensor pixels ``p`` of one ``s x s`` block
    (``u = (x + 0.5) / s - 0.5``, :mod:`skygen.conventions`). Each sensor pixel reads
    ``a_p = clip(k_p + o_p, 0, 2^bits - 1)`` with ``k_p = floor(x_p)``,
    ``x_p = (e_p + n_p) / g``, ``e_p ~ Poisson(lam_p) + c_p`` (``lam_p``: dark + sky (+ stray
    light) + PRNU x star light + hot-pixel dark current, 0 for a dead pixel; ``c_p``: cosmic-ray
    charge), ``n_p ~ N(0, sigma_read)``, ``o_p`` the static bias + FPN offset
    (:mod:`skygen.instrument.sensor`). ``INTER_AREA`` at an integer factor stores the block sum
    ``A_b = sum_p a_p`` divided by ``n`` and rounded: half to even for ``s = 4, 8``, half up
    for ``s = 2`` (OpenCV's code paths differ; :func:`area_rounding` finds the rule by asking
    OpenCV once, and refuses a factor it cannot reproduce). So the stored value is a
    function of the block sum alone, and it is the block sum we draw.

Block sums (no clipping, no full well reached)
    ``A_b = S_b + O_b`` with ``O_b = sum_p o_p`` static and ``S_b = sum_p k_p``.

    * Background-only blocks (uniform dark + sky, no star, hot, dead pixel or cosmic ray):
      the ``k_p`` are i.i.d. with the per-pixel distribution of the renderer's own
      ``fast`` sampler (:class:`skygen.instrument.sensor.BackgroundSampler`), so ``S_b`` has its
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
      spill: every sensor pixel of those blocks is drawn as :func:`skygen.instrument.sensor.read_out`
      draws it (Poisson, charge, dead pixels, blooming onto the pixels the full renderer
      draws exactly, full well, read noise, ADC, clipping), then summed. Exact.

The PSF is integrated over each sensor pixel by the renderer's own stamp code (so over
the large pixel by summation), PRNU weights it per sensor pixel, and a star lands in the
stored pixel that contains its full-resolution position: the same frame index gives the
same stars at the same stored positions as render-then-downsample.

What is not reproduced (and so refused by :func:`unsupported_reason`, the stream then
falls back to render-then-downsample): a stored width that does not divide the sensor by
an integer factor, a rounding rule OpenCV does not follow at that factor, too little
read noise per ADU (above), an offset so low that a pixel could clip at 0 ADU, a background
that fills the full well or is too noisy for the 8-bit tables (over ~9 ADU rms per stored pixel).
"""

from __future__ import annotations

import cv2
import numpy as np

from skygen.instrument.psf import gaussian_radius_px, stamp, streak
from skygen.instrument.sensor import BackgroundSampler, background_sampler
from skygen.render import binned_kernels as kern

ALIAS_BOUND = 1e-12  # largest tolerated aliasing of the block-sum model (see module doc)


# ---------------------------------------------------------------------------------- checks
def aliasing_bound(read_noise_e: float, gain_e_per_adu: float, n: int) -> float:
    """Upper bound on the error of the block-sum model (characteristic-function terms)."""
    if n <= 1:
        return 0.0
    s = read_noise_e / gain_e_per_adu
    return float(n * np.exp(-2.0 * np.pi**2 * s * s * (n - 1) / n))


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
        return (
            f"stored size {cfg.output.image_size_px} is not an integer binning of the "
            f"{cam.width_px} x {cam.height_px} sensor"
        )
    if getattr(cfg.optics, "star_jitter_px", 0.0) > 0:
        return "optics.star_jitter_px: the binned renderer draws stars where the camera puts them"
    if getattr(cam, "has_bright_shift", False):
        return "camera.bright_shift_px (_x_px, _y_px): the binned renderer draws stars where the camera puts them"
    if getattr(s, "fixed_sources", ()):
        return "sensor.fixed_sources: the binned renderer does not paint light fixed on the sensor"
    if getattr(s, "tone_gamma", 1.0) < 1.0:
        return "sensor.tone_gamma: the binned renderer reads out a linear sensor"
    if getattr(s, "processor_blur_px", 0.0) > 0:
        return "sensor.processor_blur_px: the binned renderer draws independent noise per pixel"
    if f == 1:
        return None
    if getattr(cam, "pixel_aspect", 1.0) != 1.0:
        return f"camera.pixel_aspect={cam.pixel_aspect:g}: the binned renderer paints square pixels only"
    if area_rounding(f) is None:
        return f"OpenCV's INTER_AREA rounding at factor {f} is not one this renderer reproduces"
    sigma = float(np.hypot(s.read_noise_e, renderer.levels["read_noise"]))
    bound = aliasing_bound(sigma, s.gain_e_per_adu, f * f)
    if bound > ALIAS_BOUND:
        return (
            f"read noise {sigma:g} e- is {sigma / s.gain_e_per_adu:.2f} ADU: the per-pixel quantisation "
            f"shows in a {f}x{f} sum (model error bound {bound:.1e} > {ALIAS_BOUND:g})"
        )
    low = int(renderer.maps.offset_adu.min())
    if low * s.gain_e_per_adu < 12 * sigma + 1:
        return f"the lowest pixel offset ({low} ADU) lets read noise clip pixels at 0 ADU"
    bg = renderer.background_e
    top = min(s.full_well_e, s.gain_e_per_adu * (2**s.bit_depth - 1 - int(renderer.maps.offset_adu.max())))
    if bg + 12 * np.sqrt(bg) + 12 * sigma >= top:
        return f"the background ({bg:.4g} e-/px) reaches the full well or the ADC top"
    if np.sqrt(bg + sigma**2) / (s.gain_e_per_adu * f) > 9:
        return "the stored background is too noisy for the binned renderer's 8-bit tables"
    return None


# ---------------------------------------------------------------------------------- renderer
class BinnedRenderer:
    """Stored-size uint16 frames of a :class:`skygen.render.frame.Renderer`'s scenes (module doc).

    Construct once per process (static maps are binned here). :meth:`image` is a pure
    function of (config, scene, seed, numba version): one 64-bit seed starts a SplitMix64
    stream (uniforms) and numba's generator (Poisson and Gaussian draws); by default it comes
    from the scene's generator of stage ``"binned_noise"`` (never the full renderer's draws);
    the frames stream passes counter-based seeds (:mod:`skygen.hashrng`)."""

    def __init__(self, renderer):
        reason = unsupported_reason(renderer)
        if reason is not None:
            from skygen.errors import ConfigError

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
        self.prnu = bm(maps.prnu * ~maps.dead_mask)  # float32; 0 on dead pixels
        self.hot_e = bm(maps.hot_map.astype(np.float64) * s.exposure_s)
        self.offset = bm(maps.offset_adu.astype(np.int64))
        self.offset_sum = self.offset.reshape(-1, n).sum(1)  # O_b
        self.offset_values, cls = np.unique(self.offset_sum, return_inverse=True)
        self.offset_class = cls.astype(np.uint8 if len(self.offset_values) <= 256 else np.int32)
        self.static_px = bm((maps.hot_map > 0) | maps.dead_mask)
        self.static_special = self.static_px.reshape(-1, n).any(1)
        self.static_blocks = np.flatnonzero(self.static_special)
        self.max_adu = 2**s.bit_depth - 1
        self.off_max = int(maps.offset_adu.max())
        self._mark = np.zeros(hb * wb, np.uint8)  # scratch: blocks a source touches
        self._slot = np.full(hb * wb, -1, np.int64)  # their compact slots (-1: none)
        self._blocks = np.zeros(hb * wb, np.int64)
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
        return self.n * int(px.kmin) + int(keep[0]), out[keep[0] : keep[-1] + 1]

    def background_tables(self, lam: float, sigma: float):
        """Per offset class: the stored value's distribution, as the renderer's 2^-32 tables."""
        key = (round(lam, 9), round(sigma, 9))
        if key not in self._tables:
            smin, pmf = self.block_sum_pmf(lam, sigma)
            S = smin + np.arange(len(pmf))
            samplers = []
            for offset in self.offset_values:
                v = np.clip(round_block_sums(S + offset, self.n, self.rule), 0, self.max_adu)
                vals = np.arange(v.min(), v.max() + 1)
                samplers.append(BackgroundSampler.from_pmf(vals, np.bincount(v - v.min(), weights=pmf)))
            if any(sm.lut8 is None for sm in samplers):  # unsupported_reason keeps this away
                raise ValueError("stored background too noisy for the 8-bit table")
            L = max(len(sm.thresholds) for sm in samplers)
            thr = np.full((len(samplers), L), 2**32, np.uint64)
            for c, sm in enumerate(samplers):
                thr[c, : len(sm.thresholds)] = sm.thresholds
            self._tables = {
                key: (
                    np.stack([sm.lut8 for sm in samplers]),
                    thr,
                    np.array([len(sm.thresholds) for sm in samplers], np.int64),
                    np.array([sm.kmin for sm in samplers], np.int64),
                )
            }
        return self._tables[key]

    def poisson_table(self, lam: float) -> np.ndarray:
        """32-bit CDF thresholds of Poisson(``lam``) (the background electrons of a whole block),
        resolved to 2^-32 like the renderer's background tables."""
        key = round(lam, 9)
        if getattr(self, "_poisson_key", None) != key:
            from scipy.stats import poisson

            k = np.arange(0, int(lam + 14 * np.sqrt(lam) + 30))
            cdf = np.minimum(np.rint(poisson.cdf(k, lam) * 2.0**32), 2.0**32).astype(np.uint64)
            cdf[-1] = 2**32
            self._poisson_key, self._poisson_thr = key, cdf
        return self._poisson_thr

    def _boxes(self, y0, x0, hh, ww) -> np.ndarray:
        """Clipped half-open boxes (y0, y1, x0, x1) of patches; -1 rows for patches off the sensor."""
        h, w = self.sensor_shape
        box = np.stack([np.maximum(y0, 0), np.minimum(y0 + hh, h), np.maximum(x0, 0), np.minimum(x0 + ww, w)], 1)
        box = box.astype(np.int64)
        box[(box[:, 0] >= box[:, 1]) | (box[:, 2] >= box[:, 3])] = -1
        return box

    def _sources(self, stars: dict):
        """(boxes, painter) of the scene's light sources: the painter adds them to a compact buffer
        once slots exist and returns each source's peak pixel."""
        o = self.r.cfg.optics
        h, w = self.sensor_shape
        flux = np.asarray(stars["electrons"], np.float64)
        if stars["paths"] is None and o.psf == "gaussian":
            x, y = np.asarray(stars["x_px"], np.float64), np.asarray(stars["y_px"], np.float64)
            radii = gaussian_radius_px(flux, o.psf_sigma_px).astype(np.int64) if len(flux) else np.zeros(0, np.int64)
            boxes = self._boxes(
                np.floor(y + 0.5).astype(np.int64) - radii,
                np.floor(x + 0.5).astype(np.int64) - radii,
                2 * radii + 1,
                2 * radii + 1,
            )
            return boxes, lambda buf, paint: kern.paint_gauss(
                buf, paint, self._slot, self.prnu, x, y, flux, radii, float(o.psf_sigma_px), self.f, h, w
            )
        if stars["paths"] is None:
            st = [
                stamp(float(x), float(y), float(fl), o.psf, o.psf_sigma_px, o.moffat_beta)
                for x, y, fl in zip(stars["x_px"], stars["y_px"], flux)
            ]
        else:
            st = [
                streak(xs, ys, float(fl), o.psf, o.psf_sigma_px, o.moffat_beta)
                for xs, ys, fl in zip(stars["paths"][0], stars["paths"][1], flux)
            ]
        return self._patches(st, True)

    def _patches(self, patches, weighted: bool):
        h, w = self.sensor_shape
        if not patches:
            return np.zeros((0, 4), np.int64), lambda buf, paint: np.zeros(0)
        y0 = np.array([p[0] for p in patches], np.int64)
        x0 = np.array([p[1] for p in patches], np.int64)
        hh = np.array([p[2].shape[0] for p in patches], np.int64)
        ww = np.array([p[2].shape[1] for p in patches], np.int64)
        starts = np.concatenate([[0], np.cumsum(hh * ww)[:-1]]).astype(np.int64)
        flat = np.concatenate([p[2].ravel() for p in patches]).astype(np.float64)

        def painter(buf, paint):
            return kern.paint_patches(
                buf,
                paint,
                self._slot,
                self.prnu,
                weighted,  # noqa: E731
                y0,
                x0,
                hh,
                ww,
                starts,
                flat,
                self.f,
                h,
                w,
            )

        return self._boxes(y0, x0, hh, ww), painter

    # ------------------------------------------------------------------ frame
    def image(self, scene, seed: int | None = None) -> np.ndarray:
        """The stored-size uint16 ADU image (h/s, w/s) of ``scene``; every draw comes from the
        64-bit ``seed`` (default: from the scene's generator of stage ``binned_noise``)."""
        from skygen.instrument import corruptions as corr

        r, cfg = self.r, self.r.cfg
        s = cfg.sensor
        f, n, (hb, wb) = self.f, self.n, self.shape
        if seed is None:
            seed = int(corr.stage_rng(cfg.seed, scene.rng_key, "binned_noise" + r.rng_tag).bit_generator.random_raw())
        state = np.array([seed], np.uint64)
        kern.seed(int(seed & 0xFFFFFFFF))
        sigma = self.sigma_e()
        g = float(s.gain_e_per_adu)
        bg_map = r.background_map(scene)
        use_map = bg_map is not None
        bg_bm = self.to_block_major(bg_map.astype(np.float64)) if use_map else np.zeros(1)
        # 1. the blocks light sources, cosmic rays, hot and dead pixels touch get compact slots
        boxes, paint_stars = self._sources(scene.stars)
        has_charge = bool(scene.cosmic_rays)
        cboxes, paint_charge = self._patches(scene.cosmic_rays, False)
        mark = self._mark
        kern.mark_boxes(mark, boxes, f, wb)
        kern.mark_boxes(mark, cboxes, f, wb)
        if use_map:
            mark[:] = 1
        mark[self.static_blocks] = 1
        m = kern.slots(mark, self._slot, self._blocks)
        blocks = self._blocks[:m]
        star, paint = np.zeros(m * n), np.zeros(m * n, bool)
        charge = np.zeros(m * n) if has_charge else np.zeros(1)
        peaks = paint_stars(star, paint)
        if has_charge:
            paint_charge(charge, paint)
        flux = np.asarray(scene.stars["electrons"], np.float64)
        bloom_boxes = np.zeros((0, 4), np.int64)
        if s.blooming and len(flux):  # as Renderer.deposit extends a bright star's box
            big = np.flatnonzero((boxes[:, 0] >= 0) & (peaks > 0.5 * s.full_well_e))
            if len(big):
                extra = np.ceil(flux[big] / s.full_well_e).astype(np.int64) + 2
                bloom_boxes = boxes[big].copy()
                bloom_boxes[:, 0] = np.maximum(bloom_boxes[:, 0] - extra, 0)
                bloom_boxes[:, 1] = np.minimum(bloom_boxes[:, 1] + extra, cfg.camera.height_px)
        # 2. every block from the exact n-fold convolution of the background, per offset class
        #    (marked blocks are overwritten below, so two draws never mix)
        if not use_map:
            lut8, thr, nthr, vmin = self.background_tables(float(r.background_e), sigma)
            out = kern.background_draw(state, self.offset_class, lut8, thr, nthr, vmin, 255)
        else:
            out = np.empty(hb * wb, np.uint16)
        # 3. marked blocks: the block-sum model, unless a pixel may saturate or clip
        limit = min(s.full_well_e, g * (self.max_adu - self.off_max))
        risky = np.zeros(m, bool)
        lam = np.empty(m)
        even = self.rule == "half_even"
        kern.model_blocks(
            blocks,
            n,
            star,
            charge,
            has_charge,
            self.live,
            self.hot_e,
            self.static_special,
            float(r.background_e),
            bg_bm,
            use_map,
            sigma,
            g,
            self.offset_sum,
            limit,
            even,
            self.max_adu,
            state,
            self.poisson_table(n * float(r.background_e)),
            out,
            risky,
            lam,
        )
        # 4. risky blocks, and as far along their columns as blooming reaches: pixel by pixel
        if risky.any():
            exact = self._exact_region(blocks[risky], lam[risky], bloom_boxes)
            hit = [bb for bb in bloom_boxes if self._touches(bb, exact)] if len(bloom_boxes) else []
            kern.exact_blocks(
                exact,
                self._slot,
                n,
                f,
                wb,
                self.sensor_shape[0],
                star,
                charge,
                has_charge,
                paint,
                self.live,
                self.hot_e,
                self.static_px,
                float(r.background_e),
                bg_bm,
                use_map,
                use_map or s.sampler == "exact",
                np.array(hit, np.int64).reshape(-1, 4),
                bool(s.blooming),
                float(s.full_well_e),
                sigma,
                g,
                self.offset,
                self.max_adu,
                even,
                out,
            )
        return out.reshape(hb, wb)

    def _touches(self, box, exact: np.ndarray) -> bool:
        f, wb = self.f, self.shape[1]
        by, bx = exact // wb, exact % wb
        return bool(
            ((by >= box[0] // f) & (by <= (box[1] - 1) // f) & (bx >= box[2] // f) & (bx <= (box[3] - 1) // f)).any()
        )

    def _exact_region(self, risky_blocks: np.ndarray, risky_lam: np.ndarray, bloom_boxes: np.ndarray) -> np.ndarray:
        """Risky blocks, extended along their columns as far as blooming can carry charge, and
        the whole (extended) box of a bloom-capable star that reaches them."""
        f, (hb, wb) = self.f, self.shape
        fw = self.r.cfg.sensor.full_well_e
        reach = (
            np.ceil((risky_lam / fw + 2) / f).astype(np.int64)
            if self.r.cfg.sensor.blooming
            else np.zeros(len(risky_blocks), np.int64)
        )
        key = (risky_blocks.tobytes(), reach.tobytes())
        if not len(bloom_boxes) and getattr(self, "_region_key", None) == key:
            return self._region  # the usual case: the same saturating hot pixels as before
        sel = np.zeros((hb, wb), bool)
        for b, rb in zip(risky_blocks, reach):
            by, bx = divmod(int(b), wb)
            sel[max(by - rb, 0) : by + rb + 1, bx] = True
        for ya, yb, xa, xb in bloom_boxes:
            if sel[ya // f : (yb - 1) // f + 1, xa // f : (xb - 1) // f + 1].any():
                sel[ya // f : (yb - 1) // f + 1, xa // f : (xb - 1) // f + 1] = True
        region = np.flatnonzero(sel)
        if not len(bloom_boxes):
            self._region_key, self._region = key, region
        return region


__all__ = ["BinnedRenderer", "aliasing_bound", "area_rounding", "round_block_sums", "unsupported_reason"]
