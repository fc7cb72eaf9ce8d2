"""Throughput of skygen's sample streams: samples/s per core and with all cores, both kinds.

    python benchmarks/stream_bench.py [--detections 50000] [--frames 200] [--batch 1024]

Per core: one process, reported both per wall-clock second and per CPU-second of that
process (the CPU-second figure is what one core delivers when the machine is shared).
All cores: one process per core, each making its own disjoint part of the stream
(``skygen.stream.partition``), wall clock of the slowest. Default camera, corruptions at
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


def _run(kind: str, n: int, batch: int, rank: int, world: int) -> tuple[float, float, int]:
    from skygen.config import load_config
    from skygen.stream import SampleStream
    s = SampleStream(load_config(), kind)
    if kind == "detections":
        s.batch(np.arange(batch) + 10**9)              # warm-up (caches, first allocation)
    else:
        s.frame(10**9)
    t0, c0 = time.perf_counter(), time.process_time()
    made = 0
    if kind == "detections":
        for a in range(rank * batch, n, world * batch):
            made += len(s.batch(np.arange(a, min(a + batch, n))))
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
        return {"kind": kind, "workers": 1, "samples": made, "wall_s": wall, "per_s": made / wall,
                "per_cpu_s": made / cpu, "ms_per_sample_core": 1000 * cpu / made}
    with mp.get_context("fork").Pool(workers) as pool:
        t0 = time.perf_counter()
        res = pool.map(_worker, [(kind, n, batch, r, workers) for r in range(workers)])
        wall = time.perf_counter() - t0
    made = sum(r[2] for r in res)
    cpu = sum(r[1] for r in res)
    return {"kind": kind, "workers": workers, "samples": made, "wall_s": wall, "per_s": made / wall,
            "per_cpu_s": made / cpu, "ms_per_sample_core": 1000 * cpu / made}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--detections", type=int, default=50000, help="samples of the detections stream")
    p.add_argument("--frames", type=int, default=200, help="samples of the frames stream")
    p.add_argument("--batch", type=int, default=1024, help="detections per vectorised batch")
    p.add_argument("--workers", type=int, default=len(os.sched_getaffinity(0)), help="processes for 'all cores'")
    p.add_argument("--write", action="store_true", help="write results/skygen/stream_bench.{json,md}")
    a = p.parse_args(argv)
    rows = []
    for kind, n in (("detections", a.detections), ("frames", a.frames)):
        rows.append(measure(kind, n, a.batch, 1))
        if a.workers > 1:
            rows.append(measure(kind, n, a.batch, a.workers))
    host = f"{platform.machine()}{(' ' + platform.processor()) if platform.processor() else ''}, {os.cpu_count()} logical CPUs"
    lines = [f"stream throughput ({host}; default camera, corruptions at defaults)", "",
             "| kind | processes | samples | samples/s (wall) | samples per CPU-second | ms per sample per core |",
             "|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['kind']} | {r['workers']} | {r['samples']} | {r['per_s']:,.0f} | {r['per_cpu_s']:,.0f} | "
                     f"{r['ms_per_sample_core']:.3f} |")
    text = "\n".join(lines)
    print(text)
    if a.write:
        out = Path(__file__).resolve().parents[1] / "results" / "skygen"
        out.mkdir(parents=True, exist_ok=True)
        (out / "stream_bench.json").write_text(json.dumps({"host": host, "rows": rows}, indent=2))
        (out / "stream_bench.md").write_text(text + "\n\nCommand: `python benchmarks/stream_bench.py --write`\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
