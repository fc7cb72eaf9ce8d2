"""Render speed of the default camera: per-stage time and whole-pipeline frames/s.

    python benchmarks/render_bench.py [--frames 300] [--workers 1,2] [--set key=value ...]

Prints one Markdown table (and writes it with --out FILE.json). Stage times come from
one process rendering frames back to back; the pipeline rows run ``render_dataset``
end to end (render, detect, 256x256 downsample, gzip-4 HDF5 shards, sha256, manifest)
with 1 and with all workers. Reference figures for other simulators on this machine
(one 1024x1024 frame, ~28 stars, one core, from SPEC.md): LOST 31 ms, GalSim 84 ms.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from skygen.config import load_config
from skygen.datasets.build import render_dataset
from skygen.instrument import corruptions as corr
from skygen.instrument.detect import detect
from skygen.instrument.sensor import Exposure, read_out
from skygen.render.frame import Renderer
from skygen.sky.attitude import attitude_matrix, sample_boresight


def stage_times(cfg, n: int) -> dict:
    r = Renderer(cfg)
    t = {
        k: 0.0
        for k in (
            "scene: attitude + catalog cone + projection",
            "optics: PSF stamps",
            "sensor: noise, defects, ADC",
            "detection + matching",
            "downsample 1024->256",
        )
    }
    keys = list(t)
    sh = (cfg.camera.height_px, cfg.camera.width_px)
    for i in range(n):
        t0 = time.perf_counter()
        ra, dec, roll = sample_boresight(cfg.attitude, i, corr.stage_rng(cfg.seed, i, "attitude"))
        omega, _, taus = r.motion_path(corr.stage_rng(cfg.seed, i, "motion_blur"))
        stars = r.visible_stars(attitude_matrix(ra, dec, roll), omega, taus)
        t1 = time.perf_counter()
        star_e = np.zeros(sh, np.float32)
        boxes = r.deposit(stars, star_e)
        t2 = time.perf_counter()
        full, _ = read_out(
            Exposure(star_e, None, boxes, r.background_e), cfg.sensor, r.maps, corr.stage_rng(cfg.seed, i, "noise")
        )
        t3 = time.perf_counter()
        det, _, _ = detect(full, cfg.detection.threshold_sigma, cfg.detection.min_area_px)
        t4 = time.perf_counter()
        cv2.resize(full, (sh[1] // r.factor, sh[0] // r.factor), interpolation=cv2.INTER_AREA)
        t5 = time.perf_counter()
        for k, a, b in zip(keys, (t0, t1, t2, t3, t4), (t1, t2, t3, t4, t5)):
            t[k] += b - a
    t0 = time.perf_counter()
    for i in range(n):
        r.render(i)
    t["render(i), all stages (incl. corruptions, bookkeeping)"] = time.perf_counter() - t0
    return {k: 1e3 * v / n for k, v in t.items()}


def pipeline(cfg, workers: int) -> float:
    out = Path(tempfile.mkdtemp(prefix="skygen-bench-"))
    try:
        t0 = time.perf_counter()
        render_dataset(cfg, out, workers=workers, progress=False)
        return time.perf_counter() - t0
    finally:
        shutil.rmtree(out, ignore_errors=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--workers", default=f"1,{os.cpu_count()}")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--out", help="also write the results as JSON")
    a = ap.parse_args(argv)
    cv2.setNumThreads(1)
    cfg = load_config(overrides=a.set + [f"n_frames={a.frames}", f"output.shard_size={max(1, a.frames // 4)}"])
    stages = stage_times(cfg, min(a.frames, 200))
    runs = {}
    for w in sorted({int(x) for x in a.workers.split(",")}):
        pipeline(cfg, w) if not runs else None  # warm the page cache and imports once
        sec = pipeline(cfg, w)
        runs[w] = {"seconds": sec, "frames_per_s": a.frames / sec, "ms_per_frame_per_core": 1e3 * sec * w / a.frames}
    cpu = platform.processor() or platform.machine()
    print(
        f"# skygen render benchmark — {os.cpu_count()} cores ({cpu}), {platform.python_version()}, "
        f"{a.frames} frames of {cfg.camera.width_px}x{cfg.camera.height_px}, default physics\n"
    )
    print("| stage (one core) | ms/frame |\n|---|---:|")
    for k, v in stages.items():
        print(f"| {k} | {v:.2f} |")
    print(
        "\n| pipeline: render_dataset (render + detect + store + gzip + sha256) | frames/s | ms/frame/core | 50,000 "
        "frames |"
    )
    print("|---|---:|---:|---:|")
    for w, r in runs.items():
        print(
            f"| {w} worker(s) | {r['frames_per_s']:.1f} | {r['ms_per_frame_per_core']:.1f} | "
            f"{50000 / r['frames_per_s'] / 60:.1f} min |"
        )
    if a.out:
        Path(a.out).write_text(
            json.dumps(
                {
                    "stages_ms": stages,
                    "pipeline": runs,
                    "frames": a.frames,
                    "cores": os.cpu_count(),
                    "overrides": a.set,
                },
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
