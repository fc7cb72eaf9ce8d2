"""The sensor of ``skygen fit-camera``: bias, gain and read noise where the frames constrain them; otherwise
the background's level and noise fitted directly, so that renders reproduce them.

Units: ADU of the frames after :func:`skygen.real.fit_pixels.value_scale`; electrons (e-) through the gain
(e-/ADU). The model is skygen's (:mod:`skygen.instrument.sensor`): a background pixel reads

    clip(floor((Poisson(lam) + N(0, read)) / gain) + bias + f, 0, top),   f = round(N(0, fpn)) static,

with ``lam`` the dark and sky electrons. Its level and noise as skygen's estimator measures them
(:func:`skygen.instrument.detect.estimate_background`: 3-sigma clipped mean and standard deviation) are
computed exactly from that distribution (:func:`model_background`), so quantisation, the floor's -0.5 ADU and
the clip at 0 ADU of a faint 8-bit background are the renders' own, not approximations.

1. :func:`mean_variance` — the background's noise variance against its level over the 64 px boxes of every
   frame, ``var = a + level / gain``. The variance comes from the odd rows, the level from the even ones
   (:func:`skygen.real.fit_pixels.background`), so a box's noise does not correlate with its own level. It
   is refused, with the reason, when

   * every box sits within 3 sigma of the ADC's floor (0 ADU) or top: its noise is clipped, not the line's;
   * the slope is not positive, or its standard error is over :data:`MAX_SLOPE_RSE` of it. The lever arm is
     the boxes' spread of level net of their levels' own noise (a spread of pure noise is no lever arm);
   * the bias the intercept implies (with the start camera's read noise and FPN) is above the darkest box's
     level + 0.5 ADU: dark and sky charge only add to the bias, so that is impossible.

2. :func:`fit_direct` — otherwise (or when the renders of the line's sensor miss the frames' noise): bias
   from the camera file when one was given and the frames allow it, else 0 ADU; read noise from the start
   camera; FPN the frames' own static pattern (:func:`skygen.real.fit_pixels.fixed_pattern`, from two frames
   or more; else the start camera's; 0 when it alone would exceed the measured noise); gain and background
   electrons fitted so that the model's level and noise equal the frames' (median box level and sigma).
   The frames cannot tell read noise from shot noise at one level, nor the bias from the sky: those terms
   are the start camera's choice, and the gain follows from them; the renders' level and noise do not.

:func:`electrons_at` inverts the model's level: the background electrons (dark + sky) that give a measured
level with the fitted sensor (the camera file's ``photometry.sky_mag_arcsec2`` comes from it).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import brentq, minimize
from scipy.special import ndtr
from scipy.stats import poisson

#: the mean-variance gain is refused when its slope's standard error is over this fraction of the slope
MAX_SLOPE_RSE = 0.30
#: a box whose level is within this many sigma of the ADC's floor (0) or top has a clipped noise
CLIP_SIGMA = 3.0
_CLIP, _CLIP_STD_FACTOR = 3.0, 0.98657  # skygen.instrument.detect.estimate_background's


@dataclasses.dataclass(frozen=True)
class SensorFit:
    """The fitted sensor: gain (e-/ADU), bias (ADU, an integer as skygen's model has it), read noise (e-),
    offset FPN (ADU rms); ``method``: "mean-variance", "direct" or "kept" (the start camera's: frames whose
    background shows less noise than an ADC rounds to); ``refused``: one sentence per term the frames could not
    give (empty when the line stands); ``said``: the one line that says what was used."""

    gain_e_per_adu: float
    bias_adu: int
    read_noise_e: float
    fpn_adu: float
    method: str
    refused: tuple[str, ...] = ()
    said: str = ""

    def terms(self, centre_adu: float, top: int) -> dict:
        """The measurements' sensor terms (``skygen fit-camera``'s ``meas``): gain, bias, read noise, FPN, the
        method, and the background electrons (dark + sky) at the frame centre, whose model level is the
        measured ``centre_adu`` (:func:`electrons_at`)."""
        return {
            "gain_e_per_adu": self.gain_e_per_adu,
            "bias_adu": self.bias_adu,
            "read_noise_e": self.read_noise_e,
            "fpn_adu": self.fpn_adu,
            "sensor_method": self.method,
            "background_e": electrons_at(
                centre_adu, self.gain_e_per_adu, self.read_noise_e, self.bias_adu, self.fpn_adu, top
            ),
        }


# ----------------------------------------------------------------------------------- the model
def pixel_pmf(lam_e: float, gain: float, read_e: float, bias: int, fpn_adu: float, top: int):
    """(values, probabilities) of one background pixel's reading (module doc; ``top`` = 2^bits - 1)."""
    lam = max(float(lam_e), 0.0)
    sd = np.sqrt(lam + read_e**2)
    e = np.arange(max(0, int(lam - 12 * np.sqrt(lam) - 12)), int(lam + 12 * np.sqrt(lam) + 40))
    kmin = int(np.floor((e[0] - 9 * read_e) / gain)) - 1
    kmax = int(np.ceil((e[-1] + 9 * read_e) / gain)) + 1
    k = np.arange(kmin, kmax + 1)
    if lam > 2000 or k.size * e.size > 2_000_000:  # many electrons: Poisson + read noise is Gaussian
        k = np.arange(int(np.floor((lam - 10 * sd) / gain)) - 1, int(np.ceil((lam + 10 * sd) / gain)) + 2)
        cdf = ndtr((gain * (k + 1) - lam) / sd)
    else:
        pe = poisson.pmf(e, lam)
        if read_e > 0:
            cdf = ndtr((gain * (k[:, None] + 1) - e[None, :]) / read_e) @ pe
        else:
            cdf = (e[None, :] < gain * (k[:, None] + 1)) @ pe
    p = np.diff(np.concatenate([[0.0], cdf]))
    if fpn_adu > 0:
        j = np.arange(-int(np.ceil(6 * fpn_adu)) - 1, int(np.ceil(6 * fpn_adu)) + 2)
        pj = ndtr((j + 0.5) / fpn_adu) - ndtr((j - 0.5) / fpn_adu)
        p = np.convolve(p, pj)
        k = np.arange(k[0] + j[0], k[0] + j[0] + p.size)
    k = k + int(bias)
    # the ADC: everything below 0 reads 0, everything above the top reads the top
    lo, hi = np.sum(p[k <= 0]), np.sum(p[k >= top])
    inside = (k > 0) & (k < top)
    k = np.concatenate([[0], k[inside], [top]])
    p = np.concatenate([[lo], p[inside], [hi]])
    return k.astype(float), p / p.sum()


