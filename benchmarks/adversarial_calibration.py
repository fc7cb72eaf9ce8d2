"""Is each solution's false-match probability calibrated? Solvers against adversarial detection sets (issue 37, item 2).

    python benchmarks/adversarial_calibration.py --attempts 10000 --out results/calibration \
        [--solvers whole-sky tetra3rs tetra3rs>whole-sky] [--families ...] [--jobs 1] [--seed 0] \
        [--checkpoint CK] [--config CONFIG.yaml]

Every **case** is one detection set of the nominal camera (``--config``, default skygen's 20 deg camera), given
to every solver of ``--solvers`` with that camera; one solver on one case is an **attempt**. A case's family is
``--families`` round-robin (case i: family i mod F), its N (detections given) uniform in ``--n-min..--n-max``
(3..12), and everything else is drawn from ``numpy.random.default_rng([seed, i])`` and sample i of skygen's
detection stream (:class:`skygen.stream.samples.SampleStream`, kind ``detections``: catalogue projection and
the calibrated detector emulator, no image rendered; its attitude is the case's truth), so a case is the same
whatever the chunking, the number of processes or the other families. Families:

``noise``          N detections at uniform sensor positions, magnitudes uniform over 6 mag: no truth, so
                   every returned attitude is wrong;
``hot_pixels``     the stream sample's detections plus K = 1..3 hot pixels (integer pixel positions, 1.2-5x
                   the flux of the brightest star): the hot pixels are the brightest, then N - K stars;
``focal``          the catalogue projected through the nominal camera with its focal length 5-20 % off (either
                   sign), solved as the nominal camera;
``other_camera``   the catalogue projected through another camera (a 12 deg or 30 deg field on the same
                   1024 px sensor, or the fitted Blackfly 11.4 deg 1024 x 768 with distortion), the detections
                   that fall on the nominal sensor kept, solved as the nominal camera; truth: that camera's
                   attitude;
``shuffled_mags``  the brightest min(3N, all) detections of the sample with their fluxes permuted, then the
                   brightest N of them (a random subset of true positions, with wrong magnitudes);
``false_stars``    J = 1..5 false stars at uniform positions with fluxes drawn from the sample's brightest N,
                   among its detections, then the brightest N (``param``: J; ``false_kept`` how many of them
                   are among the N);
``clean``          (control, not in the defaults) the sample's brightest N.

``focal`` and ``other_camera`` use this script's own projection (:func:`project_field`: the renderer's
catalogue, photometry and gain, stars above the emulator's threshold, 0.15 px centroid noise, 0.05 mag flux
noise), since the stream's emulator is calibrated for the nominal camera only.

Scoring (as ``fusion benchmark``): a returned attitude is **correct** when its boresight is within
``--correct-deg`` (0.1) of the truth and its roll within ``--correct-roll-deg`` (1), **wrong** otherwise
(every answer to a ``noise`` case); ``near`` marks a wrong answer within 1 deg (the right stars, a biased
attitude: a wrong focal length or camera). Each attempt records family, N, solver, status (``solved`` or the
refusal status), correct / wrong, the reported ``false_match_probability`` (p), attitude errors, matched
stars and the solve time (ms, one core; a chain composed from two solvers scored here: the first's time plus,
where it refused, the second's).

Reliability: answers binned by p (< 1e-9, 1e-9..1e-6, 1e-6..1e-3, 1e-3..1e-2, 1e-2..1e-1, >= 1e-1); per bin the answers,
the wrong ones, the sum of p (the wrong answers to expect if p is calibrated) and their ratio. Calibrated
within a factor of 3: wrong / sum(p) in [1/3, 3]; where sum(p) is below a few, a Poisson test says whether the
count observed is consistent with it (``p_value_at_least``: P(X >= wrong | sum p); below 0.01 means p
underestimates the risk). The issue's hard targets: wrong <= sum(p) overall, and no wrong answer with p < 1e-6.

Outputs in ``--out``: ``calibration.json`` (settings, the tables, every wrong answer, throughput; written
atomically once every chunk is done, with ``"complete": true``), ``calibration.md``, ``reliability.png``
and ``attempts.csv.gz`` (every attempt). While it runs, each finished chunk of ``--chunk`` cases is written
atomically to ``chunks/`` and ``progress.json`` says ``"complete": false``; a rerun with the same settings
resumes from the chunks (a run with other settings starts over), and any ``calibration.json`` of an earlier
run is removed when a run starts, so an interrupted run never leaves a report that looks complete
(:func:`load_report` refuses one that is not). The chunks are removed once the report is written
(``--keep-chunks`` keeps them).

Learned solvers (``learned+fine``, ...) need ``--checkpoint``; without one they are skipped with a note in the
report (and on stdout). They are given no image (the detection sets have none): a model that needs pixels
is skipped with a note too.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import gzip
import hashlib
import io
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FAMILIES = ("noise", "hot_pixels", "focal", "other_camera", "shuffled_mags", "false_stars")
ALL_FAMILIES = FAMILIES + ("clean",)
DEFAULT_SOLVERS = ("tetra3rs", "whole-sky", "tetra3rs>whole-sky")
BIN_EDGES = (0.0, 1e-9, 1e-6, 1e-3, 1e-2, 1e-1, math.inf)
BIN_LABELS = ("< 1e-9", "1e-9 .. 1e-6", "1e-6 .. 1e-3", "1e-3 .. 1e-2", "1e-2 .. 1e-1", ">= 1e-1")
LOW_P = 1e-6  # the issue's target: no wrong answer reported with p below this
FORMAT = "adversarial-calibration"
VERSION = 1
COLUMNS = (
    "case", "family", "n", "param", "false_kept", "solver", "status", "returned", "correct", "near",
    "p", "boresight_err_deg", "roll_err_deg", "n_matched", "ms",
)  # fmt: skip
SETTINGS_KEYS = ("seed", "attempts", "families", "solvers", "chunk", "n_min", "n_max", "correct_deg",
                 "correct_roll_deg", "focal_tol", "config", "checkpoint", "jobs", "answer_bar")  # fmt: skip
OTHER_CAMERAS = ("narrow-12deg", "wide-30deg", "blackfly-fitted")


class Incomplete(Exception):
    """A report that is not (yet) complete: an interrupted or running calibration."""


# --------------------------------------------------------------------------------------------- settings
def settings_digest(st: dict) -> str:
    """What a chunk depends on: a resumed run reuses chunks only of the same digest."""
    keys = ("seed", "families", "solvers", "chunk", "n_min", "n_max", "correct_deg", "correct_roll_deg",
            "focal_tol", "config", "checkpoint", "version")  # fmt: skip
    picked = {k: st[k] for k in keys}
    if st.get("answer_bar") is not None:  # (absent from the digest of runs made before the option)
        picked["answer_bar"] = st["answer_bar"]
    text = json.dumps(picked, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# --------------------------------------------------------------------------------------------- cases
class CaseMaker:
    """The detection sets of the cases (module docstring), from the nominal config and a seed."""

    def __init__(self, config: str | None, seed: int, families, n_min: int = 3, n_max: int = 12):
        from skygen.config import load_config
        from skygen.instrument.camera import Camera
        from skygen.stream.samples import SampleStream

        self.cfg = load_config(config, overrides=[f"seed={int(seed)}"])
        self.stream = SampleStream(self.cfg, "detections")
        r = self.stream.renderer
        self.camera = r.camera
        self.seed, self.families, self.n_min, self.n_max = int(seed), tuple(families), int(n_min), int(n_max)
        sky = r.sky
        e = r.photometry.electrons_per_s(sky.table.mag + r.mag_offset_to_hp, sky.table.bv) * self.cfg.sensor.exposure_s
        self.threshold_e = float(self.stream.model.threshold_e)
        keep = e > self.threshold_e  # the stars a detector can see at all (the emulator's threshold)
        self.sky_vec = np.ascontiguousarray(sky.vectors[keep])
        self.sky_e = e[keep]
        self.gain = float(self.stream.model.gain_e_per_adu)
        from scipy.spatial import cKDTree

        self.tree = cKDTree(self.sky_vec)
        c = self.camera
        self.others = {
            "narrow-12deg": dataclasses.replace(c, f_px=c.width_px / 2 / math.tan(math.radians(6.0))),
            "wide-30deg": dataclasses.replace(c, f_px=c.width_px / 2 / math.tan(math.radians(15.0))),
            "blackfly-fitted": Camera.from_config(
                load_config(ROOT / "configs" / "cameras" / "blackfly-fitted.yaml").camera
            ),
        }

    def family_of(self, i: int) -> str:
        return self.families[i % len(self.families)]

    def project_field(self, cam, matrix: np.ndarray, rng) -> dict:
        """Detections of the catalogue seen by ``cam`` at attitude ``matrix`` (camera -> ICRS): stars above the
        detector threshold, 0.15 px centroid noise, fluxes (ADU) with 0.05 mag noise; brightest first."""
        radius = cam.corner_radius_rad() + 0.01
        idx = np.asarray(self.tree.query_ball_point(matrix[:, 2], 2 * math.sin(radius / 2)), np.int64)
        v = self.sky_vec[idx] @ matrix  # camera frame
        x, y, front = cam.project(v)
        ok = front & cam.inside(x, y)
        x, y = x[ok] + rng.normal(0, 0.15, ok.sum()), y[ok] + rng.normal(0, 0.15, ok.sum())
        flux = self.sky_e[idx[ok]] / self.gain * 10 ** (-0.4 * rng.normal(0, 0.05, ok.sum()))
        o = np.argsort(-flux, kind="stable")
        return {"x_px": x[o], "y_px": y[o], "flux_adu": flux[o]}

    def cases(self, lo: int, hi: int) -> list[dict]:
        """Cases ``lo .. hi - 1``: family, N, parameter, detections (a Detections), truth ((matrix, roll) or None)."""
        from fusion.solve.base import Detections
        from skygen.sky.attitude import quaternion_to_matrix

        batch = self.stream.batch(np.arange(lo, hi))
        cam = self.camera
        out = []
        for j, i in enumerate(range(lo, hi)):
            s = batch.sample(j)
            rng = np.random.default_rng([self.seed, i])
            fam = self.family_of(i)
            n = int(rng.integers(self.n_min, self.n_max + 1))
            m_true = quaternion_to_matrix(np.asarray(s["quaternion"], np.float64))
            truth = (m_true, float(s["roll_deg"]))
            det = {k: np.asarray(s["detections"][k], np.float64) for k in ("x_px", "y_px", "flux_adu")}
            param, false_kept = None, None
            if fam == "noise":
                mag = rng.uniform(0.0, 6.0, n)
                det = {
                    "x_px": rng.uniform(-0.5, cam.width_px - 0.5, n),
                    "y_px": rng.uniform(-0.5, cam.height_px - 0.5, n),
                    "flux_adu": 3000.0 * 10 ** (-0.4 * mag),
                }
                truth = None
            elif fam == "hot_pixels":
                k = int(rng.integers(1, min(3, n - 1) + 1))
                top = float(det["flux_adu"].max()) if len(det["flux_adu"]) else 1000.0
                det = {
                    "x_px": np.concatenate([rng.integers(0, cam.width_px, k).astype(float), det["x_px"]]),
                    "y_px": np.concatenate([rng.integers(0, cam.height_px, k).astype(float), det["y_px"]]),
                    "flux_adu": np.concatenate([top * rng.uniform(1.2, 5.0, k), det["flux_adu"]]),
                }
                param = k
            elif fam == "focal":
                e = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.05, 0.20))
                det = self.project_field(dataclasses.replace(cam, f_px=cam.f_px * (1 + e)), m_true, rng)
                param = round(e, 4)
            elif fam == "other_camera":
                name = OTHER_CAMERAS[int(rng.integers(len(OTHER_CAMERAS)))]
                det = self.project_field(self.others[name], m_true, rng)
                ok = cam.inside(det["x_px"], det["y_px"])  # what the nominal sensor's pixels can hold
                det = {k: v[ok] for k, v in det.items()}
                param = name
            elif fam == "shuffled_mags":
                m = min(3 * n, len(det["flux_adu"]))
                det = {k: v[np.argsort(-det["flux_adu"], kind="stable")[:m]] for k, v in det.items()}
                det["flux_adu"] = rng.permutation(det["flux_adu"])
            elif fam == "false_stars":
                k = int(rng.integers(1, 6))
                pool = np.sort(det["flux_adu"])[::-1][:n]
                fake = rng.choice(pool, k) if len(pool) else np.full(k, 1000.0)
                det = {
                    "x_px": np.concatenate([det["x_px"], rng.uniform(-0.5, cam.width_px - 0.5, k)]),
                    "y_px": np.concatenate([det["y_px"], rng.uniform(-0.5, cam.height_px - 0.5, k)]),
                    "flux_adu": np.concatenate([det["flux_adu"], fake * (1 + 1e-9)]),  # a tie: the false first
                }
                is_false = np.r_[np.zeros(len(det["x_px"]) - k, bool), np.ones(k, bool)]
                order = np.argsort(-det["flux_adu"], kind="stable")[:n]
                false_kept = int(is_false[order].sum())
                param = k
            elif fam != "clean":
                raise ValueError(f"family {fam!r}: one of {', '.join(ALL_FAMILIES)}")
            d = Detections.from_table(det).brightest(n)
            out.append({"case": i, "family": fam, "n": len(d), "param": param, "false_kept": false_kept,
                        "detections": d, "truth": truth})  # fmt: skip
        return out


# --------------------------------------------------------------------------------------------- solving
def score(result, truth, correct_deg: float, correct_roll_deg: float) -> dict:
    """One attempt's outcome: returned, correct (None: refused), near, p, errors. No truth: every answer wrong."""
    from fusion.solve.base import Solution, boresight_error_deg, roll_error_deg

    if not isinstance(result, Solution):
        return {"status": result.status, "returned": False, "correct": None, "near": None, "p": None,
                "boresight_err_deg": None, "roll_err_deg": None, "n_matched": 0}  # fmt: skip
    b = o = None
    right = near = False
    if truth is not None:
        b, o = boresight_error_deg(truth[0], result.matrix), roll_error_deg(result.roll_deg, truth[1])
        right = b <= correct_deg and o <= correct_roll_deg
        near = not right and b <= 1.0
    p = result.false_match_probability
    return {"status": "solved", "returned": True, "correct": bool(right), "near": bool(near),
            "p": None if p is None else float(p), "boresight_err_deg": b, "roll_err_deg": o,
            "n_matched": int(result.n_matched)}  # fmt: skip


