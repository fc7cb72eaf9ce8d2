"""Statistics that compare frames, real or rendered, measured the same way on both.

Used by ``skygen fit-camera`` (real frames against renders of the start and the fitted camera)
and by ``benchmarks/real_vs_sim.py``. Units: ADU of the frame as given; pixels.

* background level and noise: skygen's sigma-clipped estimator over the whole frame
  (:func:`skygen.instrument.detect.estimate_background`; a gradient across the frame raises the noise);
* detections: skygen's detector with the given settings, all of them counted;
* star width: :func:`star_width_px`, the intensity-weighted second moment (per axis, 9 x 9 px, local
  background subtracted) of the 20 brightest unsaturated detections at least 6 px from the edge, median;
* zero point (with catalogue magnitudes of matched detections): median of ``mag + 2.5 log10(flux_adu)``
  (:func:`skygen.real.fit_pixels.zero_point`).

:func:`check_renders` compares the medians of real and rendered frames with :data:`TOLERANCES` (issue 35's
targets): what ``skygen fit-camera`` warns about before it writes a camera whose renders miss its frames.
"""

from __future__ import annotations

import numpy as np


def star_width_px(img: np.ndarray, det: dict, bg: float, saturation: float, n: int = 20) -> tuple[float, int]:
    """(median second-moment sigma in px, stars used): the mean of the two axes' variances of the ``n``
    brightest detections that are unsaturated and at least 6 px from the edge (nan, 0 without one).

    The background under each star is the median of the 13 x 13 px box's edge (a gradient across the frame
    would otherwise leave a pedestal that widens every star); ``bg`` only decides saturation."""
    sig: list[float] = []
    h, w = img.shape
    yy, xx = np.mgrid[-4:5, -4:5]
    for x, y, peak in zip(det["x_px"], det["y_px"], det["peak_adu"]):
        if len(sig) == n:
            break
        if peak + bg >= 0.9 * saturation:
            continue
        xi, yi = int(round(x)), int(round(y))
        if not (6 <= xi < w - 6 and 6 <= yi < h - 6):
            continue
        ring = img[yi - 6 : yi + 7, xi - 6 : xi + 7].astype(np.float64)
        local = np.median(np.concatenate([ring[0], ring[-1], ring[1:-1, 0], ring[1:-1, -1]]))
        st = np.clip(img[yi - 4 : yi + 5, xi - 4 : xi + 5] - local, 0, None)
        tot = st.sum()
        if tot <= 0:
            continue
        mx, my = (st * xx).sum() / tot, (st * yy).sum() / tot
        sig.append(float(np.sqrt(((st * ((xx - mx) ** 2 + (yy - my) ** 2)).sum() / tot) / 2)))
    return (float(np.median(sig)) if sig else float("nan")), len(sig)


def frame_stats(
    img: np.ndarray, threshold_sigma: float, min_area_px: int, background_box_px: int, saturation: float
) -> tuple[dict, dict]:
    """({background_adu, noise_adu, detections, star_sigma_px, star_width_stars}, the detections) of one frame.

    ``noise_adu`` is the noise the detector thresholds on: with a local background (``background_box_px`` > 0) the
    median of its per-box sigmas, so a sky-glow gradient that the boxes take out is not counted as noise (a frame's
    global clipped sigma would count it: on skysolve's light-polluted frames 2.47 ADU against 1.42 within the boxes);
    without one, the frame's clipped sigma, which is what that detector uses."""
    from skygen.instrument.detect import detect, estimate_background

    bg, sigma = estimate_background(img)
    det, _, box_sigma = detect(img, threshold_sigma, min_area_px, 100_000, background_box_px)
    if background_box_px:
        sigma = box_sigma
    width, n_width = star_width_px(img, det, bg, saturation)
    return (
        {
            "background_adu": bg,
            "noise_adu": sigma,
            "detections": int(len(det["x_px"])),
            "star_sigma_px": width,
            "star_width_stars": n_width,
        },
        det,
    )


#: :func:`neighbour_correlation`: a BOX_PX box mean is taken off; pixels within GROW_PX of one beyond CLIP_SIGMA robust
#: sigma from it (stars, hot pixels) are left out (3, not 4: at 4 the faint stars of skygen's own white-noise renders
#: of a dense field correlated neighbours by 0.11, at 3 by 0.075)
CORR_BOX_PX = 31
CORR_CLIP_SIGMA = 3.0
CORR_GROW_PX = 3


