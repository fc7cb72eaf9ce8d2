"""How much of a fitted camera's render check is the renders' own noise, and what its detections are made of.

    python benchmarks/render_check.py FRAMES --report FIT_REPORT_DIR [--seeds 8] [--out FILE.md]

``FIT_REPORT_DIR`` is what ``skygen fit-camera ... --report DIR`` wrote (``fit.json``: the fitted camera, each solved
frame's attitude and the real frames' statistics); ``FRAMES`` the folder it was fitted on. The frames the fit
compared (at most 16, spread evenly, as fit-camera picks them) are rendered once per dataset seed ``0 .. --seeds-1``
with the fitted camera at their attitudes, each pass measured as fit-camera measures it
(``skygen.real.fit_render._render_stats``): the table gives, per statistic of issue 35's check, the real median and
each seed's rendered median over real (min, mean, max, standard deviation): a check resting on one render per frame
moves by that much between seeds. A second table splits each pass's detections per frame into catalogue stars,
the fitted camera's false stars (``corruptions.false_stars``) and the rest (hot pixels, light fixed on the sensor,
blends), against the real frames' catalogue-explained and unexplained detections: whether renders detect too many
because they see deeper (catalogue stars) or because of the sources the catalogue lacks.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

STATS = ("background_adu", "noise_adu", "star_sigma_px", "detections", "catalogue_detections")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("frames", help="the folder of real frames the camera was fitted on (named in the report)")
    p.add_argument("--report", required=True, type=Path, help="the fit-camera report folder (its fit.json)")
    p.add_argument("--seeds", type=int, default=8, help="dataset seeds: passes of renders over the frames")
    p.add_argument("--out", type=Path, help="also write the tables here (Markdown)")
    a = p.parse_args(argv)
    if a.seeds < 2:
        p.error(f"--seeds {a.seeds}: at least 2 (a spread needs two passes)")

    from skygen.config import build_config
    from skygen.errors import ConfigError
    from skygen.real.fit_render import CHECK_FRAMES, _render_stats, spread_evenly
    from skygen.real.fit_report import read_fit
    from skygen.real.frame_stats import TOLERANCES, median_of
    from skygen.runtime import hardware_line, print_and_write

    try:
        fit = read_fit(a.report)
    except ConfigError as e:
        p.error(str(e))
    solved, real = fit["solved"], fit["real_stats"]
    # the frames fit-camera compared: at most CHECK_FRAMES, spread evenly over the solved ones (fit_model_terms)
    pick = spread_evenly(len(solved), CHECK_FRAMES)
    attitudes = [(solved[k]["ra_deg"], solved[k]["dec_deg"], solved[k]["roll_deg"]) for k in pick]
    if fit.get("check_exposure_scales"):  # frames of several exposures: each rendered at its own, as the fit did
        attitudes = [(*a, s) for a, s in zip(attitudes, fit["check_exposure_scales"])]
    cfg = build_config(fit["config"])
    sat = float(fit.get("saturation_adu") or 2**cfg.sensor.bit_depth - 1)
    ratios = {k: [] for k in STATS}

    def ratio(b: float, a: float) -> float:  # as check_renders: both 0 (a background clipped to black) agree
        return 1.0 if a == 0 and b == 0 else b / a if a else float("nan")

    def real_median(k: str) -> float:  # reports older than a statistic lack it
        return median_of(real, k) if all(k in r for r in real) else float("nan")

    split = []  # per seed, means over frames: catalogue stars, false stars, the rest (hot pixels, fixed light, blends)
    for seed in range(a.seeds):
        rows = _render_stats(dataclasses.replace(cfg, seed=seed), attitudes, None, sat)
        for k in STATS:
            ratios[k].append(ratio(median_of(rows, k), real_median(k)))
        cat, false, det = (
            np.mean([r[k] for r in rows]) for k in ("catalogue_detections", "false_star_detections", "detections")
        )
        split.append((cat, false, det - cat - false))
    lines = [
        f"{len(attitudes)} frames of {a.frames} (fit {a.report}), rendered with the fitted camera at their attitudes "
        f"with dataset seeds 0-{a.seeds - 1}; {hardware_line()}",
        "",
        "| statistic | real (median) | rendered / real: min | mean | max | sd | tolerance |",
        "|---|---|---|---|---|---|---|",
    ]
    for k in STATS:
        v = np.asarray(ratios[k], float)
        tol = f"±{100 * TOLERANCES[k]:.0f} %" if k in TOLERANCES else ""
        if not np.isfinite(v).any():
            lines.append(f"| {k} | {real_median(k):.3g} | – | – | – | – | {tol} |")
            continue
        lines.append(
            f"| {k} | {real_median(k):.3g} | {np.nanmin(v):.3f} | {np.nanmean(v):.3f} | {np.nanmax(v):.3f} | "
            f"{np.nanstd(v, ddof=1):.3f} | {tol} |"
        )
    s = np.asarray(split)
    real_cat = np.mean([r.get("catalogue_detections", np.nan) for r in real])  # nan: an older report
    real_all = np.mean([r["detections"] for r in real])
    lines += [
        "",
        "| detections per frame (mean over frames) | catalogue stars | false stars | other | all |",
        "|---|---|---|---|---|",
        f"| real frames (catalogue: a star of the fit's depth within 2 px) | {real_cat:.1f} | – | "
        f"{real_all - real_cat:.1f} (unexplained) | {real_all:.1f} |",
        f"| renders, mean over seeds (min–max) | {s[:, 0].mean():.1f} ({s[:, 0].min():.1f}–{s[:, 0].max():.1f}) | "
        f"{s[:, 1].mean():.1f} | {s[:, 2].mean():.1f} | {s.sum(1).mean():.1f} |",
    ]
    text = "\n".join(lines)
    print_and_write(text, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
