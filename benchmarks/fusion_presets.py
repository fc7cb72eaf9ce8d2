"""Train (or reuse) the CPU presets and score them on rendered test frames: one table.

    python benchmarks/fusion_presets.py --data data/demo --test data/eval5k \\
        --corrupted data/eval-corrupt --runs demo best-s0 [--out results/cpu/presets]

Each named run is ``fusion train --data DATA --config PRESET [overrides]`` into
``runs/presets/NAME`` (skipped when that run already finished), then ``fusion evaluate`` on
the test split of ``--test`` (an independent dataset: the stream never produces its frames)
and, with ``--corrupted``, on the test split of a dataset rendered with skygen's own
corruptions (e.g. ``--set corruptions.dropout=0.3 --set corruptions.false_stars=2``).
Prints one Markdown table (training wall time, samples seen, top-1/3/5, median angular
error) and writes it with the raw JSON under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# name: (preset, overrides, what it is)
OLD = ["labels.fine_k=100", "train.epochs=10"]  # cpu.yaml before fine_k = 1000
OLD_BEST = ["labels.fine_k=null", "train.epochs=32", "stream.dropout=[0,0.3]", "stream.false_stars=[0,2]"]
RUNS = {
    "demo": (
        "configs/cpu.yaml",
        [],
        "cpu.yaml (make demo): stream, brightest reference, transformer d64x2, 1000 fine regions, 786 k samples",
    ),
    "fine1000": ("configs/cpu.yaml", ["train.epochs=10"], "cpu.yaml with 983 k samples"),
    "fine600": ("configs/cpu.yaml", ["labels.fine_k=600", "train.epochs=10"], "... with 600 fine regions"),
    "fine300": ("configs/cpu.yaml", ["labels.fine_k=300", "train.epochs=10"], "... with 300 fine regions"),
    "fine100": ("configs/cpu.yaml", OLD, "... with 100 fine regions (the previous cpu.yaml)"),
    "multi": (
        "configs/cpu.yaml",
        ["model.canonical.mode=multi", *OLD],
        "... 100 fine regions, three reference views averaged",
    ),
    "multi-coarse": (
        "configs/cpu.yaml",
        ["model.canonical.mode=multi", "labels.fine_k=null", "train.epochs=10"],
        "... three reference views, trained on the 15 regions directly",
    ),
    "raw": (
        "configs/cpu.yaml",
        ["model.canonical.mode=none", *OLD],
        "... 100 fine regions, raw sensor-frame rows (no canonical frame)",
    ),
    "fixed": (
        "configs/cpu.yaml",
        [
            "model.canonical.mode=multi",
            "stream.kind=none",
            "train.epochs=60",
            "labels.fine_k=100",
            "aug.rotation_max_deg=180",
            "aug.false_star_rate=1.0",
            "aug.dropout_prob=0.15",
        ],
        "the 'multi' model on the dataset's 3,200 fixed training frames (augmented), about the same time",
    ),
    "fusion": (
        "configs/cpu-fusion.yaml",
        ["model.init_from=runs/presets/demo/best.pt"],
        "three branches (peak set + heatmap + coords, detections dropout 0.3) on the frames stream, warm-started from "
        "'demo'",
    ),
    "few": ("configs/cpu-few.yaml", [], "cpu-few.yaml: half the samples cut to their brightest 3-12 detections"),
    "best-s0": ("configs/cpu-best.yaml", ["train.seed=0"], "cpu-best.yaml, seed 0"),
    "best-s1": ("configs/cpu-best.yaml", ["train.seed=1"], "cpu-best.yaml, seed 1"),
    "best-s2": ("configs/cpu-best.yaml", ["train.seed=2"], "cpu-best.yaml, seed 2"),
    "best-coarse": (
        "configs/cpu-best.yaml",
        OLD_BEST,
        "the previous cpu-best.yaml: 15 regions directly, 3.3 M samples, dropout up to 0.3, up to 2 false stars",
    ),
    "best-k100": ("configs/cpu-best.yaml", ["labels.k=100", *OLD_BEST], "the previous cpu-best.yaml, K = 100"),
}


def _train(name: str, data: str, runs: Path, log) -> dict:
    from fusion.config import load_config
    from fusion.train.run import train

    preset, overrides, _ = RUNS[name]
    out = runs / name
    if (out / "summary.json").exists():
        return json.loads((out / "summary.json").read_text())
    cfg = load_config(ROOT / preset, [f"data.path={data}", "train.progress=false", *overrides])
    t0 = time.perf_counter()
    summary = train(cfg, out, force=True, log=log)
    summary["bench_wall_s"] = time.perf_counter() - t0
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def _evaluate(name: str, runs: Path, data: str, tag: str) -> dict:
    from fusion.measure.evaluate import evaluate_checkpoint

    quiet = lambda *a, **k: None  # noqa: E731
    return evaluate_checkpoint(
        runs / name / "best.pt", data, "test", runs / name / f"eval-{tag}", log=quiet, warn=quiet
    )


def seed_summary(rows: list[dict]) -> list[str]:
    """Mean ± sample std over the seeds of runs named NAME-s<seed> (at least two seeds)."""
    import re

    import numpy as np

    groups: dict[str, list[dict]] = {}
    for r in rows:
        m = re.fullmatch(r"(.+)-s(\d+)", r["run"])
        if m:
            groups.setdefault(m.group(1), []).append(r)
    out = []
    for name, rs in groups.items():
        if len(rs) < 2:
            continue

        def ms(key):
            return (
                f"{100 * np.mean([r[key] for r in rs]):.1f} ± {100 * np.std([r[key] for r in rs], ddof=1):.1f} %"
                if all(key in r for r in rs)
                else "–"
            )

        out.append(
            f"\n{name}, {len(rs)} seeds ({', '.join(r['run'] for r in rs)}): top-1 {ms('top1')}, top-3 "
            f"{ms('top3')}, top-5 {ms('top5')}, corrupted top-1 {ms('corrupted_top1')}; training time "
            f"{np.mean([r['train_s'] for r in rs]) / 60:.1f} min (mean), "
            f"{max(r['train_s'] for r in rs) / 60:.1f} min (longest)"
        )
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="dataset whose render config the stream uses (and val split)")
    p.add_argument("--test", required=True, help="dataset whose test split scores every run")
    p.add_argument("--corrupted", help="dataset rendered with corruptions; its test split is scored too")
    p.add_argument("--runs", nargs="+", default=["demo"], choices=sorted(RUNS), help="runs to train/score")
    p.add_argument("--run-dir", default="runs/presets", help="where the runs live (reused when finished)")
    p.add_argument("--out", help="write presets.md and presets.json here")
    a = p.parse_args(argv)
    runs = Path(a.run_dir)
    rows = []
    for name in a.runs:
        s = _train(name, a.data, runs, print)
        clean = _evaluate(name, runs, a.test, "test")
        row = {
            "run": name,
            "what": RUNS[name][2],
            "train_s": s.get("wall_time_s"),
            "samples": s.get("samples_seen"),
            "k": clean["num_classes"],
            "top1": clean["top1"],
            "top3": clean["top3"],
            "top5": clean["top5"],
            "median_err": clean["angular_error"]["median_deg"],
            "n_test": clean["n_frames"],
        }
        if a.corrupted:
            bad = _evaluate(name, runs, a.corrupted, "corrupted")
            row["corrupted_top1"] = bad["top1"]
        rows.append(row)
        print(json.dumps(row))
    host = f"{platform.machine()}, {os.cpu_count()} logical CPUs"
    lines = [
        f"CPU presets ({host}); test split of {a.test}"
        + (f"; corrupted: test split of {a.corrupted}" if a.corrupted else ""),
        "",
        "| run | K | training time | samples | top-1 | top-3 | top-5 | median error | top-1, corrupted | what |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        cor = f"{100 * r['corrupted_top1']:.1f} %" if "corrupted_top1" in r else "–"
        seen = f"{r['samples'] / 1e6:.2f} M" if r.get("samples") else "–"
        lines.append(
            f"| {r['run']} | {r['k']} | {r['train_s'] / 60:.1f} min | {seen} | {100 * r['top1']:.1f} % | "
            f"{100 * r['top3']:.1f} % | {100 * r['top5']:.1f} % | {r['median_err']:.1f}° | {cor} | {r['what']} |"
        )
    lines += seed_summary(rows)
    text = "\n".join(lines)
    print(text)
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "presets.md").write_text(
            text
            + "\n\nCommand: `python benchmarks/fusion_presets.py "
            + " ".join(argv if argv is not None else os.sys.argv[1:])
            + "`\n"
        )
        (out / "presets.json").write_text(json.dumps({"host": host, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