class Worker:
    """The solvers of one process and the case maker: ``run(lo, hi)`` -> attempt rows."""

    def __init__(self, st: dict):
        self.st = st
        self.maker = CaseMaker(st["config"], st["seed"], st["families"], st["n_min"], st["n_max"])
        self.notes: list[str] = []
        self.built, self.composite = build(self.maker.camera, st, self.notes)
        cases = self.maker.cases(0, 1)
        for solver in self.built.values():  # compile the fine stage's loops and load its index once
            try:
                solver.solve(cases[0]["detections"], self.maker.camera)
            except Exception:
                pass

    def run(self, lo: int, hi: int) -> list[list]:
        from fusion.solve.base import Solution

        rows = []
        cam, st = self.maker.camera, self.st
        for c in self.maker.cases(lo, hi):
            answers = {}
            for name, solver in self.built.items():
                t0 = time.perf_counter()
                res = solver.solve(c["detections"], cam)
                answers[name] = (res, 1e3 * (time.perf_counter() - t0))
            for name, (a, b) in self.composite.items():
                (ra, ta), (rb, tb) = answers[a], answers[b]
                answers[name] = (ra, ta) if isinstance(ra, Solution) else (rb, ta + tb)
            for name in st["solvers"]:
                if name not in answers:
                    continue
                res, ms = answers[name]
                s = score(res, c["truth"], st["correct_deg"], st["correct_roll_deg"])
                row = {**{k: c[k] for k in ("case", "family", "n", "param", "false_kept")}, "solver": name, **s}
                row["ms"] = round(ms, 3)
                rows.append([row[k] for k in COLUMNS])
        return rows


