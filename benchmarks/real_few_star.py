"""Few-star solving on real frames: the brightest N real detections, every prior-free solver side by side.

    python benchmarks/real_few_star.py FRAMES... --camera CAMERA.yaml [--n 3 4 5 6 8]
                                       [--solvers tetra3rs whole-sky tetra3rs>whole-sky] [--known-defects] --out DIR
    python benchmarks/real_few_star.py FRAMES... --checkpoint CK [--solvers ... learned+fine>whole-sky] --out DIR

For every frame: detect with skygen's detector and the camera's detection settings (exactly what
``fusion predict --camera CAMERA.yaml`` does: :meth:`fusion.solve.predict.Predictor.detect`, the camera's
``detection.background_box_px`` included), then solve with *all* detections by tetra3rs lost-in-space.
That solution is the frame's truth when it is beyond doubt (false-positive probability <=
``--truth-max-fpp`` and >= ``--truth-min-matched`` matched stars); other frames are reported and left out.
With ``--truth-wcs DIR`` the truth is instead each frame's plate solution by another solver (``DIR/STEM.wcs``,
as astrometry.net and ASTAP write them: :mod:`skygen.real.wcs`), through the camera file: independent of our
pipeline, and deeper where that solver's catalogue is (``benchmarks/wcs_agreement.py`` compares the two).
Then, for each N, only the brightest N detections go to each registered prior-free solver
(``fusion.build_solver(name, camera)``, one shared tetra3rs database). Scored as ``fusion benchmark`` does:
**correct** = boresight within ``--correct-deg`` (0.1) and roll within ``--correct-roll-deg`` (1) degrees of
the truth, **wrong** = any other returned attitude, **refused** = none; median and p95 wall-clock ms per solve
(``real_few_star.json`` has p99 too)
(one process, one call at a time). Also the share of frames where one of the brightest N detections is not
among the detections the truth solution matched (hot pixels, stars beyond the catalogue, blends).

``--track-hint-deg D...`` adds tracking cells (``--track-n``, 2 and 3 by default), as ``fusion benchmark``'s: each
frame's brightest N with a hint D deg off its truth (1 sigma D) and the zero point the other frames measured.

With ``--checkpoint CK`` (a model trained on renders of the frames' camera, e.g. ``configs/blackfly.yaml`` on a
fitted camera's dataset) the camera is the checkpoint's own and the learned solvers (``learned+fine>whole-sky``,
...) may be listed beside the prior-free ones: the brightest N detections go to the model exactly as
``fusion predict --solve`` gives them (model forward included in the milliseconds).

A skygen dataset folder (``skygen render --full-res``) may be given instead of frame files: its full-resolution
frames are detected the same way and their truth is the rendered attitude (``--max-frames`` caps them), so the
same cells on renders of a fitted camera predict the real ones.

Writes DIR/real_few_star.json and DIR/real_few_star.md and prints the Markdown table.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PRIOR_FREE_DEFAULT = ("tetra3rs", "whole-sky", "tetra3rs>whole-sky")


def prior_free_solvers() -> list[str]:
    """Registered solvers that need no prior (no model, no benchmark oracle)."""
    from fusion.solve.registry import SOLVERS

    return [name for name, spec in SOLVERS.items() if spec.prior is None]


def load_frames(paths: list[str], max_frames: int | None = None, channel: str = "luminance"):
    """(name, full-resolution image, truth matrix or None) per frame; errors as (name, None, message)."""
    from fusion.solve.frames import iter_inputs

    out = []
    for p in paths:
        path = Path(p)
        if path.is_dir() and (path / "manifest.json").exists():
            from skygen.datasets.shards import open_dataset

            with open_dataset(path) as ds:
                n = len(ds) if max_frames is None else min(max_frames, len(ds))
                for pos in range(n):
                    q = np.asarray(ds.boresight["quaternion"][pos], np.float64)
                    out.append((f"{path}#{int(ds.frames['index'][pos])}", ds.image(pos, full_res=True), q))
            continue
        for name, img, _det, _stored, err in iter_inputs([str(path)], max_frames, channel):
            out.append((name, img, err))
    return out


def all_detection_truth(tetra, det, cam, max_fpp: float = 1e-20, min_matched: int = 10):
    """(tetra3rs's solve of every detection, None) where it is beyond doubt (false-positive probability <= ``max_fpp``
    and >= ``min_matched`` stars), else (that solve or its refusal, why it is no truth): the frames' truth rule."""
    from fusion.solve.base import Solution

    full = tetra.solve(det, cam)
    if not isinstance(full, Solution):
        return full, f"all-detection tetra3rs solve refused: {full.reason}"
    fpp = float(full.extra.get("false_positive_probability", 1.0))
    if fpp > max_fpp or full.n_matched < min_matched:
        return full, f"truth not beyond doubt ({full.n_matched} matched, fpp {fpp:.3g})"
    return full, None


