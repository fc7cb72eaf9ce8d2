"""How much sky must the fine stage search? Coverage of a checkpoint's regions against the sky searched.

    python benchmarks/prior_coverage.py --checkpoint runs/presets/few/best.pt --data data/bench500 \\
        [--split test] [--frames 150] [--n 4 6 10 100] [--k 1 5 10 20 40] [--out results/benchmark]

For each brightest-N cut of the stored detections of the first ``--frames`` frames: how often
the region holding the true boresight is the model's first choice or among its top 3 of the
K regions, and how often the true **fine** region (``labels.fine_k``) is among the top k fine
regions, with the fraction of the sky those k regions cover. This is what chose the default
of the coarse-to-fine search (``fusion predict --search fine --search-k 20``). Prints one
Markdown table; ``--out`` also writes ``prior_coverage.md`` and ``prior_coverage.json`` there.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np


def coverage(checkpoint: str, data: str, split: str, frames: int, n_values, k_values) -> dict:
    from fusion.solve.base import Detections
    from fusion.solve.priors import load_prior
    from skygen.datasets.shards import open_dataset

    prior = load_prior(checkpoint, level="fine")
    if prior.fine_centroids is None:
        raise SystemExit(f"{checkpoint}: trained without fine regions (labels.fine_k); nothing to compare")
    with open_dataset(data) as ds:
        pos = ds.indices(split)[:frames]
        tables = [ds.detections(int(p)) for p in pos]
        images = [ds.image(int(p)) for p in pos]
        v = np.asarray(ds.boresight["unit_vector"][pos], np.float64)
    kc, kf = len(prior.coarse_centroids), len(prior.fine_centroids)
    lab_c = np.argmax(v @ prior.coarse_centroids.T, axis=1)
    lab_f = np.argmax(v @ prior.fine_centroids.T, axis=1)
    rows = []
    for n in n_values:
        rank_c, rank_f = [], []
        for t, im, lc, lf in zip(tables, images, lab_c, lab_f):
            pc, pf = prior.both(Detections.from_table(t).brightest(n), im)
            rank_c.append(int(np.sum(pc > pc[lc])))
            rank_f.append(int(np.sum(pf > pf[lf])))
        rank_c, rank_f = np.array(rank_c), np.array(rank_f)
        rows.append(
            {
                "n": n,
                "coarse_top1": float(np.mean(rank_c < 1)),
                "coarse_top3": float(np.mean(rank_c < 3)),
                "fine": {str(k): float(np.mean(rank_f < k)) for k in k_values},
            }
        )
    return {
        "checkpoint": str(checkpoint),
        "data": str(data),
        "split": split,
        "frames": int(len(pos)),
        "regions": kc,
        "fine_regions": kf,
        "sky_fraction": {"coarse_top3": 3 / kc, **{str(k): k / kf for k in k_values}},
        "rows": rows,
        "hardware": f"{platform.machine()} CPU",
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def markdown(r: dict) -> str:
    ks = list(r["rows"][0]["fine"])
    sky = r["sky_fraction"]
    lines = [
        f"# Region coverage of `{r['checkpoint']}`",
        "",
        f"`python benchmarks/prior_coverage.py` on {r['frames']} {r['split']} frames of `{r['data']}` "
        f"({r['hardware']}, {r['created_utc']}): share of frames whose true region is among the model's top "
        f"choices, by brightest-N detections kept; {r['regions']} regions, {r['fine_regions']} fine regions. "
        "Sky searched: average fraction of the sphere the listed regions cover.",
        "",
        "| N | top-1 of K | top-3 of K | " + " | ".join(f"fine top-{k}" for k in ks) + " |",
        "|---|---|---|" + "---|" * len(ks),
        f"| sky searched | {100 / r['regions']:.1f} % | {100 * sky['coarse_top3']:.1f} % | "
        + " | ".join(f"{100 * sky[k]:.1f} %" for k in ks)
        + " |",
    ]
    for row in r["rows"]:
        lines.append(
            f"| {row['n']} | {100 * row['coarse_top1']:.0f} % | {100 * row['coarse_top3']:.0f} % | "
            + " | ".join(f"{100 * row['fine'][k]:.0f} %" for k in ks)
            + " |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="a fusion checkpoint trained with labels.fine_k")
    p.add_argument("--data", required=True, help="a skygen dataset of the checkpoint's camera")
    p.add_argument("--split", default="test", choices=("train", "val", "test"))
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--n", type=int, nargs="+", default=[4, 6, 10, 100], help="brightest-N detections kept")
    p.add_argument("--k", type=int, nargs="+", default=[1, 5, 10, 20, 40], help="fine regions searched")
    p.add_argument("--out", help="folder for prior_coverage.md and prior_coverage.json")
    a = p.parse_args(argv)
    r = coverage(a.checkpoint, a.data, a.split, a.frames, a.n, a.k)
    md = markdown(r)
    print(md)
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "prior_coverage.json").write_text(json.dumps(r, indent=1) + "\n")
        (out / "prior_coverage.md").write_text(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
