"""Throughput of fusion's full input pipeline, per DataLoader worker count.

Measures samples/s of: shard read (image + detections through skygen's reader) ->
augmentation (all paper augmentations on) -> normalisation and coordinate rows ->
collation -> transfer to the device -> heatmap rasterisation on the device. The first
batches of each setting (worker start-up) are not timed.

    python benchmarks/loader_bench.py --data data/sky --workers 0 1 2 4

Prints one Markdown table; name the machine when you quote it.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from fusion.config import AugConfig  # noqa: E402
from fusion.model.shards import FrameDataset, make_loader, split_positions  # noqa: E402
from fusion.model.heatmap import rasterise  # noqa: E402
from skygen.datasets.shards import open_dataset  # noqa: E402


def bench(ds, workers: int, batch_size: int, batches: int, warmup: int, aug: bool, device: torch.device,
          max_stars: int, start_method: str | None) -> dict:
    pos = split_positions(ds, "train")
    fd = FrameDataset(ds, pos, np.zeros(len(pos), np.int64), max_stars=max_stars,
                      aug=AugConfig() if aug else None, seed=0)
    loader = make_loader(fd, batch_size, shuffle=True, seed=0, workers=workers, start_method=start_method,
                         pin_memory=device.type == "cuda")
    it = iter(loader)
    n, t0 = 0, None
    for b in range(warmup + batches):
        if b == warmup:
            if device.type == "cuda":
                torch.cuda.synchronize()
            t0, n = time.perf_counter(), 0
        try:
            batch = next(it)
        except StopIteration:      # a short split: start the next epoch
            loader.sampler.set_epoch(loader.sampler.epoch + 1)
            it = iter(loader)
            batch = next(it)
        coords = batch["coords"].to(device, non_blocking=True)
        mask = batch["mask"].to(device, non_blocking=True)
        batch["image"].to(device, non_blocking=True)
        rasterise(coords, mask, 64, 1.0)
        n += len(batch["label"])
    if device.type == "cuda":
        torch.cuda.synchronize()
    dt = time.perf_counter() - t0
    del it, loader
    return {"workers": workers, "samples": n, "seconds": dt, "samples_per_s": n / dt}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="skygen dataset folder")
    p.add_argument("--workers", type=int, nargs="+", default=[0, 1, 2, 4])
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--batches", type=int, default=30, help="timed batches per setting")
    p.add_argument("--warmup", type=int, default=3, help="untimed batches per setting")
    p.add_argument("--max-stars", type=int, default=6)
    p.add_argument("--no-aug", action="store_true", help="measure without augmentations")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--start-method", choices=("fork", "spawn", "forkserver"))
    args = p.parse_args(argv)
    device = torch.device(args.device)
    with open_dataset(args.data) as ds:
        print(f"dataset {args.data}: {len(ds)} frames, images {ds.image_shape}, augment {not args.no_aug}, "
              f"batch {args.batch_size}, device {device}")
        print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
              f"torch {torch.__version__}")
        print()
        print("| workers | samples/s | samples | seconds |")
        print("|---|---|---|---|")
        for w in args.workers:
            r = bench(ds, w, args.batch_size, args.batches, args.warmup, not args.no_aug, device, args.max_stars,
                      args.start_method)
            print(f"| {r['workers']} | {r['samples_per_s']:.0f} | {r['samples']} | {r['seconds']:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
