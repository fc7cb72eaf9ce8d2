"""Reading a user's frame files: PNG, TIFF (8 or 16 bit), BMP, FITS, ``.npy`` and JPEG.

:func:`read_frame` returns one monochrome float32 image ``[y, x]`` in the file's own linear
units, or raises :class:`FrameError` with the reason (unreadable, empty, multi-plane, non-numeric).
PNG, TIFF, BMP and JPEG are decoded by OpenCV with its log silenced: a damaged file gives our one line,
not libtiff's warnings first.

Colour PNG, TIFF, BMP and JPEG frames (RGB or RGBA, 8 or 16 bit; alpha dropped) become one plane, saying so
in one line (``channel``, :data:`CHANNELS`): ``luminance`` (the default) is the Rec. 709 weighted sum
0.2126 R + 0.7152 G + 0.0722 B of the values as stored. It keeps the file's range (the weights sum
to 1, so saturation stays at the top) and leans on green, the plane a Bayer sensor samples twice
and so the least noisy one; tetra3 greys colour frames the same way with the Rec. 601 weights
(0.299, 0.587, 0.114). ``r``, ``g`` or ``b`` take one plane (stars seen through one filter); ``sum``
adds the three, the charge a monochrome sensor would have collected: the best signal-to-noise for
white stars when the planes' noise is alike, at up to three times the file's range. A monochrome
frame that still holds a colour sensor's raw Bayer mosaic (a strong 2 x 2 pattern in its
background) is read as it is, with a one-line warning (:func:`bayer_warning`).

:func:`mask_bad_pixels` replaces non-finite pixels (NaN, ±inf: flagged pixels in float FITS or
``.npy`` frames) before detection. :func:`frame_files` lists the frame files of a folder. Used by
``skygen fit-camera`` and, through :mod:`fusion.solve.frames`, by ``fusion predict``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skygen.errors import ConfigError, DatasetError

FRAME_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".fits", ".fit", ".fts", ".npy", ".jpg", ".jpeg")
CHANNELS = ("luminance", "r", "g", "b", "sum")
LUMINANCE_RGB = (0.2126, 0.7152, 0.0722)  # Rec. 709 (ITU-R BT.709) weights of R, G, B
#: a monochrome frame is flagged as a raw Bayer mosaic when its four 2 x 2 sub-lattices' background
#: levels differ by more than this factor (see :func:`bayer_warning`)
BAYER_RATIO = 1.3


class FrameError(DatasetError):
    """A frame file cannot be used (unreadable, empty, colour, wrong size)."""


def _imread_quiet(path: Path):
    """``cv2.imread`` (unchanged depth) with OpenCV's log silenced; None when it cannot decode the file."""
    import cv2

    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)  # libtiff's and libpng's warnings go through it
    try:
        return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    finally:
        log.setLogLevel(level)


def read_frame(path: str | Path, channel: str = "luminance", log=None) -> np.ndarray:
    """A 2-D float32 image ``[y, x]`` from PNG/TIFF (8/16 bit), BMP, FITS, .npy or JPEG; FrameError with the reason
    otherwise.

    A colour PNG or TIFF becomes one plane by ``channel`` (:data:`CHANNELS`; see the module doc) and a
    monochrome frame that looks like a raw Bayer mosaic is flagged: each with one line through ``log``
    (on stderr when None).

    Parameters
    ----------
    path : str or Path
        ``.png``, ``.tif``/``.tiff``, ``.bmp``, ``.fits``/``.fit``/``.fts``, ``.npy`` or ``.jpg``/``.jpeg``
        (lossy, 8 bit: read with one line saying so): one full-resolution read-out.
    channel : {"luminance", "r", "g", "b", "sum"}
        How a colour file becomes one plane (Rec. 709 luminance by default).
    log : callable, optional
        Receives the one-line notes (colour conversion, a suspected mosaic).

    Returns
    -------
    numpy.ndarray
        float32, shape ``(height, width)``, in the file's own linear units (ADU as stored: a 12-bit
        value scaled by 16 in a 16-bit TIFF stays scaled; ``skygen.real.fit_pixels.value_scale`` finds it).

    Raises
    ------
    FrameError
        Missing, empty, damaged, multi-page, multi-plane or non-numeric files, with the reason.
    """
    if channel not in CHANNELS:
        raise ConfigError(f"channel {channel!r}: give one of {', '.join(CHANNELS)}")
    say = log or _stderr
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise FrameError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise FrameError(f"{path}: empty file")
    if suffix not in FRAME_SUFFIXES:
        raise FrameError(f"{path}: unsupported file type {suffix or '(none)'}; give {', '.join(FRAME_SUFFIXES)}")
    colour = False  # a colour file was converted: its planes are no mosaic to warn about
    try:
        if suffix == ".npy":
            img = np.load(path, allow_pickle=False)
        elif suffix in (".fits", ".fit", ".fts"):
            img = _read_fits(path)
        else:
            img, colour = _read_png_tiff(path, suffix, channel, say)
            if suffix in (".jpg", ".jpeg"):
                q = jpeg_luma_quality(path)
                how = (
                    ""
                    if q is None
                    else " (its luminance quantisation is all 1: quality 100, near-lossless; a camera's processing "
                    "before it, a black level or tone curve, can still erase faint stars)"
                    if q >= 100
                    else f" (quality about {q:.0f} by its luminance quantisation table)"
                )
                say(
                    f"{path}: JPEG: 8-bit and lossy{how}; its compression changes faint stars and the background "
                    "noise (a camera's raw PNG, TIFF or FITS frames are better)"
                )
    except FrameError:
        raise
    except Exception as exc:  # decoders raise many types for damaged files
        raise FrameError(
            f"{path}: unreadable ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[0] == 1:
        img = img[0]
    if img.ndim != 2:
        kind = "not an image" if img.ndim < 2 else "colour or multi-plane image"
        raise FrameError(
            f"{path}: {kind} (shape {img.shape}); give one monochrome 2-D sensor read-out "
            "(colour is read from RGB or RGBA PNG and TIFF files)"
        )
    if img.size == 0:
        raise FrameError(f"{path}: image has no pixels")
    if not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)):
        raise FrameError(f"{path}: pixel type {img.dtype} is not a real number (integer or float pixels only)")
    img = img.astype(np.float32)
    warning = None if colour else bayer_warning(img)
    if warning:
        say(f"{path}: {warning}")
    return img


