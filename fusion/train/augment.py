"""Training augmentations that keep the image and the detections in agreement.

Every function takes a :class:`Sample` (the stored image in ADU plus its detections)
and returns a new one; nothing changes in place. Each draws its randomness from the
``numpy.random.Generator`` it is given, so a sample is reproducible from
(seed, epoch, frame) whatever the worker that builds it.

Conventions (skygen's, see :mod:`skygen.conventions`): the image is the *stored* frame,
``[y, x]``, ``S x S`` pixels, area-averaged by the integer factor ``f`` from the
``W x W`` sensor; detection positions are in *full-resolution* sensor pixels with
(0, 0) the centre of the top-left pixel. A full-resolution position x lands on stored
coordinate ``u = (x + 0.5)/f - 0.5``. The optical axis is taken at the sensor centre
``((W-1)/2, (H-1)/2)`` (skygen's default principal point).

* :func:`rotate` — in-plane rotation about the sensor centre by ``theta`` degrees:
  ``x' = cx + cos(t)(x - cx) - sin(t)(y - cy)``, ``y' = cy + sin(t)(x - cx) + cos(t)(y - cy)``
  (clockwise on screen, where y points down). The image is resampled bilinearly with the
  same map; uncovered corners take the frame's background level. Detections that leave the
  sensor are dropped. The boresight label does not change.
* :func:`jitter` — ``adu' = bias + g (adu - bias) + b``; detection fluxes scale by ``g``.
* :func:`add_noise` — additive Gaussian pixel noise; detections unchanged.
* :func:`drop_stars` — each detection lost with probability p; optionally painted out of
  the image (replaced by background plus noise).
* :func:`inject_false_stars` — Gaussian point sources (the dataset's PSF sigma, pixel- and
  area-integrated) painted into the image and appended to the detections.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from ..config import AugConfig
from ..model.inputs import FrameGeometry, Sample


def _gaussian_stamp(image: np.ndarray, u: float, v: float, total: float, sigma: float) -> None:
    """Add a pixel-integrated 2-D Gaussian of integral ``total`` centred at stored (u, v), in place."""
    from scipy.special import erf

    r = int(np.ceil(4 * sigma + 1))
    s = image.shape[0]
    x0, x1 = max(int(np.floor(u)) - r, 0), min(int(np.floor(u)) + r + 2, s)
    y0, y1 = max(int(np.floor(v)) - r, 0), min(int(np.floor(v)) + r + 2, s)
    if x0 >= x1 or y0 >= y1:
        return
    k = 1.0 / (np.sqrt(2.0) * sigma)
    ex = np.arange(x0, x1 + 1) - 0.5 - u
    ey = np.arange(y0, y1 + 1) - 0.5 - v
    px = np.diff(0.5 * erf(ex * k))
    py = np.diff(0.5 * erf(ey * k))
    image[y0:y1, x0:x1] += (total * np.outer(py, px)).astype(np.float32)


def rotate(sample: Sample, theta_deg: float, geo: FrameGeometry) -> Sample:
    """Rotate image and detections about the sensor centre (see module docstring)."""
    if theta_deg == 0:
        return sample
    t = np.radians(theta_deg)
    c, s = np.cos(t), np.sin(t)
    cu, cv = (geo.image_px - 1) / 2.0, (geo.image_h - 1) / 2.0  # stored centre
    m = np.array([[c, -s, cu - c * cu + s * cv], [s, c, cv - s * cu - c * cv]])
    img = cv2.warpAffine(
        sample.image,
        m,
        (geo.image_px, geo.image_h),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float(sample.background_adu),
    )
    cx, cy = (geo.sensor_px - 1) / 2.0, (geo.sensor_h - 1) / 2.0  # full-resolution centre: the same point
    dx, dy = sample.x_px - cx, sample.y_px - cy
    x, y = cx + c * dx - s * dy, cy + s * dx + c * dy
    keep = (x >= -0.5) & (x < geo.sensor_px - 0.5) & (y >= -0.5) & (y < geo.sensor_h - 0.5)
    out = replace(sample, image=img, x_px=x, y_px=y)
    return out.take(keep)


def jitter(sample: Sample, gain: float, offset_adu: float, geo: FrameGeometry) -> Sample:
    """Contrast ``gain`` about the bias level plus a brightness ``offset_adu``; fluxes scale by gain."""
    img = (geo.bias_adu + gain * (sample.image - geo.bias_adu) + offset_adu).astype(np.float32)
    return replace(
        sample,
        image=img,
        flux_adu=(sample.flux_adu * gain).astype(np.float32),
        background_adu=geo.bias_adu + gain * (sample.background_adu - geo.bias_adu) + offset_adu,
        noise_adu=sample.noise_adu * gain,
    )


def add_noise(sample: Sample, sigma_adu: float, rng: np.random.Generator) -> Sample:
    """Add N(0, sigma_adu^2) to every stored pixel."""
    if sigma_adu <= 0:
        return sample
    img = sample.image + np.float32(sigma_adu) * rng.standard_normal(sample.image.shape, dtype=np.float32)
    return replace(sample, image=img, noise_adu=float(np.hypot(sample.noise_adu, sigma_adu)))


def drop_stars(
    sample: Sample, p: float, rng: np.random.Generator, geo: FrameGeometry, erase_image: bool = False
) -> Sample:
    """Lose each detection with probability ``p``; optionally paint lost stars out of the image."""
    if sample.n == 0 or p <= 0:
        return sample
    keep = rng.random(sample.n) >= p
    out = sample.take(keep)
    if erase_image and not keep.all():
        img = sample.image.copy()
        yy, xx = np.mgrid[0 : geo.image_h, 0 : geo.image_px]
        for j in np.flatnonzero(~keep):
            r_full = np.sqrt(max(float(sample.area_px[j]), 1.0) / np.pi) + 3.0 * geo.psf_sigma_px
            u, v = geo.to_stored(np.array([sample.x_px[j], sample.y_px[j]]))
            r = r_full / geo.factor + 1.0
            disc = (xx - u) ** 2 + (yy - v) ** 2 <= r * r
            img[disc] = sample.background_adu + rng.normal(0.0, sample.noise_adu, int(disc.sum()))
        out = replace(out, image=img.astype(np.float32))
    return out


def inject_false_stars(
    sample: Sample, n: int, snr_range: tuple[float, float], rng: np.random.Generator, geo: FrameGeometry
) -> Sample:
    """Paint ``n`` point sources at uniform positions; append them to the detections, re-sorted.

    Peak amplitude (full-resolution ADU) = snr * full-resolution noise, snr log-uniform in
    ``snr_range``; integrated flux = peak * 2 pi sigma^2. In the stored image the source is
    a Gaussian of variance (sigma^2 + f^2/12)/f^2 stored pixels^2 (area averaging) with
    integral flux / f^2 (stored pixels are block means).
    """
    if n <= 0:
        return sample
    f, sig = geo.factor, geo.psf_sigma_px
    margin = 2.0 * sig
    x = rng.uniform(margin - 0.5, geo.sensor_px - 0.5 - margin, n)
    y = rng.uniform(margin - 0.5, geo.sensor_h - 0.5 - margin, n)
    lo, hi = snr_range
    snr = np.exp(rng.uniform(np.log(lo), np.log(hi), n))
    noise_full = sample.noise_adu * f
    flux = snr * noise_full * 2.0 * np.pi * sig * sig
    img = sample.image.copy()
    sig_st = np.sqrt(sig * sig + f * f / 12.0) / f
    for xi, yi, fi in zip(x, y, flux):
        u, v = geo.to_stored(np.array([xi, yi]))
        _gaussian_stamp(img, float(u), float(v), float(fi) / (f * f), float(sig_st))
    area = np.full(n, max(int(np.pi * (2 * sig) ** 2), 1), np.int32)
    out = replace(
        sample,
        image=img,
        x_px=np.concatenate([sample.x_px, x]),
        y_px=np.concatenate([sample.y_px, y]),
        flux_adu=np.concatenate([sample.flux_adu, flux.astype(np.float32)]),
        area_px=np.concatenate([sample.area_px, area]),
    )
    return out.sorted()


def augment(sample: Sample, cfg: AugConfig, rng: np.random.Generator, geo: FrameGeometry) -> Sample:
    """All switched-on augmentations in a fixed order: dropout, false stars, rotation, jitter, noise.

    Every draw comes from ``rng``; a switched-off augmentation draws nothing (so switching
    one off changes the draws of those after it, not of those before).
    """
    if cfg.dropout:
        sample = drop_stars(sample, cfg.dropout_prob, rng, geo, cfg.dropout_erase_image)
    if cfg.false_stars and cfg.false_star_rate > 0:
        sample = inject_false_stars(sample, int(rng.poisson(cfg.false_star_rate)), cfg.false_star_snr, rng, geo)
    if cfg.rotation and cfg.rotation_max_deg > 0:
        sample = rotate(sample, float(rng.uniform(-cfg.rotation_max_deg, cfg.rotation_max_deg)), geo)
    if cfg.jitter:
        gain = float(rng.uniform(1 - cfg.contrast_frac, 1 + cfg.contrast_frac))
        offset = float(rng.uniform(-cfg.brightness_sigma, cfg.brightness_sigma)) * sample.noise_adu
        sample = jitter(sample, gain, offset, geo)
    if cfg.noise and cfg.noise_max_sigma > 0:
        sample = add_noise(sample, float(rng.uniform(0, cfg.noise_max_sigma)) * sample.noise_adu, rng)
    return sample


@dataclass(frozen=True)
class Augmenter:
    """:func:`augment` with its config bound: the ``augment`` callable :class:`fusion.model.shards.FrameDataset`
    takes (picklable, so DataLoader workers of any start method can use it)."""

    cfg: AugConfig

    def __call__(self, sample: Sample, rng: np.random.Generator, geo: FrameGeometry) -> Sample:
        return augment(sample, self.cfg, rng, geo)
