"""Reading a user's frame files: PNG, TIFF (8 or 16 bit), FITS and ``.npy``.

:func:`read_frame` returns one monochrome float32 image ``[y, x]`` in the file's own linear
units, or raises :class:`FrameError` with the reason (unreadable, empty, colour, non-numeric).
PNG and TIFF are decoded by OpenCV with its log silenced: a damaged file gives our one line,
not libtiff's warnings first. :func:`mask_bad_pixels` replaces non-finite pixels (NaN, ±inf:
flagged pixels in float FITS or ``.npy`` frames) before detection. :func:`frame_files` lists
the frame files of a folder. Used by ``skygen fit-camera`` and, through
:mod:`fusion.solve.frames`, by ``fusion predict``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skygen.errors import DatasetError

FRAME_SUFFIXES = (".png", ".tif", ".tiff", ".fits", ".fit", ".fts", ".npy")


class FrameError(DatasetError):
    """A frame file cannot be used (unreadable, empty, colour, wrong size)."""


def _imread_quiet(path: Path):
    """``cv2.imread`` (unchanged depth) with OpenCV's log silenced; None when it cannot decode the file."""
    import cv2
    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)     # libtiff's and libpng's warnings go through it
    try:
        return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    finally:
        log.setLogLevel(level)


def read_frame(path: str | Path) -> np.ndarray:
    """A 2-D image from PNG/TIFF (8/16 bit), FITS or .npy; FrameError with the reason otherwise."""
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise FrameError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise FrameError(f"{path}: empty file")
    if suffix not in FRAME_SUFFIXES:
        raise FrameError(f"{path}: unsupported file type {suffix or '(none)'}; give {', '.join(FRAME_SUFFIXES)}")
    try:
        if suffix == ".npy":
            img = np.load(path, allow_pickle=False)
        elif suffix in (".fits", ".fit", ".fts"):
            import warnings
            from astropy.io import fits
            with warnings.catch_warnings(record=True) as caught:     # astropy's own WARNING lines: ours instead
                warnings.simplefilter("always")
                try:
                    with fits.open(path, memmap=False) as hdul:
                        img = next((h.data for h in hdul if h.data is not None and np.ndim(h.data) >= 2), None)
                except Exception:
                    truncated = next((str(w.message) for w in caught if "truncated" in str(w.message)), None)
                    if truncated:
                        raise FrameError(f"{path}: truncated FITS file ({truncated.rstrip('.')}); "
                                         "copy it again from its source") from None
                    raise
            if img is None:
                raise FrameError(f"{path}: no image HDU with 2-D data")
        else:
            img = _imread_quiet(path)
            if img is None:
                raise FrameError(f"{path}: not a readable {suffix[1:].upper()} image (damaged or truncated?)")
            if suffix in (".tif", ".tiff"):
                import cv2
                pages = cv2.imcount(str(path))
                if pages > 1:                     # reading page 1 alone would drop the others without a word
                    raise FrameError(f"{path}: a multi-page TIFF ({pages} pages); give one frame per file")
            if img.ndim == 3 and img.shape[2] in (3, 4):
                img = img[:, :, :3]
                if np.array_equal(img[:, :, 0], img[:, :, 1]) and np.array_equal(img[:, :, 0], img[:, :, 2]):
                    img = img[:, :, 0]           # grey stored as RGB: one channel
    except FrameError:
        raise
    except Exception as exc:                      # decoders raise many types for damaged files
        raise FrameError(f"{path}: unreadable ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[0] == 1:
        img = img[0]
    if img.ndim != 2:
        kind = "not an image" if img.ndim < 2 else "colour or multi-plane image"
        raise FrameError(f"{path}: {kind} (shape {img.shape}); give one monochrome 2-D sensor read-out")
    if img.size == 0:
        raise FrameError(f"{path}: image has no pixels")
    if not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)):
        raise FrameError(f"{path}: pixel type {img.dtype} is not a real number (integer or float pixels only)")
    return img.astype(np.float32)


def mask_bad_pixels(img: np.ndarray, source: str = "frame") -> tuple[np.ndarray, int]:
    """``(image, n_bad)``: non-finite pixels replaced by the median of the finite ones.

    One NaN would otherwise make the frame's background and noise NaN and the detector find
    nothing. The median stands in for the sky background, so a bad pixel is neither a star
    nor a hole. A frame without a finite pixel raises :class:`FrameError`.
    """
    bad = ~np.isfinite(img)
    n = int(np.count_nonzero(bad))
    if n == 0:
        return img, 0
    if n == img.size:
        raise FrameError(f"{source}: no finite pixel (all {n} are NaN or infinite)")
    out = img.copy()
    out[bad] = np.median(img[~bad])
    return out, n


def frame_files(folder: Path) -> list[Path]:
    """The frame files directly in ``folder`` (suffixes :data:`FRAME_SUFFIXES`, hidden ones skipped), by name."""
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES and not p.name.startswith("."))
