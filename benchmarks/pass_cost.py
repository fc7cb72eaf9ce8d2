"""Where the fine stage's work goes, by pass (strict / ±focal_tol) and by place (a prior's region / the sky):
the evidence behind its work budget (``FOCAL_HYPOTHESIS_COST``, ``MAX_HYPOTHESES``; issue 37).

    OMP_NUM_THREADS=1 taskset -c 1 python benchmarks/pass_cost.py --data data/bench500 [--frames 500]
        [--n 3 4 5 6 8 10] [--corruption-n 4 6] [--solver whole-sky] [--checkpoint CK] [--out FILE.md]

The cells of ``fusion benchmark`` (clean at every ``--n``; every detection-level corruption's severities at every
``--corruption-n``), one solver (``--solver``; a learned one needs ``--checkpoint``). The compiled hypothesis loop
(:func:`fusion.solve.match.anchor_hypotheses`) is timed around each call and its hypotheses counted by pass and
place. Prints (and writes to ``--out``) three tables: the loop's nanoseconds per counted hypothesis by pass, place
and N; the correct answers (boresight within 0.1 deg, roll within 1 deg, as ``fusion benchmark`` counts them): how
many came from a focal pass, the most hypotheses and budget units (strict + FOCAL_HYPOTHESIS_COST x focal) any of
them needed; the refusals: the share of their hypotheses and of their loop time spent in the focal pass. Timing
adds a few per cent (one ``perf_counter`` pair per anchor pair): compare ratios, not absolute times, with
``fusion benchmark``'s.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))  # after PYTHONPATH: a checkout named there is the one measured


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a skygen dataset with a test split")
    p.add_argument("--frames", type=int, default=500)
    p.add_argument("--n", type=int, nargs="+", default=[3, 4, 5, 6, 8, 10])
    p.add_argument("--corruption-n", type=int, nargs="*", default=[4, 6])
    p.add_argument("--solver", default="whole-sky", help="a registered solver (fusion.solve.registry)")
    p.add_argument("--checkpoint", help="a fusion checkpoint: the prior of a learned solver")
    p.add_argument("--out", help="also write the tables to this Markdown file")
    a = p.parse_args(argv)
    import fusion
    import fusion.solve.fine as fine
    from fusion.solve.base import Solution, boresight_error_deg, roll_error_deg
    from fusion.solve.benchmark import DETECTION_CORRUPTIONS, corrupt, grid, load_benchmark_prior, load_frames
    from fusion.solve.registry import get, make_context
    from skygen.runtime import hardware_line

    fr = load_frames(a.data, "test", a.frames, with_images=bool(a.checkpoint))
    prior = load_benchmark_prior(a.checkpoint, a.data, fr, print)[0] if a.checkpoint else None
    solver = get(make_context(fr.camera, prior=prior), a.solver)
    cells = grid(a.n, a.corruption_n, DETECTION_CORRUPTIONS if a.corruption_n else ())

    loop = defaultdict(lambda: [0, 0.0])  # (pass, place, n) -> [hypotheses counted, loop seconds]
    per_solve = {"strict": 0, "focal": 0, "strict_s": 0.0, "focal_s": 0.0, "last": None}
    original = fine.anchor_hypotheses

    def timed(*args):
        t0 = time.perf_counter()
        out = original(*args)
        dt = time.perf_counter() - t0
        pas = "focal" if args[10] > 0 else "strict"
        place = "sky" if args[16] <= -1.0 else "region"
        cell = loop[(pas, place, len(args[2]))]
        cell[0] += int(out[0])
        cell[1] += dt
        per_solve[pas] += int(out[0])
        per_solve[pas + "_s"] += dt
        per_solve["last"] = pas
        return out

    fine.anchor_hypotheses = timed
    try:
        for n in sorted({c["n"] for c in cells}) if fr.tables else ():
            # outside the counts: compiling the loops for each catalogue cut (three detections search the bright
            # one), loading the pair index
            solver.solve(corrupt(fr.tables[0], None, 0.0, fr.seed, int(fr.index[0]), 1, 1).brightest(n), fr.camera)
        loop.clear()
        answers, refusals = [], []
        cam = fr.camera
        for cell in cells:
            for j, (t, i) in enumerate(zip(fr.tables, fr.index)):
                d = corrupt(t, cell["corruption"], cell["severity"], fr.seed, int(i), cam.width_px, cam.height_px)
                per_solve.update(strict=0, focal=0, strict_s=0.0, focal_s=0.0, last=None)
                res = solver.solve(d.brightest(cell["n"]), cam, fr.images[j])
                row = dict(per_solve)
                if isinstance(res, Solution):
                    m_true, roll_true = fr.truth[j]
                    ok = boresight_error_deg(m_true, res.matrix) <= 0.1 and roll_error_deg(res.roll_deg, roll_true) <= 1
                    if ok and res.solver != "tetra3rs-lis":  # the fine stage's own answers
                        answers.append(row)
                else:
                    refusals.append(row)
    finally:
        fine.anchor_hypotheses = original

    cost = fine.FOCAL_HYPOTHESIS_COST
    lines = [
        f"fusion from {Path(fusion.__file__).parent}; {hardware_line()}; solver {a.solver}; {a.data}, "
        f"{len(fr.tables)} frames x {len(cells)} cells",
        "",
        "| pass | place | N | hypotheses counted | loop s | ns per hypothesis |",
        "|---|---|---|---|---|---|",
    ]
    for (pas, place, n), (h, s) in sorted(loop.items()):
        lines.append(f"| {pas} | {place} | {n} | {h:,} | {s:.3f} | {1e9 * s / h if h else float('nan'):.0f} |")
    units = [r["strict"] + cost * r["focal"] for r in answers]
    focal = sum(1 for r in answers if r["last"] == "focal")
    lines += [
        "",
        "| correct answers of the fine stage | found in a focal pass | most hypotheses | most budget units |",
        "|---|---|---|---|",
        f"| {len(answers):,} | {focal:,} | {max((r['strict'] + r['focal'] for r in answers), default=0):,} | "
        f"{max(units, default=0):,} |",
    ]
    h_ref = np.array([[r["strict"], r["focal"], r["strict_s"], r["focal_s"]] for r in refusals] or [[0, 0, 0, 0]])
    tot = h_ref.sum(axis=0)
    lines += [
        "",
        "| refusals | share of their hypotheses in the focal pass | share of their loop time there |",
        "|---|---|---|",
        f"| {len(refusals):,} | {tot[1] / max(1, tot[0] + tot[1]):.2f} | {tot[3] / max(1e-12, tot[2] + tot[3]):.2f} |",
    ]
    text = "\n".join(lines)
    print(text)
    if a.out:
        Path(a.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
