"""Do the pixels and the detections know different things? Late-fusion ensembles of the cpu30 runs.

    python results/cpu30/ensembles.py        # ~10 min on 2 vCPUs; needs the runs' best.pt (this machine's)

For each seed, two ensembles of finished runs (`fusion evaluate --checkpoint A B`: the mean of
their log-probabilities), scored on the 2,000 test frames whole and cut to their brightest 3, 4,
5, 6 and 10 detections, as the members were:
  - geometry_only + image_only: the detections model and the pixels model, trained apart;
  - two stages + image_only: the best fused model and the pixels model.
An ensemble costs its members' training time together (~60 min), twice a row of REPORT.md: it is
a measure of what the two views hold between them, not an equal-time competitor. Writes
ensembles/<pair>-s<seed>/eval-test*.json and ensembles.md (the table) here.
"""
import json
import subprocess
import sys
from pathlib import Path

from fusion.measure.experiment import load_preset, plan, run_folder

HERE = Path(__file__).resolve().parent
PAIRS = {"geometry_only + image_only": ("geometry_only", "image_only"),
         "two stages + image_only": ("star_fusion, two stages", "image_only")}
DATA = "data/experiment-cpu30"


def top1(folder: Path, n) -> float:
    stem = "test" if n is None else f"test-brightest{n}"
    return json.loads((folder / f"eval-{stem}.json").read_text())["top1"]


if __name__ == "__main__":
    p = load_preset("cpu30")
    cuts = [None, *p.few_star]
    runs = {(r.name, r.seed): run_folder(HERE / "runs", r) for r in plan(p)["table1"]}
    rows = {}
    for label, (a, b) in PAIRS.items():
        for seed in p.seeds:
            out = HERE / "ensembles" / f"{label.replace(' + ', '+').replace(' ', '_').replace(',', '')}-s{seed}"
            for n in cuts:
                cmd = [sys.executable, "-m", "fusion.cli", "evaluate", "--checkpoint", str(runs[a, seed] / "best.pt"),
                       str(runs[b, seed] / "best.pt"), "--data", DATA, "--split", "test", "--out", str(out)]
                if n is not None:
                    cmd += ["--brightest", str(n)]
                print(" ".join(cmd), flush=True)
                subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
            rows[label, seed] = [top1(out, n) for n in cuts]
        for name in (a, b):
            for seed in p.seeds:
                rows.setdefault((name, seed), [top1(runs[name, seed], n) for n in cuts])
    names = [*dict.fromkeys(x for pair in PAIRS.values() for x in pair), *PAIRS]
    head = "| model | " + " | ".join("whole" if n is None else f"N = {n}" for n in cuts) + " |"
    lines = ["# Late-fusion ensembles of the cpu30 runs (`python results/cpu30/ensembles.py`)", "",
             "Top-1 (%) at K = 15 on the 2,000 test frames of `data/experiment-cpu30`, whole and cut to the "
             "brightest N detections (the image untouched), mean of seeds " + ", ".join(map(str, p.seeds))
             + " (each seed's ensemble joins that seed's runs). An ensemble's training time is its members' together.",
             "", head, "|---|" + "---:|" * len(cuts)]
    for name in names:
        per_seed = [rows[name, s] for s in p.seeds]
        means = [100 * sum(col) / len(col) for col in zip(*per_seed)]
        lines.append(f"| {name} | " + " | ".join(f"{m:.1f}" for m in means) + " |")
    lines += ["", "Per seed:", "", head, "|---|" + "---:|" * len(cuts)]
    for name in names:
        for s in p.seeds:
            lines.append(f"| {name}, seed {s} | " + " | ".join(f"{100 * t:.1f}" for t in rows[name, s]) + " |")
    (HERE / "ensembles.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
