"""Training samples/s of a preset's loader with the model taken out: the batches alone.

    python benchmarks/loader_bench.py --data DATA [--config configs/paper.yaml] [--workers 0 1 2]
        [--batches 100] [--device cuda] [--out FILE.json] [key=value ...]

    e.g. the paper preset on the shards' training frames, every augmentation on:
    python benchmarks/loader_bench.py --data data/demo --workers 0 1 2 --batches 25 stream.kind=none

Each row: the run's own training loader (``fusion.train.run.train_loader``: the preset's stream or
shards, in ``train.workers`` DataLoader processes), iterated for ``--batches`` batches after
``2 * workers + 2`` untimed ones (the processes' start and the prefetch queue), each batch moved to
``--device`` as the training loop moves it (``batch_inputs``, then a synchronise). Reported: samples/s,
megabytes per batch crossing from the loader processes, and the milliseconds the training process
itself spends per batch (waiting for it, and copying it to the device). With
``benchmarks/train_step_bench.py`` (the step without the loader) and a run's samples/s (metrics.csv)
it tells which half limits a training run. Prints one Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch

from fusion.config import load_config
from fusion.model.inference import batch_inputs
from fusion.train.data import prepare_data
from fusion.train.distributed import DistInfo
from fusion.train.run import train_loader


def bench(
    cfg_path: str, data: str, overrides: tuple[str, ...], workers: int, batches: int, device: torch.device
) -> dict:
    warm = 2 * workers + 2
    base = [f"data.path={data}", f"train.workers={workers}", "train.progress=false"]
    steps = warm + batches
    batch = load_config(cfg_path, overrides=[*base, *overrides]).train.batch_size
    cfg = load_config(cfg_path, overrides=[*base, f"stream.samples_per_epoch={steps * batch}", *overrides])
    prepared = prepare_data(cfg)
    loader = train_loader(cfg, prepared, DistInfo(), device, lambda *a, **k: None)
    if hasattr(loader.dataset, "set_epoch"):
        loader.dataset.set_epoch(0)
    wait = copy = 0.0
    n = nbytes = 0
    t_start = time.perf_counter()
    it = iter(loader)
    for i in range(steps):
        if i == warm:
            t0, wait, copy, n, nbytes = time.perf_counter(), 0.0, 0.0, 0, 0
        a = time.perf_counter()
        try:
            batch = next(it)
        except StopIteration:
            break
        b = time.perf_counter()
        batch_inputs(batch, device)
        if device.type == "cuda":
            torch.cuda.synchronize()
        c = time.perf_counter()
        wait, copy = wait + (b - a), copy + (c - b)
        n += len(batch["label"])
        nbytes += sum(v.numel() * v.element_size() for v in batch.values() if isinstance(v, torch.Tensor))
    t = time.perf_counter() - t0
    k = max(1, n // cfg.train.batch_size)
    return {
        "stream": "shards" if cfg.stream.kind == "none" else cfg.stream.kind,
        "workers": workers,
        "batch": cfg.train.batch_size,
        "samples": n,
        "samples_per_s": n / t,
        "mb_per_batch": nbytes / k / 1e6,
        "wait_ms": 1e3 * wait / k,
        "copy_ms": 1e3 * copy / k,
        "first_batches_s": t0 - t_start,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="skygen dataset folder (its config drives the stream)")
    ap.add_argument("--config", default="configs/paper.yaml", help="training preset (default configs/paper.yaml)")
    ap.add_argument(
        "--workers",
        type=int,
        nargs="+",
        default=[max(1, (os.cpu_count() or 2) - 1)],
        help="DataLoader process counts, one row each (default: all cores but one)",
    )
    ap.add_argument("--batches", type=int, default=100, help="timed batches per row")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--out", default=None, help="also write the rows as JSON")
    ap.add_argument("overrides", nargs="*", help="config overrides, e.g. stream.kind=detections")
    a = ap.parse_args(argv)
    device = torch.device(a.device)
    rows = [bench(a.config, a.data, tuple(a.overrides), w, a.batches, device) for w in a.workers]
    name = torch.cuda.get_device_name(0) if device.type == "cuda" else "cpu"
    print(
        f"# training loader alone: {a.config} {' '.join(a.overrides)} to {name}, "
        f"{os.cpu_count()} logical CPUs, torch {torch.__version__}\n"
    )
    print(
        "| stream | loader processes | batch | samples/s | MB per batch | wait ms/batch | to-device ms/batch | first "
        "batches (s) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['stream']} | {r['workers']} | {r['batch']} | {r['samples_per_s']:,.0f} | {r['mb_per_batch']:.1f} "
            f"| {r['wait_ms']:.1f} | {r['copy_ms']:.1f} | {r['first_batches_s']:.1f} |"
        )
    if a.out:
        with open(a.out, "w") as f:
            json.dump(
                {
                    "rows": rows,
                    "device": name,
                    "torch": torch.__version__,
                    "config": a.config,
                    "overrides": a.overrides,
                    "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
                },
                f,
                indent=2,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