def run(
    frames: list,
    camera: str | Path | None,
    n_values=(3, 4, 5, 6, 8),
    solvers=PRIOR_FREE_DEFAULT,
    *,
    truth_max_fpp: float = 1e-20,
    truth_min_matched: int = 10,
    correct_deg: float = 0.1,
    correct_roll_deg: float = 1.0,
    background_box: int | None = None,
    checkpoint: str | Path | None = None,
    search_k: int | None = None,
    max_hypotheses: int | None = None,
    known_defects: bool = False,
    mask_fixed_sources: bool = False,
    truth_wcs: str | Path | None = None,
    wcs_rows_from_bottom: bool = False,
    track_hint_deg=(),
    track_n=(2, 3),
    log=print,
) -> dict:
    """The benchmark on ``frames`` (from :func:`load_frames`) for the camera file ``camera``, or for the camera of
    ``checkpoint`` (whose prior the learned solvers then use; ``search_k``: regions they search)."""
    from fusion.solve.base import Solution, boresight_error_deg, roll_error_deg
    from fusion.solve.benchmark import coverage
    from fusion.solve.predict import Predictor
    from fusion.solve.registry import SOLVERS, build_solver, make_context
    from skygen.sky.attitude import matrix_to_radec_roll, quaternion_to_matrix

    allowed = (None, "learned") if checkpoint is not None else (None,)
    for name in solvers:
        if name not in SOLVERS or SOLVERS[name].prior not in allowed:
            learned = [n for n, spec in SOLVERS.items() if spec.prior == "learned"]
            raise SystemExit(
                f"--solvers {name}: not a prior-free registered solver ({', '.join(prior_free_solvers())})"
                + ("" if checkpoint is not None else f"; the learned ones ({', '.join(learned)}) need --checkpoint")
            )
    if (camera is None) == (checkpoint is None):
        raise SystemExit("give --camera CAMERA.yaml or --checkpoint CK (a model: its own camera), exactly one")
    pred = Predictor(checkpoint, camera=camera, background_box=background_box, mask_fixed_sources=mask_fixed_sources)
    cam = pred.camera
    t0 = time.perf_counter()
    ctx = make_context(cam, prior=pred.prior, search_k=search_k, max_hypotheses=max_hypotheses)
    built = {name: build_solver(name, cam, context=ctx) for name in solvers}
    setup_s = time.perf_counter() - t0
    truth_solver = ctx.tetra
    own_truth = build_solver("whole-sky", cam, context=ctx)

    kept, dropped = [], []
    for name, img, extra in frames:
        if img is None:
            dropped.append({"frame": name, "reason": f"unreadable: {extra}"})
            continue
        pred.check_shape(img, name)
        det, bg, sigma = pred.detect(img)
        rec = {"frame": name, "n_detections": len(det), "background_adu": bg, "noise_adu": sigma}
        if extra is not None and not isinstance(extra, str):  # a rendered frame: its true attitude
            m_true = quaternion_to_matrix(np.asarray(extra))
            full = truth_solver.solve(det, cam)
            rec["truth"] = "rendered attitude"
            rec["all_detection_solve"] = (
                "refused"
                if not isinstance(full, Solution)
                else (
                    "correct"
                    if boresight_error_deg(m_true, full.matrix) <= correct_deg
                    and roll_error_deg(full.roll_deg, matrix_to_radec_roll(m_true)[2]) <= correct_roll_deg
                    else "wrong"
                )
            )
            matched_rows = set(full.matched[:, 0].tolist()) if isinstance(full, Solution) else None
        elif truth_wcs is not None:  # another solver's plate solution: its attitude through this camera
            from skygen.real.wcs import attitude_from_wcs, read_wcs

            wcs_file = Path(truth_wcs) / f"{Path(name).stem}.wcs"
            if not wcs_file.is_file():
                dropped.append({**rec, "reason": f"no WCS file ({wcs_file.name})"})
                continue
            m_true, misfit = attitude_from_wcs(read_wcs(wcs_file), cam, wcs_rows_from_bottom)
            rec.update({"truth": f"WCS {wcs_file.name}", "truth_wcs_misfit_arcsec": misfit})
            full = truth_solver.solve(det, cam)  # which detections are stars: its matches, where it solves
            matched_rows = set(full.matched[:, 0].tolist()) if isinstance(full, Solution) else None
            if isinstance(full, Solution):
                rec["truth_matched"] = full.n_matched
                own = own_truth.solve(det, cam)
                if isinstance(own, Solution) and boresight_error_deg(m_true, own.matrix) <= correct_deg:
                    rec["_m_own"] = own.matrix
        else:
            full, why = all_detection_truth(truth_solver, det, cam, truth_max_fpp, truth_min_matched)
            if isinstance(full, Solution):
                fpp = float(full.extra.get("false_positive_probability", 1.0))
                rec.update({"truth": "all-detection tetra3rs", "truth_matched": full.n_matched, "truth_fpp": fpp})
            if why is not None:
                dropped.append({**rec, "reason": why})
                continue
            m_true = full.matrix
            matched_rows = set(full.matched[:, 0].tolist())
            # a second truth for the covariance: our own fine stage on every detection, with this camera's model
            # (distortion, principal point), kept where it agrees with tetra3rs's
            own = own_truth.solve(det, cam)
            if isinstance(own, Solution) and boresight_error_deg(m_true, own.matrix) <= correct_deg:
                rec["_m_own"] = own.matrix
                rec["own_truth_offset_arcsec"] = float(boresight_error_deg(m_true, own.matrix) * 3600)
        rec["_det"], rec["_m"], rec["_matched_rows"] = det, m_true, matched_rows
        rec["truth_radec_roll_deg"] = [float(v) for v in matrix_to_radec_roll(m_true)]
        kept.append(rec)
    log(f"{len(kept)} of {len(frames)} frames kept with a truth attitude; {len(dropped)} left out")
    if (
        known_defects
    ):  # each frame's defect map from the others: what no truth solve matched, at one pixel, 3+ pointings
        from fusion.solve.defects import leave_one_out

        tables = [
            (
                r["_det"].x_px,
                r["_det"].y_px,
                [r["_matched_rows"] is None or i in r["_matched_rows"] for i in range(len(r["_det"]))],
            )
            for r in kept
        ]
        for r, dmap in zip(kept, leave_one_out(tables, boresights=[r["_m"][:, 2] for r in kept])):
            r["_defects"] = dmap
            r["defect_pixels"] = np.round(dmap.xy, 1).tolist()
    # untimed warm-up: numba kernels, pair indices (the 3-star bright tier too) and caches are built on first use
    t0 = time.perf_counter()
    if kept:
        for solver in built.values():
            for n in sorted({min(n_values), max(n_values)}):
                solver.solve(kept[0]["_det"].brightest(n), cam)
    warmup_s = time.perf_counter() - t0

    cells = []
    pooled: dict = {key: {name: ([], []) for name in built} for key in ("coverage", "coverage_own_truth")}
    for n in n_values:
        row = {"n": int(n), "frames": 0, "solvers": {}}
        usable = [r for r in kept if len(r["_det"]) >= n]
        row["frames"] = len(usable)
        row["frames_with_fewer_detections"] = len(kept) - len(usable)
        with_truth_rows = [r for r in usable if r["_matched_rows"] is not None]
        non_cat = sum(any(i not in r["_matched_rows"] for i in range(n)) for r in with_truth_rows)
        row["share_non_catalogue_in_brightest"] = non_cat / len(with_truth_rows) if with_truth_rows else None
        for r in with_truth_rows:  # per frame: how many of its brightest n no all-detection solve matched
            r.setdefault("non_catalogue_in_brightest", {})[str(n)] = sum(i not in r["_matched_rows"] for i in range(n))
        for r in with_truth_rows:  # each such detection's distance to the nearest brighter one (px): a fragment of a
            d = r["_det"]  # bright star's halo lies close to it, an uncatalogued source anywhere
            gaps = [
                float(np.min(np.hypot(d.x_px[:i] - d.x_px[i], d.y_px[:i] - d.y_px[i]))) if i else None
                for i in range(min(n, len(d)))
                if i not in r["_matched_rows"]
            ]
            r.setdefault("non_catalogue_nearest_brighter_px", {})[str(n)] = [
                None if g is None else round(g, 1) for g in gaps
            ]
        for r in usable:  # and how many are saturated (Detections.saturated: their flux a lower bound)
            if r["_det"].saturated is not None:
                r.setdefault("saturated_in_brightest", {})[str(n)] = int(np.sum(r["_det"].saturated[:n]))
        dets = {}
        for r in usable:  # the brightest n, then (known_defects) the defect pixels' detections dropped
            d = r["_det"].brightest(n)
            dets[r["frame"]] = r["_defects"].remove(d)[0] if known_defects else d
        if known_defects:
            row["defects_removed"] = int(sum(n - len(d) for d in dets.values()))
        for sname, solver in built.items():
            ok = wrong = refused = 0
            ms = []
            errs = []
            good, good_truth = [], []  # correct answers and their truth: the covariance's coverage
            good_own, own_truth_m = [], []  # the same against our own all-detection solve
            for r in usable:
                d = dets[r["frame"]]
                roll_true = matrix_to_radec_roll(r["_m"])[2]
                t = time.perf_counter()
                res = solver.solve(d, cam)
                ms.append((time.perf_counter() - t) * 1e3)
                outcome = r.setdefault("outcomes", {}).setdefault(sname, {})  # per frame: what each cell gave
                if not isinstance(res, Solution):
                    refused += 1
                    outcome[str(n)] = res.status or "refused"
                    continue
                b, o = boresight_error_deg(r["_m"], res.matrix), roll_error_deg(res.roll_deg, roll_true)
                errs.append((b, o))
                if b <= correct_deg and o <= correct_roll_deg:
                    ok += 1
                    outcome[str(n)] = "correct"
                    good.append(res)
                    good_truth.append((r["_m"], roll_true))
                    if "_m_own" in r:
                        good_own.append(res)
                        own_truth_m.append((r["_m_own"], None))
                else:
                    wrong += 1
                    outcome[str(n)] = "wrong"
                    log(f"WRONG {sname} N={n} {r['frame']}: boresight {b:.3f} deg, roll {o:.3f} deg off")
            row["solvers"][sname] = {
                **_outcome_counts(ok, wrong, refused, ms, len(usable)),
                "coverage": coverage(good, good_truth),
                "coverage_own_truth": coverage(good_own, own_truth_m),
            }
            for key, (sols, truths) in (
                ("coverage", (good, good_truth)),
                ("coverage_own_truth", (good_own, own_truth_m)),
            ):
                pooled[key][sname][0].extend(sols)
                pooled[key][sname][1].extend(truths)
        cells.append(row)
        log(
            f"N={n}: "
            + ", ".join(f"{s} {v['n_correct']}/{row['frames']}" for s, v in row["solvers"].items())
            + f" (wrong: {sum(v['n_wrong'] for v in row['solvers'].values())})"
        )
    tracking = tracking_cells(built, kept, cam, track_hint_deg, track_n, correct_deg, correct_roll_deg, log)
    frames_out = [{k: v for k, v in r.items() if not k.startswith("_")} for r in kept]
    return {
        "camera": str(camera) if camera is not None else f"the camera of {checkpoint}",
        "checkpoint": None if checkpoint is None else str(checkpoint),
        "camera_fov_deg": [float(v) for v in cam.fov_deg],
        "work_budget": getattr(own_truth, "max_hypotheses", None),  # the fine stage's, in hypotheses per solve
        "sensor_px": [int(cam.width_px), int(cam.height_px)],
        "detection": {
            "threshold_sigma": pred.cfg.detection.threshold_sigma,
            "min_area_px": pred.cfg.detection.min_area_px,
            "max_detections": pred.cfg.detection.max_detections,
            "background_box_px": pred.background_box,
        },
        "solvers": list(solvers),
        "known_defects": bool(known_defects),
        "mask_fixed_sources": bool(mask_fixed_sources),
        "n_values": [int(n) for n in n_values],
        "truth_rule": (
            f"each frame's WCS in {truth_wcs} (another solver's plate solution) through this camera"
            + (", rows counted from the bottom" if wcs_rows_from_bottom else "")
            if truth_wcs is not None
            else f"all-detection tetra3rs solve with false-positive probability <= {truth_max_fpp:g} "
            f"and >= {truth_min_matched} matched stars (rendered frames: the rendered attitude)"
        ),
        "truth_wcs": None if truth_wcs is None else str(truth_wcs),
        "correct_definition": f"boresight error <= {correct_deg} deg and roll error <= {correct_roll_deg} deg",
        "frames_given": len(frames),
        "frames_kept": len(kept),
        "frames": frames_out,
        "dropped": dropped,
        "cells": cells,
        "tracking_cells": tracking,
        # every N's correct answers at once: one bias (the mean error) over all of them
        "coverage_pooled": {key: {name: coverage(*v) for name, v in per.items()} for key, per in pooled.items()},
        "setup_s": setup_s,
        "warmup_s": warmup_s,
        "host": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "python": platform.python_version(),
        },
    }