def build(camera, st: dict, notes: list) -> tuple[dict, dict]:
    """({name: solver} to run, {chain: (first, second)} composed from two solvers run here). Learned solvers
    without a checkpoint (or whose model needs an image) are left out with a note."""
    from fusion.solve.registry import SOLVERS, get, make_context

    prior = None
    wanted = list(st["solvers"])
    learned = [s for s in wanted if SOLVERS[s].prior == "learned"]
    if learned and not st["checkpoint"]:
        notes.append(f"{', '.join(learned)}: skipped, no --checkpoint given (a learned solver needs a trained model)")
        wanted = [s for s in wanted if s not in learned]
    elif learned:
        from fusion.solve.base import Detections
        from fusion.solve.priors import load_prior

        try:
            prior = load_prior(st["checkpoint"])
            d = Detections(np.array([100.0, 500, 900]), np.array([100.0, 600, 300]), np.array([3.0, 2, 1]))
            prior.probabilities(d, None)
        except Exception as exc:  # e.g. a model that reads pixels: these detection sets have no image
            notes.append(f"{', '.join(learned)}: skipped, the checkpoint's prior cannot be used here ({exc})")
            wanted = [s for s in wanted if s not in learned]
            prior = None
    ctx = make_context(camera, prior=prior, focal_tol=st["focal_tol"])
    built, composite = {}, {}
    for name in wanted:
        if SOLVERS[name].prior == "oracle":
            raise SystemExit(f"--solvers {name}: an oracle needs the truth; not for a calibration")
        parts = name.split(">")
        if len(parts) == 2 and all(p in wanted for p in parts):
            composite[name] = tuple(parts)
        else:
            built[name] = get(ctx, name)
    st["solvers_run"] = [s for s in st["solvers"] if s in built or s in composite]
    if st.get("answer_bar") is not None:
        for solver in built.values():
            relax(solver, float(st["answer_bar"]))
    return built, composite