def estimator_stats(values: np.ndarray, p: np.ndarray) -> tuple[float, float]:
    """(level, sigma) that :func:`skygen.instrument.detect.estimate_background` gives on a large sample of
    the distribution (``values``, ``p``): median and MAD start, three 3-sigma clipped passes."""
    level = float(values[np.searchsorted(np.cumsum(p), 0.5)])
    dev = np.abs(values - level)
    order = np.argsort(dev)
    mad = float(dev[order][np.searchsorted(np.cumsum(p[order]), 0.5)])
    sigma = max(1.4826 * mad, 0.5)
    for _ in range(3):
        w = p * (np.abs(values - level) < _CLIP * sigma)
        level = float(w @ values / w.sum())
        sigma = max(float(np.sqrt(w @ (values - level) ** 2 / w.sum())) / _CLIP_STD_FACTOR, 1e-3)
    return level, sigma


def model_background(lam_e: float, gain: float, read_e: float, bias: int, fpn_adu: float, top: int):
    """(level, sigma) in ADU of a background of ``lam_e`` electrons, as skygen's estimator measures it."""
    return estimator_stats(*pixel_pmf(lam_e, gain, read_e, bias, fpn_adu, top))


def electrons_at(level_adu: float, gain: float, read_e: float, bias: int, fpn_adu: float, top: int) -> float:
    """The background electrons (dark + sky) whose measured level is ``level_adu`` (0 when even none reads
    higher: the floor's clipping, or a level below the bias)."""

    def off(lam):
        return model_background(lam, gain, read_e, bias, fpn_adu, top)[0] - level_adu

    if off(0.0) >= 0:
        return 0.0
    hi = max((level_adu - bias + 1.0) * gain, 1.0)
    while off(hi) < 0 and hi < 1e8:
        hi *= 2
    return float(brentq(off, 0.0, hi, xtol=1e-4 * max(gain, 1e-3), rtol=1e-6))


