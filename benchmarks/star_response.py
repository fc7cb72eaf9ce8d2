"""A real camera's response to star brightness against its fitted renders', star by star (issue 35 item 5).

    python benchmarks/star_response.py FRAMES --report FIT_REPORT_DIR [--max-frames 16] [--bin 0.5] [--out FILE.md]

``FIT_REPORT_DIR`` is what ``skygen fit-camera ... --report DIR`` wrote (``fit.json``: the fitted camera and each
solved frame's attitude); ``FRAMES`` the folder it was fitted on. For up to ``--max-frames`` solved frames (spread
evenly) the fitted camera renders the same attitude, and at every catalogue star the camera puts at least 4 px
inside the sensor both images are measured the same way: the brightest pixel and the sum of a 7 x 7 box around
the projected position, each less the frame's median (its background; frame values divided by the scale the fit
found they carry, e.g. 12-bit data stored x 16). The table bins the stars by catalogue
magnitude: their number, the median peak and box sum on the frames and on the renders, and the share of stars
whose peak stands 3 ADU above the background on each. A linear sensor that skygen renders faithfully gives
equal columns down to the noise; a camera whose processing clips or smooths faint light (a black level set above
the sky, a denoiser, a tone curve) shows the frames' faint rows falling to 0 while the renders' keep their
flux: where, and how steeply, is what a model of that processing must reproduce.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

HALF = 3  # the box is (2 HALF + 1) px square
EDGE_PX = 4


def measure(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(peak, box sum) at each position, less the image's median (per pixel for the sum)."""
    bg = float(np.median(img))
    xi, yi = np.rint(x).astype(int), np.rint(y).astype(int)
    peak, total = np.empty(len(xi)), np.empty(len(xi))
    for k, (cx, cy) in enumerate(zip(xi, yi)):
        box = img[cy - HALF : cy + HALF + 1, cx - HALF : cx + HALF + 1].astype(np.float64) - bg
        peak[k], total[k] = box.max(), box.sum()
    return peak, total


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("frames", help="the folder of real frames the camera was fitted on")
    p.add_argument("--report", required=True, type=Path, help="the fit-camera report folder (its fit.json)")
    p.add_argument("--max-frames", dest="n", type=int, default=16, help="solved frames used (spread evenly)")
    p.add_argument("--bin", type=float, default=0.5, help="magnitude bin width")
    p.add_argument("--faintest", type=float, default=8.0, help="stars to this catalogue magnitude")
    p.add_argument("--out", type=Path, help="also write the table here (Markdown)")
    a = p.parse_args(argv)

    from skygen.errors import ConfigError
    from skygen.instrument.camera import Camera
    from skygen.real.fit_report import renders_of_fit
    from skygen.real.frames import read_frame
    from skygen.runtime import hardware_line, print_and_write
    from skygen.sky.attitude import attitude_matrix

    try:  # scale: the frames' values over the ADU they carry (12-bit data x 16)
        _, scale, rows, renderer = renders_of_fit(a.report, a.n)
    except ConfigError as e:
        p.error(str(e))
    cam = Camera.from_config(renderer.cfg.camera)
    sky = renderer.sky
    mags_all = np.asarray(sky.table.mag, dtype=np.float64)
    got = {"mag": [], "real_peak": [], "real_sum": [], "sim_peak": [], "sim_sum": []}
    quiet = []
    for i, r in enumerate(rows):
        real = read_frame(Path(a.frames) / r["frame"], log=quiet.append) / scale
        sim = renderer.render(i).image_full.astype(np.float32)
        R = attitude_matrix(r["ra_deg"], r["dec_deg"], r["roll_deg"])
        idx = sky.cone(R[:, 2], cam.corner_radius_rad() + 0.01)
        x, y, front = cam.project(sky.vectors[idx] @ R)
        ok = front & cam.inside(x, y, margin_px=-EDGE_PX) & (mags_all[idx] <= a.faintest)
        for key, img in (("real", real), ("sim", sim)):
            pk, sm = measure(img, x[ok], y[ok])
            got[f"{key}_peak"].append(pk)
            got[f"{key}_sum"].append(sm)
        got["mag"].append(mags_all[idx[ok]])
    g = {k: np.concatenate(v) for k, v in got.items()}
    lines = [
        f"{len(rows)} frames of {a.frames} (fit {a.report}), the fitted camera's renders at the same attitudes; "
        f"{hardware_line()}",
        "",
        "| catalogue mag | stars | peak (ADU): frames / renders | 7×7 sum (ADU): frames / renders "
        "| peak ≥ 3 ADU: frames / renders |",
        "|---|---|---|---|---|",
    ]
    lo = np.floor(g["mag"].min() / a.bin) * a.bin
    for b0 in np.arange(lo, a.faintest, a.bin):
        sel = (g["mag"] >= b0) & (g["mag"] < b0 + a.bin)
        if sel.sum() < 3:
            continue
        med = {k: float(np.median(g[k][sel])) for k in ("real_peak", "real_sum", "sim_peak", "sim_sum")}
        share = [100.0 * float(np.mean(g[k][sel] >= 3.0)) for k in ("real_peak", "sim_peak")]
        lines.append(
            f"| {b0:.1f}–{b0 + a.bin:.1f} | {int(sel.sum())} | {med['real_peak']:.1f} / {med['sim_peak']:.1f} | "
            f"{med['real_sum']:.1f} / {med['sim_sum']:.1f} | {share[0]:.0f} / {share[1]:.0f} % |"
        )
    text = "\n".join(lines)
    print_and_write(text, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
