"""How long does ``skygen fit-camera`` take for many frames? (issue 35: <= 60 s of one core per 100 frames.)

    python benchmarks/fit_camera_speed.py [--frames 100] [--camera configs/cameras/blackfly-fitted.yaml]
                                          [--work /tmp/fit-speed] [--fov-range LO HI]

Renders ``--frames`` full-resolution frames of the camera (once; kept under ``--work`` as 16-bit PNG files, as a
user's frames would be), warms the solver database up (its build is not counted: "with the database cached"),
then runs the fit as ``skygen fit-camera FRAMES --camera CAMERA`` (or ``--fov-range``) would, in this process,
with one thread for numpy, numba and torch (``taskset -c 0`` pins it to one core), and prints the time of each
stage: reading, solving, the joint geometry, the pixel measurements, the renders that check the fit, in all.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def write_frames(camera: str, folder: Path, n: int, seed: int = 5) -> list[Path]:
    """``n`` renders of ``camera`` as 16-bit PNG files in ``folder`` (reused when already there)."""
    import cv2
    import numpy as np

    from skygen.config import load_config
    from skygen.render.frame import Renderer

    folder.mkdir(parents=True, exist_ok=True)
    paths = [folder / f"frame{i:04d}.png" for i in range(n)]
    if all(p.is_file() for p in paths):
        return paths
    r = Renderer(load_config(camera, overrides=[f"n_frames={n}", f"seed={seed}", "output.full_res=true"]))
    for i, p in enumerate(paths):
        if not p.is_file():
            img = np.clip(r.render(i).image_full, 0, 65535).astype(np.uint16)
            cv2.imwrite(str(p), img)
    return paths


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--camera", default=str(ROOT / "configs" / "cameras" / "blackfly-fitted.yaml"))
    p.add_argument("--fov-range", type=float, nargs=2, default=None, help="fit from a field range instead")
    p.add_argument("--work", default="/tmp/fit-camera-speed")
    a = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    from skygen.real import fit_camera as fc

    work = Path(a.work)
    t0 = time.perf_counter()
    paths = write_frames(a.camera, work / "frames", a.frames)
    print(f"{len(paths)} frames in {work / 'frames'} ({time.perf_counter() - t0:.0f} s to render; not counted)")
    kw = {"fov_range": tuple(a.fov_range)} if a.fov_range else {"camera": a.camera}
    # warm-up on three frames: the solver database is built or loaded into the cache, numba compiles
    fc.fit_camera([str(q) for q in paths[:3]], work / "warm.yaml", log=lambda s: None, **kw)
    marks = {}
    orig = {name: getattr(fc, name) for name in ("load_frames", "solve_frames", "fit_joint_geometry", "measure_pixels")}

    def timed(name):
        def run(*args, **kwargs):
            t = time.perf_counter()
            out = orig[name](*args, **kwargs)
            marks[name] = time.perf_counter() - t
            return out

        return run

    for name in orig:
        setattr(fc, name, timed(name))
    cpu0, t1 = time.process_time(), time.perf_counter()
    rec = fc.fit_camera([str(q) for q in paths], work / "fitted.yaml", log=lambda s: None, **kw)
    wall, cpu = time.perf_counter() - t1, time.process_time() - cpu0
    for name, f in orig.items():
        setattr(fc, name, f)
    marks["renders and checks (the rest)"] = wall - sum(marks.values())
    n = len(rec["frames"]) if "frames" in rec else len(paths)
    print(f"\nskygen fit-camera, {len(paths)} frames ({n} used), one thread; load {os.getloadavg()[0]:.1f}\n")
    print("| stage | s | s per 100 frames |")
    print("|---|---|---|")
    for name, s in marks.items():
        print(f"| {name} | {s:.1f} | {100 * s / len(paths):.1f} |")
    print(f"| **all (wall)** | **{wall:.1f}** | **{100 * wall / len(paths):.1f}** |")
    print(f"| all (process CPU) | {cpu:.1f} | {100 * cpu / len(paths):.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
