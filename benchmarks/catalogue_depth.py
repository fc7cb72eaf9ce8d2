"""How many real detections does a catalogue explain? Hipparcos-2 against the deeper Gaia DR3 (to G = 10).

    python benchmarks/catalogue_depth.py FRAMES... --camera CAMERA.yaml [--radius-px 3] [--out DIR]

For every frame: detect as ``fusion predict --camera`` does, solve with all detections by tetra3rs, and keep
the frame when that solution is beyond doubt (false-positive probability <= 1e-20, >= 10 matched stars: the
rule of ``benchmarks/real_few_star.py``). Then project each catalogue cut through the camera at that attitude
(positions moved to the camera's ``epoch_yr``) and count the detections that have a catalogue star within
``--radius-px``: over all detections, and over each frame's brightest 5 and 8 (the ones a few-star solver
is given). The same count with every detection shifted by (+37, +53) px is the chance rate: a deeper
catalogue explains more, but also more by coincidence. Prints one Markdown table; with ``--out``, writes
catalogue_depth.json and catalogue_depth.md there.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_few_star import load_frames  # noqa: E402  (a sibling script: the same frame reader)

CUTS = (("Hipparcos-2, all", "hip", None), ("Gaia G <= 8", "gaia", 8.0), ("Gaia G <= 9", "gaia", 9.0),
        ("Gaia G <= 10 (all)", "gaia", 10.0))  # fmt: skip
SHIFT_PX = (37.0, 53.0)


def truth_frames(frames: list, camera: str, background_box: int | None = None, log=print) -> tuple:
    """(camera, [(name, detections table, camera -> ICRS matrix)], dropped) for frames with a certain truth."""
    from fusion.solve.base import Solution
    from fusion.solve.predict import Predictor
    from fusion.solve.registry import make_context

    pred = Predictor(camera=camera, background_box=background_box)
    cam = pred.camera
    tetra = make_context(cam).tetra
    kept, dropped = [], []
    for name, img, err in frames:
        if img is None:
            dropped.append((name, f"unreadable: {err}"))
            continue
        det, _, _ = pred.detect(img)
        sol = tetra.solve(det, cam)
        fpp = float(sol.extra.get("false_positive_probability", 1.0)) if isinstance(sol, Solution) else 1.0
        if not isinstance(sol, Solution) or fpp > 1e-20 or sol.n_matched < 10:
            dropped.append((name, "no certain all-detection solve"))
            continue
        kept.append((name, det, sol.matrix))
    log(f"{len(kept)} of {len(frames)} frames with a certain truth")
    return cam, kept, dropped


def explained(cam, det, matrix: np.ndarray, star_vec: np.ndarray, radius_px: float, shift=(0.0, 0.0)) -> tuple:
    """(explained flags of every detection, in the detections' order; catalogue stars in the field)."""
    v_cam = star_vec @ matrix  # rows: camera-frame directions
    near = v_cam[:, 2] > np.cos(cam.corner_radius_rad() + 0.02)
    x, y, front = cam.project(v_cam[near])
    inside = front & cam.inside(x, y, margin_px=radius_px)
    dx, dy = np.asarray(det.x_px) + shift[0], np.asarray(det.y_px) + shift[1]
    if not inside.any():
        return np.zeros(len(dx), bool), 0
    d, _ = cKDTree(np.column_stack([x[inside], y[inside]])).query(np.column_stack([dx, dy]))
    return d <= radius_px, int(inside.sum())


def _mean(parts: list) -> float:
    return float(np.mean(np.concatenate(parts))) if parts else float("nan")


def run(frames: list, camera: str, radius_px: float = 3.0, background_box: int | None = None, log=print) -> dict:
    from skygen.config import load_config
    from skygen.sky.catalog import load_catalog, load_gaia, propagate

    cam, kept, dropped = truth_frames(frames, camera, background_box, log)
    epoch = load_config(camera).epoch_yr
    tables = {"hip": load_catalog(), "gaia": load_gaia()}
    vecs = {k: propagate(t, epoch) for k, t in tables.items()}
    rows = []
    for label, source, cut in CUTS:
        keep = np.ones(len(tables[source]), bool) if cut is None else tables[source].mag <= cut
        all_, b5, b8, chance, n_field = [], [], [], [], []
        for _, det, m in kept:
            ok, n = explained(cam, det, m, vecs[source][keep], radius_px)
            by_chance, _ = explained(cam, det, m, vecs[source][keep], radius_px, SHIFT_PX)
            all_.append(ok)
            b5.append(ok[:5])  # detections come brightest first
            b8.append(ok[:8])
            chance.append(by_chance)
            n_field.append(n)
        rows.append({"catalogue": label, "stars": int(keep.sum()), "stars_per_frame": float(np.median(n_field or [0])),
                     "explained": _mean(all_), "brightest5": _mean(b5), "brightest8": _mean(b8),
                     "chance": _mean(chance)})  # fmt: skip
    return {"camera": str(camera), "radius_px": radius_px, "epoch_yr": epoch, "frames": len(frames),
            "frames_with_truth": len(kept), "dropped": dropped, "rows": rows,
            "detections": int(sum(len(d.x_px) for _, d, _ in kept)),
            "hardware": f"{platform.machine()}, {platform.processor() or 'cpu'}"}  # fmt: skip


def markdown(res: dict, title: str) -> str:
    lines = [
        f"### {title}",
        "",
        f"{res['frames_with_truth']} of {res['frames']} frames with a certain truth, {res['detections']} detections; "
        f"a detection is explained by a catalogue star within {res['radius_px']:g} px "
        f"(positions at J{res['epoch_yr']:g}).",
        "",
        "| catalogue | stars | in the field (median) | detections explained | brightest 5 | brightest 8 | by chance |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in res["rows"]:
        lines.append(
            f"| {r['catalogue']} | {r['stars']:,} | {r['stars_per_frame']:.0f} | {100 * r['explained']:.1f} % | "
            f"{100 * r['brightest5']:.1f} % | {100 * r['brightest8']:.1f} % | {100 * r['chance']:.1f} % |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("frames", nargs="+", help="frame files or folders (PNG, TIFF, FITS, .npy)")
    ap.add_argument("--camera", required=True, help="camera YAML (a preset or `skygen fit-camera`'s output)")
    ap.add_argument("--radius-px", type=float, default=3.0, help="match radius in pixels (default 3)")
    ap.add_argument("--background-box", type=int, help="detector background per PX box (as fusion predict)")
    ap.add_argument("--title", default=None, help="heading of the table (default: the camera file)")
    ap.add_argument("--out", help="folder for catalogue_depth.json / .md")
    a = ap.parse_args(argv)
    res = run(load_frames(a.frames), a.camera, a.radius_px, a.background_box, log=lambda m: print(m, file=sys.stderr))
    text = markdown(res, a.title or f"{a.camera}")
    print(text)
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "catalogue_depth.json").write_text(json.dumps(res, indent=2) + "\n")
        (out / "catalogue_depth.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