# ----------------------------------------------------------------------------------- the line
def mean_variance(
    levels: np.ndarray,
    variances: np.ndarray,
    level_noise: np.ndarray,
    read_noise_e: float,
    fpn_adu: float,
    top: int,
) -> dict:
    """The line ``var = a + level / gain`` over background boxes and its bias and read noise (module doc,
    step 1). ``level_noise``: each box level's own standard error (ADU). ``ok`` False with ``why`` when it
    is refused; ``term`` names what the refusal is about ("gain", "bias", "gain, bias and read noise")."""
    levels, variances = np.asarray(levels, float), np.asarray(variances, float)
    sigma = np.sqrt(np.maximum(variances, 0))
    use = (levels - CLIP_SIGMA * sigma > 0.5) & (levels + CLIP_SIGMA * sigma < top)
    out: dict = {
        "boxes": int(use.sum()),
        "boxes_all": int(levels.size),
        "darkest_adu": float(levels.min()),
        "level_span_adu": float(np.percentile(levels, 95) - np.percentile(levels, 5)),
    }
    if use.sum() < 3:
        return {
            **out,
            "ok": False,
            "term": "gain, bias and read noise",
            "why": (
                f"the background sits within {CLIP_SIGMA:g} σ of the ADC's floor (0 ADU) or top in "
                f"{'every box' if not use.any() else 'all but ' + str(int(use.sum())) + ' boxes'} (median level "
                f"{np.median(levels):.2f} ADU, σ {np.median(sigma):.2f} ADU), where its noise is clipped"
            ),
        }
    x, y = levels[use], variances[use]
    keep = np.ones(x.size, bool)
    for _ in range(3):  # clip boxes whose noise is off the line (a bright star, a satellite trail)
        b, a = np.polyfit(x[keep], y[keep], 1)
        r = y - (a + b * x)
        keep = np.abs(r) < 3 * 1.4826 * np.median(np.abs(r[keep])) + 1e-9
    n = int(keep.sum())
    xs = x[keep]
    # the lever arm: the spread of the levels net of their own noise (a spread of noise alone is none)
    lever = float(np.sqrt(max(xs.var() - np.median(np.asarray(level_noise, float)[use][keep] ** 2), 0.0)))
    resid = float(np.sqrt(np.sum(r[keep] ** 2) / max(n - 2, 1)))
    se = resid / (np.sqrt(n) * lever) if lever > 0 else np.inf
    out.update(
        intercept_adu2=float(a),
        slope=float(b),
        boxes=n,
        lever_adu=lever,
        level_span_adu=float(np.percentile(xs, 95) - np.percentile(xs, 5)),
        slope_rse=float(se / abs(b)) if b != 0 else float("inf"),
    )
    if b <= 0 or out["slope_rse"] > MAX_SLOPE_RSE:
        return {
            **out,
            "ok": False,
            "term": "gain",
            "why": (
                f"background spans {out['level_span_adu']:.1f} ADU"
                + (
                    f": the noise variance does not grow with the level (slope {b:.3g})"
                    if b <= 0
                    else ", no more than the box levels' own noise: no lever arm for the gain"
                    if lever == 0
                    else f", the line's slope ±{100 * out['slope_rse']:.0f} % (over {100 * MAX_SLOPE_RSE:.0f} %)"
                )
            ),
        }
    gain = 1.0 / b
    # a = read^2/g^2 + 1/12 + fpn^2 - (bias - 0.5)/g: the floor takes half an ADU off every level
    bias = (read_noise_e**2 / gain**2 + 1 / 12 + fpn_adu**2 - a) * gain + 0.5
    read, note = read_noise_e, "read noise kept from the start camera; bias from the intercept"
    if bias < 0:
        bias = 0.0
        read = float(np.sqrt(max((a - 1 / 12 - fpn_adu**2 - 0.5 / gain) * gain**2, 0.0)))
        note = "bias 0 (the intercept leaves no room for one); read noise from the intercept"
    out.update(gain_e_per_adu=float(gain), bias_adu=float(bias), read_noise_e=float(read), note=note)
    if bias > out["darkest_adu"] + 0.5:
        return {
            **out,
            "ok": False,
            "term": "bias",
            "why": (
                f"the mean–variance line (gain {gain:.3g} e-/ADU) puts it at {bias:.1f} ADU, above the darkest "
                f"background ({out['darkest_adu']:.2f} ADU): impossible, charge only adds to the bias"
            ),
        }
    return {**out, "ok": True}