def relax(solver, bar: float) -> None:
    """``--answer-bar P``: every fine stage in ``solver`` (a chain's parts too) answers wherever its false-match
    probability at the sky's mean density (the number its bars are on; the reported one weighs in the catalogue's
    clustering) is at most P, verified by tetra3rs or not (``min_confidence`` and
    ``unverified_confidence`` = 1 - P; tracking's bar likewise); tetra3rs keeps its own. With P well above the
    solvers' own bars (0.01, 1e-6 unverified) the answers they would refuse are scored too, so the reliability
    of p can be measured where wrong answers are common enough to count."""
    if hasattr(solver, "min_confidence"):
        solver.min_confidence = solver.unverified_confidence = solver.tracking_unverified_confidence = 1.0 - bar
    for part in (getattr(solver, "first", None), getattr(solver, "second", None)):
        if part is not None:
            relax(part, bar)


# --------------------------------------------------------------------------------------------- chunks
_WORKER: Worker | None = None


def _worker_key(st: dict) -> str:
    keys = ("config", "seed", "families", "solvers", "n_min", "n_max", "focal_tol", "checkpoint",
            "correct_deg", "correct_roll_deg", "answer_bar")  # fmt: skip
    return json.dumps({k: st.get(k) for k in keys}, sort_keys=True, default=str)


def _init(st: dict) -> None:
    global _WORKER
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if _WORKER is None or _worker_key(_WORKER.st) != _worker_key(st):  # a process's solvers, built once
        _WORKER = Worker(st)


def _run_chunk(args) -> tuple[int, list, float]:
    k, lo, hi = args
    t0 = time.perf_counter()
    assert _WORKER is not None
    rows = _WORKER.run(lo, hi)
    return k, rows, time.perf_counter() - t0


def chunk_path(out: Path, k: int) -> Path:
    return out / "chunks" / f"chunk-{k:06d}.json"


def load_chunk(out: Path, k: int, digest: str) -> list | None:
    """The rows of chunk ``k`` of a run with these settings, or None (absent, damaged or other settings)."""
    p = chunk_path(out, k)
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    if data.get("digest") != digest or data.get("columns") != list(COLUMNS):
        return None
    return data["rows"]


def run(st: dict, log=print, stop_after_chunks: int | None = None) -> dict:
    """Every case of ``st`` (see :func:`main`), chunk by chunk (resuming from the chunks of an interrupted run
    with the same settings), then the report. ``stop_after_chunks``: stop (raise :class:`Incomplete`) after
    that many new chunks, as an interruption would (tests)."""
    from skygen.runtime import write_json

    out = Path(st["out"])
    (out / "chunks").mkdir(parents=True, exist_ok=True)
    (out / "calibration.json").unlink(missing_ok=True)  # a report of an earlier run must not look like this one's
    digest = settings_digest(st)
    n_chunks = math.ceil(st["attempts"] / st["chunk"])
    spans = [(k, k * st["chunk"], min(st["attempts"], (k + 1) * st["chunk"])) for k in range(n_chunks)]
    rows: dict[int, list] = {}
    for k, lo, hi in spans:
        r = load_chunk(out, k, digest)
        if r is not None and len({row[0] for row in r}) == hi - lo:
            rows[k] = r
    todo = [s for s in spans if s[0] not in rows]
    if rows:
        log(f"resuming: {len(rows)} of {n_chunks} chunks already done")
    t_start = time.perf_counter()
    progress = {"format": FORMAT, "complete": False, "digest": digest, "chunks": n_chunks, "cases": st["attempts"]}

    def done(k, r, secs, i_done):
        rows[k] = r
        write_json(chunk_path(out, k), {"digest": digest, "chunk": k, "columns": list(COLUMNS), "rows": r,
                                        "seconds": secs})  # fmt: skip
        write_json(out / "progress.json", {**progress, "chunks_done": len(rows)})
        el = time.perf_counter() - t_start
        eta = el / i_done * (len(todo) - i_done)
        log(f"chunk {k + 1}/{n_chunks}: {len(r)} attempts in {secs:.1f} s; {len(rows)}/{n_chunks} done, "
            f"ETA {eta / 60:.1f} min")  # fmt: skip
        if stop_after_chunks is not None and i_done >= stop_after_chunks and len(rows) < n_chunks:
            raise Incomplete(f"stopped after {i_done} chunks (as an interruption would)")

    notes: list[str] = []
    if todo:
        if st["jobs"] <= 1:
            _init(st)
            assert _WORKER is not None
            notes = _WORKER.notes
            for i, span in enumerate(todo, 1):
                done(*_run_chunk(span), i)
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            probe: list[str] = []
            st_probe = dict(st)
            build_notes(st_probe, probe)
            notes = probe
            ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
            with ProcessPoolExecutor(st["jobs"], mp_context=ctx, initializer=_init, initargs=(st,)) as ex:
                for i, res in enumerate(ex.map(_run_chunk, todo), 1):
                    done(*res, i)
    else:
        build_notes(st, notes)
    for n in notes:
        log(f"NOTE: {n}")
    all_rows = [row for k in sorted(rows) for row in rows[k]]
    report = summarise(all_rows, st, notes, time.perf_counter() - t_start)
    write_outputs(report, all_rows, out, log)
    if not st.get("keep_chunks"):
        shutil.rmtree(out / "chunks", ignore_errors=True)
    (out / "progress.json").unlink(missing_ok=True)
    return report


def build_notes(st: dict, notes: list) -> None:
    """The notes a worker would make (learned solvers skipped), without building the solvers."""
    from fusion.solve.registry import SOLVERS

    learned = [s for s in st["solvers"] if SOLVERS[s].prior == "learned"]
    if learned and not st["checkpoint"]:
        notes.append(f"{', '.join(learned)}: skipped, no --checkpoint given (a learned solver needs a trained model)")
        st["solvers_run"] = [s for s in st["solvers"] if s not in learned]
    else:
        st["solvers_run"] = list(st["solvers"])


