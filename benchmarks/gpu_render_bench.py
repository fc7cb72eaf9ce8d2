"""Frames/s of the NumPy and torch renderers: 1024x1024 frames at default physics, stored at 256x256.

    python benchmarks/gpu_render_bench.py [--frames 64] [--batch-sizes 1,8,32] [--devices cpu,cuda]
                                          [--threads N] [--set key=value ...] [--out FILE.json]

Prints one Markdown table. Each row renders ``--frames`` frames (after one warm-up batch)
to the stored-size image, without detection or storage:

* ``scene`` — the host part, the same for both backends (:meth:`Renderer.scene`:
  attitude, catalog cone, projection, photometry, cosmic-ray and other corruption draws),
  ms per frame on one host thread;
* ``raster`` — star light, noise, ADC and the area average: NumPy per frame
  (:meth:`Renderer.rasterise` + ``cv2`` INTER_AREA), torch per batch on the device (with a
  CUDA synchronise before the clock stops);
* ``frames/s (scene + raster)`` — one host process doing both, back to back;
* ``frames/s (raster only)`` — the device's rate when scenes come from other host
  processes (DataLoader workers), i.e. what a GPU can deliver if the host keeps up.

A device that is not available prints its rows as "pending a GPU" (nothing is guessed).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import cv2
import torch

from skygen.config import load_config
from skygen.render.frame import Renderer


def bench_numpy(cfg, frames: int) -> dict:
    r = Renderer(cfg)
    r.downsample(r.rasterise(r.scene(0))[0])  # warm-up (LUTs, caches)
    t_scene = t_raster = 0.0
    for i in range(frames):
        t0 = time.perf_counter()
        sc = r.scene(i)
        t1 = time.perf_counter()
        r.downsample(r.rasterise(sc)[0])
        t_scene += t1 - t0
        t_raster += time.perf_counter() - t1
    return _row("numpy", "cpu", 1, frames, t_scene, t_raster)


def bench_torch(cfg, device: str, batch: int, frames: int) -> dict:
    from skygen.render.torch_frames import TorchRenderer

    tr = TorchRenderer(cfg, device)
    sync = torch.cuda.synchronize if tr.device.type == "cuda" else (lambda: None)
    g = torch.Generator(device=tr.device)
    g.manual_seed(0)
    tr.rasterise(tr.scenes(range(batch)), g)  # warm-up
    sync()
    t_scene = t_raster = 0.0
    done = 0
    while done < frames:
        idx = range(done, done + batch)
        t0 = time.perf_counter()
        scenes = tr.scenes(idx)
        t1 = time.perf_counter()
        tr.rasterise(scenes, g)
        sync()
        t_scene += t1 - t0
        t_raster += time.perf_counter() - t1
        done += batch
    return _row("torch", device, batch, done, t_scene, t_raster)


def _row(backend: str, device: str, batch: int, n: int, t_scene: float, t_raster: float) -> dict:
    return {
        "backend": backend,
        "device": device,
        "batch": batch,
        "frames": n,
        "scene_ms": 1e3 * t_scene / n,
        "raster_ms": 1e3 * t_raster / n,
        "fps_total": n / (t_scene + t_raster),
        "fps_raster": n / t_raster,
    }


def device_name(device: str) -> str:
    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    return f"{os.cpu_count()}-core {platform.processor() or platform.machine()}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=64, help="frames per row (rounded up to whole batches)")
    ap.add_argument("--batch-sizes", default="1,8,32", help="torch batch sizes, comma-separated")
    ap.add_argument(
        "--devices",
        default="cpu,cuda",
        help="torch devices to try (cuda rows print 'pending a GPU' when no CUDA device is available)",
    )
    ap.add_argument("--threads", type=int, help="torch CPU threads (default: torch's own choice)")
    ap.add_argument("--set", action="append", default=[], help="config override, e.g. sensor.sampler=exact")
    ap.add_argument("--out", help="also write the rows as JSON")
    a = ap.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    cv2.setNumThreads(1)
    cfg = load_config(overrides=a.set)
    batches = [int(b) for b in a.batch_sizes.split(",")]
    rows = [bench_numpy(cfg, a.frames)]
    pending = []
    for dev in a.devices.split(","):
        if dev.startswith("cuda") and not torch.cuda.is_available():
            pending += [("torch", dev, b) for b in batches]
            continue
        rows += [bench_torch(cfg, dev, b, a.frames) for b in batches]
    print(
        f"# render throughput — {cfg.camera.width_px}x{cfg.camera.height_px} frames stored at "
        f"{cfg.output.image_size_px}x{cfg.output.image_size_px}, sampler {cfg.sensor.sampler}, "
        f"torch {torch.__version__} ({torch.get_num_threads()} CPU threads), {platform.python_version()}"
        f"{', overrides ' + ' '.join(a.set) if a.set else ''}\n"
    )
    print(
        "| backend | device | batch | scene ms/frame (host) | raster ms/frame | frames/s (scene + raster) "
        "| frames/s (raster only) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['backend']} | {r['device']} ({device_name(r['device'])}) | {r['batch']} | {r['scene_ms']:.2f} | "
            f"{r['raster_ms']:.2f} | {r['fps_total']:.1f} | {r['fps_raster']:.1f} |"
        )
    for backend, dev, b in pending:
        print(f"| {backend} | {dev} | {b} | pending a GPU | pending a GPU | pending a GPU | pending a GPU |")
    if a.out:
        Path(a.out).write_text(
            json.dumps(
                {
                    "rows": rows,
                    "pending": pending,
                    "overrides": a.set,
                    "torch": torch.__version__,
                    "threads": torch.get_num_threads(),
                },
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
