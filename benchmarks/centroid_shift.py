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
this table does not.

A second table asks the same of a shift that is the same everywhere on the sensor (a tilted or decentred lens, a
processor's asymmetric filtering: ``camera.bright_shift_x_px`` / ``_y_px``): the mean offset along x and y (the
detection less the camera's place, px) of each frame's brightest detections against its fainter ones, as detected and
with the fitted camera's shift taken off (``Camera.unshift``). A few-star solve is given the brightest few: where they
sit together off their stars, its attitude is off the one every star gives by more than their scatter says. Writes
nothing else and renders nothing.
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
RANK_BINS = (0, 5, 10, 20, 40, 10_000)  # brightness rank of a detection within its frame, brightest 0
XY_PAIR_PX = 2.0  # the second table's pairs: within this (px, the shift taken off), so that no stray pair sets a mean
RADIUS_SHARES = (0.0, 0.3, 0.6, 0.8, 1.0)  # of the distance from the principal point to the farthest corner


def radial_offsets(det: dict, x, y, mags, cx: float, cy: float, match_px: float) -> np.ndarray:
    """Rows (catalogue magnitude, distance from (``cx``, ``cy``), radial offset, detection row, star row) for the
    catalogue stars at (``x``, ``y``) with a detection of ``det`` within ``match_px``: the offset is the star's place
    less the detection's, along the outward line from (``cx``, ``cy``) (px)."""
    from scipy.spatial import cKDTree

    if not len(det["x_px"]) or not len(x):
        return np.zeros((0, 5))
    d, j = cKDTree(np.column_stack([det["x_px"], det["y_px"]])).query(np.column_stack([x, y]))
    k = np.flatnonzero(d <= match_px)
    ux, uy = x[k] - cx, y[k] - cy
    r = np.hypot(ux, uy)
    off = ((x[k] - det["x_px"][j[k]]) * ux + (y[k] - det["y_px"][j[k]]) * uy) / np.maximum(r, 1e-9)
    return np.column_stack([mags[k], r, off, j[k], k])


def xy_offsets(det: dict, x, y, rows: np.ndarray, cam, noise_adu: float) -> np.ndarray:
    """Rows (brightness rank in the frame, dx, dy as detected, dx, dy with ``cam``'s shift taken off) of the pairs of
    :func:`radial_offsets` (``x``, ``y``: the stars it was given), the detection less the star's place, px."""
    if not len(rows):
        return np.zeros((0, 5))
    flux = np.asarray(det["flux_adu"], np.float64)
    rank = np.argsort(np.argsort(-flux, kind="stable"), kind="stable")
    j, k = rows[:, 3].astype(np.int64), rows[:, 4].astype(np.int64)
    dx, dy = det["x_px"][j] - x[k], det["y_px"][j] - y[k]
    ux, uy = cam.unshift(det["x_px"][j], det["y_px"][j], flux[j], noise_adu)
    return np.column_stack([rank[j], dx, dy, ux - x[k], uy - y[k]])


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
    rows, xy = [], []
    for r in fit["solved"]:
        R = attitude_matrix(r["ra_deg"], r["dec_deg"], r["roll_deg"])
        idx = sky.cone(R[:, 2], cam.corner_radius_rad() + 0.01)
        x, y, front = cam.project(sky.vectors[idx] @ R)
        on = front & cam.inside(x, y, margin_px=-2.0) & (mags[idx] <= 9.0)
        img = read_frame(Path(a.frames) / r["frame"], log=lambda s: None) / scale
        stats, det = frame_stats(img, det_cfg.threshold_sigma, det_cfg.min_area_px, det_cfg.background_box_px, sat)
        pairs = radial_offsets(det, x[on], y[on], mags[idx[on]], cam.cx_px, cam.cy_px, a.match_px)
        rows.append(pairs)
        xy.append(xy_offsets(det, x[on], y[on], pairs, cam, stats["noise_adu"]))
    g = np.concatenate(rows) if rows else np.zeros((0, 5))
    h = np.concatenate(xy) if xy else np.zeros((0, 5))
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
    lines += _uniform_table(h, cam)
    text = "\n".join(lines)
    print_and_write(text, a.out)
    return 0


def _uniform_table(h: np.ndarray, cam) -> list[str]:
    """The second table (module doc): mean (dx, dy) by brightness rank, as detected and with the shift taken off."""
    shift = (
        f"bright_shift_px {cam.bright_shift_px:.3g}, bright_shift_x_px {cam.bright_shift_x_px:.3g}, "
        f"bright_shift_y_px {cam.bright_shift_y_px:.3g} from 10^{cam.bright_shift_from:g}"
    )
    out = [
        "",
        "Mean offset along x and y (the detection less the camera's place, px; ± its standard error) by brightness "
        f"rank within the frame, as detected and with the fitted camera's shift taken off ({shift}); pairs within "
        f"{XY_PAIR_PX:g} px with the shift taken off:",
        "",
        "| brightness rank | pairs | dx, dy as detected | dx, dy, the shift taken off |",
        "|---|---|---|---|",
    ]
    for lo, hi in zip(RANK_BINS, RANK_BINS[1:]):
        sel = (h[:, 0] >= lo) & (h[:, 0] < hi) & (np.hypot(h[:, 3], h[:, 4]) <= XY_PAIR_PX)
        n = int(sel.sum())
        if n < 3:
            out.append(f"| {lo + 1}–{hi if hi < 10_000 else ''} | {n} | – | – |")
            continue
        cells = []
        for cols in ((1, 2), (3, 4)):
            m, se = h[sel][:, cols].mean(0), h[sel][:, cols].std(0) / np.sqrt(n)
            cells.append(f"{m[0]:+.3f} ± {se[0]:.3f}, {m[1]:+.3f} ± {se[1]:.3f}")
        out.append(f"| {lo + 1}–{hi if hi < 10_000 else ''} | {n} | " + " | ".join(cells) + " |")
    return out


if __name__ == "__main__":
    raise SystemExit(main())
