"""The render checks of several fit-camera reports side by side: renders over real per statistic, ✓ within tolerance.

    python benchmarks/fit_checks.py NAME=REPORT_DIR ... [--before NAME=REPORT_DIR ...] [--out FILE.md]

Each ``REPORT_DIR`` is what ``skygen fit-camera ... --report DIR`` wrote (its ``fit.json``: the checks of issue 35,
background, background sigma, star width and detections per frame, the fitted camera's renders over the real frames'
medians). With ``--before``, each camera named there gets a second row: the same checks of an earlier fit (another
commit or other options), so a change's effect on every camera reads in one table. Where ``REPORT_DIR/sim-vs-real``
holds what ``benchmarks/sim_vs_real.py --out`` wrote for that fit, the row adds its few-star cells: how many of them
the renders at the real attitudes predict within 5 points, the real frames' whole-sky rate at N = 4 / 5 / 6 / 8, and
the wrong answers on frames and renders. Nothing is rendered: the table is what the fits and benchmarks measured.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

STATS = ("background_adu", "noise_adu", "star_sigma_px", "detections")
HEAD = ("background", "background σ", "star width", "detections / frame")


def _pairs(items: list[str], option: str, parser) -> list[tuple[str, Path]]:
    out = []
    for item in items:
        name, sep, folder = item.partition("=")
        if not sep or not name or not folder:
            parser.error(f"{option} {item!r}: give NAME=REPORT_DIR (e.g. blackfly=results/real-frames/x/blackfly)")
        path = Path(folder) / "fit.json"
        if not path.is_file():
            parser.error(f"{option} {item!r}: no fit.json in {folder} (what skygen fit-camera --report DIR writes)")
        out.append((name, Path(folder)))
    return out


def checks(folder: Path) -> dict:
    """{stat: (ratio, ok)} of a report's fit.json, and its summed miss (beyond tolerance, log ratios)."""
    from skygen.real.fit_render import miss

    rec = json.loads((folder / "fit.json").read_text())
    rows = {c["stat"]: (float(c["ratio"]), bool(c["ok"])) for c in rec["checks"]}
    return {"rows": rows, "miss": miss(rec["checks"]), "solved": len(rec["solved"]), "frames": len(rec["frames"])}


def few_star(folder: Path) -> str:
    """'k / n' cells within 5 points, the real whole-sky rates at N = 4, 5, 6, 8 and the wrong answers, from
    ``folder/sim-vs-real/sim_vs_real.json``; '–' without one."""
    path = folder / "sim-vs-real" / "sim_vs_real.json"
    if not path.is_file():
        return "– | – | –"
    rows = json.loads(path.read_text())["rows"]
    near = sum(bool(r["at_truth"]["within_target"]) for r in rows)
    rate = {r["n"]: r["real"]["rate"] for r in rows if r["solver"] == "whole-sky"}
    wrong = sum(r["real"]["wrong"] + r["at_truth"]["wrong"] for r in rows)
    rates = " / ".join(f"{100 * rate[n]:.0f}" if n in rate else "–" for n in (4, 5, 6, 8))
    return f"{near} / {len(rows)} | {rates} % | {wrong}"


def cell(row: tuple | None) -> str:
    if row is None:
        return "–"
    ratio, ok = row
    return f"{ratio:.2f} ✓" if ok else f"**{ratio:.2f} ✗**"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("reports", nargs="+", help="NAME=REPORT_DIR of each fit")
    p.add_argument("--before", nargs="*", default=[], help="NAME=REPORT_DIR of an earlier fit of the same camera")
    p.add_argument("--out", type=Path, help="also write the table here (Markdown)")
    a = p.parse_args(argv)

    from skygen.runtime import print_and_write

    now, before = _pairs(a.reports, "reports", p), dict(_pairs(a.before, "--before", p))
    lines = [
        "| camera | fit | "
        + " | ".join(HEAD)
        + " | misses | summed miss | sim within 5 pts | real whole-sky N = 4 / 5 / 6 / 8 | wrong |",
        "|---|---|" + "---|" * (len(HEAD) + 5),
    ]
    for name, folder in now:
        for label, f in (("before", before.get(name)), ("now", folder)):
            if f is None:
                continue
            c = checks(f)
            n_miss = sum(not ok for _, ok in c["rows"].values())
            lines.append(
                f"| {name} | {label} ({f}) | "
                + " | ".join(cell(c["rows"].get(s)) for s in STATS)
                + f" | {n_miss} | {c['miss']:.3f} | {few_star(f)} |"
            )
    print_and_write("\n".join(lines), a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