def _outcome_counts(ok: int, wrong: int, refused: int, ms: list, frames: int) -> dict:
    """One solver's cell: correct / wrong / refused shares and counts, and the median / p95 / p99 ms per solve."""
    k = max(frames, 1)
    return {
        "correct": ok / k,
        "wrong": wrong / k,
        "refused": refused / k,
        "n_correct": ok,
        "n_wrong": wrong,
        "n_refused": refused,
        "median_ms": float(np.median(ms)) if ms else None,
        "p95_ms": float(np.percentile(ms, 95)) if ms else None,
        "p99_ms": float(np.percentile(ms, 99)) if ms else None,
    }


def tracking_cells(built: dict, kept: list, cam, hint_degs, track_n, correct_deg, correct_roll_deg, log) -> list:
    """Tracking on the real frames, as ``fusion benchmark --track-hint-deg`` does on renders: each frame's brightest
    N detections with a hint, its truth turned by D deg about a random axis (``fusion.solve.benchmark.track_hint``,
    seed 0 and the frame's place in the list), 1 sigma D, and the zero point the other frames measured at their
    truth (a tracker's earlier frames; leave one out). Solvers whose solve takes no hint (the chains) are left out;
    tetra3rs tracks in its own hint mode."""
    import inspect

    from fusion.solve.base import Solution, boresight_error_deg, roll_error_deg
    from fusion.solve.benchmark import track_hint
    from skygen.sky.attitude import matrix_to_radec_roll

    takers = {s: v for s, v in built.items() if "hint" in inspect.signature(v.solve).parameters}
    if not hint_degs or not takers or not kept:
        return []
    zps: dict = {}  # each solver's own zero point of each frame, on all its detections at its truth (its catalogue's
    for name, solver in takers.items():  # magnitudes: tetra3rs's are not the fine stage's; tetra3rs reads none)
        got = [solver.solve(r["_det"], cam, hint=r["_m"], hint_sigma_deg=0.05) for r in kept]
        zps[name] = [z.extra.get("zero_point") if isinstance(z, Solution) else None for z in got]
    rows = []
    for deg in hint_degs:
        for n in track_n:
            row = {"hint_deg": float(deg), "n": int(n), "solvers": {}}
            usable = [(j, r) for j, r in enumerate(kept) if len(r["_det"]) >= n]
            row["frames"] = len(usable)
            for name, solver in takers.items():
                ok = wrong = refused = 0
                ms = []
                for j, r in usable:
                    others = [z for k, z in enumerate(zps[name]) if k != j and z is not None]
                    kw = {"hint": track_hint(r["_m"], float(deg), 0, j), "hint_sigma_deg": float(deg)}
                    if others:
                        kw["hint_zero_point"] = float(np.median(others))
                    t = time.perf_counter()
                    res = solver.solve(r["_det"].brightest(n), cam, **kw)
                    ms.append((time.perf_counter() - t) * 1e3)
                    if not isinstance(res, Solution):
                        refused += 1
                        continue
                    b = boresight_error_deg(r["_m"], res.matrix)
                    o = roll_error_deg(res.roll_deg, matrix_to_radec_roll(r["_m"])[2])
                    if b <= correct_deg and o <= correct_roll_deg:
                        ok += 1
                    else:
                        wrong += 1
                        log(f"WRONG tracking {name} N={n} hint {deg} deg {r['frame']}: {b:.3f} deg, roll {o:.3f} deg")
                row["solvers"][name] = _outcome_counts(ok, wrong, refused, ms, len(usable))
            rows.append(row)
            log(
                f"tracking, hint {deg} deg, N={n}: "
                + ", ".join(f"{s} {v['n_correct']}/{row['frames']}" for s, v in row["solvers"].items())
            )
    return rows


