"""Real Blackfly S frames against skygen frames of the same camera preset: the sim-to-real gap.

    python benchmarks/real_vs_sim.py [--real DIR] [--camera configs/cameras/blackfly-s-imx265-35mm.yaml]
                                     [--sim-frames 50] [--out results/real-frames]

For every real frame (ESA tetra3 test data, real-frames/tetra3-blackfly) and every
rendered frame: background level and noise (skygen's sigma-clipped estimator), detections
per frame (skygen's detector with the preset's settings; tetra3rs's own extractor, with
local background and a matched filter, for reference), star width (intensity-weighted
second moment of the 20 brightest unsaturated detections, 9 x 9 px), and on the real
frames the tetra3rs solution from skygen's detections against the listed plate solution.
The real TIFFs hold 12-bit values scaled by 16: they are divided by 16 to compare ADU.
With ``--checkpoint CK`` (a model trained for this camera, e.g. configs/blackfly.yaml) also
the learned path on every real frame, exactly as ``fusion predict FRAME --checkpoint CK
--solve`` runs it (raw TIFF values): the rank the model gives the region that holds the
listed boresight, and the coarse-to-fine attitude against the listed one.
Writes REPORT.md, real_vs_sim.json and real_vs_sim.png (a real and a rendered frame).
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

REAL = ROOT / "real-frames" / "tetra3-blackfly"


def listed_solutions(folder: Path = REAL) -> dict:
    """file name -> (ra, dec, fov, tetra3rs roll (+y east of north)) from solutions.csv."""
    import csv

    with open(folder / "solutions.csv", newline="") as f:
        return {
            r["file"]: (float(r["ra_deg"]), float(r["dec_deg"]), float(r["fov_deg"]), float(r["tetra3rs_roll_deg"]))
            for r in csv.DictReader(f)
        }


LISTED = listed_solutions()


def frame_stats(img: np.ndarray, cfg, saturation: float, box: int) -> dict:
    """skygen.real.frame_stats.frame_stats (the measurements skygen fit-camera reports too, one background per frame),
    plus detections with a background per ``box`` px box and tetra3rs's extractor."""
    import tetra3rs

    from skygen.instrument.detect import detect
    from skygen.real.frame_stats import frame_stats as shared_stats

    d = cfg.detection
    st, det = shared_stats(img, d.threshold_sigma, d.min_area_px, 0, saturation)  # counts them all
    local, _, _ = detect(img, d.threshold_sigma, d.min_area_px, 100_000, background_box_px=box)
    t3 = tetra3rs.extract_centroids(img.astype(np.float32), sigma_threshold=d.threshold_sigma, threads=1)
    h, w = img.shape
    t3det = {
        "x_px": np.array([c.x for c in t3.centroids]) + (w - 1) / 2,
        "y_px": np.array([c.y for c in t3.centroids]) + (h - 1) / 2,
        "flux_adu": np.array([c.brightness or 0.0 for c in t3.centroids]),
    }
    return {
        **st,
        "detections_local": int(len(local["x_px"])),
        "tetra3rs_centroids": int(len(t3.centroids)),
        "_det": det,
        "_t3": t3det,
        "_local": local,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--real", default=str(REAL))
    p.add_argument("--camera", default=str(ROOT / "configs" / "cameras" / "blackfly-s-imx265-35mm.yaml"))
    p.add_argument("--sim-frames", type=int, default=50)
    p.add_argument("--out", default=str(ROOT / "results" / "real-frames"))
    p.add_argument("--checkpoint", help="a model trained for this camera: score the learned path on the real frames")
    p.add_argument("--search", choices=("fine", "coarse"), default="fine", help="as fusion predict --search")
    p.add_argument("--search-k", type=int, help="regions the fine stage searches (as fusion predict --search-k)")
    p.add_argument("--focal-tol", type=float, default=0.02, help="as fusion predict --focal-tol")
    p.add_argument(
        "--background-box",
        type=int,
        default=64,
        help="box of the local background (as fusion predict --background-box); the learned path uses "
        "it (0: one background per frame)",
    )
    a = p.parse_args(argv)
    from fusion.solve.base import Detections, Solution
    from fusion.solve.frames import read_frame
    from fusion.solve.tetra import Tetra3Solver
    from skygen.config import config_dict, load_config
    from skygen.instrument.camera import Camera
    from skygen.render.frame import Renderer

    cfg = load_config(a.camera, ["output.full_res=true", f"n_frames={a.sim_frames}"])
    cam = Camera.from_config(cfg.camera)
    sat = 2**cfg.sensor.bit_depth - 1
    solver = Tetra3Solver(cam)
    real_rows = []
    for name, (ra, dec, fov, roll_t3) in LISTED.items():
        path = Path(a.real) / name
        if not path.exists():
            continue
        img = read_frame(path) / 16.0  # 12-bit values stored x16
        st = frame_stats(img, cfg, sat, a.background_box)
        res = solver.solve(Detections.from_table(st.pop("_det")), cam)
        res_local = solver.solve(Detections.from_table(st.pop("_local")).brightest(cfg.detection.max_detections), cam)
        res_t3 = solver.solve(Detections.from_table(st.pop("_t3")).brightest(cfg.detection.max_detections), cam)
        row = {
            "frame": name,
            **st,
            "tetra3rs_extractor_solution": _compare(res_t3, ra, dec, roll_t3),
            "local_background_solution": _compare(res_local, ra, dec, roll_t3),
        }
        if isinstance(res, Solution):
            dra = ((res.ra_deg - ra + 180) % 360 - 180) * np.cos(np.radians(dec)) * 3600
            row.update(
                {
                    "solved": True,
                    "d_ra_arcsec": dra,
                    "d_dec_arcsec": (res.dec_deg - dec) * 3600,
                    "d_roll_deg": ((res.roll_deg - (roll_t3 + 180.0)) + 180) % 360 - 180,
                    "fov_deg": res.extra["fov_deg"],
                    "listed_fov_deg": fov,
                    "n_matched": res.n_matched,
                    "residual_arcsec": res.residual_arcsec,
                }
            )
        else:
            row.update({"solved": False, "reason": res.reason})
        real_rows.append(row)
    if not real_rows:
        print(f"no real frames under {a.real}", file=sys.stderr)
        return 1
    r = Renderer(cfg)
    sim_rows, sim_example = [], None
    for i in range(a.sim_frames):
        f = r.render(i)
        st = frame_stats(f.image_full.astype(np.float32), cfg, sat, a.background_box)
        st.pop("_det"), st.pop("_t3"), st.pop("_local")
        sim_rows.append({"frame": i, **st})
        sim_example = f.image_full if i == 0 else sim_example
    keys = ("background_adu", "noise_adu", "detections", "detections_local", "tetra3rs_centroids", "star_sigma_px")

    def med(rows, k):
        return float(np.nanmedian([row[k] for row in rows]))

    def rng(rows, k):
        return (float(np.nanmin([row[k] for row in rows])), float(np.nanmax([row[k] for row in rows])))

    summary = {
        k: {
            "real_median": med(real_rows, k),
            "real_range": rng(real_rows, k),
            "sim_median": med(sim_rows, k),
            "sim_range": rng(sim_rows, k),
        }
        for k in keys
    }
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    learned = (
        _learned(a.checkpoint, a.real, a.search, a.search_k, a.focal_tol, a.background_box) if a.checkpoint else None
    )
    report = {
        "camera_preset": str(Path(a.camera).resolve().relative_to(ROOT)),
        "camera_config": config_dict(cfg)["camera"],
        "summary": summary,
        "background_box": a.background_box,
        "real": real_rows,
        "sim": sim_rows,
        "learned": learned,
        "hardware": f"{platform.machine()} CPU",
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    (out / "real_vs_sim.json").write_text(json.dumps(report, indent=1, default=float) + "\n")
    _plot(Path(a.real) / list(LISTED)[6], sim_example, out / "real_vs_sim.png", read_frame)
    (out / "REPORT.md").write_text(markdown(report))
    print((out / "REPORT.md").read_text())
    return 0


def _learned(checkpoint: str, real: str, search: str, search_k: int | None, focal_tol: float, box: int) -> dict:
    """The learned path of ``fusion predict --checkpoint CK --solve`` on every listed real frame."""
    from fusion.model.regions import assign, radec_to_unit
    from fusion.solve.frames import read_frame
    from fusion.solve.predict import Predictor

    pred = Predictor(checkpoint, solve=True, search=search, search_k=search_k, focal_tol=focal_tol, background_box=box)
    centroids = pred.solver.prior.centroids
    # a process's first frame also loads numba's compiled kernels, tetra3rs's database and torch's first
    # forward: timed once here, on the first listed frame, and kept out of the per-frame figures
    first = next((Path(real) / n for n in LISTED if (Path(real) / n).exists()), None)
    warm_ms = None
    if first is not None:
        t0 = time.perf_counter()
        img = read_frame(first)
        det, _, _ = pred.detect(img)
        pred.run(first.name, det, pred.stored_image(img), {})
        warm_ms = (time.perf_counter() - t0) * 1e3
    rows = []
    for name, (ra, dec, fov, roll_t3) in LISTED.items():
        path = Path(real) / name
        if not path.exists():
            continue
        img = read_frame(path)  # as fusion predict reads it: no rescaling
        t_det = time.perf_counter()
        det, _, _ = pred.detect(img)
        t_model = time.perf_counter()
        coarse, fine = pred.prior.both(det, pred.stored_image(img))
        model_ms = (time.perf_counter() - t_model) * 1e3
        detect_ms = (t_model - t_det) * 1e3
        v = radec_to_unit(np.array([ra]), np.array([dec]))
        probs = fine if pred.search_level == "fine" else coarse
        true_region = int(assign(v, centroids)[0])
        true_coarse = int(assign(v, pred.prior.coarse_centroids)[0])
        t0 = time.perf_counter()
        res = pred.solver.solve(det, pred.camera, None, probabilities=probs)
        row = {
            "frame": name,
            "detections": len(det),
            "true_region": true_region,
            "true_region_rank": int(np.sum(probs > probs[true_region])) + 1,
            "true_region_probability": float(probs[true_region]),
            "top1_probability": float(probs.max()),
            "true_coarse_rank": int(np.sum(coarse > coarse[true_coarse])) + 1,
            "solve_ms": (time.perf_counter() - t0) * 1e3,
            "model_ms": model_ms,
            "detect_ms": detect_ms,
            **_compare(res, ra, dec, roll_t3),
        }
        if row["solved"]:
            row["confidence"] = float(res.confidence)
            row["fov_deg"] = float(res.extra["fov_deg"][0])
            row["listed_fov_deg"] = fov
        rows.append(row)
    summary = Path(checkpoint).parent / "summary.json"
    training = None
    if summary.is_file():
        sm = json.loads(summary.read_text())
        training = {
            "wall_time_min": sm.get("wall_time_s", 0) / 60,
            "samples_seen": sm.get("samples_seen"),
            "val_top1": sm["best"].get("val_top1"),
            "val_top3": sm["best"].get("val_top3"),
        }
    return {
        "checkpoint": str(checkpoint),
        "training": training,
        "search": pred.search_level,
        "search_k": pred.solver.top_k,
        "regions": int(len(centroids)),
        "focal_tol": focal_tol,
        "background_box": box,
        "rows": rows,
        "solver": pred.solver.name,
        "first_frame_ms": warm_ms,
    }


def _compare(res, ra, dec, roll_t3) -> dict:
    from fusion.solve.base import Solution

    if not isinstance(res, Solution):
        return {"solved": False, "reason": res.reason}
    return {
        "solved": True,
        "d_ra_arcsec": ((res.ra_deg - ra + 180) % 360 - 180) * np.cos(np.radians(dec)) * 3600,
        "d_dec_arcsec": (res.dec_deg - dec) * 3600,
        "d_roll_deg": ((res.roll_deg - (roll_t3 + 180.0)) + 180) % 360 - 180,
        "n_matched": res.n_matched,
        "residual_arcsec": res.residual_arcsec,
    }


def _plot(real_path, sim, path, read_frame):
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    real = read_frame(real_path) / 16.0
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.4))
    for a_, img, title in (
        (ax[0], real, f"real: {real_path.name[:30]}"),
        (ax[1], sim.astype(float), "skygen, same preset"),
    ):
        lo, hi = np.percentile(img, [1, 99.8])
        a_.imshow(np.clip((img - lo) / max(hi - lo, 1), 0, 1) ** 0.5, cmap="gray", origin="upper")
        a_.set_title(title, fontsize=9)
        a_.axis("off")
    fig.savefig(path, dpi=90, bbox_inches="tight")


