"""Where do the pixels help? Score checkpoints on frames cut to their brightest N detections.

    python benchmarks/few_star_pixels.py --data data/eval2k \\
        --checkpoint geometry=runs/geo/best.pt image=runs/image/best.pt fusion=runs/fusion/best.pt \\
        [--brightest 3,4,5,6,10] [--split test] [--out results/image]

For every N each checkpoint is evaluated with ``fusion evaluate --brightest N`` (each frame keeps
its brightest N detections, the image is left as it is), and the split's frames are counted:
``detected`` (detections per frame), ``beyond N`` (true stars the image still shows beyond the
N kept detections: a peak of the peak-set front end (fusion.model.networks.PeakSet, 5 sigma,
one-pixel spikes dropped) within one stored pixel of a true star that is not among the kept
detections) and ``below threshold`` (the same, for true stars the detector never reported: the
faint stars only the pixels hold). Prints one Markdown table, writes it and the raw JSON
under ``--out``. The hardware is named in the output.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from pathlib import Path

import numpy as np


def star_counts(data: str, split: str, ns: list[int], max_frames: int | None = None) -> dict:
    """Per N: mean detections, image-visible true stars beyond the N kept detections, and those never detected."""
    import torch

    from fusion.config import DataConfig
    from fusion.model.inputs import Preprocessor
    from fusion.model.networks import PeakSet
    from fusion.model.shards import split_positions
    from skygen.datasets.shards import open_dataset

    with open_dataset(data) as ds:
        pre = Preprocessor.from_configs(ds.config, DataConfig())
        g = pre.geo
        pos = split_positions(ds, split, max_frames)
        peaks = PeakSet(256, threshold=5.0)
        beyond = {n: [] for n in ns}
        below, detected = [], []
        for i in pos:
            i = int(i)
            det, true = ds.detections(i), ds.true_stars(i)
            img = torch.from_numpy(pre.image(ds.image(i)))[None, None]
            with torch.no_grad():
                rows, mask = peaks.peaks(img)
            px = rows[0, mask[0], :2].numpy()
            tx, ty = g.normalised(true["x_px"], true["y_px"])  # the coordinate branch's convention
            if len(px) and len(tx):
                d = np.hypot(tx[:, None] - px[None, :, 0], ty[:, None] - px[None, :, 1]).min(1)
                seen = d < 2.0 / g.image_px  # within one stored pixel
            else:
                seen = np.zeros(len(tx), bool)
            order = np.argsort(-np.asarray(det["flux_adu"]), kind="stable")
            det_hip = np.asarray(det["hip_id"])[order]
            detected.append(len(order))
            below.append(int((seen & ~np.isin(true["hip_id"], det_hip)).sum()))
            for n in ns:
                beyond[n].append(int((seen & ~np.isin(true["hip_id"], det_hip[:n])).sum()))
    return {
        "frames": len(pos),
        "detected_mean": float(np.mean(detected)),
        "below_threshold_mean": float(np.mean(below)),
        "beyond_n_mean": {n: float(np.mean(v)) for n, v in beyond.items()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="skygen dataset (its --split is scored)")
    ap.add_argument("--checkpoint", nargs="+", required=True, metavar="NAME=PATH", help="named checkpoints")
    ap.add_argument("--brightest", default="3,4,5,6,10", help="comma-separated N (default 3,4,5,6,10)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--out", default=None, help="folder for few-star.md/.json")
    args = ap.parse_args()
    from fusion.measure.evaluate import evaluate_checkpoint

    ns = [int(x) for x in args.brightest.split(",")]
    named = dict(c.split("=", 1) for c in args.checkpoint)
    counts = star_counts(args.data, args.split, ns, args.max_frames)
    scores: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, path in named.items():
            for n in [None, *ns]:
                r = evaluate_checkpoint(
                    path,
                    args.data,
                    args.split,
                    Path(tmp) / name,
                    keep_brightest=n,
                    max_frames=args.max_frames,
                    log=lambda *a: None,
                )
                scores.setdefault(name, {})["all" if n is None else n] = {
                    "top1": r["top1"],
                    "top5": r["top5"],
                    "median_deg": r["angular_error"]["median_deg"],
                }
    cpu = platform.processor() or platform.machine()
    lines = [
        f"Frames of `{args.data}` ({args.split}, {counts['frames']} frames; {counts['detected_mean']:.1f} "
        f"detections and {counts['below_threshold_mean']:.1f} image-visible undetected stars per frame), cut to "
        f"their brightest N detections, the image untouched; top-1 at K = 15 (top-5 in brackets). "
        f"CPU: {cpu}, {os.cpu_count()} cores.",
        "",
        "| N | stars the image shows beyond the N | " + " | ".join(named) + " |",
        "|---|---|" + "---|" * len(named),
    ]
    for n in ["all", *ns]:
        extra = "" if n == "all" else f"{counts['beyond_n_mean'][n]:.1f}"
        cells = [f"{100 * scores[k][n]['top1']:.1f} % ({100 * scores[k][n]['top5']:.1f})" for k in named]
        lines.append(f"| {n} | {extra} | " + " | ".join(cells) + " |")
    text = "\n".join(lines)
    print(text)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "few-star.md").write_text(text + "\n")
        (out / "few-star.json").write_text(
            json.dumps(
                {
                    "data": args.data,
                    "split": args.split,
                    "counts": counts,
                    "checkpoints": named,
                    "scores": scores,
                    "cpu": cpu,
                    "cores": os.cpu_count(),
                },
                indent=2,
                default=str,
            )
            + "\n"
        )


if __name__ == "__main__":
    main()