def _tracking_lines(res: dict) -> list[str]:
    rows = res.get("tracking_cells") or []
    if not rows:
        return []
    names = list(rows[0]["solvers"])
    lines = [
        "",
        "Tracking: each frame's brightest N with a hint, its truth turned by D deg about a random axis (1σ D), and the "
        "zero point the other frames measured (correct / wrong / refused, median / p95 ms):",
        "",
        "| hint | N | frames | " + " | ".join(names) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]
    for r in rows:
        cells = []
        for s in names:
            v = r["solvers"][s]
            ms = "–" if v["median_ms"] is None else f"{v['median_ms']:.2f} / {v['p95_ms']:.2f} ms"
            cells.append(f"**{_pct(v['correct'])}** / {_pct(v['wrong'])} / {_pct(v['refused'])}, {ms}")
        lines.append(f"| {r['hint_deg']:g}° | {r['n']} | {r['frames']} | " + " | ".join(cells) + " |")
    return lines


def _pct(x) -> str:
    return "–" if x is None else f"{100 * x:.0f} %"


def markdown(res: dict, title: str | None = None) -> str:
    solvers = res["solvers"]
    lines = []
    if title:
        lines += [f"### {title}", ""]
    lines += [
        f"Camera `{res['camera']}` ({res['camera_fov_deg'][0]:.3f}° × {res['camera_fov_deg'][1]:.3f}°, "
        f"{res['sensor_px'][0]} × {res['sensor_px'][1]} px); {res['frames_kept']} of {res['frames_given']} frames "
        f"with a truth attitude ({res['truth_rule']}). Correct: {res['correct_definition']}. "
        "Cells: correct / wrong / refused, median / p95 ms per solve.",
        "",
        "| N brightest | frames | " + " | ".join(solvers) + " | brightest N not all matched by the truth |",
        "|---|---|" + "---|" * len(solvers) + "---|",
    ]
    for c in res["cells"]:
        cells = []
        for s in solvers:
            v = c["solvers"][s]
            ms = "–" if v["median_ms"] is None else f"{v['median_ms']:.2f} / {v['p95_ms']:.2f} ms"
            cells.append(f"**{_pct(v['correct'])}** / {_pct(v['wrong'])} / {_pct(v['refused'])}, {ms}")
        lines.append(
            f"| {c['n']} | {c['frames']} | " + " | ".join(cells) + f" | {_pct(c['share_non_catalogue_in_brightest'])} |"
        )
    lines += _coverage_lines(res)
    lines += _tracking_lines(res)
    if res["dropped"]:
        lines += ["", "Left out: " + "; ".join(f"{Path(d['frame']).name}: {d['reason']}" for d in res["dropped"])]
    return "\n".join(lines) + "\n"