# ----------------------------------------------------------------------------------- the direct fit
QUANTISATION_SIGMA_ADU = 1 / np.sqrt(12)  # the noise an ADC's rounding alone gives a level that varies (ADU rms)


def fit_direct(
    level_adu: float, sigma_adu: float, bias: int, read_e: float, fpn_adu: float, top: int
) -> tuple[float, float, float]:
    """(gain e-/ADU, background e-, FPN ADU) whose model background (:func:`model_background`) has the
    measured ``level_adu`` and ``sigma_adu`` with ``bias``, ``read_e`` fixed; FPN is set to 0 when it alone
    leaves no room for the measured noise."""
    free = sigma_adu**2 - 1 / 12 - fpn_adu**2
    if free <= 0.05 * sigma_adu**2:
        fpn_adu = 0.0
        free = max(sigma_adu**2 - 1 / 12, 0.25 * sigma_adu**2)
    m = max(level_adu - bias + 0.5, 0.05 * sigma_adu)
    # var = m/g + read^2/g^2 (+ quantisation, FPN): u = 1/g from the quadratic
    u = (-m + np.sqrt(m * m + 4 * read_e**2 * free)) / (2 * read_e**2) if read_e > 0 else free / m
    g0, lam0 = 1.0 / u, m / u

    def cost(p):
        g, lam = np.exp(p)
        lv, sg = model_background(lam, g, read_e, bias, fpn_adu, top)
        return ((lv - level_adu) / max(level_adu, 0.1)) ** 2 + ((sg - sigma_adu) / sigma_adu) ** 2

    best = minimize(
        cost,
        np.log([g0, max(lam0, 1e-3)]),
        method="Nelder-Mead",
        options={"xatol": 1e-4, "fatol": 1e-10, "maxiter": 400},
    )
    g, lam = np.exp(best.x)
    return float(g), float(lam), float(fpn_adu)


