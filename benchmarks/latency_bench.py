"""Latency of the paper's Star-Fusion and the CPU preset: forward pass and end to end, one table.

    python benchmarks/latency_bench.py [--device cpu] [--precision fp32] [--batch 1] [--iters 100]
                                       [--out-dir results/timing]

Runs :func:`fusion.timing.run_timing` (what ``fusion timing`` runs) for each model, writes
each report as ``<out-dir>/<device>_<model>_<precision>_b<batch>.json`` and prints one
Markdown table. Models: ``star_fusion`` (the default config: SwinV2-T image branch, 256 x 256)
and ``cpu-preset`` (``configs/cpu.yaml``), both with random weights: latency does not depend
on them. Raw frames for the end-to-end mode come from skygen's default 1024 x 1024 camera.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fusion.measure.timing import run_timing
from skygen.runtime import write_json

ROOT = Path(__file__).resolve().parent.parent
MODELS = {"star_fusion": None, "cpu-preset": ROOT / "configs" / "cpu.yaml"}


def row(name: str, r: dict) -> str:
    e, f, p = r["end2end"], r["flops"], r["parameters"]
    st = e["stages"]
    pre = st["detect"]["median_ms"] + st["downsample_normalise"]["median_ms"] + st["encode_coords"]["median_ms"]
    return (
        f"| {name} | {p['total'] / 1e6:.2f} | {f['per_image_gflops']:.3f} / {f['per_image_gmacs']:.3f} | "
        f"{r['forward']['median_ms']:.2f} | {r['forward']['p99_ms']:.2f} | {e['total']['median_ms']:.2f} | "
        f"{pre:.2f} | {st['forward']['median_ms']:.2f} |"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--precision", default="fp32", choices=("fp32", "fp16", "bf16"))
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--iters", type=int, default=100)
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--models", default=",".join(MODELS), help=f"comma-separated subset of {', '.join(MODELS)}")
    ap.add_argument("--out-dir", default=str(ROOT / "results" / "timing"))
    args = ap.parse_args(argv)
    lines = [
        "| model | params (M) | GFLOPs / GMACs per image | forward median (ms) | forward p99 (ms) | "
        "end-to-end median (ms) | preprocessing (ms) | e2e forward (ms) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    hw = None
    for name in args.models.split(","):
        r = run_timing(
            config=MODELS[name],
            device=args.device,
            precision=args.precision,
            batch=args.batch,
            iters=args.iters,
            warmup=args.warmup,
            mode="both",
        )
        out = Path(args.out_dir) / f"{args.device}_{name}_{args.precision}_b{args.batch}.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        write_json(out, r)
        lines.append(row(name, r))
        hw = r["hardware"]
    print(
        f"{hw['device_name']} ({hw['usable_cores']} cores, torch {hw['torch']}, {hw['torch_threads']} threads), "
        f"{args.precision}, batch {args.batch}, {args.iters} iterations; preprocessing = detection + "
        "downsample/normalise + coordinate encoding of one 1024 x 1024 frame"
    )
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