def _coverage_lines(res: dict) -> list[str]:
    """Each solver's attitude covariance against the truth, pooled over the N cells (few frames per cell): the
    share of correct answers whose error lies within 1 / 2 sigma (68 / 95 % if calibrated). The truth is itself
    an estimate (the all-detection solve, arcsec-level), so this bounds the covariance's calibration from above."""
    out = []
    truth = (
        "the truth (each frame's WCS: another solver's plate solution, through this camera)"
        if res.get("truth_wcs")
        else "the truth (the all-detection tetra3rs solve, itself good to a few arcsec)"
    )
    for key, what in (
        ("coverage", truth),
        (
            "coverage_own_truth",
            "our own fine stage's all-detection solve (this camera's model, distortion included; where it agrees "
            "with tetra3rs's to the correct bound)",
        ),
    ):
        out += _coverage_table(res, key, what)
    return out


def _coverage_table(res: dict, key: str, what: str) -> list[str]:
    rows = []
    for s in res["solvers"]:
        c = res.get("coverage_pooled", {}).get(key, {}).get(s)
        if not c:
            continue
        bx, by, br = c["bias_arcsec"]
        sx, _, sr = c["sigma_arcsec_median"]
        rows.append(
            f"| {s} | {c['frames']} | {100 * c['cross_1sigma']:.0f} / {100 * c['cross_2sigma']:.0f} % | "
            f"{100 * c['roll_1sigma']:.0f} / {100 * c['roll_2sigma']:.0f} % | {bx:+.2f} / {by:+.2f} / {br:+.1f} | "
            f"{sx:.2f} / {sr:.1f} | {100 * c['cross_1sigma_unbiased']:.0f} / {100 * c['cross_2sigma_unbiased']:.0f} % |"
        )
    if not rows:
        return []
    head = (
        f"Covariance against {what}, correct answers of every N pooled (within 1σ / 2σ; 68 / 95 % if calibrated); "
        "their mean error (x / y / roll, arcsec: what every answer shares, e.g. the same saturated stars in every "
        "frame), the median 1σ (cross / roll), and the cross-boresight coverage with that mean taken off:"
    )
    return [
        "",
        head,
        "",
        "| solver | answers | cross-boresight | roll | mean error (″) | median 1σ (″) | cross, mean off |",
        "|---|---|---|---|---|---|---|",
        *rows,
    ]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("frames", nargs="+", help="frame files, folders of them, or a skygen dataset folder (--full-res)")
    p.add_argument("--camera", default=None, help="camera YAML (configs/cameras/*.yaml or skygen fit-camera's)")
    p.add_argument(
        "--checkpoint",
        default=None,
        help="a model trained for this camera (instead of --camera): the learned solvers may then be listed",
    )
    p.add_argument("--search-k", type=int, default=None, help="regions the learned solvers search (their default)")
    p.add_argument(
        "--max-hypotheses",
        type=int,
        default=None,
        metavar="H",
        help="the fine stage's work budget per solve (fusion benchmark --max-hypotheses; default: "
        "fusion.solve.fine.MAX_HYPOTHESES, the same on every camera)",
    )
    p.add_argument("--n", type=int, nargs="+", default=[3, 4, 5, 6, 8], help="brightest-N cells")
    p.add_argument(
        "--solvers",
        nargs="+",
        default=list(PRIOR_FREE_DEFAULT),
        help="registered solvers: prior-free ones, and the learned ones with --checkpoint",
    )
    p.add_argument("--channel", default="luminance", help="colour frames: luminance, r, g, b or sum")
    p.add_argument("--max-frames", type=int, default=None, help="first N frames of each folder or dataset")
    p.add_argument(
        "--truth-wcs",
        default=None,
        help="folder of FRAME_STEM.wcs plate solutions (astrometry.net, ASTAP): the truth is each frame's WCS "
        "through --camera, not our all-detection solve (benchmarks/wcs_agreement.py checks the two agree)",
    )
    p.add_argument("--wcs-rows-from-bottom", action="store_true", help="the WCS counts pixel rows from the bottom")
    p.add_argument(
        "--track-hint-deg",
        type=float,
        nargs="+",
        default=[],
        help="tracking cells: hints D deg off each frame's truth (1 sigma D), as fusion benchmark --track-hint-deg",
    )
    p.add_argument("--track-n", type=int, nargs="+", default=[2, 3], help="brightest-N of the tracking cells")
    p.add_argument("--truth-max-fpp", type=float, default=1e-20)
    p.add_argument("--truth-min-matched", type=int, default=10)
    p.add_argument("--correct-deg", type=float, default=0.1)
    p.add_argument("--correct-roll-deg", type=float, default=1.0)
    p.add_argument(
        "--background-box",
        type=int,
        default=None,
        help="detector background box, px (default: the camera's detection.background_box_px; 64 for sky glow, "
        "as `fusion predict --background-box 64`)",
    )
    p.add_argument(
        "--known-defects",
        action="store_true",
        help="drop detections at the sensor's defect pixels first: each frame's map learned from the other frames' "
        "detections no truth solve matched, recurring at one pixel at 3+ pointings (fusion.solve.defects)",
    )
    p.add_argument(
        "--mask-fixed-sources",
        action="store_true",
        help="drop the detections of the camera's sensor.fixed_sources (--camera's, or the checkpoint's) at "
        "detection, before the brightest N are taken (fusion predict --mask-fixed-sources): what a tracker that knows "
        "its glow is given",
    )
    p.add_argument("--title", default=None)
    p.add_argument("--out", required=True, help="folder for real_few_star.json and real_few_star.md")
    a = p.parse_args(argv)
    if (a.camera is None) == (a.checkpoint is None):
        p.error("give --camera CAMERA.yaml or --checkpoint CK (a model trained for the camera), exactly one")
    frames = load_frames(a.frames, a.max_frames, a.channel)
    res = run(
        frames,
        a.camera,
        a.n,
        a.solvers,
        truth_max_fpp=a.truth_max_fpp,
        truth_min_matched=a.truth_min_matched,
        correct_deg=a.correct_deg,
        correct_roll_deg=a.correct_roll_deg,
        background_box=a.background_box,
        checkpoint=a.checkpoint,
        search_k=a.search_k,
        max_hypotheses=a.max_hypotheses,
        known_defects=a.known_defects,
        mask_fixed_sources=a.mask_fixed_sources,
        truth_wcs=a.truth_wcs,
        wcs_rows_from_bottom=a.wcs_rows_from_bottom,
        track_hint_deg=a.track_hint_deg,
        track_n=a.track_n,
        log=lambda s: print(s, file=sys.stderr),
    )
    res["command"] = "python benchmarks/real_few_star.py " + " ".join(argv if argv is not None else sys.argv[1:])
    md = markdown(res, a.title)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "real_few_star.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    (out / "real_few_star.md").write_text(md + f"\nCommand: `{res['command']}`\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
