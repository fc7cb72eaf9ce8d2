"""Pixel statistics of ``skygen fit-camera``: what the sensor and the sky did, measured from real frames.

Units: ADU of the frames after :func:`value_scale` (a 16-bit file of 12-bit data stored x16 is
divided by 16); electrons only through the fitted gain; pixel positions in skygen's convention.

* :func:`value_scale` — the factor the stored values carry (common trailing zero bits of every
  pixel below the file's maximum) and the ADC depth.
* :func:`background` — per-box sigma-clipped level and noise (:func:`skygen.instrument.detect.background_map`)
  and ``level = centre + gx x + gy y - drop r^2`` fitted to the box levels (``r^2`` normalised to 1 at
  the corner, as skygen's ``optics.vignetting``): the level at the centre, the large-scale gradient
  (ADU from the dark edge to the bright edge, and its direction) and the vignetting drop at the corner.
* the background boxes' noise (from differences of horizontal neighbours in the odd rows, so a gradient
  inside a box does not count as noise and the noise does not share pixels with the level, which the
  even rows give): the input of the sensor fit (:mod:`skygen.real.fit_sensor`).
* :func:`fixed_pattern` — the offset pattern every frame shares (FPN, ADU rms): the covariance of two
  frames' background residuals (frame minus its level map; pixels within 3 sigma in both, so stars, which
  move between pointings, and hot pixels are out), net of the start camera's PRNU on the level; the
  median over consecutive pairs, as the sigma of skygen's rounded FPN of that variance. Temporal noise does
  not correlate between frames; the pattern does.
* :func:`psf_fit` — Gaussian and Moffat profiles (pixel-integrated, round on the sky with the
  fitted pixel aspect) fitted to isolated, unsaturated matched stars; the Moffat is kept when it
  lowers the median squared residual by more than 10 %.
* :func:`hot_pixels` — single pixels far above their background with quiet neighbours, at the
  same place in at least half the frames (all of them for fewer than three frames).
* :func:`processor_blur` — the blur a processor (demosaicing, JPEG, a denoiser) put on the frames, from their
  background noise's neighbour correlation (:func:`skygen.real.frame_stats.neighbour_correlation`), as the
  ``sensor.processor_blur_px`` that renders it; where the camera renders it, the read-out's noise and PSF are
  fitted as before it (:func:`unblurred_boxes`, :func:`unblurred_psf`). Whether it does is fit-camera's
  ``--processor-blur`` (auto: where its renders miss the frames by less; results/real-frames/processor-blur).
* :func:`zero_point` — median of ``Hp + 2.5 log10(flux_adu)`` over matched, unsaturated stars: the
  magnitude of a star giving 1 ADU of detected flux (the detector's own flux, so renders measured
  the same way are comparable).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.special import erf

from skygen.instrument.detect import background_map, clipped_stats, estimate_background


def value_scale(images: list[np.ndarray]) -> tuple[int, int, float]:
    """(scale, bit_depth, saturation in scaled ADU): integer frames whose values below the maximum
    are all multiples of 2^k carry data x 2^k (e.g. 12-bit in 16-bit TIFF: 16)."""
    top = max(float(img.max()) for img in images)
    scale = 1
    if all(np.all(img == np.round(img)) for img in images):
        for k in range(8, 0, -1):
            if all(np.all(np.mod(img[img < top], 2**k) == 0) for img in images):
                scale = 2**k
                break
    top_scaled = top / scale
    bits = int(min(16, max(8, np.ceil(np.log2(np.floor(top_scaled) + 1)))))
    return scale, bits, float(2**bits - 1)


def background(img: np.ndarray, box_px: int = 64) -> dict:
    """Level/noise maps, box samples and a fitted plane (level at the centre, gradient amplitude and angle).

    The plane is fitted to the level map at the box centres. Per box, for the sensor fit: ``box_level`` and
    ``box_clip_sigma`` (skygen's clipped estimator on the box's even rows), ``box_sigma`` (difference noise of
    its odd rows) and ``box_level_noise`` (the level's own standard error, ADU)."""
    h, w = img.shape
    level, sigma = background_map(img, box_px)
    ys = np.arange(box_px // 2, h, box_px)
    xs = np.arange(box_px // 2, w, box_px)
    ly, lx = np.meshgrid(ys, xs, indexing="ij")
    # each box's level and clipped sigma from its even rows, its difference noise from its odd rows: the
    # noise shares no pixel with the level (and no neighbour box's level: no median filter over a curved sky)
    boxes = [
        img[y - box_px // 2 : y + box_px // 2, x - box_px // 2 : x + box_px // 2]
        for y, x in zip(ly.ravel(), lx.ravel())
    ]
    # whole boxes all at once (the same numbers as one at a time, up to summation order), a partial edge box alone
    whole = np.array([b.shape == (box_px, box_px) for b in boxes])
    even, sv = np.empty((len(boxes), 2)), np.empty(len(boxes))
    if whole.any():
        stack = np.stack([b for b, w in zip(boxes, whole) if w])
        even[whole] = np.column_stack(clipped_stats(stack[:, 0::2].reshape(len(stack), -1)))
        sv[whole] = _difference_sigmas(stack[:, 1::2])
    for k in np.flatnonzero(~whole):
        even[k] = estimate_background(boxes[k][0::2], 1)
        sv[k] = _difference_sigma(boxes[k][1::2])
    lv = level[ly, lx].ravel()
    box_level, clip_sigma = even[:, 0], even[:, 1]
    level_noise = clip_sigma / np.sqrt([max(b[0::2].size, 1) for b in boxes])
    bx, by = lx.ravel() - (w - 1) / 2, ly.ravel() - (h - 1) / 2
    r2 = (bx**2 + by**2) / ((w / 2) ** 2 + (h / 2) ** 2)  # as skygen's vignetting: 1 at the corner
    A = np.column_stack([np.ones(lv.size), bx, by, r2])
    c = np.linalg.lstsq(A, lv, rcond=None)[0]
    amp = abs(c[1]) * (w - 1) + abs(c[2]) * (h - 1)  # dark edge to bright edge of the plane
    resid = lv - A @ c
    return {
        "level_map": level,
        "sigma_map": sigma,
        "box_level": box_level,
        "box_sigma": sv,
        "box_clip_sigma": clip_sigma,
        "box_level_noise": level_noise,
        "level_adu": float(np.median(level)),
        "noise_adu": float(np.median(sigma)),
        "centre_adu": float(c[0]),
        "corner_drop_adu": float(-c[3]),
        "gradient_adu": float(amp),
        "gradient_angle_deg": float(np.degrees(np.arctan2(c[2], c[1]))),
        "residual_std_adu": float(resid.std()),
    }


def _difference_sigma(box: np.ndarray) -> float:
    """Pixel noise of a box from differences of horizontal neighbours (a smooth gradient cancels), clipped
    against stars: 1.4826 MAD / sqrt(2), then a 3-sigma clipped standard deviation."""
    d = np.diff(box.astype(np.float64), axis=1).ravel()
    s = 1.4826 * np.median(np.abs(d - np.median(d)))
    keep = d[np.abs(d - np.median(d)) < 3 * max(s, 1e-6)]
    return float(keep.std() / 0.98657 / np.sqrt(2)) if keep.size > 10 else float(s / np.sqrt(2))


def _difference_sigmas(stack: np.ndarray) -> np.ndarray:
    """:func:`_difference_sigma` of every box of ``stack`` (boxes, rows, columns) at once."""
    n_box = stack.shape[0]
    d = np.diff(stack.astype(np.float64), axis=2).reshape(n_box, -1)
    dev = d - np.median(d, axis=1, keepdims=True)
    s = 1.4826 * np.median(np.abs(dev), axis=1)
    keep = np.abs(dev) < 3 * np.maximum(s, 1e-6)[:, None]
    n = keep.sum(axis=1)
    mean = np.where(keep, d, 0.0).sum(axis=1) / np.maximum(n, 1)
    std = np.sqrt((np.where(keep, d - mean[:, None], 0.0) ** 2).sum(axis=1) / np.maximum(n, 1))
    return np.where(n > 10, std / 0.98657 / np.sqrt(2), s / np.sqrt(2))


def fixed_pattern(images: list, levels: list, sigmas: list, prnu_frac: float) -> dict:
    """{fpn_adu (None from one frame), pairs, covariance_adu2}: the static pattern (module doc)."""
    covs = []
    for k in range(len(images) - 1):
        ra = images[k] - levels[k]
        rb = images[k + 1] - levels[k + 1]
        keep = (np.abs(ra) < 3 * sigmas[k]) & (np.abs(rb) < 3 * sigmas[k + 1])
        a, b = ra[keep].astype(np.float64), rb[keep].astype(np.float64)
        prnu2 = prnu_frac**2 * float(np.median(levels[k])) * float(np.median(levels[k + 1]))
        covs.append(float(np.mean((a - a.mean()) * (b - b.mean()))) - prnu2)
    fpn = _unrounded_sigma(float(np.median(covs))) if covs else None
    return {"fpn_adu": fpn, "pairs": len(covs), "covariance_adu2": covs}


def _unrounded_sigma(var: float) -> float:
    """The sigma ``s`` whose rounded normal, round(N(0, s)) (skygen's integer FPN), has variance ``var``."""
    from scipy.optimize import brentq
    from scipy.special import ndtr

    def rounded_var(s: float) -> float:
        j = np.arange(-int(8 * s) - 2, int(8 * s) + 3)
        return float(np.sum(j * j * (ndtr((j + 0.5) / s) - ndtr((j - 0.5) / s))))

    if var <= 1e-6:
        return 0.0
    return float(brentq(lambda s: rounded_var(s) - var, 1e-3, np.sqrt(var) + 1.0))


def _gauss_img(p, yy, xx, aspect):
    x0, y0, flux, sig, b = p
    sx, sy = np.sqrt(2) * sig, np.sqrt(2) * sig / aspect
    gx = 0.5 * (erf((xx + 0.5 - x0) / sx) - erf((xx - 0.5 - x0) / sx))
    gy = 0.5 * (erf((yy + 0.5 - y0) / sy) - erf((yy - 0.5 - y0) / sy))
    return flux * gx * gy + b


_SUB = (np.arange(4) + 0.5) / 4 - 0.5


def _moffat_img(p, yy, xx, aspect):
    x0, y0, flux, alpha, beta, b = p
    dx = xx[..., None, None] + _SUB[None, :] - x0
    dy = (yy[..., None, None] + _SUB[:, None] - y0) * aspect
    prof = (1 + (dx * dx + dy * dy) / (alpha * alpha)) ** (-beta)
    norm = (beta - 1) / (np.pi * alpha * alpha) * aspect  # per unit flux, per (column x row) pixel
    return flux * norm * prof.mean(axis=(-1, -2)) + b


def psf_fit(
    images, bg_maps, dets, matched, aspect: float, saturation: float, max_stars: int = 80, box: int = 5
) -> dict:
    """Median Gaussian sigma and Moffat (FWHM-sigma, beta) over isolated unsaturated matched stars (see module doc)."""
    rows = []
    for img, bgm, det, idx in zip(images, bg_maps, dets, matched):
        h, w = img.shape
        xs, ys = det["x_px"], det["y_px"]
        for i in idx:
            x, y = xs[i], ys[i]
            xi, yi = int(round(x)), int(round(y))
            if not (box <= xi < w - box and box <= yi < h - box):
                continue
            if det["peak_adu"][i] + bgm[yi, xi] > 0.8 * saturation:
                continue
            near = np.hypot(xs - x, ys - y)
            if np.sum(near < 3 * box) > 1:
                continue
            st = (
                img[yi - box : yi + box + 1, xi - box : xi + box + 1]
                - bgm[yi - box : yi + box + 1, xi - box : xi + box + 1]
            )
            rows.append((float(det["flux_adu"][i]), st.astype(float), x - xi, y - yi))
    rows.sort(key=lambda r: -r[0])
    rows = rows[:max_stars]
    yy, xx = np.mgrid[-box : box + 1, -box : box + 1].astype(float)
    gs, ms, ratio = [], [], []
    for flux, st, dx, dy in rows:
        tot = max(st.sum(), 1.0)
        pg = least_squares(
            lambda p: (_gauss_img(p, yy, xx, aspect) - st).ravel(),
            [dx, dy, tot, 1.5, 0.0],
            bounds=([-2, -2, 0, 0.3, -np.inf], [2, 2, np.inf, 10, np.inf]),
            x_scale=[0.1, 0.1, tot, 0.1, 1.0],
        )
        pm = least_squares(
            lambda p: (_moffat_img(p, yy, xx, aspect) - st).ravel(),
            [dx, dy, tot, 2.5, 3.0, 0.0],
            bounds=([-2, -2, 0, 0.3, 1.2, -np.inf], [2, 2, np.inf, 20, 20, np.inf]),
            x_scale=[0.1, 0.1, tot, 0.1, 0.3, 1.0],
        )
        gs.append(pg.x[3])
        a, beta = pm.x[3], pm.x[4]
        ms.append((a * 2 * np.sqrt(2 ** (1 / beta) - 1) / (2 * np.sqrt(2 * np.log(2))), beta))
        ratio.append(float(pm.fun @ pm.fun) / max(float(pg.fun @ pg.fun), 1e-12))
    if not gs:
        return {"ok": False, "why": "no isolated, unsaturated matched star to fit a PSF to", "n_stars": 0}
    ms = np.array(ms)
    out = {
        "ok": True,
        "n_stars": len(gs),
        "gaussian_sigma_px": float(np.median(gs)),
        "moffat_sigma_px": float(np.median(ms[:, 0])),
        "moffat_beta": float(np.median(ms[:, 1])),
        "moffat_over_gaussian_sse": float(np.median(ratio)),
    }
    out["psf"] = "moffat" if out["moffat_over_gaussian_sse"] < 0.9 and out["moffat_beta"] < 19 else "gaussian"
    return out


def hot_pixels(images, levels, sigmas, k_sigma: float = 8.0) -> dict:
    """Static hot pixels: count per frame, the static set and its excess (ADU, median)."""
    hits, excess = [], []
    for img, lv, sg in zip(images, levels, sigmas):
        hi = img > lv + k_sigma * sg
        quiet = img < lv + 3 * sg
        pad = np.pad(quiet, 1, constant_values=True)
        h, w = img.shape
        nb = np.ones_like(hi)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy or dx:
                    nb &= pad[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
        single = hi & nb
        hits.append(single)
        excess.append(np.where(single, img - lv, 0.0))
    count = np.sum(hits, axis=0)
    need = len(images) if len(images) < 3 else int(np.ceil(len(images) / 2))
    static = count >= need
    n = int(static.sum())
    ex = float(np.median(np.sum(excess, axis=0)[static] / count[static])) if n else 0.0
    return {
        "n_static": n,
        "fraction": n / static.size,
        "excess_adu": ex,
        "frames_needed": need,
        "single_pixel_spikes_per_frame": float(np.median([h.sum() for h in hits])),
    }


#: matches whose own zero point is this much (mag) above the brighter stars' are not their stars' light
#: (zero_point_rows)
ZERO_POINT_CLIP_MAG = 2.5
ZERO_POINT_ANCHOR_SHARE = 1 / 3  # the brightest third of the matches anchors that clip
ZERO_POINT_MIN_STARS = 5


#: a saturated core is the pixels at or above this share of the saturation level, connected, at least BLOOM_MIN_PX
BLOOM_CORE_SHARE = 0.98
BLOOM_MIN_PX = 4
#: the frames bloom (charge spilling along columns) where their saturated cores' median rows / columns spanned exceeds
#: this; measured from at least BLOOM_MIN_CORES cores
BLOOM_RATIO = 1.5
BLOOM_MIN_CORES = 3


def blooming(images: list, sat: float) -> dict:
    """{on: whether the frames' saturated stars bloom along columns (None: too few saturated cores to say), ratio,
    cores, note}: from the shape of their saturated cores (pixels at or above :data:`BLOOM_CORE_SHARE` of ``sat``,
    connected): a sensor that spills charge along its columns draws them as vertical streaks, one with anti-blooming
    (most CMOS, DSLRs, interline CCDs) as round blobs. On every camera here the cores are round (median rows /
    columns 1.0-1.07), where renders with ``sensor.blooming`` drew the brightest stars as streaks."""
    from scipy import ndimage

    ratios = []
    for img in images:
        lab, _ = ndimage.label(np.asarray(img) >= BLOOM_CORE_SHARE * sat)
        for k, sl in enumerate(ndimage.find_objects(lab), start=1):
            if sl is None or np.count_nonzero(lab[sl] == k) < BLOOM_MIN_PX:
                continue
            ratios.append((sl[0].stop - sl[0].start) / (sl[1].stop - sl[1].start))
    if len(ratios) < BLOOM_MIN_CORES:
        return {"on": None, "cores": len(ratios), "note": f"not measured: {len(ratios)} saturated cores in the frames "
                f"(at least {BLOOM_MIN_CORES}); the start camera's sensor.blooming kept"}  # fmt: skip
    ratio = float(np.median(ratios))
    on = ratio > BLOOM_RATIO
    said = f"the frames' {len(ratios)} saturated cores span {ratio:.2f} x as many rows as columns (median)"
    note = (
        f"sensor.blooming on: {said}, streaks along the columns (tolerance {BLOOM_RATIO})"
        if on
        else f"sensor.blooming off: {said}: round, an anti-blooming sensor (charge above the full well is drained, not "
        "spilled along the column)"
    )
    return {"on": bool(on), "ratio": ratio, "cores": len(ratios), "note": note}


def zero_point(
    flux_adu: np.ndarray, mag: np.ndarray, peak_adu: np.ndarray, level_adu: np.ndarray, saturation: float
) -> tuple[float, int]:
    """(median of Hp + 2.5 log10 flux over the unsaturated stars with positive flux that
    :func:`zero_point_rows` keeps, number used)."""
    zp, rows = zero_point_rows(flux_adu, mag, peak_adu, level_adu, saturation)
    return zp, int(rows.sum())


def zero_point_rows(
    flux_adu: np.ndarray, mag: np.ndarray, peak_adu: np.ndarray, level_adu: np.ndarray, saturation: float
) -> tuple[float, np.ndarray]:
    """(zero point, flags of the matches it is the median over). Unsaturated matches with positive flux, less
    those whose own zero point (Hp + 2.5 log10 flux) lies more than :data:`ZERO_POINT_CLIP_MAG` above the median
    of the brightest :data:`ZERO_POINT_ANCHOR_SHARE` of them (by catalogue magnitude, at least
    :data:`ZERO_POINT_MIN_STARS`): a detection that much brighter than the catalogue star it was paired with by
    position (a non-star or a blend beside a faint star, frequent in a wide field, where a pixel holds many faint
    stars) is not that star's light, and its zero point, magnitudes too faint, would pull the median with it. A
    detection fainter than its star (clipped by an edge, split) stays: it is that star's light, measured short."""
    flux_adu, mag = np.asarray(flux_adu, dtype=np.float64), np.asarray(mag, dtype=np.float64)
    ok = (flux_adu > 0) & (np.asarray(peak_adu) + np.asarray(level_adu) < 0.8 * saturation) & np.isfinite(mag)
    if not ok.any():
        return float("nan"), ok
    zp = np.full(len(mag), np.nan)
    zp[ok] = mag[ok] + 2.5 * np.log10(flux_adu[ok])
    rows = np.flatnonzero(ok)
    take = max(ZERO_POINT_MIN_STARS, int(np.ceil(ZERO_POINT_ANCHOR_SHARE * len(rows))))
    anchor = float(np.median(zp[rows[np.argsort(mag[rows], kind="stable")[:take]]]))
    ok &= np.where(ok, zp, anchor) - anchor <= ZERO_POINT_CLIP_MAG
    return float(np.median(zp[ok])), ok


#: a processor's blur is fitted where the frames' background noise correlates with its neighbours by at least this
#: (raw read-outs here: 0.00-0.01; processed ones 0.2-0.6; skygen's white-noise renders of a dense field of 113"
#: pixels, where stars below the clip correlate neighbours too: 0.075) and is at least BLUR_MIN_SIGMA_ADU (a crushed
#: background, its noise clipped away, reads close to 1 without being blurred)
BLUR_MIN_RHO = 0.12
BLUR_MIN_SIGMA_ADU = 0.5
#: frames measured (spread evenly) and the central crop of each (px): the statistic needs no more
BLUR_FRAMES = 4
BLUR_CROP_PX = 1024
#: a rounded read-out's own variance (ADU^2), added after the blur and so not blurred
QUANTUM_VAR = 1.0 / 12.0


def processor_blur(images: list, sigma_adu: float) -> dict:
    """{px (``sensor.processor_blur_px``; 0: none), rho (the frames' median neighbour correlation), rho_x, rho_y,
    frames, note} from up to :data:`BLUR_FRAMES` frames: the Gaussian blur whose sampled kernel correlates
    neighbours as much (:func:`skygen.instrument.sensor.blur_for_correlation`), where the correlation and the noise
    (``sigma_adu``, the frames' background sigma) pass :data:`BLUR_MIN_RHO` and :data:`BLUR_MIN_SIGMA_ADU`."""
    from skygen.instrument.sensor import blur_for_correlation, blur_variance_factor
    from skygen.real.fit_render import spread_evenly
    from skygen.real.frame_stats import neighbour_correlation

    rows = []
    for k in spread_evenly(len(images), BLUR_FRAMES):
        img = np.asarray(images[k])
        h, w = img.shape
        y0, x0 = max((h - BLUR_CROP_PX) // 2, 0), max((w - BLUR_CROP_PX) // 2, 0)
        rows.append(neighbour_correlation(img[y0 : y0 + BLUR_CROP_PX, x0 : x0 + BLUR_CROP_PX])[:2])
    if not rows:
        return {"px": 0.0, "rho": float("nan"), "frames": 0, "note": "not measured: no frame"}
    rx, ry = (float(np.nanmedian([r[i] for r in rows])) for i in (0, 1))
    rho = float(np.nanmean([rx, ry]))
    said = f"the frames' background noise correlates {rx:+.2f} / {ry:+.2f} with the right / lower neighbour"
    base = {"rho": rho, "rho_x": rx, "rho_y": ry, "frames": len(rows)}
    if not np.isfinite(rho) or rho < BLUR_MIN_RHO:
        return {**base, "px": 0.0, "note": f"none: {said} (below {BLUR_MIN_RHO}: independent noise per pixel, a raw "
                "read-out)"}  # fmt: skip
    if sigma_adu < BLUR_MIN_SIGMA_ADU:
        return {**base, "px": 0.0, "note": f"none: {said}, but the background's noise is {sigma_adu:.2f} ADU (below "
                f"{BLUR_MIN_SIGMA_ADU}): a crushed background, not a blurred one"}  # fmt: skip
    px = blur_for_correlation(rho)
    return {**base, "px": px, "variance_factor": blur_variance_factor(px),
            "note": f"{said}: a processor's blur (demosaicing, JPEG compression, denoising) of "
                    f"sensor.processor_blur_px {px:.2f} renders it"}  # fmt: skip


def unblurred_boxes(boxes: dict, blur_px: float) -> dict:
    """The sensor fit's background boxes (``level``, ``variance`` from horizontal neighbour differences, ``sigma``)
    as the read-out had them before a processor's blur of ``blur_px``: its variance divided by the blur's variance
    factor (and the differences' by 1 - the blur's neighbour correlation), the rounding's own 1/12 ADU^2 kept."""
    from skygen.instrument.sensor import blur_correlation, blur_variance_factor

    if blur_px <= 0:
        return boxes
    f, r = blur_variance_factor(blur_px), blur_correlation(blur_px)
    var = np.maximum(boxes["variance"] - QUANTUM_VAR, 0.0) / (f * (1.0 - r)) + QUANTUM_VAR
    sig2 = np.maximum(boxes["sigma"] ** 2 - QUANTUM_VAR, 0.0) / f + QUANTUM_VAR
    return {**boxes, "variance": var, "sigma": np.sqrt(sig2)}


def unblurred_psf(psf: dict, blur_px: float) -> dict:
    """The fitted PSF (:func:`psf_fit`) less a processor's blur of ``blur_px``: each profile's sigma reduced in
    quadrature by the blur kernel's second moment (at least 0.3 px)."""
    from skygen.instrument.sensor import blur_width_variance

    if blur_px <= 0 or not psf.get("ok"):
        return psf
    v = blur_width_variance(blur_px)
    out = dict(psf)
    for key in ("gaussian_sigma_px", "moffat_sigma_px"):
        out[key] = float(np.sqrt(max(psf[key] ** 2 - v, 0.09)))
    out["blur_removed_px"] = float(np.sqrt(v))
    return out