# --------------------------------------------------------------------------------------------- analysis
def poisson_at_least(k: int, lam: float) -> float:
    """P(X >= k) for X ~ Poisson(lam)."""
    from scipy.stats import poisson

    return 1.0 if k <= 0 else float(poisson.sf(k - 1, lam))


def verdict(wrong: int, expected: float) -> str:
    """Calibrated within a factor of 3? (module docstring)"""
    if expected <= 0:
        return "no probability reported" if wrong else "no answers to test"
    from scipy.stats import poisson

    ratio = wrong / expected
    lo_p = poisson_at_least(wrong, expected)  # small: more wrong answers than p allows
    hi_p = float(poisson.cdf(wrong, expected))  # small: fewer wrong answers than p promises
    if 1 / 3 <= ratio <= 3:
        return "within x3"
    if ratio > 3:
        return "UNDER-estimates risk" if lo_p < 0.01 else "consistent (few expected)"
    return "over-conservative" if hi_p < 0.01 else "consistent (few expected)"


def cell(rows: list) -> dict:
    """Counts of one group of attempt dicts."""
    ret = [r for r in rows if r["returned"]]
    wrong = [r for r in ret if not r["correct"]]
    ps = [r["p"] for r in ret if r["p"] is not None]
    expected = float(sum(ps))
    ms = np.array([r["ms"] for r in rows]) if rows else np.zeros(1)
    low = [r for r in wrong if r["p"] is not None and r["p"] < LOW_P]
    return {
        "attempts": len(rows),
        "returned": len(ret),
        "correct": len(ret) - len(wrong),
        "wrong": len(wrong),
        "wrong_near": sum(1 for r in wrong if r["near"]),
        "no_probability": len(ret) - len(ps),
        "p_sum": expected,
        "p_sum_wrong": float(sum(r["p"] for r in wrong if r["p"] is not None)),
        "ratio_wrong_to_expected": (len(wrong) / expected) if expected > 0 else None,
        "p_value_at_least": poisson_at_least(len(wrong), expected) if expected > 0 else None,
        "verdict": verdict(len(wrong), expected),
        "wrong_below_1e-6": len(low),
        "ms_mean": float(ms.mean()),
        "ms_p99": float(np.percentile(ms, 99)),
    }


def reliability(rows: list) -> list[dict]:
    """Returned answers binned by reported p (BIN_EDGES): count, wrong, sum of p, mean p, observed rate, ratio."""
    ret = [r for r in rows if r["returned"] and r["p"] is not None]
    out = []
    for lo, hi, label in zip(BIN_EDGES[:-1], BIN_EDGES[1:], BIN_LABELS):
        b = [r for r in ret if lo <= r["p"] < hi or (hi == math.inf and r["p"] >= lo)]
        w = sum(1 for r in b if not r["correct"])
        s = float(sum(r["p"] for r in b))
        out.append({
            "bin": label, "lo": lo, "hi": hi, "count": len(b), "wrong": w, "p_sum": s,
            "p_mean": s / len(b) if b else None, "observed_rate": w / len(b) if b else None,
            "ratio": w / s if s > 0 else None,
            # zero wrong: the 95 % upper bound of the rate
            "rate_upper95": (min(1.0, 3.0 / len(b)) if w == 0 else None) if b else None,
        })  # fmt: skip
    return out


COARSE_EDGES = (0.0, 1e-6, 1e-2, math.inf)
COARSE_LABELS = ("< 1e-6", "1e-6 .. 1e-2", ">= 1e-2")


def coarse_reliability(rows: list) -> list[dict]:
    """Every solver's returned answers of ``rows`` in three bins of p (COARSE_EDGES): count, wrong, sum of p."""
    ret = [r for r in rows if r["returned"] and r["p"] is not None]
    out = []
    for lo, hi, label in zip(COARSE_EDGES[:-1], COARSE_EDGES[1:], COARSE_LABELS):
        b = [r for r in ret if lo <= r["p"] < hi]
        w = sum(1 for r in b if not r["correct"])
        out.append({"bin": label, "count": len(b), "wrong": w, "p_sum": float(sum(r["p"] for r in b))})
    return out


def targets(t: dict) -> dict:
    """The issue's targets for one solver's answers: wrong <= sum p, no wrong answer with p < 1e-6, and whether
    a factor-of-3 calibration is testable at all (3 or more wrong answers expected or seen: below that, zero
    wrong answers are what a calibrated p predicts, and also what a p 1000 times too large or too small would)."""
    return {
        "wrong_le_expected": t["wrong"] <= t["p_sum"],
        "no_wrong_below_1e-6": t["wrong_below_1e-6"] == 0,
        "factor3_testable": t["p_sum"] >= 3 or t["wrong"] >= 3,
        "verdict": t["verdict"],
    }


def _composed(name: str, solvers) -> bool:
    parts = name.split(">")
    return len(parts) == 2 and all(p in solvers for p in parts)


def as_dicts(rows: list) -> list[dict]:
    return [dict(zip(COLUMNS, r)) for r in rows]


