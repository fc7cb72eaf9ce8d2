"""Another solver's plate solution (a FITS WCS) as a camera attitude: an independent truth for real frames.

astrometry.net and ASTAP write one ``.wcs`` file per solved frame (a FITS header: a TAN projection, SIP terms
where fitted). :func:`wcs_directions` puts pixels on the sky through it (``astropy.wcs``);
:func:`attitude_from_wcs` finds the camera -> ICRS rotation that puts the same pixels there through a skygen
camera (Wahba's problem over a grid of pixels), with the rms of what the rotation cannot absorb: where the camera
file and the WCS disagree about the field or the distortion, that misfit says by how much.

Pixels here are skygen's: 0-based, x right, y down the stored rows. A solver that read the image bottom-up
counts FITS rows from the bottom: ``rows_from_bottom`` (ASTAP on a PNG does; check with
``benchmarks/wcs_agreement.py``, whose offsets are then arcseconds, not the frame's height).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skygen.errors import SkygenError

GRID = 7  # pixels per side of the grid the attitude is fitted on


class WCSError(SkygenError):
    """A WCS file that cannot be read as a celestial plate solution."""


def read_wcs(path: str | Path):
    """The ``astropy.wcs.WCS`` of a FITS header file (a ``.wcs``: 80-character cards, with or without newlines;
    non-ASCII bytes in comments, such as ASTAP's degree sign, are replaced)."""
    import warnings

    from astropy.io import fits
    from astropy.wcs import WCS

    path = Path(path)
    try:
        text = path.read_bytes().decode("latin-1").encode("ascii", "replace").decode()
        sep = "\n" if "\n" in text.strip() else ""
        header = fits.Header.fromstring(text, sep=sep)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # FITS-standard notes on fixable keywords (e.g. a missing RADESYS)
            w = WCS(header, relax=True)
    except (OSError, ValueError, KeyError) as exc:
        raise WCSError(f"{path}: not a FITS WCS header ({exc})") from None
    if not w.has_celestial:
        raise WCSError(f"{path}: its WCS has no celestial axes (CTYPE RA---TAN / DEC--TAN or the like)")
    return w


def wcs_directions(w, x: np.ndarray, y: np.ndarray, rows_from_bottom: int | None = None) -> np.ndarray:
    """Unit vectors (N, 3, ICRS) of skygen pixel positions under WCS ``w`` (a :func:`read_wcs` result or a file);
    ``rows_from_bottom``: the image height, where the WCS counts rows from the bottom."""
    if not hasattr(w, "all_pix2world"):
        w = read_wcs(w)
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    yy = (rows_from_bottom - 1 - y) if rows_from_bottom is not None else y
    ra, dec = (np.radians(v) for v in w.all_pix2world(x, yy, 0))
    return np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=-1)


def angle_arcsec(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (arcsec) between unit vectors ``a`` and ``b`` (..., 3), row by row (accurate for tiny angles)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))) * 3600.0


def attitude_from_wcs(w, camera, rows_from_bottom: bool = False) -> tuple[np.ndarray, float]:
    """(camera -> ICRS matrix, rms misfit in arcsec) of the rotation that best puts a grid of ``camera``'s pixels
    (:class:`skygen.instrument.camera.Camera`) where the WCS ``w`` puts them."""
    gx, gy = np.meshgrid(np.linspace(0, camera.width_px - 1, GRID), np.linspace(0, camera.height_px - 1, GRID))
    gx, gy = gx.ravel(), gy.ravel()
    cam_v = camera.unproject(gx, gy)
    sky_v = wcs_directions(w, gx, gy, camera.height_px if rows_from_bottom else None)
    u, _, vt = np.linalg.svd(sky_v.T @ cam_v)  # Wahba: the rotation m with sky ~ m @ cam
    m = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    fit = cam_v @ m.T
    return m, float(np.sqrt(np.mean(angle_arcsec(fit, sky_v) ** 2)))
