"""Does a fitted camera predict real few-star solving? The real frames' cells beside the same cells on renders.

    python benchmarks/sim_vs_real.py FRAMES... --camera FITTED.yaml --out DIR
                                     [--renders 60] [--per-attitude 5] [--n 3 4 5 6 8]
                                     [--solvers whole-sky tetra3rs>whole-sky] [--seed 0] [--work DIR]
                                     [--checkpoint CK --solvers whole-sky learned+fine>whole-sky]
                                     [--fit-report FIT_REPORT_DIR]

Three columns for every N and solver, each the share of frames solved correctly from the brightest N detections
(``benchmarks/real_few_star.py``'s cells and scoring, the camera's own detection settings):

* **real**: the frames, truth from each frame's all-detection tetra3rs solve (frames without a certain one are
  left out and named);
* **renders, real attitudes**: the camera rendered at every real frame's truth attitude, ``--per-attitude``
  noise realisations each: the sensor model alone, the sky held as the frames saw it; with ``--fit-report`` (the
  camera's fit-camera report) each at its frame's own exposure, where the frames were taken at several;
* **renders, random sky**: ``--renders`` frames of the camera at uniformly drawn attitudes: what a user of this
  camera should expect over the sky (the real frames may point at richer or poorer fields than average).

With ``--checkpoint CK`` (a model trained on renders of this camera) the learned solvers may be listed too; all
three columns then detect and solve with the model's own camera (real_few_star's ``--checkpoint``).

Each rate comes with its 95 % Wilson interval. The issue's target is renders within 5 points of the real; with a
handful of real frames the real rate itself is uncertain by tens of points, so the table also says whether the
two intervals overlap. Renders are written under ``--work`` (default DIR/renders; datasets, not for committing).
Writes DIR/sim_vs_real.json and DIR/sim_vs_real.md and prints the Markdown.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_few_star import load_frames, run  # noqa: E402  (a sibling script: the same cells and scoring)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DEFAULT_SOLVERS = ("whole-sky", "tetra3rs>whole-sky")
TARGET_POINTS = 5.0


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion k / n (nan, nan for n = 0)."""
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    d = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / d
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return max(0.0, centre - half), min(1.0, centre + half)


def render(camera: str, out: Path, n: int, seed: int, attitudes=None, exposure_scale: float = 1.0) -> Path:
    """Full-resolution renders of ``camera`` into ``out``: ``n`` uniform attitudes, or the (ra, dec, roll) list
    ``attitudes`` (every entry once per frame, in order); ``exposure_scale`` times its exposure."""
    from skygen.config import build_config, config_dict, load_config
    from skygen.datasets.build import render_dataset

    d = config_dict(load_config(camera))
    d["sensor"] = {**d["sensor"], "exposure_s": float(d["sensor"]["exposure_s"]) * float(exposure_scale)}
    d["seed"] = int(seed)
    d["n_frames"] = int(n if attitudes is None else len(attitudes))
    d["output"] = {**d["output"], "full_res": True}
    if attitudes is not None:
        ra, dec, roll = ([float(a[i]) for a in attitudes] for i in range(3))
        d["attitude"] = {**d["attitude"], "mode": "list", "ra_deg": ra, "dec_deg": dec, "roll_deg": roll}
    render_dataset(build_config(d), out, workers=1, force=True, progress=False)
    return out


def exposure_scales(report: Path, frames: list[dict]) -> list[float]:
    """Each real frame's exposure relative to the fitted camera's (``skygen fit-camera``'s fit.json in ``report``,
    ``solved[k].exposure_scale``, matched by file name); 1 for a frame the fit has none for (not solved there)."""
    from skygen.errors import ConfigError
    from skygen.real.fit_report import read_fit

    try:
        known = {r["frame"]: r.get("exposure_scale") for r in read_fit(report, "--fit-report")["solved"]}
    except ConfigError as e:
        raise SystemExit(f"sim_vs_real: {e}") from None
    out = []
    for f in frames:
        v = known.get(Path(str(f["frame"])).name)
        out.append(float(v) if v is not None and np.isfinite(v) and v > 0 else 1.0)
    return out


