"""Seed 0 of configs/experiments/cpu30.yaml: the runs of results/image (same presets, seed 0),
adopted into the experiment's run folders; the experiment evaluates them and trains seeds 1-2."""
import shutil
from pathlib import Path

from fusion.measure.experiment import ensure_dataset, load_preset, plan, run_folder

SRC = {"geometry_only": "runs/geo53", "image_only": "runs/image", "star_fusion, from scratch": "runs/three",
       "geometry_only, 42 epochs (the first stage)": "runs/geo30", "star_fusion, two stages": "runs/fusion-d"}

if __name__ == "__main__":
    p = load_preset("cpu30")
    ensure_dataset(p, Path("data/experiment-cpu30"), 2, print)
    for r in plan(p)["table1"]:
        if r.seed == 0:
            dst = run_folder(Path("results/cpu30/runs"), r)
            dst.mkdir(parents=True, exist_ok=True)
            for f in ("best.pt", "summary.json", "metrics.csv", "config.yaml", "centroids.npy"):
                shutil.copy2(Path(SRC[r.name]) / f, dst / f)
            print(r.name, "<-", SRC[r.name])
