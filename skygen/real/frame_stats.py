"""Statistics that compare frames, real or rendered, measured the same way on both.

Used by ``skygen fit-camera`` (real frames against renders of the start and the fitted camera)
and by ``benchmarks/real_vs_sim.py``. Units: ADU of the frame as given; pixels.

* background level and noise: skygen's sigma-clipped estimator over the whole frame
  (:func:`skygen.instrument.detect.estimate_background`; a gradient across the frame raises the noise);
* detections: skygen's detector with the given settings, all of them counted;
* star width: :func:`star_width_px`, the intensity-weighted second moment (per axis, 9 x 9 px, local
  background subtracted) of the 20 brightest unsaturated detections, median;
* zero point (with catalogue magnitudes of matched detections): median of ``mag + 2.5 log10(flux_adu)``
  (:func:`skygen.real.fit_pixels.zero_point`).
"""

from __future__ import annotations

import numpy as np


def star_width_px(img: np.ndarray, det: dict, bg: float, saturation: float, n: int = 20) -> float:
    """Median second-moment sigma (px, mean of the two axes' variances) of the ``n`` brightest unsaturated detections.

    The background under each star is the median of the 13 x 13 px box's edge (a gradient across the frame
    would otherwise leave a pedestal that widens every star); ``bg`` only decides saturation."""
    sig = []
    h, w = img.shape
    for x, y, peak in zip(det["x_px"][:n], det["y_px"][:n], det["peak_adu"][:n]):
        if peak + bg >= 0.9 * saturation:
            continue
        xi, yi = int(round(x)), int(round(y))
        if not (6 <= xi < w - 6 and 6 <= yi < h - 6):
            continue
        ring = img[yi - 6 : yi + 7, xi - 6 : xi + 7].astype(np.float64)
        local = np.median(np.concatenate([ring[0], ring[-1], ring[1:-1, 0], ring[1:-1, -1]]))
        st = np.clip(img[yi - 4 : yi + 5, xi - 4 : xi + 5] - local, 0, None)
        yy, xx = np.mgrid[-4:5, -4:5]
        tot = st.sum()
        if tot <= 0:
            continue
        mx, my = (st * xx).sum() / tot, (st * yy).sum() / tot
        sig.append(np.sqrt(((st * ((xx - mx) ** 2 + (yy - my) ** 2)).sum() / tot) / 2))
    return float(np.median(sig)) if sig else float("nan")


def frame_stats(
    img: np.ndarray, threshold_sigma: float, min_area_px: int, background_box_px: int, saturation: float
) -> tuple[dict, dict]:
    """({background_adu, noise_adu, detections, star_sigma_px}, the detections) of one frame."""
    from skygen.instrument.detect import detect, estimate_background

    bg, sigma = estimate_background(img)
    det, _, _ = detect(img, threshold_sigma, min_area_px, 100_000, background_box_px)
    return (
        {
            "background_adu": bg,
            "noise_adu": sigma,
            "detections": int(len(det["x_px"])),
            "star_sigma_px": star_width_px(img, det, bg, saturation),
        },
        det,
    )
