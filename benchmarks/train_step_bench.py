"""Training samples/s of a preset's model with the loader taken out: the training step alone.

    python benchmarks/train_step_bench.py [--config configs/paper.yaml] [--batch-sizes 64,256]
        [--device cuda] [--amp auto] [--steps 30] [--deterministic] [--out FILE.json] [key=value ...]

Each row: one batch of random inputs of the right shapes (``fusion.measure.timing.random_inputs``)
put on the device once, then ``--steps`` timed steps of the real training code
(``fusion.train.loop.train_one_epoch``: autocast, focal loss, backward, AdamW, schedule, its
once-per-step host sync) after 5 untimed ones. ``--deterministic`` sets torch's deterministic
algorithms as ``fusion train`` does by default (``train.deterministic``); without it they are off. Compare with a run's
``samples/s`` (metrics.csv)
to tell whether the device or the loader limits a training run. Prints one Markdown table.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from fusion.measure.timing import load_timed_model, random_inputs
from fusion.model.inference import autocast_dtype
from fusion.train.loop import WarmupCosine, build_optimizer, train_one_epoch
from fusion.train.losses import FocalLoss


def bench(cfg_path: str, overrides: tuple[str, ...], batch: int, device: torch.device, amp: str, steps: int) -> dict:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    tm = load_timed_model(config=cfg_path, overrides=overrides)
    model = tm.model.to(device).train()
    cfg = tm.cfg
    image, coords, mask = random_inputs(batch, tm.image_size, tm.max_stars, torch.device("cpu"), torch.float32)
    label = torch.randint(0, tm.num_classes, (batch,), generator=torch.Generator().manual_seed(0))
    item = {"coords": coords, "mask": mask, "label": label}
    if cfg.model.branches.image:
        item["image"] = image
    opt = build_optimizer(model, cfg.optim.lr, tuple(cfg.optim.betas), cfg.optim.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, WarmupCosine(1, 10 * steps, 0.01))
    dtype = autocast_dtype(amp, device)
    scaler = torch.amp.GradScaler(device.type, enabled=dtype == torch.float16)
    loss = FocalLoss(None, cfg.loss.gamma).to(device)
    on_dev = {k: (v if k == "label" else v.to(device)) for k, v in item.items()}  # the loop compares labels on the host

    def run(n: int) -> float:
        r = train_one_epoch(model, [on_dev] * n, loss, opt, sched, scaler, device, amp_dtype=dtype)
        return r["time_s"]

    run(5)
    if device.type == "cuda":
        torch.cuda.synchronize()
    t = run(steps)
    return {
        "model": cfg.model.name,
        "batch": batch,
        "amp": str(dtype).replace("torch.", "") if dtype else "fp32",
        "step_ms": 1e3 * t / steps,
        "samples_per_s": batch * steps / t,
        "peak_mem_gib": (torch.cuda.max_memory_allocated() / 2**30) if device.type == "cuda" else None,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="configs/paper.yaml")
    ap.add_argument("--batch-sizes", default="64,256")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--amp", default="auto", choices=("auto", "bf16", "fp16", "off"))
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument(
        "--deterministic",
        action="store_true",
        help="torch deterministic algorithms, as fusion train sets them (train.deterministic)",
    )
    ap.add_argument("--out", default=None, help="also write the rows as JSON")
    ap.add_argument("overrides", nargs="*", help="config overrides, e.g. model.name=swinv2_tiny")
    a = ap.parse_args(argv)
    device = torch.device(a.device)
    if a.deterministic:  # as fusion.train.run.setup_torch, before the first cuBLAS call
        import os

        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
        torch.backends.cudnn.benchmark = False
    rows = [bench(a.config, tuple(a.overrides), int(b), device, a.amp, a.steps) for b in a.batch_sizes.split(",")]
    name = torch.cuda.get_device_name(0) if device.type == "cuda" else "cpu"
    det = ", deterministic algorithms" if a.deterministic else ""
    print(f"# training step alone: {a.config} {' '.join(a.overrides)} on {name}, torch {torch.__version__}{det}\n")
    print("| model | batch | precision | step ms | samples/s | peak GPU memory (GiB) |")
    print("|---|---:|---|---:|---:|---:|")
    for r in rows:
        mem = f"{r['peak_mem_gib']:.1f}" if r["peak_mem_gib"] is not None else "—"
        print(f"| {r['model']} | {r['batch']} | {r['amp']} | {r['step_ms']:.1f} | {r['samples_per_s']:.0f} | {mem} |")
    if a.out:
        with open(a.out, "w") as f:
            json.dump(
                {
                    "rows": rows,
                    "device": name,
                    "torch": torch.__version__,
                    "config": a.config,
                    "overrides": a.overrides,
                    "deterministic": a.deterministic,
                    "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
                },
                f,
                indent=2,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