def fit_sensor(
    boxes: dict,
    start_sensor,
    bias_given: int | None,
    top: int,
    start_name: str,
    targets: tuple | None = None,
    bias_name: str = "the camera file's",
    fpn_measured: float | None = None,
) -> tuple[SensorFit, dict]:
    """The sensor from the frames' background boxes (``boxes``: level, variance, level_noise, sigma arrays):
    the mean-variance line where it stands, else the direct fit. ``bias_given``: the camera file's bias, or
    None without one (``bias_name`` says whose in the report); ``start_name`` says where read noise and FPN
    (``start_sensor``'s) come from in the one line that reports a direct fit. ``targets`` (level, sigma): fit
    those directly instead of the boxes' medians (the correction after renders). Returns (the sensor, a record
    for the report). ``fpn_measured``: the frames' own offset pattern
    (:func:`skygen.real.fit_pixels.fixed_pattern`), used by the direct fit instead of the start camera's."""
    s = start_sensor
    mv = mean_variance(boxes["level"], boxes["variance"], boxes["level_noise"], s.read_noise_e, s.fpn_adu, top)
    level = float(np.median(boxes["level"]))
    sigma = float(np.median(boxes["sigma"]))
    rec = {"mean_variance": mv, "level_adu": level, "sigma_adu": sigma}
    if mv["ok"] and targets is None:
        fit = SensorFit(
            mv["gain_e_per_adu"], int(round(mv["bias_adu"])), mv["read_noise_e"], s.fpn_adu, "mean-variance"
        )
        return fit, {**rec, "method": fit.method}
    if targets is not None:
        level, sigma = targets
    darkest = mv["darkest_adu"]
    if bias_given is not None and bias_given <= darkest + 0.5:
        bias, bias_from = int(bias_given), bias_name
    elif mv["ok"]:  # a direct fit after renders: the line's bias stands
        bias, bias_from = int(round(mv["bias_adu"])), "the mean–variance line's"
    else:
        bias, bias_from = (
            0,
            (
                f"{bias_name} {bias_given} ADU is above the darkest background, {darkest:.2f} ADU"
                if bias_given is not None
                else "no camera file gives one"
            ),
        )
    fpn0, fpn_from = (
        (s.fpn_adu, start_name) if fpn_measured is None else (fpn_measured, "measured: the pattern frames share")
    )
    refused = () if mv["ok"] else (f"{mv['term']} not constrained by these frames ({mv['why']})",)
    if sigma < QUANTISATION_SIGMA_ADU:
        # no read-out of charge through an ADC shows less noise than its own rounding: these darks were clipped or
        # smoothed (an 8-bit JPEG's crushed blacks, a denoiser), and no gain reproduces them
        gain, fpn = float(s.gain_e_per_adu), float(fpn0)
        lam = max(level - bias + 0.5, 0.0) * gain
        lv, sg = model_background(lam, gain, s.read_noise_e, bias, fpn, top)
        used = (
            f"the background's noise, σ {sigma:.2f} ADU, is below an ADC's own rounding ({QUANTISATION_SIGMA_ADU:.2f} "
            f"ADU): the frames' darks are clipped or smoothed (8-bit JPEG, a denoiser) and no gain reproduces them; "
            f"{start_name} gain {gain:.3g} e-/ADU, read noise {s.read_noise_e:.3g} e- and FPN {fpn:.3g} ADU kept, "
            f"{lam:.3g} e- of background from the level {level:.2f} ADU (bias {bias} ADU, {bias_from}): renders will "
            f"show more background noise ({sg:.2f} ADU) than these frames"
        )
        said = "; ".join(refused) + ": " + used if refused else used
        fit = SensorFit(gain, bias, s.read_noise_e, fpn, "kept", refused, said)
        return fit, {**rec, "method": "kept", "said": said}
    gain, lam, fpn = fit_direct(level, sigma, bias, s.read_noise_e, fpn0, top)
    lv, sg = model_background(lam, gain, s.read_noise_e, bias, fpn, top)
    used = (
        f"gain {gain:.3g} e-/ADU and {lam:.3g} e- of background fitted to the background's level {level:.2f} ADU "
        f"and σ {sigma:.2f} ADU (model: {lv:.2f}, {sg:.2f}), with bias {bias} ADU ({bias_from}), read noise "
        f"{s.read_noise_e:.3g} e- ({start_name}) and FPN {fpn:.3g} ADU ({fpn_from}"
        + (f"; {fpn0:.3g} ADU alone would exceed the noise" if fpn != fpn0 else "")
        + ") used instead"
    )
    said = "; ".join(refused) + ": " + used if refused else used
    fit = SensorFit(gain, bias, s.read_noise_e, fpn, "direct", refused, said)
    return fit, {
        **rec,
        "method": "direct",
        "direct": {
            "gain_e_per_adu": gain,
            "background_e": lam,
            "target_level_adu": level,
            "target_sigma_adu": sigma,
            "model_level_adu": lv,
            "model_sigma_adu": sg,
            "bias_from": bias_from,
        },
        "said": said,
    }
