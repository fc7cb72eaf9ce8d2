"""Does the detector's background noise depend on which pixels it samples? Strides 8 and 7 against every pixel.

    python benchmarks/background_stride.py NAME=FRAMES ... [--max-frames 3] [--out FILE.md]

For up to ``--max-frames`` frames of each folder (read as fit-camera reads them: colour to luminance), the frame's
sigma-clipped background noise (:func:`skygen.instrument.detect.estimate_background`, the threshold's sigma of the
detector's global background) from every 8th pixel each way (the detector's stride before session 37), every 7th (its
stride since) and every pixel. A JPEG codes 8 x 8 blocks, and a stride of 8 samples one place of each block, the
same place in all of them: where the compression leaves that place noisier or quieter than the rest, the sigma is
off, and with it every detection threshold. A raw read-out reads the same at any stride.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

STRIDES = (8, 7, 1)
SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".fits", ".fit"}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="+", help="NAME=FOLDER of real frames")
    p.add_argument("--max-frames", dest="n", type=int, default=3, help="frames per folder (the first, sorted)")
    p.add_argument("--out", type=Path, help="also write the table here (Markdown)")
    a = p.parse_args(argv)

    from skygen.instrument.detect import estimate_background
    from skygen.real.frames import read_frame
    from skygen.runtime import hardware_line, print_and_write

    lines = [
        f"Background noise (ADU, median over up to {a.n} frames) by the detector's estimator at each stride; "
        f"{hardware_line()}",
        "",
        "| camera | frames | stride 8 | stride 7 | every pixel | stride 8 / every pixel | stride 7 / every pixel |",
        "|---|---|---|---|---|---|---|",
    ]
    for item in a.folders:
        name, sep, folder = item.partition("=")
        if not sep or not Path(folder).is_dir():
            p.error(f"{item!r}: give NAME=FOLDER, a folder of real frames")
        files = sorted(f for f in Path(folder).iterdir() if f.suffix.lower() in SUFFIXES)[: a.n]
        quiet: list = []
        sig = np.array([[estimate_background(read_frame(f, log=quiet.append), s)[1] for s in STRIDES] for f in files])
        if not len(sig):
            p.error(f"{item!r}: no frame read")
        m = np.median(sig, axis=0)
        lines.append(f"| {name} | {len(files)} | {m[0]:.3f} | {m[1]:.3f} | {m[2]:.3f} | {m[0] / m[2]:.2f} | "
                     f"{m[1] / m[2]:.2f} |")  # fmt: skip
    print_and_write("\n".join(lines), a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
