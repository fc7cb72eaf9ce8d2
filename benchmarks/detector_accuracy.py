"""Detector accuracy and frame statistics of the default camera.

    python benchmarks/detector_accuracy.py [--frames 1000] [--out results/skygen]

Renders frames with the default config (default sensor defects included, all other
corruptions at their defaults) and reports, per magnitude bin of the true star:
completeness (found within the match radius), centroid error (RMS and median, px), and
the share of false detections; plus histograms of true stars and detections per frame.
Writes detector_accuracy.json, detector_accuracy.md and stars_per_frame.png.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

import numpy as np

from skygen.config import load_config
from skygen.render.frame import Renderer


def measure(cfg, n: int) -> dict:
    r = Renderer(cfg)
    lim = r.detection_limit_mag
    edges = np.round(np.arange(np.floor(lim) - 6, np.ceil(lim) + 1.01, 1.0), 1)
    found = np.zeros(len(edges) - 1)
    total = np.zeros(len(edges) - 1)
    errs = [[] for _ in range(len(edges) - 1)]
    n_true, n_det, n_false, n_visible = [], [], 0, []
    for i in range(n):
        f = r.render(i)
        s, d = f.stars, f.detections
        cat = s["hip_id"] >= 0
        n_true.append(int(cat.sum()))
        n_visible.append(int((cat & (s["mag"] <= lim)).sum()))
        n_det.append(len(d["x_px"]))
        n_false += int((d["hip_id"] < 0).sum())
        b = np.digitize(s["mag"], edges) - 1
        for k in range(len(edges) - 1):
            sel = np.flatnonzero(cat & (b == k))
            total[k] += len(sel)
            for j in sel:
                m = np.flatnonzero(d["star_index"] == j)
                if len(m):
                    found[k] += 1
                    errs[k].append(np.hypot(d["x_px"][m[0]] - s["x_px"][j], d["y_px"][m[0]] - s["y_px"][j]))
    bins = []
    for k in range(len(edges) - 1):
        e = np.array(errs[k])
        bins.append(
            {
                "mag_lo": float(edges[k]),
                "mag_hi": float(edges[k + 1]),
                "stars": int(total[k]),
                "completeness": float(found[k] / total[k]) if total[k] else None,
                "rms_px": float(np.sqrt(np.mean(e**2))) if len(e) else None,
                "median_px": float(np.median(e)) if len(e) else None,
                "p95_px": float(np.percentile(e, 95)) if len(e) else None,
            }
        )
    all_e = np.concatenate([np.array(x) for x in errs if x])
    return {
        "frames": n,
        "detection_limit_mag": lim,
        "mag_limit": r.mag_limit,
        "bins": bins,
        "all_matched": {"rms_px": float(np.sqrt(np.mean(all_e**2))), "median_px": float(np.median(all_e))},
        "false_detection_share": n_false / max(sum(n_det), 1),
        "true_stars_per_frame": n_true,
        "stars_brighter_than_limit_per_frame": n_visible,
        "detections_per_frame": n_det,
        "fov_deg": r.camera.fov_deg[0],
        "pixel_scale_arcsec": r.camera.pixel_scale_arcsec,
    }


def write(res: dict, out: Path) -> str:
    out.mkdir(parents=True, exist_ok=True)
    nd = np.array(res["detections_per_frame"])
    nv = np.array(res["stars_brighter_than_limit_per_frame"])
    lines = [
        f"# Detector accuracy, default camera ({res['frames']} frames)",
        "",
        f"Command: `python benchmarks/detector_accuracy.py --frames {res['frames']}` on "
        f"{os.cpu_count()}-core {platform.machine()} CPU. FOV {res['fov_deg']:.1f} deg, "
        f"{res['pixel_scale_arcsec']:.1f} arcsec/px, detection limit Hp {res['detection_limit_mag']:.2f}.",
        "",
        "| Hp bin | true stars | completeness | centroid RMS (px) | median (px) | p95 (px) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for b in res["bins"]:
        if b["stars"]:
            c = "-" if b["completeness"] is None else f"{100 * b['completeness']:.1f}%"

            def fmt(v):
                return "-" if v is None else f"{v:.3f}"

            lines.append(
                f"| {b['mag_lo']:.0f} to {b['mag_hi']:.0f} | {b['stars']} | {c} | {fmt(b['rms_px'])} | "
                f"{fmt(b['median_px'])} | {fmt(b['p95_px'])} |"
            )
    lines += [
        "",
        f"All matched detections: RMS {res['all_matched']['rms_px']:.3f} px, median "
        f"{res['all_matched']['median_px']:.3f} px. False detections: "
        f"{100 * res['false_detection_share']:.2f}% of all detections.",
        "",
        f"Detections per frame: median {np.median(nd):.0f}, 10th-90th percentile "
        f"{np.percentile(nd, 10):.0f}-{np.percentile(nd, 90):.0f}, min {nd.min()}, max {nd.max()}; "
        f"catalog stars brighter than the limit: median {np.median(nv):.0f}.",
        "",
    ]
    text = "\n".join(lines)
    (out / "detector_accuracy.md").write_text(text + "\n")
    (out / "detector_accuracy.json").write_text(json.dumps(res, indent=1))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.4))
    bins = np.arange(0, max(nd.max(), nv.max()) + 3, 2)
    ax.hist(nv, bins=bins, alpha=0.6, label="catalog stars brighter than the detection limit")
    ax.hist(nd, bins=bins, alpha=0.6, label="detections (default detector)")
    ax.set_xlabel("per frame")
    ax.set_ylabel("frames")
    ax.set_title(f"Default camera, {res['frames']} random boresights", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "stars_per_frame.png", dpi=110)
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--out", default="results/skygen")
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args(argv)
    print(write(measure(load_config(overrides=a.set), a.frames), Path(a.out)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
