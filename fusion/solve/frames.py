"""Reading a user's frames for ``fusion predict``: files (:mod:`skygen.real.frames` reads PNG, TIFF 8/16 bit,
BMP, FITS, ``.npy`` and JPEG), folders of them, or a skygen dataset's stored frames.

:func:`iter_inputs` walks the arguments of ``fusion predict``: files, skygen dataset folders (a
``manifest.json``) and other folders (their frame files, sorted by name). The file reader itself
(:func:`read_frame`, :func:`mask_bad_pixels`, :class:`FrameError`) lives in :mod:`skygen.real.frames`
(``skygen fit-camera`` reads frames too, and skygen never imports fusion); it is re-exported here.
"""

from __future__ import annotations

from pathlib import Path

from skygen.real.frames import FRAME_SUFFIXES, FrameError, frame_files, mask_bad_pixels, read_frame

__all__ = ["FRAME_SUFFIXES", "FrameError", "frame_files", "iter_inputs", "mask_bad_pixels", "read_frame"]


def iter_inputs(paths: list[str], max_frames: int | None, channel: str = "luminance"):
    """(source name, full image or None, detections table or None, stored image or None, error) per frame.

    A skygen dataset folder gives its first ``max_frames`` stored frames; any other folder its
    first ``max_frames`` frame files by name (an error entry when it holds none). Colour frame files
    become one plane (``channel``: see :func:`skygen.real.frames.read_frame`)."""
    for p in paths:
        path = Path(p)
        if path.is_dir() and (path / "manifest.json").exists():
            from skygen.datasets.shards import open_dataset

            with open_dataset(path) as ds:
                for pos in range(len(ds) if max_frames is None else min(max_frames, len(ds))):
                    table = ds.detections(pos)
                    if (
                        "noise_adu" in ds.frames
                    ):  # the frame's noise: what camera.bright_shift_px (_x_px, _y_px) is relative to
                        table = {**table, "noise_adu": float(ds.frames["noise_adu"][pos])}
                    yield f"{path}#{int(ds.frames['index'][pos])}", None, table, ds.image(pos), None
            continue
        if path.is_dir():
            files = frame_files(path)
            if not files:
                yield (
                    str(path),
                    None,
                    None,
                    None,
                    (f"{path}: folder holds no frame files ({', '.join(FRAME_SUFFIXES)}) and is not a skygen dataset"),
                )
            for f in files[:max_frames]:
                yield from _one_file(f, channel)
            continue
        yield from _one_file(path, channel)


def _one_file(path: Path, channel: str):
    try:
        yield str(path), read_frame(path, channel), None, None, None
    except FrameError as exc:
        yield str(path), None, None, None, str(exc)
