"""Is a real camera's background noise white, as skygen renders it? Neighbour correlation, frames against renders.

    python benchmarks/noise_correlation.py FRAMES --report FIT_REPORT_DIR [--max-frames 8] [--out FILE.md]

``FIT_REPORT_DIR`` is what ``skygen fit-camera ... --report DIR`` wrote (``fit.json``); ``FRAMES`` the folder it was
fitted on. For up to ``--max-frames`` solved frames (spread evenly) the fitted camera renders the same attitude, and
on both images the background's noise is isolated: a 31 px box mean is taken off, and pixels within 3 px of any
pixel more than 3 robust sigma from it (stars, hot pixels) are left out. The table gives the correlation of each
remaining pixel with its right-hand and its lower neighbour, and the robust sigma. skygen draws independent noise
per pixel (correlation ~0, less the box mean's own small share); a demosaiced colour sensor, a JPEG's compression or
a denoiser correlate neighbours, which widens noise blobs (more, larger false detections; wider faint stars by
second moment) in a way that a noise sigma alone does not render.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("frames", help="the folder of real frames the camera was fitted on")
    p.add_argument("--report", required=True, type=Path, help="the fit-camera report folder (its fit.json)")
    p.add_argument("--max-frames", dest="n", type=int, default=8, help="solved frames used (spread evenly)")
    p.add_argument("--out", type=Path, help="also write the table here (Markdown)")
    a = p.parse_args(argv)

    from skygen.errors import ConfigError
    from skygen.real.fit_report import renders_of_fit
    from skygen.real.frame_stats import neighbour_correlation
    from skygen.real.frames import read_frame
    from skygen.runtime import hardware_line, print_and_write

    try:
        _, scale, rows, renderer = renders_of_fit(a.report, a.n)
    except ConfigError as e:
        p.error(str(e))
    quiet: list = []
    got = {"real": [], "sim": []}
    for i, r in enumerate(rows):
        got["real"].append(neighbour_correlation(read_frame(Path(a.frames) / r["frame"], log=quiet.append) / scale))
        got["sim"].append(neighbour_correlation(renderer.render(i).image_full.astype(np.float32)))
    med = {k: np.median(np.array(v), axis=0) for k, v in got.items()}
    text = "\n".join(
        [
            f"{len(rows)} frames of {a.frames} (fit {a.report}), the fitted camera's renders at the same attitudes; "
            f"{hardware_line()}",
            "",
            "| | right neighbour | lower neighbour | robust σ (ADU) |",
            "|---|---|---|---|",
            *(
                f"| {name} | {med[k][0]:+.3f} | {med[k][1]:+.3f} | {med[k][2]:.2f} |"
                for k, name in (("real", "frames (median)"), ("sim", "renders (median)"))
            ),
        ]
    )
    print_and_write(text, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
