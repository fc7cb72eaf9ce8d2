"""What a refusal of N detections costs, with and without the budget's per-detection hypothesis cost (issue 37).

    OMP_NUM_THREADS=1 taskset -c 1 python benchmarks/work_per_n.py [--cases 1200] [--n-min 4] [--n-max 12] \
        [--families noise focal other_camera] [--repeats 2] [--out FILE.md]

The cases are :mod:`adversarial_calibration`'s (the same generator, seed and families: detection sets no attitude
of this sky explains, so every solve searches until its budget or the evidence bar stops it), N uniform in
``--n-min..--n-max``. Each case is solved by the whole-sky fine stage twice per repeat, interleaved (the order
alternating case by case), once with ``fusion.solve.fine.COST_REFERENCE_N`` as shipped (a hypothesis of N > 6
detections counts (N - 2) / 4 units of the work budget) and once with it set beyond any N (every hypothesis
counts 1: the budget before), so both see the same machine state. The table: per N and variant, the cases, their
refusal statuses, the hypotheses tried (median), the time per hypothesis (ns, total time over total hypotheses),
and the median / p99 / max ms per solve (the least p99 of the repeats), and the answers, scored as the
calibration scores them (correct: within 0.1 deg and 1 deg of roll of the case's truth; every answer to a set
without one, ``noise``, is wrong). The families with a truth (``hot_pixels``, ``false_stars``,
``shuffled_mags``) show what a smaller budget at large N gives up: the answers that needed many hypotheses.
Every wrong answer is listed after the table (case, family, N, attitude errors, the reported false-match
probability and 1-sigma covariance: cross-boresight x, y and roll, arcsec).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

OFF = 10**9  # COST_REFERENCE_N beyond any N: every hypothesis counts 1


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=1200)
    p.add_argument("--n-min", type=int, default=4)
    p.add_argument("--n-max", type=int, default=12)
    p.add_argument("--families", nargs="+", default=["noise", "focal", "other_camera"])
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, help="also write the table here (Markdown)")
    a = p.parse_args(argv)
    if not 3 <= a.n_min <= a.n_max:
        p.error("--n-min, --n-max: 3 <= n-min <= n-max")

    from adversarial_calibration import CaseMaker, score

    import fusion.solve.fine as fine
    from fusion.solve.base import Solution
    from fusion.solve.registry import get, make_context
    from skygen.runtime import hardware_line, print_and_write

    shipped = fine.COST_REFERENCE_N
    maker = CaseMaker(None, a.seed, a.families, a.n_min, a.n_max)
    cam = maker.camera
    solver = get(make_context(cam, focal_tol=0.02), "whole-sky")
    cases = maker.cases(0, a.cases)
    solver.solve(cases[0]["detections"], cam)  # compile the loops, load the index
    variants = {"per-detection cost (shipped)": shipped, "every hypothesis 1 (before)": OFF}
    rows: dict = {(v, c["n"]): [] for v in variants for c in cases}  # per (variant, N): [(ms, H, status)] per repeat
    times: dict = {}
    wrong = []
    t_all = time.perf_counter()
    try:
        for rep in range(a.repeats):
            for i, c in enumerate(cases):
                order = list(variants.items())
                if (i + rep) % 2:
                    order.reverse()
                for name, ref in order:
                    fine.COST_REFERENCE_N = ref
                    t0 = time.perf_counter()
                    r = solver.solve(c["detections"], cam)
                    ms = (time.perf_counter() - t0) * 1e3
                    if isinstance(r, Solution):
                        sc = score(r, c["truth"], 0.1, 1.0)
                        status = "correct" if sc["correct"] else "wrong"
                        if status == "wrong" and rep == 0:
                            wrong.append((name, c, sc, r.to_dict().get("covariance_arcsec")))
                    else:
                        status = r.status
                    times.setdefault((name, c["n"], rep), []).append(ms)
                    if rep == 0:
                        rows[(name, c["n"])].append((r.extra.get("hypotheses") or 0, status))
    finally:
        fine.COST_REFERENCE_N = shipped
    wall = time.perf_counter() - t_all

    lines = [
        f"{hardware_line()}; one process; {a.cases} cases of {', '.join(a.families)} (seed {a.seed}), N uniform in "
        f"{a.n_min}..{a.n_max}; whole sky, focal tolerance ±2 %, budget {solver.max_hypotheses:,} units; each case "
        f"solved by both variants in turn, {a.repeats} repeats ({wall:.0f} s)",
        "",
        "| N | variant | cases | correct / wrong | refusals | hypotheses (median) | ns per hypothesis "
        "| ms median / p99 / max |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n in sorted({c["n"] for c in cases}):
        for name in variants:
            got = rows[(name, n)]
            h = np.array([x[0] for x in got], float)
            st = Counter(x[1] for x in got)
            reps = [np.asarray(times[(name, n, r)]) for r in range(a.repeats)]
            best = min(reps, key=lambda t: np.percentile(t, 99))
            ns = 1e6 * float(np.sum(best)) / max(1.0, float(h.sum()))
            refusals = ", ".join(f"{k} {v}" for k, v in sorted(st.items()) if k not in ("correct", "wrong"))
            lines.append(
                f"| {n} | {name} | {len(got)} | {st.get('correct', 0)} / {st.get('wrong', 0)} | {refusals} | "
                f"{np.median(h):,.0f} | {ns:.0f} | {np.median(best):.1f} / {np.percentile(best, 99):.1f} / "
                f"{best.max():.1f} |"
            )
    if wrong:
        lines += ["", "| variant | case | family | N | boresight / roll error (deg) | p | 1σ x / y / roll (arcsec) |",
                  "|---|---|---|---|---|---|---|"]  # fmt: skip
        for name, c, sc, cov in wrong:
            b, o = sc["boresight_err_deg"], sc["roll_err_deg"]
            err = "–" if b is None else f"{b:.3f} / {o:.3f}"
            sig = "–" if not cov else " / ".join(f"{x:.0f}" for x in cov)
            lines.append(f"| {name} | {c['case']} | {c['family']} | {c['n']} | {err} | {sc['p']:.2g} | {sig} |")
    text = "\n".join(lines)
    print_and_write(text, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
