"""Sensor model: photo-electrons in, ADU out.

Per pixel p, over one exposure of t seconds::

    e_p   = Poisson(lambda_p) + cosmic-ray charge            [e-]
    lambda_p = t * (dark(T) + sky * vig_p + stray_p) + prnu_p * star_p + t * hot_p
    e_p  -> min(e_p, full_well), excess spilled along the column (blooming)
    ADU_p = clip(floor((e_p + n_p) / gain) + bias + fpn_p, 0, 2^bits - 1),  n_p ~ N(0, sigma_read)

A processor's blur (``sensor.processor_blur_px`` > 0: demosaicing, JPEG compression, denoising) takes the read-out
before quantisation, ``(e_p + n_p) / gain + bias + fpn_p``, through a Gaussian of that sigma (px), then floors and
clips it: neighbouring pixels' noise correlates (lag-1 correlation :func:`blur_correlation`) and its variance falls by
:func:`blur_variance_factor`. Every pixel is then drawn by the exact sampler.

A processed camera's tone curve (``sensor.tone_gamma`` < 1, :class:`ToneCurve`) maps each read-out, clipped at the
read-out that reaches the top instead, through a lookup table onto 0 .. 2^bits - 1.

Static maps (drawn once from ``sensor_seed``): ``prnu_p`` ~ 1 + N(0, prnu_frac); the
integer fixed-pattern offset ``fpn_p`` = round(N(0, fpn_adu)); hot pixels (a pixel is hot
when its static uniform rank is below the hot-pixel fraction, so a larger fraction is a
superset of a smaller one) with log-normal dark current around ``hot_pixel_dark_e_s``;
dead pixels that collect no charge (they read bias + read noise).

Two samplers give the same distribution:

* ``exact``: numpy Poisson and Gaussian draws for every pixel.
* ``fast`` (default): for a spatially uniform background the distribution of
  ``floor((Poisson(lambda_0) + N(0, sigma)) / gain)`` is computed once, exactly, and
  sampled for every pixel from one 32-bit uniform through a two-level lookup table
  (probabilities resolved to 2^-32; only the top byte is drawn where it decides alone). Every pixel that receives
  anything else — star
  light, cosmic rays, hot or dead pixels — is drawn again with the exact per-pixel model
  (its LUT value is discarded, so the two draws never mix). The
  fast path neglects PRNU acting on the sub-electron diffuse sky only. A non-uniform
  background (vignetting, stray light) uses the exact sampler automatically.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from scipy.special import ndtr
from scipy.stats import poisson

from skygen.config import tone_inverse, tone_value
from skygen.instrument.photometry import dark_current_e_s

_AMBIGUOUS = 65535
_AMBIGUOUS8 = 255


@dataclass(frozen=True)
class SensorMaps:
    """Static per-pixel maps of one physical sensor (same for every frame)."""

    prnu: np.ndarray  # float32 (H, W), mean 1
    offset_adu: np.ndarray  # int32 (H, W): bias (less a processor's black level) + integer FPN
    hot_index: np.ndarray  # flat indices of hot pixels
    hot_dark_e_s: np.ndarray  # their extra dark current, e-/s
    dead_index: np.ndarray  # flat indices of dead pixels
    hot_map: np.ndarray  # float32 (H, W): extra dark current, e-/s (0 except hot pixels)
    dead_mask: np.ndarray  # bool (H, W)


@dataclass(frozen=True)
class ToneCurve:
    """A camera processor's tone curve on whole read-outs (``sensor.tone_gamma``, ``sensor.tone_knee_adu``).

    With x the read-out above the pedestal p (bias less the black level), x_k the knee and g the exponent::

        T(x) = x                                    x <= x_k
        T(x) = x_k + (x_k / g) ((x / x_k)^g - 1)    x > x_k   (continuous in value and slope at x_k)
        ADU  = clip(round(p + T(x)), 0, 2^bits - 1)

    Below the knee (the background and its noise) a frame reads as a linear sensor's; above it a star's light
    grows as its brightness to the power g, as in a JPEG's gamma-encoded frame. ``raw_top``: the read-out the
    curve maps onto the top (:func:`skygen.config.tone_raw_top`): read-outs are clipped there, not at the top."""

    raw_top: int
    lut: np.ndarray  # uint16 (raw_top + 1,): ADU of each read-out
    gamma: float = 1.0
    knee: float = 0.0
    pedestal: int = 0

    @staticmethod
    def of(sensor) -> "ToneCurve | None":
        """The sensor's curve, None for a linear one (tone_gamma 1)."""
        if sensor.tone_gamma >= 1.0:
            return None
        return _tone_curve(
            float(sensor.tone_gamma),
            float(sensor.tone_knee_adu),
            max(int(sensor.bias_adu) - int(sensor.black_level_adu), 0),
            int(sensor.bit_depth),
        )

    def apply(self, raw: np.ndarray) -> np.ndarray:
        """ADU of whole read-outs ``raw`` (any int dtype, within 0 .. raw_top), as uint16."""
        return self.lut[raw]

    def value(self, x: float) -> float:
        """T(x): ADU above the pedestal of a read-out ``x`` ADU above it, unrounded and unclipped."""
        return float(tone_value(x, self.gamma, self.knee))

    def inverse(self, y: float) -> float:
        """The read-out above the pedestal that T maps onto ``y`` ADU above it."""
        return float(tone_inverse(y, self.gamma, self.knee))

    def slope(self, x: float) -> float:
        """dT/dx at ``x``: 1 below the knee, (x / knee)^(gamma - 1) above it."""
        return float(1.0 if x <= self.knee else (x / self.knee) ** (self.gamma - 1.0))


