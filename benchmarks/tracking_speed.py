"""Tracking's latency per solve (issue 37: median <= 1 ms with a 2-deg hint), the whole-sky fine stage's tracking.

    OMP_NUM_THREADS=1 taskset -c 1 python benchmarks/tracking_speed.py --data data/track300-s31 [--hint-deg 2]
        [--n 2 3] [--repeat 3] [--known-defects]

The first ``--frames`` test frames' brightest N detections, each with the benchmark's hint (the true attitude
turned by ``--hint-deg`` about a random axis, ``fusion.solve.benchmark.track_hint``) and the frames' zero point
(``tracking_zero_point``), solved ``--repeat`` times over (five untimed solves first: compilation, caches). Prints
a table of median / p95 / p99 ms per solve and the share answered. To compare two versions of the code, run it
with ``PYTHONPATH`` set to each checkout in turn on the same core, alternating.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))  # after PYTHONPATH: a checkout named there is the one measured


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a skygen dataset with a test split")
    p.add_argument("--hint-deg", type=float, default=2.0)
    p.add_argument("--n", type=int, nargs="+", default=[2, 3])
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--known-defects", action="store_true", help="drop the defect pixels' detections first")
    a = p.parse_args(argv)
    import fusion
    from fusion.solve.base import Detections, Solution
    from fusion.solve.benchmark import load_frames, track_hint, tracking_zero_point
    from fusion.solve.defects import from_dataset_tables, leave_one_out
    from fusion.solve.registry import get, make_context
    from skygen.runtime import hardware_line

    fr = load_frames(a.data, "test", a.frames, False)
    solver = get(make_context(fr.camera), "whole-sky")
    zp = tracking_zero_point(solver, fr)
    maps = leave_one_out(from_dataset_tables(fr.tables)) if a.known_defects else None
    hints = [track_hint(fr.truth[j][0], a.hint_deg, fr.seed, int(fr.index[j])) for j in range(len(fr.tables))]
    print(f"fusion from {Path(fusion.__file__).parent}; {hardware_line()}; {len(fr.tables)} frames x {a.repeat}")
    print("| N | solves | answered | median ms | p95 ms | p99 ms |\n|---|---|---|---|---|---|")
    for n in a.n:
        dets = [Detections.from_table(t).brightest(n) for t in fr.tables]
        if maps is not None:
            dets = [m.remove(d)[0] for m, d in zip(maps, dets)]
        kw = {"hint_sigma_deg": a.hint_deg, "hint_zero_point": zp}
        for j in range(min(5, len(dets))):
            solver.solve(dets[j], fr.camera, None, hint=hints[j], **kw)
        ms, answered = [], 0
        for j in list(range(len(dets))) * a.repeat:
            if len(dets[j]) < 2:
                continue
            t0 = time.perf_counter()
            r = solver.solve(dets[j], fr.camera, None, hint=hints[j], **kw)
            ms.append((time.perf_counter() - t0) * 1e3)
            answered += isinstance(r, Solution)
        q = np.percentile(ms, [50, 95, 99])
        print(f"| {n} | {len(ms)} | {100 * answered / len(ms):.1f} % | {q[0]:.3f} | {q[1]:.3f} | {q[2]:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