def markdown(r: dict) -> str:
    s = r["summary"]
    lab = {
        "background_adu": "background level (12-bit ADU)",
        "noise_adu": "background noise σ (ADU)",
        "detections": "detections / frame (skygen detector, one background, 5σ, ≥3 px)",
        "detections_local": f"detections / frame (skygen detector, {r['background_box']} px background boxes)",
        "tetra3rs_centroids": "centroids / frame (tetra3rs extractor, 5σ, matched filter)",
        "star_sigma_px": "star width σ (px, 2nd moment, 9×9)",
    }

    def ratio(k):
        return s[k]["real_median"] / s[k]["sim_median"]

    lines = [
        "# Real Blackfly S frames vs skygen frames of the same camera",
        "",
        f"`python benchmarks/real_vs_sim.py` ({r['hardware']}, {r['created_utc']}): the 8 real frames of "
        "`real-frames/tetra3-blackfly` (ESA tetra3 test data, Apache-2.0; ground-based, through the "
        f"atmosphere) against {len(r['sim'])} frames rendered from `{r['camera_preset']}` (uniform random "
        "boresights). Real TIFF values are divided by 16 (12-bit data stored ×16).",
        "",
        "| quantity | real median (range) | skygen median (range) |",
        "|---|---|---|",
    ]
    for k, v in s.items():
        lines.append(
            f"| {lab[k]} | {v['real_median']:.1f} ({v['real_range'][0]:.1f}–{v['real_range'][1]:.1f}) | "
            f"{v['sim_median']:.1f} ({v['sim_range'][0]:.1f}–{v['sim_range'][1]:.1f}) |"
        )
    lines += [
        "",
        "What the gap says (the preset is datasheet-nominal, not fitted to these frames):",
        "",
        f"- **background and noise**: the real frames sit {ratio('background_adu'):.0f}x higher and are "
        f"{ratio('noise_adu'):.0f}x noisier than the preset renders — ground sky glow and a longer exposure "
        "or higher gain than the guessed 0.2 s at 10 e-/ADU; an orbiting tracker sees neither the glow nor "
        "its gradients;",
        f"- **detections**: skygen's detector with one background level per frame (5σ) finds a median "
        f"{s['detections']['real_median']:.0f} stars per real frame, with a background per "
        f"{r['background_box']} px box (`--background-box {r['background_box']}`) "
        f"{s['detections_local']['real_median']:.0f}, tetra3rs's extractor (local background, matched "
        f"filter) {s['tetra3rs_centroids']['real_median']:.0f}: the sky glow is not flat; rendered frames "
        "of the preset give far more detections than real ones because their noise is far lower;",
        f"- **star width**: real stars are {ratio('star_sigma_px'):.2f}x wider (seeing and focus; σ "
        f"{s['star_sigma_px']['real_median']:.2f} px against {s['star_sigma_px']['sim_median']:.2f} px "
        "measured the same way on renders with `psf_sigma_px` 1.0);",
        "- **geometry**: the plate solutions give a field of 11.42–11.43°, the nominal 35 mm lens 11.53°: "
        "the effective focal length is ~1 % longer. tetra3rs fits the scale and is unaffected; the "
        "coarse-to-fine stage fits it too (`--focal-tol`, ±2 % by default).",
        "",
    ]
    lines += [
        "",
        "## Solving the real frames (skygen detector → tetra3rs lost-in-space)",
        "",
        "Compared with the listed plate solutions (tetra3rs 0.14 on its own 64–144 centroids). Listed roll is "
        "tetra3rs's (+y east of north) = skygen roll − 180°.",
        "",
        "| frame | detections | solved | ΔRA cos δ (″) | ΔDec (″) | Δroll (°) | fov solved / listed (°) | matched | "
        "rms (″) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in r["real"]:
        if row["solved"]:
            lines.append(
                f"| {row['frame'][18:-10]} | {row['detections']} | yes | {row['d_ra_arcsec']:.1f} | "
                f"{row['d_dec_arcsec']:.1f} | {row['d_roll_deg']:.3f} | {row['fov_deg']:.3f} / "
                f"{row['listed_fov_deg']:.3f} | {row['n_matched']} | {row['residual_arcsec']:.1f} |"
            )
        else:
            lines.append(f"| {row['frame'][18:-10]} | {row['detections']} | no ({row['reason']}) | | | | | | |")
    t3 = [row["tetra3rs_extractor_solution"] for row in r["real"]]
    ok = [x for x in t3 if x["solved"]]
    if ok:
        lines += [
            "",
            f"With tetra3rs's extractor instead (`fusion predict --detector tetra3rs`, brightest 64): "
            f"{len(ok)} of {len(t3)} frames solved; largest offsets from the listed solutions "
            f"{max(abs(x['d_ra_arcsec']) for x in ok):.1f}″ in RA cos δ, "
            f"{max(abs(x['d_dec_arcsec']) for x in ok):.1f}″ "
            f"in Dec, {max(abs(x['d_roll_deg']) for x in ok):.3f}° in roll; median "
            f"{np.median([x['n_matched'] for x in ok]):.0f} matched stars, rms "
            f"{np.median([x['residual_arcsec'] for x in ok]):.1f}″.",
        ]
    loc = [row["local_background_solution"] for row in r["real"]]
    ok = [x for x in loc if x["solved"]]
    lines += [
        "",
        f"With a background per {r['background_box']} px box (`--background-box {r['background_box']}`, "
        f"brightest 64): tetra3rs lost-in-space solves {len(ok)} of {len(loc)} frames"
        + (
            f"; largest offsets from the listed solutions {max(abs(x['d_ra_arcsec']) for x in ok):.1f}″ in RA "
            f"cos δ, {max(abs(x['d_dec_arcsec']) for x in ok):.1f}″ in Dec, "
            f"{max(abs(x['d_roll_deg']) for x in ok):.3f}° in roll; median "
            f"{np.median([x['n_matched'] for x in ok]):.0f} matched stars."
            if ok
            else "."
        ),
    ]
    if r.get("learned"):
        lines += _learned_markdown(r["learned"])
    lines += [
        "",
        "Commands for the same from the CLI: `fusion predict real-frames/tetra3-blackfly/*.tiff "
        "--camera configs/cameras/blackfly-s-imx265-35mm.yaml --solve [--background-box 64 | --detector "
        "tetra3rs] --overlay DIR` (tetra3rs lost-in-space) and `fusion predict "
        "real-frames/tetra3-blackfly/*.tiff --checkpoint runs/blackfly/best.pt --solve "
        "--background-box 64` (the learned path).",
        "",
        "![real vs sim](real_vs_sim.png)",
        "",
        "The gap closed by fitting a camera to these frames (`skygen fit-camera`): [FIT_CAMERA.md](FIT_CAMERA.md) "
        "(`configs/cameras/blackfly-fitted.yaml`).",
        "",
    ]
    return "\n".join(lines)


def _learned_markdown(le: dict) -> list[str]:
    rows = le["rows"]
    n, k = len(rows), le["search_k"]
    top1 = sum(r["true_region_rank"] == 1 for r in rows)
    topk = sum(r["true_region_rank"] <= k for r in rows)
    coarse3 = sum(r["true_coarse_rank"] <= 3 for r in rows)
    solved = [r for r in rows if r["solved"]]
    wrong = [r for r in solved if abs(r["d_ra_arcsec"]) > 360 or abs(r["d_dec_arcsec"]) > 360]
    what = f"{le['regions']} fine regions" if le["search"] == "fine" else f"{le['regions']} regions"
    lines = [
        "",
        "## The learned path: `fusion predict --checkpoint CK --solve` on the real frames",
        "",
        f"Checkpoint `{le['checkpoint']}` (trained only on skygen's detections stream of its camera file"
        + (
            f"; {tr['samples_seen'] / 1e6:.1f} M samples in {tr['wall_time_min']:.0f} min on this CPU, "
            f"{100 * tr['val_top1']:.1f} % top-1 / {100 * tr['val_top3']:.0f} % top-3 on rendered val frames"
            if (tr := le.get("training"))
            else ""
        )
        + "). "
        f"Searched: the {k} most probable of its {what}, focal length within ±{100 * le['focal_tol']:g} % of "
        f"the preset's (`--focal-tol {le['focal_tol']:g}`), skygen's detector with "
        + (
            f"{le['background_box']} px background boxes (`--background-box {le['background_box']}`)"
            if le.get("background_box")
            else "one background per frame"
        )
        + ". The region holding the listed boresight is ranked "
        f"first in {top1} of {n} frames and within the {k} searched in {topk} (coarse regions: within the top 3 "
        f"in {coarse3}); the coarse-to-fine stage returns an attitude for {len(solved)} of {n} frames, "
        f"{len(wrong)} of them more than 0.1° from the listed one. (A frame whose own fine region is not "
        "among those searched can still be solved: each searched region is a cap around its centroid that "
        "covers its whole cell, and so parts of the neighbouring cells; the attitude itself is always "
        "verified against the catalog, never taken from the region.)"
        + (f" Solver `{le['solver']}`." if le.get("solver") else "")
        + (
            f" Times below are per frame once the process is warm: its first frame, which also loads the "
            f"compiled kernels, the tetra3rs database and torch, took {le['first_frame_ms']:.0f} ms (detector, "
            "model and solver together; run once before the table)."
            if le.get("first_frame_ms")
            else ""
        ),
        "",
        "| frame | detections | rank of the true region (probability) | solved | ΔRA cos δ (″) | "
        "ΔDec (″) | Δroll (°) | fov fitted / listed (°) | confidence | ms: model + fine stage (detector) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        head = (
            f"| {r['frame'][18:-10]} | {r['detections']} | {r['true_region_rank']} "
            f"({r['true_region_probability']:.3f}) | "
        )
        if r["solved"]:
            lines.append(
                head + f"yes | {r['d_ra_arcsec']:.1f} | {r['d_dec_arcsec']:.1f} | {r['d_roll_deg']:.3f} | "
                f"{r['fov_deg']:.3f} / {r['listed_fov_deg']:.3f} | {r['confidence']:.6f} | "
                f"{r.get('model_ms', 0) + r['solve_ms']:.0f} ({r.get('detect_ms', 0):.0f}) |"
            )
        else:
            lines.append(
                head + f"no ({r['reason']}) | | | | | | "
                f"{r.get('model_ms', 0) + r['solve_ms']:.0f} ({r.get('detect_ms', 0):.0f}) |"
            )
    return lines


if __name__ == "__main__":
    sys.exit(main())