def group_by_exposure(scales: list[float], step_mag: float = 0.02) -> dict[float, list[int]]:
    """Frame indices by exposure scale, scales within ``step_mag`` of each other rendered as one (their group's
    scale: the first's rounded to the step)."""
    groups: dict[float, list[int]] = {}
    for k, v in enumerate(scales):
        key = round(round(2.5 * np.log10(v) / step_mag) * step_mag, 6)
        groups.setdefault(key, []).append(k)
    return {float(10 ** (0.4 * key)): ks for key, ks in groups.items()}


def _rates(res: dict) -> dict:
    """{(n, solver): (correct, wrong, frames)} of a real_few_star result."""
    out = {}
    for c in res["cells"]:
        for s, v in c["solvers"].items():
            out[(c["n"], s)] = (v["n_correct"], v["n_wrong"], c["frames"])
    return out


def compare(real: dict, at_truth: dict | None, random_sky: dict | None, solvers, n_values) -> list[dict]:
    """One row per (N, solver): each column's counts, rate and interval; the renders' distance to the real."""
    cols = {"real": _rates(real)}
    if at_truth is not None:
        cols["at_truth"] = _rates(at_truth)
    if random_sky is not None:
        cols["random_sky"] = _rates(random_sky)
    rows = []
    for n in n_values:
        for s in solvers:
            row = {"n": int(n), "solver": s}
            for name, rates in cols.items():
                k, w, f = rates.get((n, s), (0, 0, 0))
                lo, hi = wilson(k, f)
                row[name] = {"correct": k, "wrong": w, "frames": f, "rate": k / f if f else float("nan"),
                             "ci95": [lo, hi]}  # fmt: skip
            r = row["real"]
            for name in ("at_truth", "random_sky"):
                if name in row and r["frames"] and row[name]["frames"]:
                    c = row[name]
                    c["points_off"] = 100 * (c["rate"] - r["rate"])
                    c["within_target"] = abs(c["points_off"]) <= TARGET_POINTS
                    c["intervals_overlap"] = c["ci95"][0] <= r["ci95"][1] and r["ci95"][0] <= c["ci95"][1]
            rows.append(row)
    return rows


def _cell(c: dict | None, real: bool = False) -> str:
    if c is None or not c["frames"]:
        return "–"
    lo, hi = (100 * v for v in c["ci95"])
    txt = f"**{100 * c['rate']:.0f} %** ({c['correct']}/{c['frames']}, {lo:.0f}–{hi:.0f})"
    if c["wrong"]:
        txt += f", {c['wrong']} wrong"
    if not real and "points_off" in c:
        mark = "✓" if c["within_target"] else ("≈" if c["intervals_overlap"] else "✗")
        txt += f", {c['points_off']:+.0f} pts {mark}"
    return txt


def per_frame(
    real: dict, at_truth: dict | None, per_attitude: int, solver: str, n_values, origin: dict | None = None
) -> list[dict]:
    """Per real frame, for ``solver``: its outcome in each N cell beside how many of its renders (the
    ``per_attitude`` renders at its truth attitude, in order) were correct, and how many of its brightest N its
    all-detection solve did not match: which frames the renders get wrong, and whether non-star detections are
    why."""
    rendered: dict[int, list] = {}
    if at_truth is not None and per_attitude > 0:
        for f in at_truth["frames"]:
            folder, index = str(f["frame"]).rsplit("#", 1)
            # renders of several exposures sit in one folder each, with the real frames they stand for (origin)
            k = origin[folder][int(index)] if origin else int(index) // per_attitude
            rendered.setdefault(k, []).append(f.get("outcomes", {}).get(solver, {}))
    rows = []
    for k, f in enumerate(real["frames"]):
        cells = {}
        for n in n_values:
            got = f.get("outcomes", {}).get(solver, {}).get(str(n))
            renders = [o.get(str(n)) for o in rendered.get(k, [])]
            cells[str(n)] = {
                "real": got,
                "renders_correct": sum(o == "correct" for o in renders),
                "renders": len(renders),
                "non_catalogue_in_brightest": f.get("non_catalogue_in_brightest", {}).get(str(n)),
            }
        rows.append({"frame": Path(str(f["frame"])).name, "cells": cells})
    return rows


