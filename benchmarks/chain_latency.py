"""Median latency of the solver chains per frame, repeated in one process: medians robust to this machine's drift.

    OMP_NUM_THREADS=1 taskset -c 1 python benchmarks/chain_latency.py --data data/bench500-s41 \
        --checkpoint runs/few30/best.pt [--frames 300] [--repeats 3] [--out FILE.md]

``fusion benchmark`` times every cell once, in turn; on a shared 2-vCPU machine a cell's median then moves by
±0.5-1.5 ms between runs of identical code (whatever else the host does meanwhile). Here each (solver, N) cell of
clean frames (the brightest N detections) is solved ``--repeats`` times, the repeats interleaved across cells, and
the table gives each repeat's median and the smallest of them (the least disturbed), beside p99 and the answers
(which must not change between repeats: a check). Before/after a change: run it with ``PYTHONPATH`` naming a
worktree of the earlier commit, then of this one, back to back.

Cells (``--cells``): ``SOLVER:N`` pairs, or ``SOLVER:N:CORRUPTION=SEVERITY`` for a detection-level corruption
applied as ``fusion benchmark`` applies it (the same detections); the default is issue 37's median targets: the
learned chain at N = 3, 4, 5 (the model's forward included) and the chains at N = 6 and 10. ``--corrupted-n N``
adds every corruption of the benchmark's sweep at N for each solver named at that N.

``--prior-first``: the learned chain's order before ``fine.SKY_FIRST_FROM`` (the prior's regions first at every N
below ``WHOLE_SKY_FROM``) as one more solver, ``learned+fine>whole-sky (prior first)``, measured in the same
process, its cells interleaved with the chain's: a before/after of the order on the same machine state.
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

DEFAULT_CELLS = (
    "learned+fine>whole-sky:3",
    "learned+fine>whole-sky:4",
    "learned+fine>whole-sky:5",
    "learned+fine>whole-sky:6",
    "whole-sky:4",
    "whole-sky:6",
    "whole-sky:10",
    "tetra3rs>whole-sky:6",
    "tetra3rs>whole-sky:10",
)


PRIOR_FIRST = "learned+fine>whole-sky (prior first)"


def label(c: tuple) -> str:
    return f"{c[0]} N={c[1]}" + (f" {c[2]}={c[3]:g}" if c[2] else "")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a skygen dataset with a test split")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--cells", nargs="+", default=list(DEFAULT_CELLS), help="SOLVER:N pairs")
    p.add_argument("--checkpoint", help="a fusion checkpoint: the prior of the learned solvers")
    p.add_argument("--corrupted-n", type=int, nargs="*", default=[], help="add every corruption's cells at N")
    p.add_argument("--prior-first", action="store_true", help="also the learned chain with the prior first (above)")
    p.add_argument("--out", type=Path, help="also write the table here (Markdown)")
    a = p.parse_args(argv)

    import fusion
    from fusion.solve.base import Solution, boresight_error_deg, roll_error_deg
    from fusion.solve.benchmark import DETECTION_CORRUPTIONS, corrupt, grid, load_benchmark_prior, load_frames
    from fusion.solve.registry import get, make_context
    from skygen.runtime import hardware_line, print_and_write

    cells = []
    for c in a.cells:
        parts = c.split(":")
        if len(parts) not in (2, 3) or not parts[0] or not parts[1].isdigit() or "=" not in (parts[2:] or ["="])[0]:
            p.error(f"--cells {c}: SOLVER:N or SOLVER:N:CORRUPTION=SEVERITY, e.g. whole-sky:6, whole-sky:4:dropout=0.2")
        kind, _, sev = (parts[2] if len(parts) == 3 else "").partition("=")
        cells.append((parts[0], int(parts[1]), kind or None, float(sev) if sev else 0.0))
    for n in a.corrupted_n:
        names = [c[0] for c in cells if c[1] == n and c[2] is None] or sorted({c[0] for c in cells})
        sweep = [(g["corruption"], g["severity"]) for g in grid((), (n,), DETECTION_CORRUPTIONS)]
        cells += [(name, n, k, v) for k, v in sweep for name in names]
    if a.prior_first:
        chain = "learned+fine>whole-sky"
        cells += [(PRIOR_FIRST, *c[1:]) for c in list(cells) if c[0] == chain]
        cells.sort(key=lambda c: (c[2] or "", c[3], c[1]))  # each cell's variants side by side, in turn
    learned = any("learned" in c[0] for c in cells)
    if learned and not a.checkpoint:
        p.error("a learned solver needs --checkpoint")
    fr = load_frames(a.data, "test", a.frames, with_images=learned)
    prior = load_benchmark_prior(a.checkpoint, a.data, fr, print)[0] if learned else None
    ctx = make_context(fr.camera, prior=prior, search_k=None)
    solvers = {name: get(ctx, name) for name in {c[0] for c in cells} if name != PRIOR_FIRST}
    if a.prior_first:
        import fusion.solve.fine as fine

        keep, fine.SKY_FIRST_FROM = fine.SKY_FIRST_FROM, None
        try:
            own = make_context(fr.camera, prior=prior, search_k=None, tetra=ctx.tetra)  # the same tetra3rs
            solvers[PRIOR_FIRST] = get(own, "learned+fine>whole-sky")
        finally:
            fine.SKY_FIRST_FROM = keep
    cam = fr.camera
    dets = {
        c[1:]: [
            corrupt(t, c[2], c[3], fr.seed, int(i), cam.width_px, cam.height_px).brightest(c[1])
            for t, i in zip(fr.tables, fr.index)
        ]
        for c in cells
    }
    for c in cells:  # warm up: numba loads, the prior traces
        for j in range(3):
            solvers[c[0]].solve(dets[c[1:]][j], fr.camera, fr.images[j])

    ms = {c: [] for c in cells}  # per repeat: the per-frame times (ms)
    answers: dict = {}
    for _ in range(a.repeats):
        for c in cells:
            s, t = solvers[c[0]], []
            got = []
            for j, d in enumerate(dets[c[1:]]):
                t0 = time.perf_counter()
                r = s.solve(d, fr.camera, fr.images[j])
                t.append((time.perf_counter() - t0) * 1e3)
                if isinstance(r, Solution):
                    m_true, roll_true = fr.truth[j]
                    ok = boresight_error_deg(m_true, r.matrix) <= 0.1 and roll_error_deg(r.roll_deg, roll_true) <= 1.0
                    got.append("c" if ok else "w")
                else:
                    got.append("r")
            if answers.setdefault(c, got) != got:
                raise SystemExit(f"{label(c)}: the answers changed between repeats (a nondeterministic solver)")
            ms[c].append(np.asarray(t))

    lines = [
        f"fusion from {Path(fusion.__file__).parent}; {hardware_line()}; one process; {a.data}, {len(fr.tables)} "
        f"test frames, the brightest N detections; {a.repeats} repeats interleaved across cells",
        "",
        "| solver | N | detections | correct / wrong / refused | median ms, least of the repeats "
        "| each repeat's median | p99 ms (least) |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in cells:
        got = answers[c]
        share = [100.0 * got.count(x) / len(got) for x in "cwr"]
        med = [float(np.median(t)) for t in ms[c]]
        p99 = min(float(np.percentile(t, 99)) for t in ms[c])
        each = " / ".join(f"{m:.2f}" for m in med)
        kind = f"{c[2]}={c[3]:g}" if c[2] else "clean"
        lines.append(
            f"| {c[0]} | {c[1]} | {kind} | {share[0]:.1f} / {share[1]:.1f} / {share[2]:.1f} % | **{min(med):.2f}** | "
            f"{each} | {p99:.1f} |"
        )
    text = "\n".join(lines)
    print_and_write(text, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