@lru_cache(maxsize=8)
def _tone_curve(gamma: float, knee: float, pedestal: int, bits: int) -> ToneCurve:
    top = 2**bits - 1
    raw_top = int(np.ceil(pedestal + tone_inverse(top - pedestal, gamma, knee))) if top - pedestal > knee else top
    t = [tone_value(x - pedestal, gamma, knee) for x in range(raw_top + 1)]  # once per curve (cached)
    lut = np.clip(np.round(pedestal + np.array(t)), 0, top).astype(np.uint16)
    lut.setflags(write=False)
    return ToneCurve(raw_top, lut, gamma, knee, pedestal)


@lru_cache(maxsize=4)
def sensor_maps(
    height: int,
    width: int,
    seed: int,
    prnu_frac: float,
    fpn_adu: float,
    bias_adu: int,
    hot_fraction: float,
    hot_dark_e_s: float,
    dead_fraction: float,
) -> SensorMaps:
    """Draw the static maps from ``seed``; cached per process (same args, same maps)."""
    rng = np.random.default_rng([seed, 0x5E45])
    prnu = (1.0 + prnu_frac * rng.standard_normal((height, width), dtype=np.float32)).clip(0, None)
    fpn = np.rint(fpn_adu * rng.standard_normal((height, width), dtype=np.float32)).astype(np.int32)
    offset = fpn + np.int32(bias_adu)
    rank_hot = rng.random(height * width, dtype=np.float32)
    rank_dead = rng.random(height * width, dtype=np.float32)
    hot = np.flatnonzero(rank_hot < hot_fraction)
    # Each pixel's hot-pixel strength is fixed by its own index, so maps nest.
    strength_rng = np.random.default_rng([seed, 0x407])
    strength = hot_dark_e_s * 10 ** (0.5 * strength_rng.standard_normal(height * width, dtype=np.float32)[hot])
    dead = np.flatnonzero(rank_dead < dead_fraction)
    hot_keep = ~np.isin(hot, dead)
    hot, strength = hot[hot_keep], strength[hot_keep].astype(np.float64)
    hot_map = np.zeros(height * width, np.float32)
    hot_map[hot] = strength
    dead_mask = np.zeros(height * width, bool)
    dead_mask[dead] = True
    maps = SensorMaps(
        prnu, offset, hot, strength, dead, hot_map.reshape(height, width), dead_mask.reshape(height, width)
    )
    for arr in (prnu, offset, maps.hot_map, maps.dead_mask):
        arr.setflags(write=False)
    return maps