def agreement(rows: list[dict]) -> tuple[int, int]:
    """(frame x N cells where most of the frame's own renders end as the frame did — both solved or both not —,
    cells with renders): a paired measure, free of the spread between fields that the cells' rates carry."""
    agree = total = 0
    for r in rows:
        for c in r["cells"].values():
            if not c["renders"] or c["real"] is None:
                continue
            total += 1
            agree += (c["real"] == "correct") == (2 * c["renders_correct"] > c["renders"])
    return agree, total


def markdown(res: dict) -> str:
    lines = [
        f"Camera `{res['camera']}`; real frames: {res['real']['frames_kept']} of {res['real']['frames_given']} with a "
        f"certain truth; renders at the real attitudes: {res['per_attitude']} per frame"
        + (
            f" (each at its frame's own exposure, x {min(res['exposure_scales']):.2f} to "
            f"x {max(res['exposure_scales']):.2f} the camera's: --fit-report)"
            if res.get("exposure_scales")
            else ""
        )
        + "; renders over the sky: "
        f"{res['renders']} (seed {res['seed']}). Cells: correct share (correct/frames, 95 % interval), wrong "
        f"answers if any, and the renders' distance to the real: ✓ within {TARGET_POINTS:g} points, ≈ outside "
        "but the 95 % intervals overlap, ✗ they do not.",
        "",
        "| N | solver | real | renders, real attitudes | renders, random sky |",
        "|---|---|---|---|---|",
    ]
    for r in res["rows"]:
        lines.append(
            f"| {r['n']} | {r['solver']} | {_cell(r['real'], True)} | {_cell(r.get('at_truth'))} | "
            f"{_cell(r.get('random_sky'))} |"
        )
    if res.get("per_frame"):
        n_values = list(res["per_frame"][0]["cells"])
        agree, total = agreement(res["per_frame"])
        lines += [
            "",
            f"**Frame by frame**: in {agree} of {total} (frame, N) cells most of the frame's own renders end as the "
            "frame did (both solved, or both not).",
            "",
            f"Per real frame ({res['per_frame_solver']}): ✓ solved, or why not; then how many of its renders at its "
            "attitude were solved, and in brackets how many of its brightest N detections its all-detection solve "
            "did not match (non-stars) where any:",
            "",
            "| frame | " + " | ".join(f"N = {n}" for n in n_values) + " |",
            "|---|" + "---|" * len(n_values),
        ]
        for r in res["per_frame"]:
            out = []
            for n in n_values:
                c = r["cells"][n]
                real = "–" if c["real"] is None else ("✓" if c["real"] == "correct" else c["real"])
                txt = f"{real} · {c['renders_correct']}/{c['renders']}" if c["renders"] else real
                out.append(txt + (f" ({c['non_catalogue_in_brightest']})" if c["non_catalogue_in_brightest"] else ""))
            lines.append(f"| {r['frame']} | " + " | ".join(out) + " |")
    if res["real"].get("dropped"):
        lines += ["", "Real frames left out: " + "; ".join(
            f"{Path(d['frame']).name}: {d['reason']}" for d in res["real"]["dropped"])]  # fmt: skip
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("frames", nargs="+", help="real frame files or folders of them")
    p.add_argument("--camera", required=True, help="the camera YAML fitted to these frames (skygen fit-camera)")
    p.add_argument("--n", type=int, nargs="+", default=[3, 4, 5, 6, 8], help="brightest-N cells")
    p.add_argument(
        "--solvers", nargs="+", default=list(DEFAULT_SOLVERS), help="registered solvers (learned: with --checkpoint)"
    )
    p.add_argument("--checkpoint", default=None, help="a model trained on renders of this camera: its learned solvers")
    p.add_argument("--renders", type=int, default=60, help="renders at random attitudes (0: none)")
    p.add_argument("--per-attitude", type=int, default=5, help="renders at each real truth attitude (0: none)")
    p.add_argument("--seed", type=int, default=0, help="the renders' seed")
    p.add_argument("--channel", default="luminance", help="colour frames: luminance, r, g, b or sum")
    p.add_argument("--work", default=None, help="folder for the renders (default OUT/renders)")
    p.add_argument(
        "--known-defects",
        action="store_true",
        help="real frames and renders alike: drop detections at defect pixels learned from the other frames "
        "(real_few_star.py --known-defects)",
    )
    p.add_argument(
        "--mask-fixed-sources",
        action="store_true",
        help="real frames and renders alike: drop the detections of the camera's sensor.fixed_sources (--camera's, "
        "or the checkpoint's) at detection (real_few_star.py --mask-fixed-sources)",
    )
    p.add_argument(
        "--correct-deg",
        type=float,
        default=0.1,
        help="boresight bound of a correct answer (real_few_star.py's; a wide field needs more than 0.1 deg, which "
        "is 2 px at 51 deg over 1024 px)",
    )
    p.add_argument(
        "--fit-report",
        type=Path,
        default=None,
        help="the folder skygen fit-camera --report wrote for --camera: renders at each real attitude take that "
        "frame's own exposure (fit.json's exposure_scale: frames of other exposures or gains than the camera's)",
    )
    p.add_argument("--out", required=True, help="folder for sim_vs_real.json and sim_vs_real.md")
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(a.work) if a.work else out / "renders"
    log = lambda s: print(s, file=sys.stderr)  # noqa: E731
    t0 = time.perf_counter()
    # with a model, its own camera detects and solves (the camera file still renders the frames)
    cam, kw = (None, {"checkpoint": a.checkpoint}) if a.checkpoint else (a.camera, {})
    kw["known_defects"] = a.known_defects
    kw["mask_fixed_sources"] = a.mask_fixed_sources
    kw["correct_deg"] = a.correct_deg
    real = run(load_frames(a.frames, None, a.channel), cam, a.n, a.solvers, log=log, **kw)
    if not real["frames_kept"]:
        raise SystemExit("sim_vs_real: no real frame has a certain truth attitude: nothing to predict")
    at_truth = random_sky = origin = None
    scales = exposure_scales(a.fit_report, real["frames"]) if a.fit_report else None
    if a.per_attitude > 0 and scales is None:
        atts = [f["truth_radec_roll_deg"] for f in real["frames"] for _ in range(a.per_attitude)]
        folder = render(a.camera, work / "at-truth", 0, a.seed, atts)
        at_truth = run(load_frames([str(folder)]), cam, a.n, a.solvers, log=log, **kw)
    elif a.per_attitude > 0:  # each frame at its own exposure: one render folder per exposure (0.02 mag steps)
        origin, folders = {}, []
        for j, (scale, ks) in enumerate(sorted(group_by_exposure(scales).items())):
            atts = [real["frames"][k]["truth_radec_roll_deg"] for k in ks for _ in range(a.per_attitude)]
            folder = render(a.camera, work / "at-truth" / f"exposure-{j:02d}", 0, a.seed, atts, scale)
            origin[str(folder)] = [k for k in ks for _ in range(a.per_attitude)]
            folders.append(str(folder))
        at_truth = run(load_frames(folders), cam, a.n, a.solvers, log=log, **kw)
    if a.renders > 0:
        folder = render(a.camera, work / "random-sky", a.renders, a.seed)
        random_sky = run(load_frames([str(folder)]), cam, a.n, a.solvers, log=log, **kw)
    res = {
        "command": "python benchmarks/sim_vs_real.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "camera": a.camera,
        "checkpoint": a.checkpoint,
        "renders": a.renders,
        "known_defects": a.known_defects,
        "mask_fixed_sources": a.mask_fixed_sources,
        "per_attitude": a.per_attitude,
        "fit_report": str(a.fit_report) if a.fit_report else None,
        "exposure_scales": scales,  # each real frame's renders at its own exposure (None: the camera's)
        "seed": a.seed,
        "rows": compare(real, at_truth, random_sky, a.solvers, a.n),
        "per_frame_solver": "whole-sky" if "whole-sky" in a.solvers else a.solvers[0],
        "per_frame": per_frame(
            real, at_truth, a.per_attitude, "whole-sky" if "whole-sky" in a.solvers else a.solvers[0], a.n, origin
        ),
        "real": {k: v for k, v in real.items() if k != "cells"},
        "wall_s": time.perf_counter() - t0,
        "runs": {"real": real, "at_truth": at_truth, "random_sky": random_sky},
    }
    md = markdown(res)
    (out / "sim_vs_real.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    (out / "sim_vs_real.md").write_text(md + f"\nCommand: `{res['command']}` ({res['wall_s']:.0f} s)\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