def neighbour_correlation(img: np.ndarray) -> tuple[float, float, float]:
    """(correlation of the background noise with the right-hand neighbour, with the lower one, its robust sigma in
    ADU). skygen draws independent noise per pixel unless ``sensor.processor_blur_px`` blurs it (~0 for raw
    read-outs); demosaicing, JPEG compression or a denoiser correlate neighbours (0.15-0.6 on the processed cameras
    of results/real-frames/noise-correlation). A crushed background (sigma ~0) reads close to 1: no noise to
    correlate."""
    import cv2

    f = img.astype(np.float64)
    res = f - cv2.blur(f, (CORR_BOX_PX, CORR_BOX_PX), borderType=cv2.BORDER_REFLECT)
    sigma = 1.4826 * float(np.median(np.abs(res - np.median(res))))
    if sigma <= 0:
        sigma = float(res.std()) or 1.0
    bad = (np.abs(res) > CORR_CLIP_SIGMA * sigma).astype(np.uint8)
    grow = 2 * CORR_GROW_PX + 1
    good = ~cv2.dilate(bad, np.ones((grow, grow), np.uint8)).astype(bool)

    def corr(a, b, ok):
        a, b = a[ok], b[ok]
        if a.size < 100:
            return float("nan")
        a, b = a - a.mean(), b - b.mean()
        return float((a * b).mean() / max(np.sqrt((a * a).mean() * (b * b).mean()), 1e-12))

    rx = corr(res[:, :-1], res[:, 1:], good[:, :-1] & good[:, 1:])
    ry = corr(res[:-1, :], res[1:, :], good[:-1, :] & good[1:, :])
    return rx, ry, sigma


def nonstar_brightest(flux_adu: np.ndarray, nonstar: np.ndarray, n: int = 10) -> int:
    """How many of the ``n`` brightest detections are flagged ``nonstar`` (no catalogue star): what a
    few-star solver is given, so what renders must reproduce for their few-star cells to predict the real."""
    order = np.argsort(-np.asarray(flux_adu, dtype=np.float64), kind="stable")[:n]
    return int(np.asarray(nonstar, bool)[order].sum())


#: renders of a fitted camera match its frames when their medians are this close (relative): issue 35
TOLERANCES = {"background_adu": 0.10, "noise_adu": 0.15, "star_sigma_px": 0.10, "detections": 0.25}
LABELS = {
    "background_adu": "background",
    "noise_adu": "background σ",
    "star_sigma_px": "star width",
    "detections": "detections / frame",
}


def median_of(rows: list[dict], key: str) -> float:
    """Median of ``key`` over the rows' finite values (nan when none, without numpy's all-nan warning)."""
    v = np.array([r[key] for r in rows], float) if rows else np.zeros(0)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else float("nan")


def repeat_ratios(real: list[dict], rendered: list[dict], key: str) -> list[float]:
    """Rendered over real medians of ``key``, one per pass of renders over the frames (rows' ``render_pass``, as
    :func:`skygen.real.fit_render.check_stats` gives them): how much the verdict's ratio owes to the renders' own
    noise. Empty with fewer than two passes."""
    passes = sorted({r["render_pass"] for r in rendered if "render_pass" in r})
    a = median_of(real, key)
    if len(passes) < 2 or not (np.isfinite(a) and a != 0):
        return []
    return [median_of([r for r in rendered if r.get("render_pass") == p], key) / a for p in passes]


def check_renders(real: list[dict], rendered: list[dict]) -> list[dict]:
    """One verdict per statistic of :data:`TOLERANCES`: {stat, label, real, rendered, ratio, tolerance, ok,
    why, passes}. ``why`` says how far off a statistic is, or why it could not be measured (a nan is off);
    ``passes``: the ratio of each pass of renders over the frames alone (:func:`repeat_ratios`), said in ``why``."""
    out = []
    for k, tol in TOLERANCES.items():
        a, b = median_of(real, k), median_of(rendered, k)
        ratio = b / a if np.isfinite(a) and np.isfinite(b) and a != 0 else float("nan")
        if np.isfinite(a) and a == 0 and b == 0:  # both exactly 0 (a background clipped to black): they agree
            ratio = 1.0
        ok = bool(np.isfinite(ratio) and abs(ratio - 1) <= tol)
        passes = repeat_ratios(real, rendered, k)
        if ok:
            why = ""
        elif np.isfinite(ratio):
            why = f"{LABELS[k]} {b:.3g} rendered vs {a:.3g} real: {ratio:.2f} x (tolerance {100 * tol:.0f} %)"
            if passes:
                one = f"{min(passes):.2f}-{max(passes):.2f} x"
                why = why[:-1] + f"; {len(passes)} renders of each frame, one by one {one})"
        else:
            if np.isfinite(a) and np.isfinite(b):  # a real 0 and a rendered value: no ratio, both said
                out.append({"stat": k, "label": LABELS[k], "real": a, "rendered": b, "ratio": ratio, "tolerance": tol,
                            "ok": False, "why": f"{LABELS[k]} {b:.3g} rendered vs 0 real", "passes": []})  # fmt: skip
                continue
            which = "renders" if not np.isfinite(b) else "real frames"
            rows = rendered if which == "renders" else real
            reason = (
                "no detection"
                if k == "star_sigma_px" and not any(r.get("detections") for r in rows)
                else "no unsaturated detection at least 6 px from the edge"
                if k == "star_sigma_px"
                else "not measurable"
            )
            why = f"{LABELS[k]} not measured on the {which} ({reason}): nan"
        out.append(
            {
                "stat": k,
                "label": LABELS[k],
                "real": a,
                "rendered": b,
                "ratio": ratio,
                "tolerance": tol,
                "ok": ok,
                "why": why,
                "passes": passes,
            }
        )
    return out