def _read_fits(path: Path) -> np.ndarray:
    import warnings

    from astropy.io import fits

    with warnings.catch_warnings(record=True) as caught:  # astropy's own WARNING lines: ours instead
        warnings.simplefilter("always")
        try:
            with fits.open(path, memmap=False) as hdul:
                img = next((h.data for h in hdul if h.data is not None and np.ndim(h.data) >= 2), None)
        except Exception:
            truncated = next((str(w.message) for w in caught if "truncated" in str(w.message)), None)
            if truncated:
                raise FrameError(
                    f"{path}: truncated FITS file ({truncated.rstrip('.')}); copy it again from its source"
                ) from None
            raise
    if img is None:
        raise FrameError(f"{path}: no image HDU with 2-D data")
    return img


#: the IJG (libjpeg) standard luminance quantisation table at quality 50, in zig-zag order as a file stores it
IJG_LUMA = (
    16, 11, 12, 14, 12, 10, 16, 14, 13, 14, 18, 17, 16, 19, 24, 40, 26, 24, 22, 22, 24, 49, 35, 37, 29, 40, 58, 51,
    61, 60, 57, 51, 56, 55, 64, 72, 92, 78, 64, 68, 87, 69, 55, 56, 80, 109, 81, 87, 95, 98, 103, 104, 103, 62, 77,
    113, 121, 112, 100, 120, 92, 101, 103, 99,
)  # fmt: skip


def frame_epoch(path) -> tuple[float, str] | None:
    """(Julian year, the field it came from) of when a frame file was taken, where the file says: EXIF
    ``DateTimeOriginal`` (else ``DateTime``) of a JPEG or TIFF, as the camera's clock wrote it and read as UTC (a few
    hours do not matter to proper motions), or FITS ``DATE-OBS`` (else ``MJD-OBS``) of the first header. None
    where the file holds no date (PNG, ``.npy``, a frame stripped of its EXIF) or cannot be read."""
    from astropy.time import Time

    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix in (".jpg", ".jpeg", ".tif", ".tiff"):
            from PIL import Image

            with Image.open(path) as im:
                exif = im.getexif()
                for field, value in (
                    ("EXIF DateTimeOriginal", exif.get_ifd(0x8769).get(36867)),
                    ("EXIF DateTime", exif.get(306)),
                ):
                    if isinstance(value, str) and len(value) >= 19:
                        stamp = value[:10].replace(":", "-") + "T" + value[11:19]
                        return float(Time(stamp, format="isot", scale="utc").jyear), field
        elif suffix in (".fits", ".fit", ".fts"):
            from astropy.io import fits

            header = fits.getheader(path)
            if isinstance(header.get("DATE-OBS"), str):
                return float(Time(header["DATE-OBS"], scale="utc").jyear), "FITS DATE-OBS"
            if isinstance(header.get("MJD-OBS"), (int, float)):
                return float(Time(float(header["MJD-OBS"]), format="mjd", scale="utc").jyear), "FITS MJD-OBS"
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return None