def summarise(rows: list, st: dict, notes: list, wall_s: float) -> dict:
    from skygen.runtime import hardware_line

    d = as_dicts(rows)
    solvers = [s for s in st["solvers"] if any(r["solver"] == s for r in d)]
    fams = [f for f in st["families"] if any(r["family"] == f for r in d)]
    table = []
    for s in solvers:
        for f in fams + ["all"]:
            g = [r for r in d if r["solver"] == s and (f == "all" or r["family"] == f)]
            table.append({"solver": s, "family": f, **cell(g)})
    rel = {s: reliability([r for r in d if r["solver"] == s]) for s in solvers}
    # throughput: attempts per second of one core, per solver (a composed chain: first + second where refused)
    thr = {}
    for s in solvers:
        ms = sum(r["ms"] for r in d if r["solver"] == s)
        n = sum(1 for r in d if r["solver"] == s)
        thr[s] = {"attempts": n, "ms_mean": ms / max(n, 1), "attempts_per_s": 1e3 * n / ms if ms > 0 else None}
    # latency by detection count: the refusals' time grows with N (a hypothesis scores every detection)
    latency = {}
    for s in solvers:
        by_n: dict = {}
        for r in d:
            if r["solver"] == s:
                by_n.setdefault(int(r["n"]), []).append(r["ms"])
        latency[s] = {
            str(n): {"attempts": len(v), "median_ms": float(np.median(v)), "p99_ms": float(np.percentile(v, 99))}
            for n, v in sorted(by_n.items())
        }
    run_solvers = [s for s in solvers if not _composed(s, solvers)]  # a composed chain costs nothing extra
    case_ms = sum(thr[s]["ms_mean"] for s in run_solvers)
    cases = len({r["case"] for r in d})
    wrong_rows = [r for r in d if r["returned"] and not r["correct"]]
    wrong_rows.sort(key=lambda r: r["p"] if r["p"] is not None else 1.0)
    return {
        "format": FORMAT,
        "version": VERSION,
        "complete": True,
        "digest": settings_digest(st),
        "settings": {k: st.get(k) for k in SETTINGS_KEYS},
        "cases": cases,
        "solve_attempts": len(d),
        "notes": notes,
        "table": table,
        "reliability": rel,
        "reliability_all": reliability(d),
        "reliability_by_family": {f: coarse_reliability([r for r in d if r["family"] == f]) for f in fams},
        "overall": {s: next(t for t in table if t["solver"] == s and t["family"] == "all") for s in solvers},
        "targets": {s: targets(next(t for t in table if t["solver"] == s and t["family"] == "all")) for s in solvers},
        "wrong_answers": wrong_rows[:500],
        "wrong_below_1e-6": [r for r in wrong_rows if r["p"] is not None and r["p"] < LOW_P],
        "latency_by_n": latency,
        "throughput": {
            "per_solver": thr,
            "ms_per_case": case_ms,
            "cases_per_s_one_core": 1e3 / case_ms if case_ms > 0 else None,
            "projected_100k_cases_h_one_core": case_ms * 1e5 / 3.6e6,
            "projected_100k_attempts_h_one_core": (case_ms / max(len(run_solvers), 1)) * 1e5 / 3.6e6,
        },
        "hardware": hardware_line() + f", {st['jobs']} process(es)",
        "wall_time_s": wall_s,
    }


def rebuild(out, log=print) -> dict:
    """The report of a complete run in ``out`` made again from its ``attempts.csv.gz`` (a newer analysis or
    plot of the same attempts)."""
    out = Path(out)
    old = load_report(out)
    with gzip.open(out / "attempts.csv.gz", "rt") as f:
        rd = csv.reader(f)
        if tuple(next(rd)) != COLUMNS:
            raise Incomplete(f"{out / 'attempts.csv.gz'}: other columns than {COLUMNS}")
        rows = [[_cell_value(k, v) for k, v in zip(COLUMNS, line)] for line in rd]
    st = {**old["settings"], "version": VERSION}
    report = summarise(rows, st, old["notes"], old["wall_time_s"])
    report["hardware"] = old["hardware"]
    write_outputs(report, rows, out, log)
    return report


_INT = ("case", "n", "n_matched")
_FLOAT = ("p", "boresight_err_deg", "roll_err_deg", "ms")
_BOOL = ("returned", "correct", "near")


def _cell_value(k: str, v: str):
    if v == "":
        return None
    if k in _INT:
        return int(v)
    if k in _FLOAT:
        return float(v)
    if k in _BOOL:
        return v == "True"
    if k == "false_kept":
        return int(v)
    if k == "param":
        try:
            return float(v) if "." in v else int(v)
        except ValueError:
            return v
    return v


def load_report(out) -> dict:
    """The report in ``out``, or :class:`Incomplete` where there is none, or it is partial or unfinished."""
    out = Path(out)
    p = out / "calibration.json"
    if not p.exists():
        prog = out / "progress.json"
        what = f" ({json.loads(prog.read_text()).get('chunks_done')} chunks done)" if prog.exists() else ""
        raise Incomplete(f"{out}: no complete calibration report{what}")
    r = json.loads(p.read_text())
    if r.get("format") != FORMAT or not r.get("complete") or r.get("cases") != r["settings"]["attempts"]:
        raise Incomplete(f"{p}: not a complete calibration report")
    return r


# --------------------------------------------------------------------------------------------- outputs
def _g(v, fmt=".2g") -> str:
    return "–" if v is None else format(v, fmt)


