"""Do a camera's bright stars sit where its faint ones say they should? Radial centroid offsets by radius and magnitude.

    python benchmarks/centroid_shift.py FRAMES --report FIT_REPORT_DIR [--match-px 8] [--out FILE.md]

``FIT_REPORT_DIR`` is what ``skygen fit-camera ... --report DIR`` wrote (``fit.json``: the fitted camera and each solved
frame's attitude); ``FRAMES`` the folder it was fitted on. Every catalogue star the fitted camera puts on the sensor is
paired with the nearest detection (the fitted detector settings) within ``--match-px``, and the offset (the camera's
place less the detection's) is split along the line from the principal point: negative where the frame shows the star
farther out than the camera puts it. The table gives the median radial offset by distance from the principal point
and catalogue magnitude. A camera model that is right for every star gives the same column at every magnitude; a
star image that grows an asymmetric tail away from the centre (coma, or a bloom) shifts the centroid of the pixels
above the threshold outward by more the brighter the star is, which no distortion term can fit (distortion moves
every star at one place alike). The geometry fit's 3.5 sigma cut leaves the worst of such stars out of its residual;
this table does not. Writes nothing else and renders nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

MAG_BINS = (-2.0, 4.0, 5.0, 6.0, 7.0, 9.0)
RADIUS_SHARES = (0.0, 0.3, 0.6, 0.8, 1.0)  # of the distance from the principal point to the farthest corner


def radial_offsets(det: dict, x, y, mags, cx: float, cy: float, match_px: float) -> np.ndarray:
    """Rows (catalogue magnitude, distance from (``cx``, ``cy``), radial offset) for the catalogue stars at (``x``,
    ``y``) with a detection of ``det`` within ``match_px``: the offset is the star's place less the detection's, along
    the outward line from (``cx``, ``cy``) (px)."""
    from scipy.spatial import cKDTree

    if not len(det["x_px"]) or not len(x):
        return np.zeros((0, 3))
    d, j = cKDTree(np.column_stack([det["x_px"], det["y_px"]])).query(np.column_stack([x, y]))
    k = np.flatnonzero(d <= match_px)
    ux, uy = x[k] - cx, y[k] - cy
    r = np.hypot(ux, uy)
    off = ((x[k] - det["x_px"][j[k]]) * ux + (y[k] - det["y_px"][j[k]]) * uy) / np.maximum(r, 1e-9)
    return np.column_stack([mags[k], r, off])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("frames", help="the folder of real frames the camera was fitted on")
    p.add_argument("--report", required=True, type=Path, help="the fit-camera report folder (its fit.json)")
    p.add_argument("--match-px", type=float, default=8.0, help="a detection this close to a catalogue star is it (px)")
    p.add_argument("--out", type=Path, help="also write the table here (Markdown)")
    a = p.parse_args(argv)

    from skygen.config import build_config
    from skygen.errors import ConfigError
    from skygen.instrument.camera import Camera
    from skygen.real.fit_render import renderer_at
    from skygen.real.fit_report import read_fit
    from skygen.real.frame_stats import frame_stats
    from skygen.real.frames import read_frame
    from skygen.runtime import hardware_line, print_and_write
    from skygen.sky.attitude import attitude_matrix

    try:
        fit = read_fit(a.report)
    except ConfigError as e:
        p.error(str(e))
    scale = float(fit.get("value_scale") or 1.0)
    cfg = build_config(fit["config"])
    cam = Camera.from_config(cfg.camera)
    sat = float(fit.get("saturation_adu") or 2**cfg.sensor.bit_depth - 1)
    first = fit["solved"][0]
    sky = renderer_at(cfg, [(first["ra_deg"], first["dec_deg"], first["roll_deg"])]).sky  # the renders' catalogue
    mags = np.asarray(sky.table.mag, dtype=np.float64)
    det_cfg = cfg.detection
    rows = []
    for r in fit["solved"]:
        R = attitude_matrix(r["ra_deg"], r["dec_deg"], r["roll_deg"])
        idx = sky.cone(R[:, 2], cam.corner_radius_rad() + 0.01)
        x, y, front = cam.project(sky.vectors[idx] @ R)
        on = front & cam.inside(x, y, margin_px=-2.0) & (mags[idx] <= 9.0)
        img = read_frame(Path(a.frames) / r["frame"], log=lambda s: None) / scale
        _, det = frame_stats(img, det_cfg.threshold_sigma, det_cfg.min_area_px, det_cfg.background_box_px, sat)
        rows.append(radial_offsets(det, x[on], y[on], mags[idx[on]], cam.cx_px, cam.cy_px, a.match_px))
    g = np.concatenate(rows) if rows else np.zeros((0, 3))
    r_max = float(np.hypot(max(cam.cx_px, cam.width_px - cam.cx_px), max(cam.cy_px, cam.height_px - cam.cy_px)))
    edges = [s * r_max for s in RADIUS_SHARES]
    mag_labels = [f"Hp {lo:g}–{hi:g}" if lo > -2 else f"Hp < {hi:g}" for lo, hi in zip(MAG_BINS, MAG_BINS[1:])]
    lines = [
        f"{len(fit['solved'])} frames of {a.frames} (fit {a.report}); catalogue stars (the renderer's, to Hp 9) "
        "paired with a detection "
        f"within {a.match_px:g} px; median radial offset (the camera's place less the detection's, px; negative: the "
        f"frame shows the star farther out) and stars in each cell; {hardware_line()}",
        "",
        "| distance from the principal point (px) | " + " | ".join(mag_labels) + " |",
        "|---|" + "---|" * len(mag_labels),
    ]
    for lo, hi in zip(edges, edges[1:]):
        cells = []
        for mlo, mhi in zip(MAG_BINS, MAG_BINS[1:]):
            sel = (g[:, 1] >= lo) & (g[:, 1] < hi) & (g[:, 0] >= mlo) & (g[:, 0] < mhi)
            cells.append(
                f"{np.median(g[sel, 2]):+.2f} ({int(sel.sum())})" if sel.sum() >= 3 else f"– ({int(sel.sum())})"
            )
        lines.append(f"| {lo:.0f}–{hi:.0f} | " + " | ".join(cells) + " |")
    text = "\n".join(lines)
    print_and_write(text, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
