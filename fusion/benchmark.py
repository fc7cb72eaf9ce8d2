"""``fusion benchmark``: every solver scored on the same detections of the same frames.

Frames: the first ``--frames`` frames of a split (default ``test``) of a skygen dataset,
fixed. Cells of the grid:

* ``clean``: the stored detections, brightest ``N`` kept, for each N of ``--n``;
* one cell per (corruption, severity, N) for the detection-level corruptions of skygen's
  registry (``dropout``, ``false_stars``, ``centroid_noise``, ``magnitude_noise``; severities
  from the registry's sweep, in its units) at each N of ``--corruption-n``. Dropout,
  centroid and magnitude noise are :func:`skygen.corruptions.apply_detection_corruptions` on
  the stored table with the stream ``/benchmark``; ``false_stars`` (a *scene* corruption in
  the generator) is emulated on the table: Poisson(severity) detections at uniform sensor
  positions, each with the flux of a randomly chosen real detection of the frame, so they
  compete for the brightest-N slots. Every draw depends only on (dataset seed, frame index,
  corruption), so all solvers see identical inputs; then the brightest N are kept.

Solvers (``--solvers``):

* ``tetra3rs`` — tetra3rs lost-in-space (the classical baseline, :mod:`fusion.solvers.tetra`);
* ``oracle-prior`` — coarse-to-fine with a prior that ranks the true region first (an upper
  bound for a learned prior; regions: the ones the learned prior searches — the checkpoint's
  fine regions with ``--search fine`` (default) or its K regions — or, without a checkpoint,
  K = 15 spherical K-means regions of the sphere);
* ``sim85-prior`` — the same with the true region first in 85 % of frames, second otherwise
  (the top-1 expected of the issue-10 model; a simulation, not a model);
* ``whole-sky`` — the same few-star identification over the whole sky (no prior): what the
  prior adds over classical search alone (slow: about 0.2–0.4 s per frame);
* ``learned`` / ``learned+fine`` — with ``--checkpoint``: the model's regions alone (top-1/top-3
  accuracy of its K regions, angular error of the top-1 centroid, and how often the true fine
  region is among the ``--top-k`` searched), and coarse-to-fine with the model as prior;
* ``tetra3rs>learned+fine`` — tetra3rs lost-in-space, and learned + fine where it refuses
  (``fusion predict --solve --lis-first``).

The coarse-to-fine solvers run as ``fusion predict --solve`` does: ``--search fine`` (the
20 most probable fine regions) and ``--focal-tol 0.02`` by default, so the benchmark scores
what a user gets; the frames are rendered at the nominal focal length, so the tolerance
only costs here (``--focal-tol 0`` shows how much).

Definitions: a returned attitude is **correct** when its boresight is within ``--correct-deg``
(0.1° by default) of the true boresight and its roll within ``--correct-roll-deg`` (1°) of the
true roll, **wrong** otherwise; a refusal is **refused**. A wrong star identification errs by
degrees; the looser roll bound keeps correct identifications of a few close stars with
noisy centroids (roll is the weakly constrained angle then) from counting as wrong, and
the error statistics report the precision. Boresight and roll errors are over
returned attitudes (median, p95 and max, arcseconds); ms/frame is the mean wall time of the
solver call on one core. A region is correct when it is the max-cosine region of the true
boresight (as ``fusion evaluate`` labels frames).

Outputs in ``--out``: ``benchmark.json`` (every cell, every solver), ``benchmark.md``
(tables), ``success_vs_n.png`` and ``success_vs_<corruption>.png``.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np

from skygen import corruptions as corr
from skygen.camera import Camera
from skygen.config import build_config as build_render_config
from skygen.io import open_dataset

from .checkpoint import atomic_write_text, write_json
from .errors import ConfigError
from .solvers.base import Detections, Solution, boresight_error_deg, roll_error_deg

DETECTION_CORRUPTIONS = ("dropout", "false_stars", "centroid_noise", "magnitude_noise")
FULL_N = (3, 4, 5, 6, 7, 8, 10, 12, 15, 20)
SMALL_N = (4, 6, 10)
SOLVERS = ("tetra3rs", "oracle-prior", "sim85-prior", "whole-sky", "learned", "learned+fine", "tetra3rs>learned+fine")


def corrupt(det: dict, name: str | None, severity: float, seed: int, frame_index: int,
            width_px: int, height_px: int) -> Detections:
    """The detection table of one frame with one detection-level corruption (see the module doc)."""
    if name is None or severity == 0:
        return Detections.from_table(det)
    if name == "false_stars":
        rng = corr.stage_rng(seed, frame_index, "false_stars/benchmark")
        n = int(rng.poisson(severity))
        flux = np.asarray(det["flux_adu"], np.float64)
        fake = rng.choice(flux, n) if len(flux) else np.full(n, 1000.0)
        table = {"x_px": np.concatenate([det["x_px"], rng.uniform(-0.5, width_px - 0.5, n)]),
                 "y_px": np.concatenate([det["y_px"], rng.uniform(-0.5, height_px - 0.5, n)]),
                 "flux_adu": np.concatenate([flux, fake])}
        return Detections.from_table(table)
    corr.get(name)
    out, _ = corr.apply_detection_corruptions(det, {name: float(severity)}, seed, frame_index, stream="/benchmark")
    return Detections.from_table(out)


def grid(n_values, corruption_n, corruptions, severities: dict | None = None) -> list[dict]:
    """Cells: clean at every N of ``n_values``; each corruption's severities (default: the registry's nonzero
    sweep) at every N of ``corruption_n``."""
    cells = [{"corruption": None, "severity": 0.0, "n": int(n)} for n in n_values]
    for name in corruptions:
        sev = (severities or {}).get(name) or [s for s in corr.get(name).sweep if s > 0]
        cells += [{"corruption": name, "severity": float(s), "n": int(n)} for n in corruption_n for s in sev]
    return cells


def default_centroids(k: int = 15) -> np.ndarray:
    """K regions of the sphere for the oracle priors when no checkpoint is given (spherical K-means)."""
    from .labels import spherical_kmeans
    rng = np.random.default_rng(0)
    v = rng.standard_normal((20000, 3))
    return spherical_kmeans(v / np.linalg.norm(v, axis=1, keepdims=True), k, seed=0, n_init=2).centroids


def _summary(results: list, truth: list, secs: list, correct_deg: float, correct_roll_deg: float) -> dict:
    ok = wrong = refused = 0
    bore, roll = [], []
    for res, (m_true, roll_true) in zip(results, truth):
        if not isinstance(res, Solution):
            refused += 1
            continue
        b, o = boresight_error_deg(m_true, res.matrix), roll_error_deg(res.roll_deg, roll_true)
        ok, wrong = (ok + 1, wrong) if b <= correct_deg and o <= correct_roll_deg else (ok, wrong + 1)
        bore.append(b * 3600)
        roll.append(o * 3600)
    n = len(results)
    stat = lambda a: ({"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(np.max(a))}
                      if a else None)
    return {"frames": n, "correct": ok / n, "wrong": wrong / n, "refused": refused / n,
            "boresight_error_arcsec": stat(bore), "roll_error_arcsec": stat(roll),
            "ms_per_frame": 1e3 * float(np.mean(secs))}


def run_benchmark(data: str | Path, out: str | Path, *, checkpoint: str | Path | None = None, split: str = "test",
                  frames: int = 200, n_values=FULL_N, corruption_n=(6, 10), corruptions=DETECTION_CORRUPTIONS,
                  severities=None, solvers=("tetra3rs", "oracle-prior", "sim85-prior", "learned", "learned+fine"),
                  correct_deg: float = 0.1, correct_roll_deg: float = 1.0, top_k: int | None = None,
                  search: str = "fine", focal_tol: float = 0.02, log=print) -> dict:
    from .solvers.coarse_fine import CoarseToFineSolver
    from .predict import check_search_options, default_search_k
    from .solvers.priors import OraclePrior, load_prior
    from .solvers.tetra import Tetra3Solver
    check_search_options(focal_tol, top_k, "--top-k")
    unknown = set(solvers) - set(SOLVERS)
    if unknown:
        raise ConfigError(f"--solvers: unknown {sorted(unknown)}; choose from {', '.join(SOLVERS)}")
    for c in corruptions:
        if c not in DETECTION_CORRUPTIONS:
            raise ConfigError(f"--corruptions: {c!r} is not a detection-level corruption; choose from "
                              f"{', '.join(DETECTION_CORRUPTIONS)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    with open_dataset(data) as ds:
        rcfg = build_render_config(ds.config)
        cam = Camera.from_config(rcfg.camera)
        pos = ds.indices(split)[:frames]
        if not len(pos):
            raise ConfigError(f"--split {split}: dataset {data} holds no {split} frames")
        idx = ds.frames["index"][pos]
        tables = [ds.detections(int(p)) for p in pos]
        images = [ds.image(int(p)) for p in pos] if checkpoint else [None] * len(pos)
        q_true = np.asarray(ds.boresight["quaternion"][pos], np.float64)
        v_true = np.asarray(ds.boresight["unit_vector"][pos], np.float64)
        roll_true = np.asarray(ds.boresight["roll_deg"][pos], np.float64)
        seed = int(ds.config["seed"])
        dataset_info = {"path": str(ds.root), "dataset_id": ds.manifest.get("dataset_id"), "split": split,
                        "frames": int(len(pos))}
    from skygen.attitude import quaternion_to_matrix
    truth = [(quaternion_to_matrix(q), r) for q, r in zip(q_true, roll_true)]
    tetra = Tetra3Solver(cam, log=log)
    prior, search_prior, notes = None, None, []
    if checkpoint:
        from .checkpoint import load_checkpoint
        own = load_checkpoint(checkpoint).get("render_config")       # older checkpoints: the benchmark dataset's
        prior = load_prior(checkpoint, None if own else dict(ds.config))
        if own and own["camera"] != ds.config["camera"]:
            raise ConfigError(f"{checkpoint} was trained for another camera than dataset {data} "
                              f"({own['camera']} vs {ds.config['camera']}); benchmark it on frames of its camera")
        search_prior = prior.at_level(search) if hasattr(prior, "at_level") else prior
        centroids = prior.centroids
        search_centroids = search_prior.centroids
        level = getattr(search_prior, "level", "coarse")
    else:
        centroids = search_centroids = default_centroids()
        level = "coarse"
        dropped = [s for s in solvers if "learned" in s]
        if dropped:
            notes.append(f"{', '.join(dropped)}: skipped, no --checkpoint given (pending a trained model)")
        solvers = [s for s in solvers if "learned" not in s]
    top_k = top_k or default_search_k(level)
    c2f = dict(top_k=top_k, focal_tol=focal_tol)
    built = {}
    if "tetra3rs" in solvers:
        built["tetra3rs"] = tetra
    oracle = OraclePrior(search_centroids, 1.0)
    sim = OraclePrior(search_centroids, 0.85, seed=1)
    if "oracle-prior" in solvers:
        built["oracle-prior"] = CoarseToFineSolver(tetra, oracle, name="oracle-prior", **c2f)
    if "sim85-prior" in solvers:
        built["sim85-prior"] = CoarseToFineSolver(tetra, sim, name="sim85-prior", **c2f)
    if "whole-sky" in solvers:
        built["whole-sky"] = CoarseToFineSolver(tetra, None, name="whole-sky", focal_tol=focal_tol)
    if "learned+fine" in solvers or "tetra3rs>learned+fine" in solvers:
        lf = CoarseToFineSolver(tetra, search_prior, name="learned+fine", **c2f)
        if "learned+fine" in solvers:
            built["learned+fine"] = lf
    composite = {}
    if "tetra3rs>learned+fine" in solvers:
        if "tetra3rs" in built and "learned+fine" in built:
            # both parts are scored anyway: compose their per-frame answers instead of solving twice
            composite["tetra3rs>learned+fine"] = ("tetra3rs", "learned+fine")
        else:
            from .solvers.base import FallbackSolver
            built["tetra3rs>learned+fine"] = FallbackSolver(tetra, lf)
    labels = np.argmax(v_true @ centroids.T, axis=1)
    search_labels = np.argmax(v_true @ search_centroids.T, axis=1)
    cells = grid(n_values, corruption_n, corruptions, severities)
    log(f"benchmark: {len(pos)} frames x {len(cells)} cells; solvers: {', '.join(solvers)}")
    rows = []
    for ci, cell in enumerate(cells):
        dets = [corrupt(t, cell["corruption"], cell["severity"], seed, int(i), cam.width_px, cam.height_px)
                .brightest(cell["n"]) for t, i in zip(tables, idx)]
        row = {**cell, "mean_detections": float(np.mean([len(d) for d in dets])), "solvers": {}}
        answers = {}
        for name, solver in built.items():
            results, secs = [], []
            for j, d in enumerate(dets):
                kw = {}
                if name == "oracle-prior":
                    kw["probabilities"] = oracle.probabilities_for(v_true[j], int(idx[j]))
                elif name == "sim85-prior":
                    kw["probabilities"] = sim.probabilities_for(v_true[j], int(idx[j]))
                t0 = time.perf_counter()
                results.append(solver.solve(d, cam, images[j], **kw))
                secs.append(time.perf_counter() - t0)
            row["solvers"][name] = _summary(results, truth, secs, correct_deg, correct_roll_deg)
            answers[name] = (results, secs)
        for name, (a, b) in composite.items():
            (ra, sa), (rb, sb) = answers[a], answers[b]
            first = [isinstance(x, Solution) for x in ra]
            row["solvers"][name] = _summary([x if ok else y for x, y, ok in zip(ra, rb, first)], truth,
                                            [x if ok else x + y for x, y, ok in zip(sa, sb, first)],
                                            correct_deg, correct_roll_deg)
        if "learned" in solvers:
            row["solvers"]["learned"] = _learned_cell(prior, dets, images, labels, v_true, centroids,
                                                      search_labels if level == "fine" else None, top_k)
        rows.append(row)
        log(_cell_line(row, ci, len(cells)))
    report = {"dataset": dataset_info, "camera": {"width_px": cam.width_px, "height_px": cam.height_px,
                                                  "fov_deg": list(cam.fov_deg)},
              "checkpoint": str(checkpoint) if checkpoint else None, "solvers": list(built) + list(composite) + (
                  ["learned"] if "learned" in solvers else []),
              "correct_definition": f"boresight error <= {correct_deg} deg and roll error <= {correct_roll_deg} deg",
              "region_count": int(len(centroids)), "search": {"level": level, "regions": int(len(search_centroids)),
                                                              "top_k": top_k, "focal_tol": focal_tol},
              "top_k": top_k, "notes": notes, "cells": rows,
              "hardware": _hardware(),
              "tetra3rs_version": tetra.t3.__version__, "wall_time_s": time.perf_counter() - t_start}
    write_json(out / "benchmark.json", report)
    atomic_write_text(out / "benchmark.md", markdown(report))
    plot(report, out)
    log(f"wrote {out / 'benchmark.json'}, benchmark.md and plots ({report['wall_time_s']:.0f} s)")
    return report


def _hardware() -> str:
    import os
    model = platform.processor() or "unknown model"
    try:
        with open("/proc/cpuinfo") as f:
            model = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), model)
    except OSError:
        pass
    return f"{platform.machine()} {model}, {os.cpu_count()} logical CPUs, one process"


def _learned_cell(prior, dets, images, labels, v_true, centroids, search_labels, search_k) -> dict:
    """The model's regions alone: top-1 / top-3 of its K regions, angular error of the top-1 centroid, and
    (``search_labels`` given) how often the true fine region is among the ``search_k`` searched."""
    t, probs, fine = [], [], []
    for d, im in zip(dets, images):
        t0 = time.perf_counter()
        if hasattr(prior, "both"):
            c, f = prior.both(d, im)
        else:
            c, f = prior.probabilities(d, im), None
        t.append(time.perf_counter() - t0)
        probs.append(c)
        fine.append(f)
    p = np.array(probs)
    order = np.argsort(-p, axis=1)
    top1 = order[:, 0] == labels
    top3 = (order[:, :3] == labels[:, None]).any(axis=1)
    err = np.degrees(np.arccos(np.clip(np.sum(v_true * centroids[order[:, 0]], axis=1), -1, 1)))
    out = {"frames": len(dets), "top1": float(top1.mean()), "top3": float(top3.mean()),
           "angular_error_deg": {"median": float(np.median(err)), "p95": float(np.percentile(err, 95))},
           "ms_per_frame": 1e3 * float(np.mean(t))}
    if search_labels is not None and fine[0] is not None:
        fo = np.argsort(-np.array(fine), axis=1)[:, :search_k]
        out[f"fine_top{search_k}"] = float((fo == search_labels[:, None]).any(axis=1).mean())
    return out


def _cell_name(c: dict) -> str:
    return "clean" if c["corruption"] is None else f"{c['corruption']}={c['severity']:g}"


def _cell_line(row: dict, i: int, n: int) -> str:
    parts = []
    for name, s in row["solvers"].items():
        parts.append(f"{name} {100 * s['correct']:.0f}%/{100 * s['wrong']:.0f}%" if "correct" in s
                     else f"{name} top1 {100 * s['top1']:.0f}%")
    return f"[{i + 1}/{n}] {_cell_name(row)} N={row['n']}: " + ", ".join(parts)


def markdown(r: dict) -> str:
    full = [s for s in r["solvers"] if s != "learned"]
    lines = [f"# Solver benchmark on `{r['dataset']['path']}` ({r['dataset']['split']}, {r['dataset']['frames']} "
             "frames)", "",
             f"Camera {r['camera']['width_px']} x {r['camera']['height_px']} px, field "
             f"{r['camera']['fov_deg'][0]:.2f} x {r['camera']['fov_deg'][1]:.2f} deg; {r['region_count']} regions; "
             f"{_search_text(r)}; tetra3rs {r['tetra3rs_version']}; {r['hardware']}; "
             f"{r['wall_time_s']:.0f} s in all.", "",
             f"**correct** = {r['correct_definition']}; **wrong** = any other returned attitude; **refused** = no "
             "attitude returned. Each entry: correct / wrong / refused (%), then ms per frame.", ""]
    lines += [f"- {n}" for n in r["notes"]] + ([""] if r["notes"] else [])
    head = "| cell | N | mean det. | " + " | ".join(full) + (" | learned top-1 / top-3 |" if "learned" in r["solvers"]
                                                            else "")
    lines += [head.rstrip(" |") + " |", "|" + "---|" * (3 + len(full) + ("learned" in r["solvers"]))]
    for row in r["cells"]:
        cols = []
        for name in full:
            s = row["solvers"][name]
            cols.append(f"{100 * s['correct']:.0f} / {100 * s['wrong']:.0f} / {100 * s['refused']:.0f} "
                        f"({s['ms_per_frame']:.1f} ms)")
        if "learned" in r["solvers"]:
            s = row["solvers"]["learned"]
            k = [key for key in s if key.startswith("top") and key != "top1"][0]
            fk = [key for key in s if key.startswith("fine_top")]
            fine = f"; fine top-{fk[0][8:]} {100 * s[fk[0]]:.0f}" if fk else ""
            cols.append(f"{100 * s['top1']:.0f} / {100 * s[k]:.0f}{fine} (median err "
                        f"{s['angular_error_deg']['median']:.1f}°)")
        lines.append(f"| {_cell_name(row)} | {row['n']} | {row['mean_detections']:.1f} | " + " | ".join(cols) + " |")
    lines += ["", "Attitude errors of returned solutions (median boresight / median roll, arcsec), clean cells:", "",
              "| N | " + " | ".join(full) + " |", "|---|" + "---|" * len(full)]
    for row in r["cells"]:
        if row["corruption"] is None:
            cols = []
            for name in full:
                s = row["solvers"][name]
                b, o = s["boresight_error_arcsec"], s["roll_error_arcsec"]
                cols.append("–" if b is None else f"{b['median']:.1f} / {o['median']:.1f}")
            lines.append(f"| {row['n']} | " + " | ".join(cols) + " |")
    return "\n".join(lines) + "\n"


def _search_text(r: dict) -> str:
    se = r.get("search") or {"level": "coarse", "regions": r["region_count"], "top_k": r["top_k"], "focal_tol": 0.0}
    what = "fine regions" if se["level"] == "fine" else "regions"
    return (f"coarse-to-fine solvers search the top {se['top_k']} of {se['regions']} {what}, focal length "
            f"within ±{100 * se['focal_tol']:g} %")


def plot(r: dict, out: Path) -> None:
    from .plots import _figure, _save
    plt = _figure()
    full = [s for s in r["solvers"] if s != "learned"]
    clean = [row for row in r["cells"] if row["corruption"] is None]
    if clean:
        fig, ax = plt.subplots(figsize=(6, 4))
        ns = [row["n"] for row in clean]
        for name in full:
            ax.plot(ns, [100 * row["solvers"][name]["correct"] for row in clean], "o-", label=f"{name} correct")
            wrong = [100 * row["solvers"][name]["wrong"] for row in clean]
            if any(wrong):
                ax.plot(ns, wrong, "x:", label=f"{name} wrong")
        if "learned" in r["solvers"]:
            ax.plot(ns, [100 * row["solvers"]["learned"]["top1"] for row in clean], "s--", label="learned region top-1")
        ax.set_xlabel("detections kept (brightest N)")
        ax.set_ylabel("% of frames")
        ax.set_ylim(-2, 102)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        ax.set_title("clean detections")
        _save(fig, out / "success_vs_n.png")
        plt.close(fig)
    for name in sorted({row["corruption"] for row in r["cells"] if row["corruption"]}):
        rows = [row for row in r["cells"] if row["corruption"] == name]
        fig, ax = plt.subplots(figsize=(6, 4))
        for n in sorted({row["n"] for row in rows}):
            sub = sorted([row for row in rows if row["n"] == n], key=lambda x: x["severity"])
            base = [row for row in clean if row["n"] == n]
            sev = ([0.0] if base else []) + [row["severity"] for row in sub]
            for s in full:
                y = ([100 * base[0]["solvers"][s]["correct"]] if base else []) + \
                    [100 * row["solvers"][s]["correct"] for row in sub]
                ax.plot(sev, y, "o-", label=f"{s}, N={n}")
        ax.set_xlabel(f"{name} ({corr.get(name).unit})")
        ax.set_ylabel("% correct")
        ax.set_ylim(-2, 102)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
        _save(fig, out / f"success_vs_{name}.png")
        plt.close(fig)


# --------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True, help="skygen dataset folder (its frames are the fixed test frames)")
    p.add_argument("--out", required=True, help="folder for benchmark.json, benchmark.md and the plots")
    p.add_argument("--checkpoint", help="a fusion checkpoint: adds the 'learned' and 'learned+fine' solvers")
    p.add_argument("--split", default="test", choices=("train", "val", "test"))
    p.add_argument("--frames", type=int, help="first N frames of the split (default 200; 30 with --grid small)")
    p.add_argument("--grid", choices=("small", "full"), default="full",
                   help="small: N in 4 6 10, corruptions at N=6, two severities each (a CPU minute or two); "
                        "full: N in 3..20, every sweep severity at N=6 and N=10")
    p.add_argument("--n", type=int, nargs="+", metavar="N", help="brightest-N values of the clean cells (overrides --grid)")
    p.add_argument("--corruption-n", type=int, nargs="+", metavar="N", help="N values of the corruption cells")
    p.add_argument("--corruptions", nargs="*", default=list(DETECTION_CORRUPTIONS), metavar="NAME",
                   help=f"detection-level corruptions (default all: {', '.join(DETECTION_CORRUPTIONS)}); none: clean only")
    p.add_argument("--solvers", nargs="+", metavar="NAME",
                   default=["tetra3rs", "oracle-prior", "sim85-prior", "learned", "learned+fine"],
                   help=f"solvers to score, from: {', '.join(SOLVERS)} (default: all but whole-sky)")
    p.add_argument("--correct-deg", type=float, default=0.1, help="boresight error counted as correct (default 0.1 deg)")
    p.add_argument("--correct-roll-deg", type=float, default=1.0, help="roll error counted as correct (default 1 deg)")
    from .predict import add_search_arguments
    add_search_arguments(p, "--top-k")                 # the coarse-to-fine solvers run as fusion predict --solve


def run(args: argparse.Namespace) -> int:
    small = args.grid == "small"
    severities = {c: [s for s in corr.get(c).sweep if s > 0][:2] for c in args.corruptions} if small else None
    run_benchmark(args.data, args.out, checkpoint=args.checkpoint, split=args.split,
                  frames=args.frames or (30 if small else 200), n_values=args.n or (SMALL_N if small else FULL_N),
                  corruption_n=args.corruption_n or ((6,) if small else (6, 10)), corruptions=args.corruptions,
                  severities=severities, solvers=args.solvers, correct_deg=args.correct_deg,
                  correct_roll_deg=args.correct_roll_deg, top_k=args.search_k, search=args.search,
                  focal_tol=args.focal_tol)
    return 0
