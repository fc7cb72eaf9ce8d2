"""Throughput of skygen's sample streams: samples/s per core and with all cores.

    python benchmarks/stream_bench.py [--detections 50000] [--frames 200] [--binned 2000] [--batch 1024]

Rows: ``detections`` (emulated detection sets, batches of --batch); ``frames (full)`` (every
sensor pixel rendered, area-averaged to the stored size, real detector: the frames stream's
``frames_renderer="full"``); ``frames (binned)`` (the frames stream's default: the stored image
drawn directly by skygen.render.binned plus emulated detections, batches of --frames-batch, the
size a training step asks for).

Per core: one process, reported both per wall-clock second and per CPU-second of that
process (the CPU-second figure is what one core delivers when the machine is shared).
All cores: one process per core, each making its own disjoint part of the stream
(``skygen.stream.samples.partition``), wall clock of the slowest. Default camera, corruptions at
their defaults. Writes results/skygen/stream_bench.{json,md} with --write.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import time
from pathlib import Path

import numpy as np

ROWS = {
    "detections": ("detections", None),
    "frames (full)": ("frames", "full"),
    "frames (binned)": ("frames", "binned"),
}


def _run(row: str, n: int, batch: int, rank: int, world: int) -> tuple[float, float, int]:
    from skygen.config import load_config
    from skygen.stream.samples import SampleStream

    kind, renderer = ROWS[row]
    s = SampleStream(load_config(), kind, frames_renderer=renderer or "binned")
    if kind == "detections":
        s.batch(np.arange(batch) + 10**9)  # warm-up (caches, first allocation, JIT)
    else:
        s.frames_batch(np.arange(4) + 10**9)
    t0, c0 = time.perf_counter(), time.process_time()
    made = 0
    if kind == "detections" or renderer == "binned":
        step = s.batch if kind == "detections" else s.frames_batch
        for a in range(rank * batch, n, world * batch):
            out = step(np.arange(a, min(a + batch, n)))
            made += len(out if kind == "detections" else out[0])
    else:
        for i in range(rank, n, world):
            s.frame(i)
            made += 1
    return time.perf_counter() - t0, time.process_time() - c0, made


def _worker(args):
    return _run(*args)


def measure(kind: str, n: int, batch: int, workers: int) -> dict:
    if workers == 1:
        wall, cpu, made = _run(kind, n, batch, 0, 1)
        return {
            "kind": kind,
            "workers": 1,
            "samples": made,
            "wall_s": wall,
            "per_s": made / wall,
            "per_cpu_s": made / cpu,
            "ms_per_sample_core": 1000 * cpu / made,
        }
    with mp.get_context("fork").Pool(workers) as pool:
        t0 = time.perf_counter()
        res = pool.map(_worker, [(kind, n, batch, r, workers) for r in range(workers)])
        wall = time.perf_counter() - t0
    made = sum(r[2] for r in res)
    cpu = sum(r[1] for r in res)
    return {
        "kind": kind,
        "workers": workers,
        "samples": made,
        "wall_s": wall,
        "per_s": made / wall,
        "per_cpu_s": made / cpu,
        "ms_per_sample_core": 1000 * cpu / made,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--detections", type=int, default=50000, help="samples of the detections stream")
    p.add_argument("--frames", type=int, default=200, help="samples of the frames stream, full renderer")
    p.add_argument("--binned", type=int, default=2000, help="samples of the frames stream, binned renderer")
    p.add_argument("--batch", type=int, default=1024, help="detections per vectorised batch")
    p.add_argument("--frames-batch", type=int, default=64, help="binned frames per batch (a training step's)")
    p.add_argument("--workers", type=int, default=len(os.sched_getaffinity(0)), help="processes for 'all cores'")
    p.add_argument("--write", action="store_true", help="write results/skygen/stream_bench.{json,md}")
    a = p.parse_args(argv)
    load_before = os.getloadavg()[0]
    rows = []
    for row, n, batch in (
        ("detections", a.detections, a.batch),
        ("frames (full)", a.frames, 1),
        ("frames (binned)", a.binned, a.frames_batch),
    ):
        if n <= 0:
            continue
        rows.append(measure(row, n, batch, 1))
        if a.workers > 1:
            rows.append(measure(row, n, batch, a.workers))
    host = (
        f"{platform.machine()}{(' ' + platform.processor()) if platform.processor() else ''}, {os.cpu_count()} "
        "logical CPUs"
    )
    threads = os.environ.get("OMP_NUM_THREADS", "unset")
    load = (load_before, os.getloadavg()[0])
    lines = [
        f"stream throughput ({host}; OMP_NUM_THREADS={threads}; default camera 1024² stored at 256², "
        f"corruptions at defaults; 1-min load average {load[0]:.1f} before, {load[1]:.1f} after: "
        "other work shares the CPUs when it exceeds the processes used here)",
        "",
        "| kind | processes | samples | samples/s (wall) | samples per CPU-second | ms per sample per core |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['kind']} | {r['workers']} | {r['samples']} | {r['per_s']:,.0f} | {r['per_cpu_s']:,.0f} | "
            f"{r['ms_per_sample_core']:.3f} |"
        )
    text = "\n".join(lines)
    print(text)
    if a.write:
        out = Path(__file__).resolve().parents[1] / "results" / "skygen"
        out.mkdir(parents=True, exist_ok=True)
        (out / "stream_bench.json").write_text(
            json.dumps({"host": host, "load_average_1min": load, "rows": rows}, indent=2)
        )
        (out / "stream_bench.md").write_text(
            text + "\n\nCommand: `OMP_NUM_THREADS=1 python benchmarks/stream_bench.py --write`\n"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
