"""Tracking on real frames with a hint that misses: is a wrong answer as rare as its false-match probability says?

    python benchmarks/real_tracking_offhint.py FRAMES... --camera CAMERA.yaml [--n 2 3] [--off-sigmas 6]
                                               [--reps 10] [--sigma-deg S] --out DIR

Each frame's truth is its all-detection tetra3rs solve (``benchmarks/real_few_star.py``'s rule and options). Its
brightest N detections then go to the fine stage's tracking (``whole-sky``'s ``solve(..., hint=...)``) with a hint
whose attitude is the truth turned by ``--off-sigmas`` x S about a random axis (``--reps`` axes per frame, seed 0),
1 sigma S (default: a fifth of the horizontal field, within 0.1-2 deg), and the zero point the frames measured at
their truth (the median). The truth then lies outside the hint's 3-sigma region: an answer more than 0.1 deg from it
is wrong, and the wrong ones are set beside the sum of the false-match probabilities reported with every answer.
(A turn about an axis near the boresight moves the stars little, so some answers are right.)

Writes DIR/offhint.json and DIR/offhint.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def run(
    frames, camera, n_values=(2, 3), off_sigmas=6.0, reps=10, sigma_deg=None, min_matched=10, max_fpp=1e-20, log=print
) -> dict:
    from real_few_star import all_detection_truth

    from fusion.solve.base import Solution, rotation_angle_deg
    from fusion.solve.predict import Predictor
    from fusion.solve.registry import build_solver, make_context
    from skygen.sky.attitude import rotation_about

    pred = Predictor(None, camera=camera)
    cam = pred.camera
    ctx = make_context(cam, prior=None)
    solver = build_solver("whole-sky", cam, context=ctx)
    kept = []
    for name, img, _ in frames:
        if img is None:
            continue
        det, _, _ = pred.detect(img)
        full, why = all_detection_truth(ctx.tetra, det, cam, max_fpp, min_matched)
        if why is None:
            kept.append((name, det, full.matrix))
    zps = [solver.solve(d, cam, hint=m, hint_sigma_deg=0.05) for _, d, m in kept]
    zp = [z.extra.get("zero_point") for z in zps if isinstance(z, Solution) and z.extra.get("zero_point") is not None]
    zero_point = float(np.median(zp)) if zp else None
    sigma = float(sigma_deg) if sigma_deg else float(np.clip(0.2 * cam.fov_deg[0], 0.1, 2.0))
    rng = np.random.default_rng(0)
    cells = {int(n): {"attempts": 0, "answers": 0, "wrong": 0, "sum_p": 0.0, "wrong_p": []} for n in n_values}
    for _, det, truth in kept:
        for _ in range(reps):
            axis = rng.normal(size=3)
            hint = rotation_about(axis / np.linalg.norm(axis), np.radians(off_sigmas * sigma)) @ truth
            for n in n_values:
                c = cells[int(n)]
                res = solver.solve(det.brightest(n), cam, hint=hint, hint_sigma_deg=sigma, hint_zero_point=zero_point)
                c["attempts"] += 1
                if isinstance(res, Solution):
                    c["answers"] += 1
                    c["sum_p"] += float(res.false_match_probability)
                    if rotation_angle_deg(res.matrix, truth) > 0.1:
                        c["wrong"] += 1
                        c["wrong_p"].append(float(res.false_match_probability))
    log(f"{len(kept)} frames with a truth; hint sigma {sigma:.3g} deg, the truth {off_sigmas:g} sigma off")
    return {
        "camera": str(camera),
        "frames_kept": len(kept),
        "hint_sigma_deg": sigma,
        "off_sigmas": off_sigmas,
        "reps": reps,
        "zero_point": zero_point,
        "cells": cells,
        "host": {"platform": platform.platform(), "processor": platform.processor()},
    }


def markdown(r: dict, command: str) -> str:
    lines = [
        f"Tracking with a hint that misses, camera `{r['camera']}`: {r['frames_kept']} frames, each {r['reps']} hints "
        f"{r['off_sigmas']:g} sigma off its truth (1 sigma {r['hint_sigma_deg']:.3g} deg). Wrong: more than 0.1 deg "
        "from the truth.",
        "",
        "| N | attempts | answers | wrong | sum of reported p (answers) | p of the wrong ones |",
        "|---|---|---|---|---|---|",
    ]
    for n, c in r["cells"].items():
        wp = ", ".join(f"{p:.2g}" for p in c["wrong_p"]) or "–"
        lines.append(f"| {n} | {c['attempts']} | {c['answers']} | {c['wrong']} | {c['sum_p']:.3g} | {wp} |")
    lines += ["", f"Command: `{command}`"]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    from real_few_star import load_frames

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("frames", nargs="+")
    p.add_argument("--camera", required=True)
    p.add_argument("--n", type=int, nargs="+", default=[2, 3])
    p.add_argument("--off-sigmas", type=float, default=6.0)
    p.add_argument("--reps", type=int, default=10)
    p.add_argument("--sigma-deg", type=float, default=None)
    p.add_argument("--truth-min-matched", type=int, default=10)
    p.add_argument("--truth-max-fpp", type=float, default=1e-20)
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    if a.off_sigmas <= 3 or a.reps < 1 or min(a.n) < 2:
        raise SystemExit("--off-sigmas > 3 (outside the hint's region), --reps >= 1, --n >= 2")
    r = run(
        load_frames(a.frames), a.camera, a.n, a.off_sigmas, a.reps, a.sigma_deg, a.truth_min_matched, a.truth_max_fpp
    )
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    command = "python benchmarks/real_tracking_offhint.py " + " ".join(argv if argv is not None else sys.argv[1:])
    (out / "offhint.json").write_text(json.dumps({**r, "command": command}, indent=1))
    (out / "offhint.md").write_text(markdown(r, command))
    print(markdown(r, command))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