def markdown(r: dict) -> str:
    st = r["settings"]
    th = r["throughput"]
    lines = [
        "# False-match probability against adversarial detection sets",
        "",
        f"{r['cases']:,} cases x solvers = {r['solve_attempts']:,} solve attempts; seed {st['seed']}, N "
        f"{st['n_min']}..{st['n_max']}, focal tolerance ±{100 * st['focal_tol']:g} %; correct = boresight <= "
        f"{st['correct_deg']} deg and roll <= {st['correct_roll_deg']} deg; {r['hardware']}; "
        f"{r['wall_time_s'] / 60:.1f} min wall. `benchmarks/adversarial_calibration.py` (its docstring defines "
        "the families)."
        + (
            f" **Answer bar {st['answer_bar']:g}**: the fine stages answer wherever their p is at most that "
            "(their own bars off), so that p can be tested where it is large."
            if st.get("answer_bar") is not None
            else ""
        ),
        "",
    ]
    lines += [f"- **NOTE**: {n}" for n in r["notes"]] + ([""] if r["notes"] else [])
    lines += [
        "**wrong / expected**: wrong answers beside the sum of their reported false-match probabilities "
        "(what p promises); *near*: wrong but within 1 deg; *P(>=)*: the Poisson chance of at least that many "
        "wrong answers if p were right; **wrong p<1e-6**: the issue's target is 0.",
        "",
        "| solver | family | attempts | returned | correct | wrong (near) | expected (sum p) | wrong / expected | "
        "P(>=) | verdict | wrong p<1e-6 | ms mean / p99 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for t in r["table"]:
        fam = f"**{t['family']}**" if t["family"] == "all" else t["family"]
        lines.append(
            f"| {t['solver']} | {fam} | {t['attempts']:,} | {t['returned']:,} | {t['correct']:,} | "
            f"{t['wrong']} ({t['wrong_near']}) | {t['p_sum']:.3g} | {_g(t['ratio_wrong_to_expected'], '.3g')} | "
            f"{_g(t['p_value_at_least'], '.2g')} | {t['verdict']} | {t['wrong_below_1e-6']} | "
            f"{t['ms_mean']:.1f} / {t['ms_p99']:.0f} |"
        )
    lines += ["", "Reliability (answers of every family, by reported p):", ""]
    lines += ["| solver | p bin | answers | wrong | sum p | mean p | observed rate | wrong / sum p |",
              "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for s, bins in list(r["reliability"].items()) + [("all solvers", r["reliability_all"])]:
        for b in bins:
            rate = _g(b["observed_rate"], ".2g")
            if b["rate_upper95"] is not None:
                rate += f" (< {b['rate_upper95']:.2g}, 95 %)"
            lines.append(f"| {s} | {b['bin']} | {b['count']:,} | {b['wrong']} | {b['p_sum']:.3g} | "
                         f"{_g(b['p_mean'], '.2g')} | {rate} | {_g(b['ratio'], '.3g')} |")  # fmt: skip
    by_fam = r.get("reliability_by_family") or {}
    if by_fam:
        lines += ["", "Reliability by family (every solver; answers / wrong / sum of p per bin of p):", ""]
        lines += ["| family | " + " | ".join(COARSE_LABELS) + " |", "|---|" + "---|" * len(COARSE_LABELS)]
        for fam, bins in by_fam.items():
            lines.append(
                f"| {fam} | " + " | ".join(f"{b['count']:,} / {b['wrong']} / {b['p_sum']:.3g}" for b in bins) + " |"
            )
    lines += ["", "Targets (every family together):", ""]
    for s, g in r.get("targets", {}).items():
        t = r["overall"][s]
        lines.append(
            f"- {s}: wrong {t['wrong']} <= expected {t['p_sum']:.3g}: {'yes' if g['wrong_le_expected'] else '**NO**'}; "
            f"wrong with p < 1e-6: {t['wrong_below_1e-6']} ({'met' if g['no_wrong_below_1e-6'] else '**MISSED**'}); "
            f"factor-3 calibration {'testable: ' + g['verdict'] if g['factor3_testable'] else 'not testable here'} "
            f"({'3 or more' if g['factor3_testable'] else 'under 3'} wrong answers expected or seen)"
        )
    lines += ["", f"Wrong answers with p < 1e-6: **{len(r['wrong_below_1e-6'])}**"]
    for w in r["wrong_below_1e-6"][:20]:
        lines.append(f"- case {w['case']} {w['family']} (param {w['param']}) N={w['n']} {w['solver']}: p = "
                     f"{w['p']:.2g}, boresight off {_g(w['boresight_err_deg'], '.3g')} deg, "
                     f"{w['n_matched']} matched")  # fmt: skip
    lines += [
        "",
        "Throughput (one core, mean ms per attempt, refusals included; a chain composed from two solvers run "
        "here: the first's time plus the second's where the first refused):",
        "",
        "| solver | attempts | ms / attempt | attempts / s |",
        "|---|---|---|---|",
    ]
    for s, t in th["per_solver"].items():
        lines.append(f"| {s} | {t['attempts']:,} | {t['ms_mean']:.1f} | {_g(t['attempts_per_s'], '.1f')} |")
    lat = r.get("latency_by_n") or {}
    if lat:
        ns = sorted({int(n) for v in lat.values() for n in v})
        lines += [
            "",
            f"Latency by detection count N (every family, refusals included; ms per attempt, median / p99; "
            f"{r['hardware']}):",
            "",
            "| solver | " + " | ".join(f"N = {n}" for n in ns) + " |",
            "|---|" + "---|" * len(ns),
        ]
        for s, v in lat.items():
            cells = [f"{v[str(n)]['median_ms']:.1f} / {v[str(n)]['p99_ms']:.1f}" if str(n) in v else "–" for n in ns]
            lines.append(f"| {s} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"One case through every solver run: {th['ms_per_case']:.0f} ms; 100,000 cases: "
        f"{th['projected_100k_cases_h_one_core']:.1f} h on one core; 100,000 solve attempts (the run solvers "
        f"alternating): {th['projected_100k_attempts_h_one_core']:.1f} h on one core (divide by the cores).",
        "",
        "![reliability](reliability.png)",
        "",
    ]
    return "\n".join(lines)


def plot(r: dict, path: Path) -> None:
    sys.path.insert(0, str(ROOT))
    from fusion.plots import _figure, _save

    plt = _figure()
    fig, ax = plt.subplots(figsize=(7, 5.5))
    lo = 1e-12
    xs = np.logspace(-12, 0, 50)
    ax.fill_between(xs, xs / 3, np.minimum(3 * xs, 1.0), color="0.85", label="within x3")
    ax.plot(xs, xs, "k--", lw=1, label="calibrated (rate = p)")
    markers = "osD^v<>"
    for m, (s, bins) in zip(markers, r["reliability"].items()):
        pts = [b for b in bins if b["count"]]
        for b in pts:
            x = max(b["p_mean"], lo)
            c = f"C{list(r['reliability']).index(s)}"
            if b["wrong"]:
                y = b["observed_rate"]
                ax.plot(x, y, m, color=c, ms=7)
            else:  # none wrong: the 95 % upper bound of the rate, an open marker with an arrow down
                y = min(1.0, b["rate_upper95"])
                ax.plot(x, y, m, mfc="none", color=c, ms=7)
                ax.annotate("", (x, y / 4), (x, y), arrowprops={"arrowstyle": "->", "color": c, "lw": 0.8})
            ax.annotate(f"{b['wrong']}/{b['count']}", (x, y), textcoords="offset points", xytext=(6, 4), fontsize=7,
                        color=f"C{list(r['reliability']).index(s)}")  # fmt: skip
        ax.plot([], [], m, color=f"C{list(r['reliability']).index(s)}", label=s)
    ax.plot([], [], "o", mfc="none", color="0.3", label="0 wrong: 95 % upper bound (3/n)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lo / 3, 3)
    ax.set_ylim(1e-7, 3)
    ax.set_xlabel("mean reported false-match probability of the bin (p < 1e-12 drawn at 1e-12)")
    ax.set_ylabel("observed wrong rate (wrong / answers)")
    tot = r["reliability_all"]
    ax.set_title(f"{r['solve_attempts']:,} attempts: {sum(b['wrong'] for b in tot)} wrong vs "
                 f"{sum(b['p_sum'] for b in tot):.3g} expected (sum p)", fontsize=10)  # fmt: skip
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="lower right")
    _save(fig, path)
    plt.close(fig)


def write_outputs(report: dict, rows: list, out: Path, log) -> None:
    from skygen.runtime import atomic_write_bytes, atomic_write_text, write_json

    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(COLUMNS)
    w.writerows(rows)
    atomic_write_bytes(out / "attempts.csv.gz", gzip.compress(buf.getvalue().encode(), mtime=0))
    atomic_write_text(out / "calibration.md", markdown(report))
    plot(report, out / "reliability.png")
    write_json(out / "calibration.json", report)  # last: its presence says every output is there
    log(f"wrote {out / 'calibration.json'}, calibration.md, reliability.png, attempts.csv.gz")


def print_table(r: dict, log=print) -> None:
    log(f"{'solver':<20} {'family':<14} {'att':>6} {'ret':>6} {'wrong':>6} {'near':>5} {'sum p':>9} "
        f"{'w<1e-6':>6} {'ms':>7}  verdict")  # fmt: skip
    for t in r["table"]:
        log(f"{t['solver']:<20} {t['family']:<14} {t['attempts']:>6} {t['returned']:>6} {t['wrong']:>6} "
            f"{t['wrong_near']:>5} {t['p_sum']:>9.3g} {t['wrong_below_1e-6']:>6} {t['ms_mean']:>7.1f}  "
            f"{t['verdict']}")  # fmt: skip
    th = r["throughput"]
    for s, t in th["per_solver"].items():
        log(f"throughput {s}: {_g(t['attempts_per_s'], '.1f')} attempts/s ({t['ms_mean']:.1f} ms) on one core")
    log(f"one case through the solvers run: {th['ms_per_case']:.0f} ms -> 100k cases "
        f"{th['projected_100k_cases_h_one_core']:.1f} h, 100k attempts {th['projected_100k_attempts_h_one_core']:.1f}"
        " h on one core")  # fmt: skip


# --------------------------------------------------------------------------------------------- command line
def settings_from_args(a) -> dict:
    from fusion.solve.registry import SOLVERS

    unknown = [s for s in a.solvers if s not in SOLVERS]
    if unknown:
        raise SystemExit(f"--solvers {unknown[0]}: unknown; choose from {', '.join(SOLVERS)}")
    bad = [f for f in a.families if f not in ALL_FAMILIES]
    if bad:
        raise SystemExit(f"--families {bad[0]}: unknown; choose from {', '.join(ALL_FAMILIES)}")
    if a.attempts < 1 or a.chunk < 1 or a.jobs < 1 or not 3 <= a.n_min <= a.n_max:
        raise SystemExit("--attempts, --chunk, --jobs >= 1 and 3 <= --n-min <= --n-max")
    if a.answer_bar is not None and not 0 < a.answer_bar < 1:
        raise SystemExit(f"--answer-bar {a.answer_bar:g}: a probability in (0, 1), e.g. 0.5")
    return {
        "seed": a.seed, "attempts": a.attempts, "families": list(a.families), "solvers": list(a.solvers),
        "chunk": a.chunk, "n_min": a.n_min, "n_max": a.n_max, "correct_deg": a.correct_deg,
        "correct_roll_deg": a.correct_roll_deg, "focal_tol": a.focal_tol,
        "config": str(a.config) if a.config else None,
        "checkpoint": str(a.checkpoint) if a.checkpoint else None, "jobs": a.jobs, "out": str(a.out),
        "keep_chunks": a.keep_chunks, "version": VERSION, "answer_bar": a.answer_bar,
    }  # fmt: skip


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--attempts", type=int, default=2000, help="cases (detection sets); each goes to every solver")
    p.add_argument("--solvers", nargs="+", default=list(DEFAULT_SOLVERS))
    p.add_argument("--families", nargs="+", default=list(FAMILIES), help=f"of {', '.join(ALL_FAMILIES)}")
    p.add_argument("--jobs", type=int, default=1, help="processes (each builds its own solvers)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--checkpoint", type=Path, default=None, help="a trained model: the learned solvers' prior")
    p.add_argument("--config", type=Path, default=None, help="the nominal camera's skygen config (default: skygen's)")
    p.add_argument("--chunk", type=int, default=250, help="cases per chunk (the unit of resuming)")
    p.add_argument("--n-min", type=int, default=3)
    p.add_argument("--n-max", type=int, default=12)
    p.add_argument("--correct-deg", type=float, default=0.1)
    p.add_argument("--correct-roll-deg", type=float, default=1.0)
    p.add_argument("--focal-tol", type=float, default=0.02, help="the fine stage's, as fusion predict --solve")
    p.add_argument(
        "--answer-bar",
        type=float,
        default=None,
        metavar="P",
        help="fine stages answer wherever their false-match probability is <= P (default: their own bars), to\n"
        "measure p's reliability where wrong answers are frequent",
    )
    p.add_argument("--keep-chunks", action="store_true")
    p.add_argument("--rebuild", action="store_true", help="only remake the report of a complete run in --out")
    a = p.parse_args(argv)
    if a.rebuild:
        print_table(rebuild(a.out))
        return 0
    st = settings_from_args(a)
    if a.config is not None:  # a bad config file is said here, not as a broken process pool from the workers
        from skygen.config import load_config
        from skygen.errors import ConfigError

        try:
            load_config(a.config)
        except ConfigError as e:
            p.error(str(e))
    report = run(st)
    print_table(report)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    raise SystemExit(main())