def jpeg_luma_quality(path) -> float | None:
    """The IJG quality (1-100) a JPEG's luminance quantisation table (table 0 of its DQT segments) corresponds to:
    100 where every entry is 1; otherwise from its mean ratio to the standard table (libjpeg's scaling). None
    where the file holds no readable table."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        return None
    i = 2
    while i + 4 <= len(data) and data[i] == 0xFF:
        marker, length = data[i + 1], int.from_bytes(data[i + 2 : i + 4], "big")
        if marker == 0xDA:  # start of scan: no table before it
            return None
        if marker == 0xDB:
            j, end = i + 4, i + 2 + length
            while j < end:
                precision, table = data[j] >> 4, data[j] & 0x0F
                size = 128 if precision else 64
                raw = data[j + 1 : j + 1 + size]
                values = [int.from_bytes(raw[k : k + 2], "big") for k in range(0, 128, 2)] if precision else list(raw)
                if table == 0 and len(values) == 64:
                    if max(values) <= 1:
                        return 100.0
                    scale = 100.0 * float(np.mean([v / s for v, s in zip(values, IJG_LUMA)]))
                    return float(np.clip((200.0 - scale) / 2.0 if scale <= 100 else 5000.0 / scale, 1.0, 100.0))
                j += 1 + size
        i += 2 + length
    return None


def _read_png_tiff(path: Path, suffix: str, channel: str, say) -> tuple[np.ndarray, bool]:
    """The image (one plane for a colour file) and whether it was a colour file."""
    img = _imread_quiet(path)
    if img is None:
        raise FrameError(f"{path}: not a readable {suffix[1:].upper()} image (damaged or truncated?)")
    if suffix in (".tif", ".tiff"):
        import cv2

        pages = cv2.imcount(str(path))
        if pages > 1:  # reading page 1 alone would drop the others without a word
            raise FrameError(f"{path}: a multi-page TIFF ({pages} pages); give one frame per file")
    if img.ndim == 3 and img.shape[2] in (3, 4):
        alpha = img.shape[2] == 4
        bgr = img[:, :, :3]  # OpenCV's order: B, G, R (, A)
        if np.array_equal(bgr[:, :, 0], bgr[:, :, 1]) and np.array_equal(bgr[:, :, 0], bgr[:, :, 2]):
            return bgr[:, :, 0], False  # grey stored as RGB: one channel
        plane, how = to_one_plane(bgr[:, :, ::-1], channel)
        bits = 8 * img.dtype.itemsize
        say(
            f"{path}: colour frame ({'RGBA' if alpha else 'RGB'}, {bits} bit{'; alpha dropped' if alpha else ''}) "
            f"read as one plane: {how}"
        )
        return plane, True
    return img, False


def to_one_plane(rgb: np.ndarray, channel: str = "luminance") -> tuple[np.ndarray, str]:
    """(float32 plane ``[y, x]``, how it was made) of an ``[y, x, (R, G, B)]`` image (see the module doc)."""
    rgb = np.asarray(rgb, np.float32)
    if channel == "luminance":
        w = LUMINANCE_RGB
        return (
            w[0] * rgb[..., 0] + w[1] * rgb[..., 1] + w[2] * rgb[..., 2],
            f"luminance {w[0]} R + {w[1]} G + {w[2]} B (Rec. 709; --channel r, g, b or sum for another)",
        )
    if channel == "sum":
        return rgb.sum(axis=2), "R + G + B (up to 3 x the file's range)"
    if channel in ("r", "g", "b"):
        return rgb[..., "rgb".index(channel)].copy(), f"the {channel.upper()} plane"
    raise ConfigError(f"channel {channel!r}: give one of {', '.join(CHANNELS)}")


def bayer_warning(img: np.ndarray) -> str:
    """'' or one line when a monochrome frame looks like a colour sensor's raw Bayer mosaic.

    Star fields are mostly background, so the interquartile mean of each of the four 2 x 2
    sub-lattices is its background level; behind different colour filters they differ (the sky
    and any lamp light are coloured), through one filter they agree. Flagged when the brightest
    level exceeds the faintest by :data:`BAYER_RATIO` and the pattern is not a mere row or
    column offset (even/odd read-out channels of a monochrome sensor: ``l00 + l11 = l01 + l10``;
    a Bayer R, G, G, B mosaic is not of that form unless R + B = 2 G)."""
    h, w = (img.shape[0] // 2) * 2, (img.shape[1] // 2) * 2
    if h < 16 or w < 16:
        return ""
    step = max(1, int(np.sqrt(h * w / 4 / 250_000)))  # at most ~250 k cells looked at
    grid = img[:h, :w].reshape(h // 2, 2, w // 2, 2).transpose(0, 2, 1, 3).reshape(h // 2, w // 2, 4)
    cells = grid[::step, ::step].reshape(-1, 4).astype(np.float64)  # one row per 2 x 2 cell
    cells = cells[np.all(np.isfinite(cells), axis=1)]
    if len(cells) < 64:
        return ""
    q = np.sort(cells, axis=0)[len(cells) // 4 : (3 * len(cells)) // 4 + 1]
    lev = q.mean(axis=0)  # order: (0,0), (0,1), (1,0), (1,1)
    spread = lev.max() - lev.min()
    if not lev.min() > 0 or lev.max() / lev.min() <= BAYER_RATIO:
        return ""
    if abs(lev[0] + lev[3] - lev[1] - lev[2]) < 0.25 * spread:
        return ""  # rows or columns offset, not a colour mosaic
    return (
        f"looks like a raw Bayer mosaic (the background of its four 2 x 2 sub-lattices is "
        f"{', '.join(f'{v:.4g}' for v in lev)}: {lev.max() / lev.min():.2f} x apart); debayer it or give one "
        "colour plane"
    )


def _stderr(message: str) -> None:
    import sys

    print(message, file=sys.stderr, flush=True)


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
    return sorted(
        p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES and not p.name.startswith(".")
    )
