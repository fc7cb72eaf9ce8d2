"""Reading a user's frames: PNG, TIFF (8 or 16 bit), FITS and ``.npy`` files, or a skygen dataset's stored frames.

:func:`read_frame` returns one monochrome float32 image ``[y, x]`` in the file's own linear
units, or raises :class:`FrameError` with the reason (unreadable, empty, colour, non-numeric).
:func:`iter_inputs` walks the arguments of ``fusion predict``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FusionError

FRAME_SUFFIXES = (".png", ".tif", ".tiff", ".fits", ".fit", ".fts", ".npy")


class FrameError(FusionError):
    """A frame file cannot be used (unreadable, empty, colour, wrong size)."""


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
            from astropy.io import fits
            with fits.open(path, memmap=False) as hdul:
                img = next((h.data for h in hdul if h.data is not None and np.ndim(h.data) >= 2), None)
            if img is None:
                raise FrameError(f"{path}: no image HDU with 2-D data")
        else:
            import cv2
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise FrameError(f"{path}: not a readable {suffix[1:].upper()} image")
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
        raise FrameError(f"{path}: colour or multi-plane image (shape {img.shape}); give one monochrome "
                         "sensor read-out")
    if img.size == 0:
        raise FrameError(f"{path}: image has no pixels")
    if not np.issubdtype(img.dtype, np.number):
        raise FrameError(f"{path}: pixel type {img.dtype} is not numeric")
    return img.astype(np.float32)


def iter_inputs(paths: list[str], max_frames: int | None):
    """(source name, full image or None, detections table or None, stored image or None, error) per frame."""
    for p in paths:
        path = Path(p)
        if path.is_dir() and (path / "manifest.json").exists():
            from skygen.datasets.shards import open_dataset
            with open_dataset(path) as ds:
                for pos in range(len(ds) if max_frames is None else min(max_frames, len(ds))):
                    yield f"{path}#{int(ds.frames['index'][pos])}", None, ds.detections(pos), ds.image(pos), None
            continue
        try:
            yield str(path), read_frame(path), None, None, None
        except FrameError as exc:
            yield str(path), None, None, None, str(exc)
