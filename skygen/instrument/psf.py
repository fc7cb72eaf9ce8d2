"""Point-spread functions integrated over pixels, and star stamps.

All stamps are returned as ``(y0, x0, patch)``: ``patch[j, i]`` is the expected
signal (same unit as ``flux``) in full-resolution pixel ``(y0 + j, x0 + i)``.
Pixel ``(x, y)`` covers [x - 0.5, x + 0.5) x [y - 0.5, y + 0.5) (see conventions).

* ``gaussian``: exact integral of a circular Gaussian over each pixel (product of erf
  differences). ``sigma`` sets the width; defocus is modelled by a larger sigma.
* ``moffat``: I(r) ~ (1 + (r/alpha)^2)^-beta with the FWHM of the Gaussian of the same
  ``sigma``.
* ``airy``: [2 J1(v)/v]^2 with the same FWHM (1.029 lambda N).

Moffat and Airy have no closed-form pixel integral. Once per PSF, the profile is
sampled on a grid 1/16 pixel fine and box-filtered over one pixel (the pixel integral
at every 1/16-pixel phase); a star's stamp is then read from that table by bilinear
interpolation in its sub-pixel phase. Centroids of these stamps are true to < 0.005 px
(Moffat) and < 0.01 px (Airy, whose slowly falling wings are cut at 8 FWHM).

Non-square pixels (``aspect`` = pixel height / width, see :mod:`skygen.instrument.camera`): the PSF is
round on the sky, so in pixels it is ``aspect`` times narrower along y (Gaussian: sigma_y =
sigma / aspect); ``sigma`` is always measured in pixel widths (along x).

Every stamp is normalised to sum to ``flux``: a Gaussian stamp reaches far enough
that the flux beyond its edge would be below 0.01 e- (4 to 6.5 sigma, see
:func:`gaussian_radius_px`), so the renormalisation moves nothing measurable; for Moffat and Airy the wings beyond the
stamp radius
(8 FWHM) are folded into the stamp, conserving flux. A motion-blurred star is the sum
of stamps at sub-exposure positions, each carrying an equal share of the flux.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.special import erf, j1

FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))
_SQRT2 = np.sqrt(2.0)
PHASES = 16  # table resolution of Moffat/Airy pixel integrals, per pixel


def stamp_radius_px(psf: str, sigma: float) -> int:
    """Largest stamp half-size, px (Gaussian: for the brightest possible star)."""
    if psf == "gaussian":
        return int(np.ceil(6.5 * sigma)) + 1
    return int(np.ceil(8.0 * FWHM_PER_SIGMA * sigma)) + 1


TAIL_E = 0.01  # Gaussian stamps are cut where less than this much flux lies outside


def gaussian_radius_px(flux: np.ndarray, sigma: float) -> np.ndarray:
    """Half-size of a Gaussian stamp so that < TAIL_E of ``flux`` falls outside it."""
    from scipy.special import ndtri

    frac = np.clip(TAIL_E / np.maximum(np.asarray(flux, dtype=np.float64), 1e-300) / 4.0, 1e-15, 0.25)
    z = -ndtri(frac)
    return (np.ceil(np.maximum(z, 3.0) * sigma) + 1).astype(int)


def gaussian_stamps(xs: np.ndarray, ys: np.ndarray, fluxes: np.ndarray, sigma: float, aspect: float = 1.0) -> list:
    """Vectorised :func:`stamp` for many Gaussian point sources: [(y0, x0, patch)], in input order."""
    out = [None] * len(xs)
    sigma_y = sigma / aspect
    radii = gaussian_radius_px(fluxes, sigma)
    radii_y = gaussian_radius_px(fluxes, sigma_y)
    for r, ry in np.unique(np.column_stack([radii, radii_y]), axis=0):
        sel = np.flatnonzero((radii == r) & (radii_y == ry))
        x0 = np.floor(xs[sel] + 0.5).astype(int) - r
        y0 = np.floor(ys[sel] + 0.5).astype(int) - ry
        gx = np.diff(erf((x0[:, None] + np.arange(2 * r + 2) - 0.5 - xs[sel, None]) / (_SQRT2 * sigma)), axis=1)
        gy = np.diff(erf((y0[:, None] + np.arange(2 * ry + 2) - 0.5 - ys[sel, None]) / (_SQRT2 * sigma_y)), axis=1)
        norm = fluxes[sel] / (gx.sum(1) * gy.sum(1))
        patches = gy[:, :, None] * gx[:, None, :] * norm[:, None, None]
        for k, a, b, p in zip(sel, y0, x0, patches):
            out[k] = (int(a), int(b), p)
    return out


def _gaussian_1d(centre: float, lo: int, n: int, sigma: float) -> np.ndarray:
    edges = (np.arange(lo, lo + n + 1) - 0.5 - centre) / (_SQRT2 * sigma)
    return 0.5 * np.diff(erf(edges))


def _radial_profile(psf: str, r: np.ndarray, sigma: float, beta: float) -> np.ndarray:
    fwhm = FWHM_PER_SIGMA * sigma
    if psf == "moffat":
        alpha = fwhm / (2.0 * np.sqrt(2.0 ** (1.0 / beta) - 1.0))
        return (1.0 + (r / alpha) ** 2) ** (-beta)
    # airy: FWHM = 1.029 lambda N  ->  v = pi r / (lambda N) = 1.029 pi r / FWHM
    v = 1.029 * np.pi * np.maximum(r, 1e-12) / fwhm
    return (2.0 * j1(v) / v) ** 2


def _table_radius_px(psf: str, sigma: float, aspect: float) -> int:
    """Half-size of a Moffat/Airy stamp: the stamp radius, in rows too when pixels are short (aspect < 1)."""
    r = stamp_radius_px(psf, sigma)
    return r if aspect >= 1 else int(np.ceil(r / aspect))


@lru_cache(maxsize=8)
def _pixel_integral_table(psf: str, sigma: float, beta: float, aspect: float = 1.0) -> np.ndarray:
    """Pixel integrals of the profile for pixel centres on a 1/PHASES grid (see module doc)."""
    r = _table_radius_px(psf, sigma, aspect)
    m = (2 * r + 2) * PHASES + 1
    # fine samples at offsets (k + 0.5)/P - R - 1 ... covering the stamp plus one pixel margin
    off = (np.arange(m + PHASES) + 0.5) / PHASES - (r + 1.0)
    prof = _radial_profile(psf, np.hypot(off[:, None] * aspect, off[None, :]), sigma, beta)  # rows: y
    c = np.cumsum(np.cumsum(np.pad(prof, ((1, 0), (1, 0))), 0), 1)
    box = c[PHASES:, PHASES:] - c[:-PHASES, PHASES:] - c[PHASES:, :-PHASES] + c[:-PHASES, :-PHASES]
    return box / PHASES**2


def stamp(
    x: float, y: float, flux: float, psf: str = "gaussian", sigma: float = 1.0, beta: float = 3.0, aspect: float = 1.0
) -> tuple[int, int, np.ndarray]:
    """Pixel-integrated image of one point source at (x, y) carrying ``flux`` in total
    (``aspect``: pixel height / width; the PSF is round on the sky)."""
    if psf == "gaussian":
        r, ry = int(gaussian_radius_px(flux, sigma)), int(gaussian_radius_px(flux, sigma / aspect))
        x0, y0 = int(np.floor(x + 0.5)) - r, int(np.floor(y + 0.5)) - ry
        patch = np.outer(_gaussian_1d(y, y0, 2 * ry + 1, sigma / aspect), _gaussian_1d(x, x0, 2 * r + 1, sigma))
        patch *= flux / patch.sum()
        return y0, x0, patch
    r = _table_radius_px(psf, sigma, aspect)
    x0, y0 = int(np.floor(x + 0.5)) - r, int(np.floor(y + 0.5)) - r
    n = 2 * r + 1
    if True:  # (block kept for a small diff)
        table = _pixel_integral_table(psf, float(sigma), float(beta), float(aspect))
        # table[a, b] = pixel integral for a pixel centred (a/P - R - 0.5, b/P - R - 0.5) px from the star
        fy = (y0 - y + r + 0.5) * PHASES
        fx = (x0 - x + r + 0.5) * PHASES
        iy, ix = int(np.floor(fy)), int(np.floor(fx))
        wy, wx = fy - iy, fx - ix
        rows = iy + PHASES * np.arange(n)
        cols = ix + PHASES * np.arange(n)
        t00 = table[np.ix_(rows, cols)]
        t01 = table[np.ix_(rows, cols + 1)]
        t10 = table[np.ix_(rows + 1, cols)]
        t11 = table[np.ix_(rows + 1, cols + 1)]
        patch = (1 - wy) * ((1 - wx) * t00 + wx * t01) + wy * ((1 - wx) * t10 + wx * t11)
    patch *= flux / patch.sum()
    return y0, x0, patch


def streak(
    xs: np.ndarray,
    ys: np.ndarray,
    flux: float,
    psf: str = "gaussian",
    sigma: float = 1.0,
    beta: float = 3.0,
    aspect: float = 1.0,
) -> tuple[int, int, np.ndarray]:
    """Sum of stamps at positions (xs, ys), each with flux/len(xs): a motion-blurred star."""
    if len(xs) == 1:
        return stamp(float(xs[0]), float(ys[0]), flux, psf, sigma, beta, aspect)
    r = _table_radius_px(psf, sigma, aspect) if psf != "gaussian" else stamp_radius_px(psf, max(sigma, sigma / aspect))
    x0 = int(np.floor(xs.min() + 0.5)) - r
    y0 = int(np.floor(ys.min() + 0.5)) - r
    w = int(np.floor(xs.max() + 0.5)) + r + 1 - x0
    h = int(np.floor(ys.max() + 0.5)) + r + 1 - y0
    out = np.zeros((h, w))
    share = flux / len(xs)
    for x, y in zip(xs, ys):
        sy, sx, p = stamp(float(x), float(y), share, psf, sigma, beta, aspect)
        out[sy - y0 : sy - y0 + p.shape[0], sx - x0 : sx - x0 + p.shape[1]] += p
    return y0, x0, out


def peak_fraction(psf: str, sigma: float, beta: float = 3.0, aspect: float = 1.0) -> float:
    """Fraction of a star's flux in its brightest pixel when centred on a pixel."""
    return float(stamp(0.0, 0.0, 1.0, psf, sigma, beta, aspect)[2].max())


def add_patch(image: np.ndarray, y0: int, x0: int, patch: np.ndarray) -> tuple[int, int, int, int] | None:
    """Add ``patch`` into ``image`` in place, clipped to the image. Returns the box touched
    as (y0, y1, x0, x1), half-open, or None if the patch is entirely outside."""
    h, w = image.shape
    ya, xa = max(y0, 0), max(x0, 0)
    yb, xb = min(y0 + patch.shape[0], h), min(x0 + patch.shape[1], w)
    if ya >= yb or xa >= xb:
        return None
    image[ya:yb, xa:xb] += patch[ya - y0 : yb - y0, xa - x0 : xb - x0]
    return ya, yb, xa, xb