class BackgroundSampler:
    """Exact sampler of ``floor((Poisson(lam) + N(0, sigma)) / gain)`` via a 2-level LUT."""

    def __init__(self, lam: float, sigma: float, gain: float):
        self.lam, self.sigma, self.gain = lam, sigma, gain
        sd = np.sqrt(lam)
        e = np.arange(max(0, int(lam - 12 * sd - 12)), int(lam + 12 * sd + 40))
        pe = poisson.pmf(e, lam)
        kmin = int(np.floor((e[0] - 9 * sigma) / gain)) - 1
        kmax = int(np.ceil((e[-1] + 9 * sigma) / gain)) + 1
        k = np.arange(kmin, kmax + 1)
        if sigma > 0:
            upper = ndtr((gain * (k[:, None] + 1) - e[None, :]) / sigma)  # P(e + n < g (k+1))
            cdf = upper @ pe
        else:
            cdf = np.array([pe[e < gain * (kk + 1)].sum() for kk in k])
        self._build_tables(k, cdf)

    @classmethod
    def from_pmf(cls, k: np.ndarray, pmf: np.ndarray) -> "BackgroundSampler":
        """A sampler of any distribution on consecutive integers ``k`` (``pmf`` need not be
        normalised): the same two-level table, value = ``kmin + j``. Used for the sum of a
        stored pixel's full-resolution values (:mod:`skygen.render.binned`)."""
        self = cls.__new__(cls)
        self.lam = self.sigma = self.gain = float("nan")
        self._build_tables(np.asarray(k), np.cumsum(np.asarray(pmf, np.float64)))
        return self

    def _build_tables(self, k: np.ndarray, cdf: np.ndarray) -> None:
        kmin = int(k[0])
        cdf = np.maximum.accumulate(cdf / cdf[-1])
        self.kmin = kmin
        # u (uint32) maps to the first j with u < thresholds[j]
        self.thresholds = np.minimum(np.rint(cdf * 2.0**32), 2.0**32).astype(np.uint64)
        self.thresholds[-1] = 2**32
        prefixes = np.arange(65536, dtype=np.uint64) << np.uint64(16)
        j_lo = np.searchsorted(self.thresholds, prefixes, side="right")
        j_hi = np.searchsorted(self.thresholds, prefixes + np.uint64(65535), side="right")
        if len(k) >= _AMBIGUOUS:
            raise ValueError("background distribution too wide for the 16-bit table; use sampler=exact")
        self.lut16 = np.where(j_lo == j_hi, j_lo, _AMBIGUOUS).astype(np.uint16)
        self.lut8 = None
        if len(k) < _AMBIGUOUS8:
            p8 = np.arange(256, dtype=np.uint64) << np.uint64(24)
            lo8 = np.searchsorted(self.thresholds, p8, side="right")
            hi8 = np.searchsorted(self.thresholds, p8 + np.uint64((1 << 24) - 1), side="right")
            self.lut8 = np.where(lo8 == hi8, lo8, _AMBIGUOUS8).astype(np.uint8)

        self.pmf = np.diff(np.concatenate([[0.0], cdf]))
        self.k = k

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` draws of the table index j (uint8, or uint16 for wide tables); value = ``kmin + j``.

        The top byte of a 32-bit uniform ``u`` (raw generator output) picks the answer
        from a 256-entry table wherever that byte alone decides it (about 95 % of draws);
        where it straddles a CDF step, 24 more bits are drawn and the exact 32-bit
        thresholds searched.
        """
        if self.lut8 is None:
            u = rng.bit_generator.random_raw((n + 1) // 2).view(np.uint32)[:n]
            j = np.take(self.lut16, u >> 16)
            amb = np.flatnonzero(j == _AMBIGUOUS)
            if amb.size:
                j[amb] = np.searchsorted(self.thresholds, u[amb].astype(np.uint64), side="right")
            return j
        top = rng.bit_generator.random_raw((n + 7) // 8).view(np.uint8)[:n]
        j = cv2.LUT(top, self.lut8).ravel()
        amb = np.flatnonzero(j == _AMBIGUOUS8)
        if amb.size:  # the straddling top bytes: 24 more bits, exact search
            low = rng.bit_generator.random_raw(amb.size) & np.uint64(0xFFFFFF)
            u = (top[amb].astype(np.uint64) << np.uint64(24)) | low
            j[amb] = np.searchsorted(self.thresholds, u, side="right")
        return j


@lru_cache(maxsize=16)
def background_sampler(lam: float, sigma: float, gain: float) -> BackgroundSampler:
    return BackgroundSampler(lam, sigma, gain)


def bloom(e: np.ndarray, full_well: float) -> int:
    """Spill charge above ``full_well`` along columns (in place); returns columns affected.

    Excess charge of a column is shared equally between the pixels above and below the
    saturated run, filling each to full well outwards; charge reaching the array edge
    is lost (drained), as in a real sensor.
    """
    cols = np.flatnonzero((e > full_well).any(axis=0))
    h = e.shape[0]
    for c in cols:
        col = e[:, c]
        over = col > full_well
        excess = float((col[over] - full_well).sum())
        col[over] = full_well
        rows = np.flatnonzero(over)
        for direction, start in ((-1, rows[0] - 1), (1, rows[-1] + 1)):
            q = excess / 2.0
            r = start
            while q > 0 and 0 <= r < h:
                room = full_well - col[r]
                take = min(room, q)
                col[r] += take
                q -= take
                r += direction
    return len(cols)


def dark_e(sensor) -> float:
    """Mean dark charge per pixel over the exposure, e-."""
    return dark_current_e_s(sensor) * sensor.exposure_s


@dataclass(frozen=True)
class Exposure:
    """What reaches the sensor in one exposure (all in electrons over the exposure).

        ``star_e``: expected photo-electrons from point sources per pixel (before PRNU);
        ``charge_e``: charge deposited directly (cosmic rays), not Poisson-sampled again;
        ``boxes``: half-open (y0, y1, x0, x1) rectangles outside which both are zero (they
    may overlap);
        ``background_e``: uniform expected background (dark + sky);
        ``background_map_e``: optional full non-uniform background (replaces the uniform one).
    """

    star_e: np.ndarray
    charge_e: np.ndarray | None
    boxes: list
    background_e: float
    background_map_e: np.ndarray | None = None


def read_out(
    exp: Exposure, sensor, maps: SensorMaps, rng: np.random.Generator, extra_read_noise_e: float = 0.0
) -> tuple[np.ndarray, dict]:
    """Sample one frame: electrons -> noise -> blooming -> ADC. Returns (uint16 image, info)."""
    h, w = exp.star_e.shape
    sigma = float(np.hypot(sensor.read_noise_e, extra_read_noise_e))
    tone = ToneCurve.of(sensor)
    max_adu = tone.raw_top if tone is not None else 2**sensor.bit_depth - 1  # read-outs clip here
    t = sensor.exposure_s
    blur = float(getattr(sensor, "processor_blur_px", 0.0))
    if sensor.sampler == "fast" and exp.background_map_e is None and blur <= 0:
        sampler = background_sampler(round(float(exp.background_e), 9), round(sigma, 9), float(sensor.gain_e_per_adu))
        out = _dense_background(sampler, maps, max_adu, h * w, rng).reshape(h, w)
        painted = np.zeros((h, w), bool)
        for y0, y1, x0, x1 in exp.boxes:
            painted[y0:y1, x0:x1] = True
        painted.ravel()[maps.hot_index] = True
        painted.ravel()[maps.dead_index] = True
        idx = np.flatnonzero(painted)
    else:
        out = np.empty((h, w), np.uint16)
        idx = np.arange(h * w)
    if exp.background_map_e is not None:
        lam = exp.background_map_e.ravel()[idx].astype(np.float64)
    else:
        lam = np.full(idx.size, float(exp.background_e))
    lam += exp.star_e.ravel()[idx] * maps.prnu.ravel()[idx]
    lam += maps.hot_map.ravel()[idx] * t
    e = rng.poisson(lam).astype(np.float64)
    if exp.charge_e is not None:
        e += exp.charge_e.ravel()[idx]
    e[maps.dead_mask.ravel()[idx]] = 0.0
    bloomed = 0
    if sensor.blooming and (e > sensor.full_well_e).any():
        # Saturating stars' boxes reach flux/full_well rows further along their columns
        # (Renderer.deposit), so spilled charge always lands on pixels drawn here.
        cols = np.unique(idx[e > sensor.full_well_e] % w)
        charge = np.zeros((h, w))
        charge.ravel()[idx] = e
        sub = charge[:, cols]
        bloomed = bloom(sub, sensor.full_well_e)
        charge[:, cols] = sub
        e = charge.ravel()[idx]
    np.minimum(e, sensor.full_well_e, out=e)
    if sigma > 0:
        e += sigma * rng.standard_normal(e.size)
    if blur > 0:  # every pixel was drawn (idx is all of them): the processor blurs the read-out, then quantises
        v = (e / sensor.gain_e_per_adu + maps.offset_adu.ravel()).reshape(h, w).astype(np.float32)
        v = cv2.GaussianBlur(v, (0, 0), blur, borderType=cv2.BORDER_REFLECT)
        k = np.floor(v).astype(np.int64).ravel()
    else:
        k = np.floor(e / sensor.gain_e_per_adu).astype(np.int64) + maps.offset_adu.ravel()[idx]
    out.ravel()[idx] = np.clip(k, 0, max_adu)
    if tone is not None:
        out = tone.apply(out)
    return out, {"exact_pixels": int(idx.size), "bloomed_columns": bloomed}


def _dense_background(
    sampler: BackgroundSampler, maps: SensorMaps, max_adu: int, n: int, rng: np.random.Generator
) -> np.ndarray:
    """Every pixel drawn from the uniform-background distribution, offsets added, as uint16."""
    j = sampler.sample(n, rng)
    kmax = sampler.kmin + len(sampler.k) - 1
    key = (id(maps), sampler.kmin)
    off = _OFFSET_CACHE.get(key)
    if off is None:
        lo, hi = int(maps.offset_adu.min()), int(maps.offset_adu.max())
        off = (
            (maps.offset_adu.ravel() + sampler.kmin).astype(np.uint16)
            if lo + sampler.kmin >= 0 and hi + kmax <= max_adu
            else None
        )
        _OFFSET_CACHE.clear()
        _OFFSET_CACHE[key] = off if off is not None else False
    if off is not None and off is not False:
        return np.add(j, off, dtype=np.uint16)  # no clipping possible: stay in uint16
    k = j.astype(np.int32) + sampler.kmin + maps.offset_adu.ravel()
    return np.clip(k, 0, max_adu).astype(np.uint16)


_OFFSET_CACHE: dict = {}


def _blur_kernel(sigma_px: float) -> np.ndarray:
    """The 1-D Gaussian kernel :func:`read_out` blurs with (OpenCV's, normalised)."""
    return cv2.getGaussianKernel(2 * int(np.ceil(4 * sigma_px)) + 1, sigma_px).ravel()


def blur_variance_factor(sigma_px: float) -> float:
    """White noise's variance after ``sensor.processor_blur_px`` = ``sigma_px``, relative to before (1 at 0)."""
    if sigma_px <= 0:
        return 1.0
    k = _blur_kernel(sigma_px)
    return float((k * k).sum()) ** 2


def blur_correlation(sigma_px: float) -> float:
    """White noise's correlation with its horizontal (or vertical) neighbour after a blur of ``sigma_px``."""
    if sigma_px <= 0:
        return 0.0
    k = _blur_kernel(sigma_px)
    return float((k[:-1] * k[1:]).sum() / (k * k).sum())


def blur_width_variance(sigma_px: float) -> float:
    """What the blur adds to a star's second-moment variance per axis, px^2 (its kernel's; sigma_px^2 from ~0.6 px
    up, less below where the sampled kernel barely reaches the neighbours)."""
    if sigma_px <= 0:
        return 0.0
    k = _blur_kernel(sigma_px)
    i = np.arange(k.size) - k.size // 2
    return float((k * i * i).sum())


def blur_for_correlation(rho: float, hi_px: float = 3.0) -> float:
    """The blur sigma (px) whose neighbour correlation (:func:`blur_correlation`) is ``rho``; 0 for rho <= 0, the
    ``hi_px`` bound's for a correlation beyond it."""
    from scipy.optimize import brentq

    if rho <= 0:
        return 0.0
    if rho >= blur_correlation(hi_px):
        return hi_px
    return float(brentq(lambda s: blur_correlation(s) - rho, 1e-3, hi_px, xtol=1e-4))
