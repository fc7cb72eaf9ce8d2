"""What are the non-star detections among a camera's brightest, and where do they sit? Frames against renders.

    python benchmarks/bright_neighbours.py FRAMES --report FIT_REPORT_DIR [--max-frames 16] [--brightest 10]
                                          [--bright-mag 3.0] [--radius PX] [--out FILE.md]

``FIT_REPORT_DIR`` is what ``skygen fit-camera ... --report DIR`` wrote (``fit.json``: the fitted camera and each
solved frame's attitude); ``FRAMES`` the folder it was fitted on. For up to ``--max-frames`` solved frames (spread
evenly) the real frame and a render of the fitted camera at its attitude are detected alike (the fitted detector
settings). Among each one's ``--brightest`` detections, those with no catalogue star within ``--radius`` (the
renderer's catalogue, to its magnitude limit) are the non-stars a few-star solver is given. The table counts them
by distance to the nearest catalogue star brighter than ``--bright-mag`` (pieces of a bright star's image, its halo,
spikes or bloom split by the detector, sit beside it; the fitted false stars, ``corruptions.false_stars``, are drawn
anywhere), and says how many have a catalogue star just beyond the radius (a star the fitted camera puts 1-3 radii
from where the frame shows it: a geometry the camera model misses). Results: results/real-frames/held-out-amalthea.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

BINS_PX = (0.0, 20.0, 50.0, 150.0, np.inf)


#: the columns :func:`nonstars` returns per non-star
COLUMNS = ("bright_px", "nearest_px", "x_px", "y_px", "dx_px", "dy_px", "nearest_mag", "area_px")


def nonstars(img, det_cfg, sat: float, x, y, mags, bright_mag: float, brightest: int, radius: float) -> np.ndarray:
    """One row per non-star (no catalogue star within ``radius``) among the ``brightest`` detections of ``img``, the
    columns of :data:`COLUMNS`: distance to the nearest catalogue star brighter than ``bright_mag`` (inf without one),
    distance to the nearest catalogue star of any magnitude, the detection's place, that star's place less it (px),
    the star's magnitude and the detection's area (px): catalogue stars at (``x``, ``y``) with ``mags``."""
    from scipy.spatial import cKDTree

    from skygen.real.frame_stats import frame_stats

    _, det = frame_stats(img, det_cfg.threshold_sigma, det_cfg.min_area_px, det_cfg.background_box_px, sat)
    top = np.argsort(-np.asarray(det["flux_adu"], np.float64), kind="stable")[:brightest]
    pos = np.column_stack([det["x_px"][top], det["y_px"][top]]).astype(np.float64)
    if not len(pos) or not len(x):
        return np.zeros((0, len(COLUMNS)))
    near, j = cKDTree(np.column_stack([x, y])).query(pos)
    keep = near > radius
    pos, near, j, area = pos[keep], near[keep], j[keep], np.asarray(det["area_px"], np.float64)[top][keep]
    bright = mags <= bright_mag
    to_bright = (
        cKDTree(np.column_stack([x[bright], y[bright]])).query(pos)[0] if bright.any() and len(pos) else
        np.full(len(pos), np.inf)
    )  # fmt: skip
    return np.column_stack([to_bright, near, pos, x[j] - pos[:, 0], y[j] - pos[:, 1], mags[j], area])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("frames", help="the folder of real frames the camera was fitted on")
    p.add_argument("--report", required=True, type=Path, help="the fit-camera report folder (its fit.json)")
    p.add_argument("--max-frames", dest="n", type=int, default=16, help="solved frames used (spread evenly)")
    p.add_argument("--brightest", type=int, default=10, help="detections a few-star solver is given, per frame")
    p.add_argument("--bright-mag", type=float, default=3.0, help="catalogue stars this bright or brighter are 'bright'")
    p.add_argument(
        "--radius",
        type=float,
        default=None,
        help="a detection this close to a catalogue star is that star (px; default: 2, or 3.5 x the camera's "
        "measured centroid error camera.centroid_sigma_px where that is more)",
    )
    p.add_argument("--out", type=Path, help="also write the table here (Markdown)")
    a = p.parse_args(argv)

    from skygen.config import build_config
    from skygen.errors import ConfigError
    from skygen.instrument.camera import Camera
    from skygen.real.fit_render import renderer_at, spread_evenly
    from skygen.real.fit_report import read_fit
    from skygen.real.frames import read_frame
    from skygen.runtime import hardware_line, print_and_write
    from skygen.sky.attitude import attitude_matrix

    try:
        fit = read_fit(a.report)
    except ConfigError as e:
        p.error(str(e))
    scale = float(fit.get("value_scale") or 1.0)
    solved = fit["solved"]
    pick = spread_evenly(len(solved), a.n)
    rows = [solved[k] for k in pick]
    attitudes = [(r["ra_deg"], r["dec_deg"], r["roll_deg"]) for r in rows]
    renderer = renderer_at(build_config(fit["config"]), attitudes)
    cfg = renderer.cfg
    sat = float(fit.get("saturation_adu") or 2**cfg.sensor.bit_depth - 1)
    cam = Camera.from_config(cfg.camera)
    radius = a.radius if a.radius is not None else max(2.0, 3.5 * (cam.centroid_sigma_px or 0.0))
    sky = renderer.sky
    mags_all = np.asarray(sky.table.mag, dtype=np.float64)
    got = {"real": [], "renders": []}
    for i, r in enumerate(rows):
        R = attitude_matrix(r["ra_deg"], r["dec_deg"], r["roll_deg"])
        idx = sky.cone(R[:, 2], cam.corner_radius_rad() + 0.01)
        x, y, front = cam.project(sky.vectors[idx] @ R)
        on = front & cam.inside(x, y, margin_px=2.0)
        args = (cfg.detection, sat, x[on], y[on], mags_all[idx[on]], a.bright_mag, a.brightest, radius)
        real = read_frame(Path(a.frames) / r["frame"], log=lambda s: None) / scale
        got["real"].append(nonstars(real, *args))
        got["renders"].append(nonstars(renderer.render(i).image_full.astype(np.float32), *args))
    labels = [f"{lo:.0f}–{hi:.0f} px" if np.isfinite(hi) else f"≥ {lo:.0f} px" for lo, hi in zip(BINS_PX, BINS_PX[1:])]
    lines = [
        f"{len(rows)} frames of {a.frames} (fit {a.report}) and one render of the fitted camera at each one's "
        "attitude; "
        f"non-stars among each one's {a.brightest} brightest detections (no catalogue star within {radius:.2f} px), "
        "by distance to "
        f"the nearest catalogue star of Hp ≤ {a.bright_mag:g} on the sensor; {hardware_line()}",
        "",
        "| | non-stars per frame | " + " | ".join(labels) + " | no bright star on the sensor "
        f"| of them, a catalogue star {radius:.1f}–{3 * radius:.1f} px away |",
        "|---|---|" + "---|" * (len(labels) + 2),
    ]
    for key in ("real", "renders"):
        d = np.concatenate(got[key]) if got[key] else np.zeros((0, len(COLUMNS)))
        counts = np.histogram(d[np.isfinite(d[:, 0]), 0], bins=np.asarray(BINS_PX))[0]
        lines.append(
            f"| {key} | {len(d) / len(rows):.2f} | "
            + " | ".join(str(int(c)) for c in counts)
            + f" | {int(np.sum(~np.isfinite(d[:, 0])))} | {int(np.sum(d[:, 1] <= 3 * radius))} |"
        )
    # the real non-stars one by one: where they are, and which way the nearest catalogue star lies (its radial part:
    # positive where the camera puts the star farther from the principal point than the frame shows it)
    real = np.concatenate(got["real"]) if got["real"] else np.zeros((0, len(COLUMNS)))
    if len(real):
        lines += [
            "",
            "Real non-stars one by one (nearest catalogue star's place less the detection's; radial: along the line "
            f"from the principal point ({cam.cx_px:.1f}, {cam.cy_px:.1f}), positive outwards):",
            "",
            "| x, y (px) | from the principal point (px) | nearest star: Hp, distance (px) | dx, dy (px) | radial (px) "
            "| area (px) |",
            "|---|---|---|---|---|---|",
        ]
        for r in real[np.argsort(-np.hypot(real[:, 2] - cam.cx_px, real[:, 3] - cam.cy_px))]:
            u = np.array([r[2] - cam.cx_px, r[3] - cam.cy_px])
            rad = float(np.dot(u, r[4:6]) / max(np.hypot(*u), 1e-9))
            lines.append(
                f"| {r[2]:.1f}, {r[3]:.1f} | {np.hypot(*u):.0f} | {r[6]:.2f}, {r[1]:.1f} | {r[4]:+.1f}, {r[5]:+.1f} "
                f"| {rad:+.1f} | {r[7]:.0f} |"
            )
    text = "\n".join(lines)
    print_and_write(text, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
