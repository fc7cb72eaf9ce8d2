"""Star detection and centroiding on the full-resolution frame.

1. Background: sigma-clipped mean and standard deviation of a 7 x 7-strided subsample (7, not 8: a stride of 8
   samples one pixel of every 8 x 8 JPEG block, the same place in each, whose noise the compression changes; on the
   Canon 70D's JPEGs that read 2.76 ADU where all pixels read 2.14, and 1.16 x on Amalthea's, 1.24 x on
   openstartracker's PNGs) —
   one level for the frame (the default: what skygen's renders have and what the emulator
   is calibrated on) — or, with ``background_box_px`` = B > 0, a local background
   (:func:`background_map`): the same statistics per B x B box, a 3 x 3 median filter
   over the boxes (a box filled by a bright star takes its neighbours' level) and bilinear
   interpolation between box centres, for frames with sky glow, gradients or vignetting
   (ground-based frames; the same idea as SExtractor's and photutils' mesh background).
2. Threshold: pixels above ``background + threshold_sigma * sigma`` (per pixel with a map).
3. Connected components (8-connectivity, OpenCV); components smaller than
   ``min_area_px`` are dropped (single hot pixels, noise spikes).
4. For each component: intensity-weighted centroid of the background-subtracted
   signal over the component grown by one pixel (8-neighbourhood; negative values
   clipped to 0), summed flux over the same pixels, peak value and area above threshold.
5. Sorted brightest first; positions in full-resolution pixels (see conventions).

:func:`match` pairs detections with true stars (nearest within a radius, brightest
true star first, each used once).
"""

from __future__ import annotations

import cv2
import numpy as np

EMPTY = {
    "x_px": np.zeros(0),
    "y_px": np.zeros(0),
    "flux_adu": np.zeros(0, np.float32),
    "peak_adu": np.zeros(0, np.float32),
    "area_px": np.zeros(0, np.int32),
}


_CLIP = 3.0
_CLIP_STD_FACTOR = 0.98657  # std of a unit Gaussian truncated at +-3 sigma


# the least background noise a threshold is set from: an integer read-out's rounding alone (ADU rms). Frames whose
# darks are clipped to one value (an 8-bit JPEG's crushed blacks) measure ~0, and a threshold of a few times that
# would detect every compression artefact as a source
QUANTUM_SIGMA_ADU = 1.0 / np.sqrt(12.0)


def estimate_background(image: np.ndarray, stride: int = 7) -> tuple[float, float]:
    """(level, sigma) of the background in ADU from a strided subsample (7: odd and prime to a JPEG's 8 x 8 blocks
    and a colour sensor's 2 x 2 pattern, so every place in them is sampled; module doc).

    Iterative 3-sigma clipping around the median; the clipped standard deviation is
    corrected for the truncation. Unlike the MAD this stays accurate when the noise is
    only one or two ADU (quantised values). Never below :data:`QUANTUM_SIGMA_ADU`.
    """
    sub = image[::stride, ::stride].astype(np.float32).ravel()
    level = float(np.median(sub))
    sigma = max(1.4826 * float(np.median(np.abs(sub - level))), 0.5)
    for _ in range(3):
        keep = sub[np.abs(sub - level) < _CLIP * sigma]
        level = float(keep.mean())
        sigma = max(float(keep.std()) / _CLIP_STD_FACTOR, 1e-3)
    return level, max(sigma, QUANTUM_SIGMA_ADU)


def background_map(image: np.ndarray, box_px: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """(level, sigma) maps, float32 and the image's shape, from per-box clipped statistics (see module doc)."""
    from scipy import ndimage

    h, w = image.shape
    if box_px < 8:
        raise ValueError(f"background box of {box_px} px: use at least 8 px (several star widths)")
    ny, nx = -(-h // box_px), -(-w // box_px)
    level, sigma = np.empty((ny, nx)), np.empty((ny, nx))
    stride = 2 if box_px >= 32 else 1
    fy, fx = h // box_px, w // box_px  # whole boxes: all at once (estimate_background's steps, vectorised)
    if fy and fx and box_px % stride == 0:
        level[:fy, :fx], sigma[:fy, :fx] = _whole_box_backgrounds(image, box_px, stride, fy, fx)
    else:
        fy = fx = 0
    for i in range(ny):
        for j in range(nx):
            if i < fy and j < fx:
                continue
            level[i, j], sigma[i, j] = estimate_background(
                image[i * box_px : (i + 1) * box_px, j * box_px : (j + 1) * box_px], stride
            )
    if ny >= 3 and nx >= 3:
        level = ndimage.median_filter(level, size=3, mode="nearest")
        sigma = ndimage.median_filter(sigma, size=3, mode="nearest")

    # bilinear between box centres, linear beyond the outer centres (half a box): the mesh gets a ring
    # extrapolated from its two outer rows/columns; box centres at (i + 0.5) * box - 0.5 (a partial last
    # box: the centre of its pixels), ring centres one box further out
    def ring(a):
        for axis in (0, 1):
            if a.shape[axis] >= 2:
                first, second = np.take(a, [0], axis), np.take(a, [1], axis)
                last, before = np.take(a, [-1], axis), np.take(a, [-2], axis)
                a = np.concatenate([2 * first - second, a, 2 * last - before], axis)
            else:
                a = np.concatenate([a, a, a], axis)
        return a

    def index(n_box, size):
        c = np.minimum((np.arange(n_box) + 0.5) * box_px, (np.arange(n_box) * box_px + size) / 2) - 0.5
        c = np.concatenate([[c[0] - box_px], c, [c[-1] + box_px]])
        return np.interp(np.arange(size), c, np.arange(n_box + 2))

    # bilinear interpolation is separable: rows' weights (h, ny + 2) @ mesh @ columns' weights (nx + 2, w),
    # the same numbers as ndimage.map_coordinates(order=1) at these coordinates, ~50x faster
    wy, wx = _linear_weights(index(ny, h), ny + 2), _linear_weights(index(nx, w), nx + 2)
    level_px = wy @ ring(level) @ wx.T
    sigma_px = wy @ ring(sigma) @ wx.T
    return level_px.astype(np.float32), np.maximum(sigma_px, 0.5 * sigma.min()).astype(np.float32)


def _whole_box_backgrounds(image: np.ndarray, box_px: int, stride: int, fy: int, fx: int):
    """:func:`estimate_background` of each of the fy x fx whole boxes (the same strided pixels, the same
    median, MAD and three clipping passes in float32), vectorised over the boxes: a 2048 x 1536 frame has
    768 boxes of 64 px, whose one-at-a-time estimates cost ~45 ms of Python overhead. Equal to the
    per-box estimates up to float32 summation order (~1e-6 relative)."""
    b = box_px // stride
    sub = image[: fy * box_px : stride, : fx * box_px : stride]
    level, sigma = clipped_stats(sub.reshape(fy, b, fx, b).transpose(0, 2, 1, 3).reshape(fy * fx, b * b))
    return level.reshape(fy, fx), sigma.reshape(fy, fx)


def clipped_stats(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(level, sigma) of each row of ``samples`` (one row per box): :func:`estimate_background`'s steps (median,
    MAD, three 3-sigma clipping passes, in float32) on every row at once; float64 arrays. Equal to
    ``estimate_background`` of each row up to float32 summation order (~1e-6 relative)."""
    a = np.asarray(samples).astype(np.float32)
    level = np.median(a, axis=1)
    sigma = np.maximum(1.4826 * np.median(np.abs(a - level[:, None]), axis=1), 0.5)
    level, sigma = level.astype(np.float64), sigma.astype(np.float64)
    for _ in range(3):
        keep = np.abs(a - level.astype(np.float32)[:, None]) < (_CLIP * sigma).astype(np.float32)[:, None]
        n = np.maximum(keep.sum(axis=1), 1)
        mean = np.where(keep, a, np.float32(0)).sum(axis=1, dtype=np.float32) / n
        dev = np.where(keep, a - mean.astype(np.float32)[:, None], np.float32(0))
        std = np.sqrt((dev * dev).sum(axis=1, dtype=np.float32) / n)
        level = mean.astype(np.float64)
        sigma = np.maximum(std.astype(np.float64) / _CLIP_STD_FACTOR, 1e-3)
    return level, np.maximum(sigma, QUANTUM_SIGMA_ADU)


def _linear_weights(position: np.ndarray, n: int) -> np.ndarray:
    """(len(position), n) matrix of linear-interpolation weights at fractional indices ``position``."""
    i0 = np.clip(np.floor(position).astype(int), 0, n - 1)
    f = position - i0
    i1 = np.minimum(i0 + 1, n - 1)
    w = np.zeros((len(position), n))
    rows = np.arange(len(position))
    np.add.at(w, (rows, i0), 1 - f)
    np.add.at(w, (rows, i1), f)
    return w


_NEIGHBOURS = np.array([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)])


def detect(
    image: np.ndarray,
    threshold_sigma: float = 5.0,
    min_area_px: int = 3,
    max_detections: int = 64,
    background_box_px: int = 0,
    *,
    background: tuple | None = None,
) -> tuple[dict, float, float]:
    """Detect stars in a full-resolution ADU frame. Returns (detections, background, sigma);
    with ``background_box_px`` > 0 (local background) the last two are the medians of the maps.

    ``background``: this image's background already estimated, to be used instead of estimating it again
    (several thresholds on one frame): ``background_map(image, background_box_px)``'s two maps, optionally
    followed by their medians (what is returned; a median of a whole map costs a few ms), or with
    ``background_box_px`` 0 ``estimate_background(image)``'s (level, sigma).

    Vectorised over components: only the few pixels above threshold (and their
    neighbours) are touched after the connected-component labelling.
    """
    medians = None
    if background is not None and background_box_px:
        bg_map, sigma_map, *medians = background
        if np.shape(bg_map) != image.shape or np.shape(sigma_map) != image.shape or len(medians) not in (0, 2):
            raise ValueError(
                f"detect: background maps of shape {np.shape(bg_map)} for an image of {image.shape}: give "
                "background_map(image, background_box_px) of this image (and optionally the maps' two medians)"
            )
    if background_box_px:
        if background is None:
            bg_map, sigma_map = background_map(image, background_box_px)
        if medians:
            bg, sigma = float(medians[0]), float(medians[1])
        else:
            bg, sigma = float(np.median(bg_map)), float(np.median(sigma_map))
        mask = image > bg_map + threshold_sigma * sigma_map
        bg_at = lambda idx: bg_map.ravel()[idx].astype(np.float64)  # noqa: E731
    else:
        bg, sigma = estimate_background(image) if background is None else (float(background[0]), float(background[1]))
        mask = image > bg + threshold_sigma * sigma
        bg_at = lambda idx: bg  # noqa: E731
    _, labels = cv2.connectedComponents(mask.view(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    fg = np.flatnonzero(mask)
    lab = labels.ravel()[fg]
    area = np.bincount(lab)
    sel = area[lab] >= min_area_px
    fg, lab = fg[sel], lab[sel]
    if fg.size == 0:
        return {k: v.copy() for k, v in EMPTY.items()}, bg, sigma
    h, w = image.shape
    # grow each component by one pixel (8-neighbourhood), each pixel counted once per component
    ys, xs = np.divmod(fg, w)
    ny = ys[:, None] + _NEIGHBOURS[:, 0]
    nx = xs[:, None] + _NEIGHBOURS[:, 1]
    ok = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)
    key = np.unique(np.repeat(lab, 9)[ok.ravel()].astype(np.int64) * (h * w) + (ny * w + nx)[ok])
    glab, gpix = np.divmod(key, h * w)
    ids, comp = np.unique(glab, return_inverse=True)
    val = image.ravel()[gpix].astype(np.float64) - bg_at(gpix)
    wgt = np.clip(val, 0, None)
    gy, gx = np.divmod(gpix, w)
    tot = np.bincount(comp, wgt)
    flux = np.bincount(comp, val)
    good = tot > 0
    cx = np.bincount(comp, wgt * gx)[good] / tot[good]
    cy = np.bincount(comp, wgt * gy)[good] / tot[good]
    # peak over the thresholded pixels of each component
    fcomp = np.searchsorted(ids, lab)
    peak = np.full(len(ids), -np.inf)
    np.maximum.at(peak, fcomp, image.ravel()[fg].astype(np.float64) - bg_at(fg))
    flux, peak, ar = flux[good], peak[good], area[ids][good]
    order = np.argsort(-flux, kind="stable")[:max_detections]
    det = {
        "x_px": cx[order],
        "y_px": cy[order],
        "flux_adu": flux[order].astype(np.float32),
        "peak_adu": peak[order].astype(np.float32),
        "area_px": ar[order].astype(np.int32),
    }
    return det, bg, sigma


def match(
    det_x: np.ndarray,
    det_y: np.ndarray,
    star_x: np.ndarray,
    star_y: np.ndarray,
    star_flux: np.ndarray,
    radius_px: float,
) -> np.ndarray:
    """For each detection, the index of its true star, or -1.

    True stars are taken brightest first; each claims the nearest unclaimed detection
    within ``radius_px``.
    """
    out = np.full(len(det_x), -1, np.int32)
    if len(det_x) == 0 or len(star_x) == 0:
        return out
    d2 = (det_x[None, :] - star_x[:, None]) ** 2 + (det_y[None, :] - star_y[:, None]) ** 2
    free = np.ones(len(det_x), bool)
    near = np.flatnonzero((d2 <= radius_px**2).any(axis=1))  # only these can claim one
    for s in near[np.argsort(-star_flux[near], kind="stable")]:
        cand = np.where(free & (d2[s] <= radius_px**2), d2[s], np.inf)
        j = int(np.argmin(cand))
        if np.isfinite(cand[j]):
            out[j] = s
            free[j] = False
    return out
