"""``fusion benchmark``: every solver scored on the same detections of the same frames.

Frames: the first ``--frames`` frames of a split (default ``test``) of a skygen dataset,
fixed. Cells of the grid:

* ``clean``: the stored detections, brightest ``N`` kept, for each N of ``--n``;
* one cell per (corruption, severity, N) for the detection-level corruptions of skygen's
  registry (``dropout``, ``false_stars``, ``centroid_noise``, ``magnitude_noise``; severities
  from the registry's sweep, in its units) at each N of ``--corruption-n``. Dropout,
  centroid and magnitude noise are :func:`skygen.instrument.corruptions.apply_detection_corruptions` on
  the stored table with the stream ``/benchmark``; ``false_stars`` (a *scene* corruption in
  the generator) is emulated on the table: Poisson(severity) detections at uniform sensor
  positions, each with the flux of a randomly chosen real detection of the frame, so they
  compete for the brightest-N slots. Every draw depends only on (dataset seed, frame index,
  corruption), so all solvers see identical inputs; then the brightest N are kept.

Solvers (``--solvers``):

* ``tetra3rs`` — tetra3rs lost-in-space (the classical baseline, :mod:`fusion.solve.tetra`);
* ``oracle-prior`` — coarse-to-fine with a prior that ranks the true region first (an upper
  bound for a learned prior; regions: the ones the learned prior searches — the checkpoint's
  fine regions with ``--search fine`` (default) or its K regions — or, without a checkpoint,
  K = 15 spherical K-means regions of the sphere);
* ``sim85-prior`` — the same with the true region first in 85 % of frames, second otherwise
  (the top-1 expected of the issue-10 model; a simulation, not a model);
* ``whole-sky`` — the same few-star identification over the whole sky (no prior): what the
  prior adds over classical search alone (2–5 ms per frame at 4–10 clean stars);
* ``learned`` / ``learned+fine`` — with ``--checkpoint``: the model's regions alone (top-1/top-3
  accuracy of its K regions, angular error of the top-1 centroid, and how often the true fine
  region is among the ``--top-k`` searched), and coarse-to-fine with the model as prior;
* ``learned+fine>whole-sky`` — learned + fine, then the rest of the sky in the same search where the
  prior's regions refuse (what ``fusion predict --solve`` runs with a model);
* ``tetra3rs>learned+fine`` — tetra3rs lost-in-space, and learned + fine where it refuses;
  ``tetra3rs>learned+fine>whole-sky`` (``fusion predict --solve --lis-first``); ``tetra3rs>whole-sky``
  likewise without a prior (what ``fusion predict --solve`` runs without a model);
* any other solver registered in :mod:`fusion.solve.registry` (docs/ARCHITECTURE.md, "A new solver").

The solvers that need a learned prior (``learned`` and every registered solver with
``prior="learned"``) need ``--checkpoint``: named in ``--solvers`` without one they are
refused before any work; among the default solvers they are skipped with a note in the
report. A checkpoint trained for another camera is refused; one trained on other frame
settings (sensor, optics, ...: :func:`fusion.model.checkpoint.frame_config_differences`)
is scored with a one-line WARNING, and the report lists the keys under ``config_differences``.

The coarse-to-fine solvers run as ``fusion predict --solve`` does: ``--search fine`` (the
20 most probable fine regions; 5 from four detections in ``learned+fine>whole-sky``) and ``--focal-tol 0.02`` by
default, so the benchmark scores
what a user gets; the frames are rendered at the nominal focal length, so the tolerance
only costs here (``--focal-tol 0`` shows how much).

Definitions: a returned attitude is **correct** when its boresight is within ``--correct-deg``
(0.1° by default) of the true boresight and its roll within ``--correct-roll-deg`` (1°) of the
true roll, **wrong** otherwise; a refusal is **refused**. A wrong star identification errs by
degrees; the looser roll bound keeps correct identifications of a few close stars with
noisy centroids (roll is the weakly constrained angle then) from counting as wrong, and
the error statistics report the precision. Boresight and roll errors are over
returned attitudes (median, p95 and max, arcseconds); ms/frame is the wall time of the
solver call on one core: mean, median, p95, p99 and max over every call of the cell, refusals
included (``ms_per_frame``, ``ms_per_frame_median``, ``_p95``, ``_p99``, ``_max``). Per cell and
solver the report also counts refusals by status (``refusals_by_status``, the codes of
:data:`fusion.solve.base.REFUSAL_STATUSES`), sums the answers' false-match probabilities
(``false_match_probability_sum``: the wrong answers to expect if they are calibrated, beside
``wrong``), checks each correct answer's attitude covariance against its true error
(``coverage``: the fraction within 1 and 2 sigma, cross-boresight and roll; 68 / 95 % if calibrated) and counts
the work of the fine stage's answers and refusals (``hypotheses``: median, p99 and max of each).

Tracking cells (``--track-hint-deg 0.5 2 5``, at each N of ``--track-n``, default 2 and 3): the clean
detections, and every solver is given a hint, the true attitude turned by that angle about a random
axis (one draw per frame, :func:`track_hint`), with that angle as the hint's 1-sigma error
(``solve(..., hint=, hint_sigma_deg=)``: the fine stage searches the attitudes within 3 sigma, tetra3rs
tracks with ``hint_uncertainty_deg`` = 3 sigma, strict), and the camera's photometric zero point as
``hint_zero_point`` (:func:`tracking_zero_point`: the median over the frames of the zero point measured at
the true attitude, what a tracker knows from the frames it solved before; report key ``tracking_zero_point``).

``--known-defects``: before solving, each cell's detections lose those at the sensor's defect pixels
(:mod:`fusion.solve.defects`), each frame's map learned from the *other* frames' detections that are no
rendered star (``hip_id`` = -1) and recur at one pixel in three frames or more: a static hot pixel. The cell
keeps the brightest N first and then drops the flagged ones, so a solver may get fewer than N
(``defects_removed`` per cell).
A region is correct when it is the max-cosine region of the true
boresight (as ``fusion evaluate`` labels frames).

Outputs in ``--out``: ``benchmark.json`` (every cell, every solver), ``benchmark.md``
(tables), ``success_vs_n.png`` and ``success_vs_<corruption>.png``. A benchmark holds the
lock of ``--out`` (:class:`skygen.lock.FolderLock`) while it runs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skygen.config import build_config as build_render_config
from skygen.datasets.shards import open_dataset
from skygen.instrument import corruptions as corr
from skygen.instrument.camera import Camera
from skygen.lock import FolderLock
from skygen.runtime import atomic_write_text, hardware_line, write_json

from ..errors import ConfigError
from .base import Detections, Solution, boresight_error_deg, roll_error_deg, rotation_vector_deg
from .registry import SOLVERS as REGISTERED

DETECTION_CORRUPTIONS = ("dropout", "false_stars", "centroid_noise", "magnitude_noise")
FULL_N = (3, 4, 5, 6, 7, 8, 10, 12, 15, 20)
SMALL_N = (4, 6, 10)
TRACK_N = (2, 3)  # tracking cells: where lost in space cannot work
# every registered solver, and ``learned``: the model's regions alone (top-1/top-3, no attitude)
SOLVERS = tuple(REGISTERED) + ("learned",)
DEFAULT_SOLVERS = ("tetra3rs", "oracle-prior", "sim85-prior", "learned", "learned+fine")


def corrupt(
    det: dict, name: str | None, severity: float, seed: int, frame_index: int, width_px: int, height_px: int
) -> Detections:
    """The detection table of one frame with one detection-level corruption (see the module doc)."""
    if name is None or severity == 0:
        return Detections.from_table(det)
    if name == "false_stars":
        rng = corr.stage_rng(seed, frame_index, "false_stars/benchmark")
        n = int(rng.poisson(severity))
        flux = np.asarray(det["flux_adu"], np.float64)
        fake = rng.choice(flux, n) if len(flux) else np.full(n, 1000.0)
        table = {
            "x_px": np.concatenate([det["x_px"], rng.uniform(-0.5, width_px - 0.5, n)]),
            "y_px": np.concatenate([det["y_px"], rng.uniform(-0.5, height_px - 0.5, n)]),
            "flux_adu": np.concatenate([flux, fake]),
        }
        return Detections.from_table(table)
    corr.get(name)
    out, _ = corr.apply_detection_corruptions(det, {name: float(severity)}, seed, frame_index, stream="/benchmark")
    return Detections.from_table(out)


def resolve_corruptions(names) -> tuple[str, ...]:
    """The detection-level corruptions named by ``--corruptions``: ``none`` (or nothing) is clean only."""
    names = tuple(names)
    if "none" in names:
        if len(names) > 1:
            raise ConfigError(f"--corruptions: 'none' (clean cells only) cannot be combined with {names}")
        return ()
    for c in names:
        if c not in DETECTION_CORRUPTIONS:
            raise ConfigError(
                f"--corruptions: {c!r} is not a detection-level corruption; choose from "
                f"{', '.join(DETECTION_CORRUPTIONS)}, or none (clean only)"
            )
    return names


def small_severities(corruptions) -> dict[str, list[float]]:
    """``--grid small``: the two lowest nonzero severities of each corruption's sweep."""
    return {c: [s for s in corr.get(c).sweep if s > 0][:2] for c in resolve_corruptions(corruptions)}


def check_grid(frames: int, n_values, corruption_n, correct_deg: float, correct_roll_deg: float) -> None:
    """Refuse counts and thresholds that would measure nothing (one line naming the option and its range)."""
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise ConfigError(f"--frames {frames}: give at least 1 frame")
    for flag, values in (("--n", n_values), ("--corruption-n", corruption_n)):
        bad = [n for n in values if n < 1]
        if bad:
            raise ConfigError(f"{flag} {bad[0]}: each N (detections kept, brightest first) must be at least 1")
    if not len(n_values):
        raise ConfigError("--n: give at least one N")
    for flag, value in (("--correct-deg", correct_deg), ("--correct-roll-deg", correct_roll_deg)):
        if not 0 < value <= 180:
            raise ConfigError(f"{flag} {value:g}: the error counted as correct must be in (0, 180] degrees")


def grid(
    n_values, corruption_n, corruptions, severities: dict | None = None, track_hint_deg=(), track_n=TRACK_N
) -> list[dict]:
    """Cells: clean at every N of ``n_values``; each corruption's severities (default: the registry's nonzero
    sweep) at every N of ``corruption_n``; tracking (clean detections, a hint ``track_hint_deg`` off) at every N
    of ``track_n``."""
    cells = [{"corruption": None, "severity": 0.0, "n": int(n)} for n in n_values]
    for name in corruptions:
        sev = (severities or {}).get(name) or [s for s in corr.get(name).sweep if s > 0]
        cells += [{"corruption": name, "severity": float(s), "n": int(n)} for n in corruption_n for s in sev]
    for deg in track_hint_deg:
        cells += [{"corruption": None, "severity": 0.0, "n": int(n), "track_hint_deg": float(deg)} for n in track_n]
    return cells


def default_centroids(k: int = 15) -> np.ndarray:
    """K regions of the sphere for the oracle priors when no checkpoint is given (spherical K-means)."""
    from ..model.regions import spherical_kmeans

    rng = np.random.default_rng(0)
    v = rng.standard_normal((20000, 3))
    return spherical_kmeans(v / np.linalg.norm(v, axis=1, keepdims=True), k, seed=0, n_init=2).centroids


def coverage(solutions: list, truth: list) -> dict | None:
    """How often the true attitude error lies within 1 and 2 sigma of each solution's covariance
    (:attr:`Solution.covariance_arcsec`; 68 / 95 % for a calibrated Gaussian): ``cross_*`` pools the
    two cross-boresight axes, ``roll_*`` the roll axis; ``frames``: solutions with a covariance.

    ``bias_arcsec``: the mean signed error per axis (x, y, roll; the truth's camera frame), and
    ``*_unbiased``: the coverage once that mean is taken off every error. Random errors average out; an error
    all answers share does not (real frames: the same bright stars, saturated or shifted alike, in every frame
    of a set, or a truth that differs from them by a constant), and that part is what a covariance drawn from
    per-star scatter cannot hold."""
    errs, sig = [], []
    for res, (m_true, _) in zip(solutions, truth):
        if res.covariance_arcsec is not None:
            errs.append(rotation_vector_deg(m_true, res.matrix) * 3600)
            sig.append(res.covariance_arcsec)
    if not errs:
        return None
    e, sd = np.array(errs), np.maximum(np.array(sig), 1e-12)
    z, zu = np.abs(e) / sd, np.abs(e - e.mean(0)) / sd
    out: dict = {"frames": len(z)}
    for k in (1, 2):
        out[f"cross_{k}sigma"] = float(np.mean(z[:, :2] <= k))
        out[f"roll_{k}sigma"] = float(np.mean(z[:, 2] <= k))
        out[f"cross_{k}sigma_unbiased"] = float(np.mean(zu[:, :2] <= k))
        out[f"roll_{k}sigma_unbiased"] = float(np.mean(zu[:, 2] <= k))
    out["cross_error_over_sigma_median"] = float(np.median(z[:, :2]))
    out["roll_error_over_sigma_median"] = float(np.median(z[:, 2]))
    out["bias_arcsec"] = [float(v) for v in e.mean(0)]
    out["sigma_arcsec_median"] = [float(v) for v in np.median(sd, 0)]
    return out


def _summary(results: list, truth: list, secs: list, correct_deg: float, correct_roll_deg: float) -> dict:
    ok = wrong = refused = 0
    bore, roll = [], []
    statuses: dict[str, int] = {}
    good, good_truth = [], []
    fmp_sum = fmp_wrong = 0.0  # summed false-match probabilities of every answer, and of the wrong ones
    for res, (m_true, roll_true) in zip(results, truth):
        if not isinstance(res, Solution):
            refused += 1
            statuses[res.status] = statuses.get(res.status, 0) + 1
            continue
        b, o = boresight_error_deg(m_true, res.matrix), roll_error_deg(res.roll_deg, roll_true)
        right = b <= correct_deg and o <= correct_roll_deg
        ok, wrong = (ok + 1, wrong) if right else (ok, wrong + 1)
        fmp = res.false_match_probability
        fmp_sum += 0.0 if fmp is None else fmp
        fmp_wrong += 0.0 if fmp is None or right else fmp
        if right:
            good.append(res)
            good_truth.append((m_true, roll_true))
        bore.append(b * 3600)
        roll.append(o * 3600)
    n = len(results)

    def stat(a):
        return (
            {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(np.max(a))} if a else None
        )

    return {
        "frames": n,
        "correct": ok / n,
        "wrong": wrong / n,
        "refused": refused / n,
        "boresight_error_arcsec": stat(bore),
        "roll_error_arcsec": stat(roll),
        "refusals_by_status": dict(sorted(statuses.items())),
        "false_match_probability_sum": fmp_sum,  # the wrong answers expected, if the probabilities are right
        "false_match_probability_of_wrong": fmp_wrong,
        "coverage": coverage(good, good_truth),
        # every call timed, refusals included (a refusal that searches everything is the tail)
        "ms_per_frame": 1e3 * float(np.mean(secs)),
        "ms_per_frame_median": 1e3 * float(np.median(secs)),
        "ms_per_frame_p95": 1e3 * float(np.percentile(secs, 95)),
        "ms_per_frame_p99": 1e3 * float(np.percentile(secs, 99)),
        "ms_per_frame_max": 1e3 * float(np.max(secs)),
        # the work each answer and each refusal took (the fine stage's extra["hypotheses"]): where a work budget
        # (--max-hypotheses) would cut the refusals' tail without losing answers
        "hypotheses": {
            "answered": _quantiles([r.extra.get("hypotheses") for r in results if isinstance(r, Solution)]),
            "refused": _quantiles([r.extra.get("hypotheses") for r in results if not isinstance(r, Solution)]),
        },
    }


def _quantiles(values: list) -> dict | None:
    """{median, p99, max} of the numbers among ``values`` (None where a solver does not count), or None."""
    a = [float(v) for v in values if v is not None]
    if not a:
        return None
    return {"median": float(np.median(a)), "p99": float(np.percentile(a, 99)), "max": float(np.max(a))}


def needs_learned_prior(name: str) -> bool:
    """Whether solver ``name`` (or the benchmark's ``learned`` column) needs a checkpoint's prior."""
    return name == "learned" or (name in REGISTERED and REGISTERED[name].prior == "learned")


def check_solvers(solvers, checkpoint) -> tuple[str, ...]:
    """The solvers to score (None: :data:`DEFAULT_SOLVERS`). Unknown names are refused, and so are solvers that
    need a learned prior when no checkpoint is given, unless they came with the defaults (then they are skipped
    with a note in the report)."""
    solvers = DEFAULT_SOLVERS if solvers is None else tuple(solvers)
    unknown = set(solvers) - set(SOLVERS)
    if unknown:
        raise ConfigError(f"--solvers: unknown {sorted(unknown)}; choose from {', '.join(SOLVERS)}")
    if not solvers:
        raise ConfigError(f"--solvers: give at least one solver, from {', '.join(SOLVERS)}")
    need = [s for s in solvers if needs_learned_prior(s)]
    if need and not checkpoint and solvers != DEFAULT_SOLVERS:
        free = [s for s in SOLVERS if not needs_learned_prior(s)]
        raise ConfigError(
            f"--solvers {' '.join(need)}: {'it needs' if len(need) == 1 else 'they need'} a learned "
            f"prior; pass --checkpoint CK (a trained model), or choose solvers without one: "
            f"{', '.join(free)}"
        )
    return solvers


def run_benchmark(
    data: str | Path,
    out: str | Path,
    *,
    checkpoint: str | Path | None = None,
    split: str = "test",
    frames: int = 200,
    n_values=FULL_N,
    corruption_n=(6, 10),
    corruptions=DETECTION_CORRUPTIONS,
    severities=None,
    solvers=None,
    correct_deg: float = 0.1,
    correct_roll_deg: float = 1.0,
    top_k: int | None = None,
    search: str = "fine",
    focal_tol: float = 0.02,
    track_hint_deg=(),
    track_n=TRACK_N,
    max_hypotheses: int | None = None,
    known_defects: bool = False,
    log=print,
    warn=None,
) -> dict:
    """Score ``solvers`` on every cell of the grid (module docstring) and write the outputs into ``out``.

    Arguments are checked first (ConfigError naming the option; :func:`check_solvers`); ``out`` is
    locked while the benchmark runs (a second one into it is refused, naming the first). ``warn``
    (default: stderr) receives a one-line warning when the checkpoint was trained on data of other
    frame settings than ``data`` (also in the report: ``config_differences``)."""
    import sys

    from .registry import check_search_options

    warn = warn or (lambda msg: print(msg, file=sys.stderr))
    check_search_options(focal_tol, top_k, "--top-k", max_hypotheses)
    check_grid(frames, n_values, corruption_n, correct_deg, correct_roll_deg)
    bad = [d for d in track_hint_deg if not 0 < d <= 20]
    if bad:
        raise ConfigError(f"--track-hint-deg {bad[0]:g}: a hint's error in (0, 20] degrees, e.g. 0.5 2 5")
    if any(n < 1 for n in track_n):
        raise ConfigError(f"--track-n {min(track_n)}: each N must be at least 1")
    solvers = check_solvers(solvers, checkpoint)
    corruptions = resolve_corruptions(corruptions)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out {out}: cannot create the folder ({exc.strerror or exc})") from None
    settings = {
        "split": split,
        "frames": frames,
        "n_values": n_values,
        "corruption_n": corruption_n,
        "corruptions": corruptions,
        "severities": severities,
        "correct_deg": correct_deg,
        "correct_roll_deg": correct_roll_deg,
        "top_k": top_k,
        "search": search,
        "focal_tol": focal_tol,
        "track_hint_deg": tuple(track_hint_deg),
        "track_n": tuple(track_n),
        "max_hypotheses": max_hypotheses,
        "known_defects": bool(known_defects),
    }
    with FolderLock(out, what="fusion benchmark"):
        return _run_benchmark(data, out, checkpoint, list(solvers), settings, log, warn)


@dataclass
class BenchmarkFrames:
    """The fixed frames of a benchmark: the camera, their stored detections (and images, for a model) and truth."""

    config: dict  # the dataset's render config
    camera: Camera
    index: np.ndarray  # frame index of each frame
    tables: list  # stored detection tables
    images: list  # stored images, or None each (no model to read them)
    v_true: np.ndarray  # (n, 3) true boresight unit vectors
    truth: list  # (true rotation matrix, true roll_deg) per frame
    seed: int  # the dataset's seed: every corruption draw derives from it
    info: dict  # path, dataset_id, split, frames (for the report)
    defects: list | None = None  # --known-defects: each frame's defect map, learned from the other frames
    zero_point: float | None = None  # tracking cells' hint_zero_point (tracking_zero_point)
    zero_point_scatter: float | None = None  # its scatter from frame to frame (mag, robust)


def load_frames(data, split: str, frames: int, with_images: bool) -> BenchmarkFrames:
    """The first ``frames`` frames of ``split`` of dataset ``data``."""
    from skygen.sky.attitude import quaternion_to_matrix

    with open_dataset(data) as ds:
        rcfg = build_render_config(ds.config)
        pos = ds.indices(split)[:frames]
        if not len(pos):
            raise ConfigError(f"--split {split}: dataset {data} holds no {split} frames")
        tables = [ds.detections(int(p)) for p in pos]
        images = [ds.image(int(p)) for p in pos] if with_images else [None] * len(pos)
        q_true = np.asarray(ds.boresight["quaternion"][pos], np.float64)
        roll_true = np.asarray(ds.boresight["roll_deg"][pos], np.float64)
        return BenchmarkFrames(
            config=dict(ds.config),
            camera=Camera.from_config(rcfg.camera),
            index=ds.frames["index"][pos],
            tables=tables,
            images=images,
            v_true=np.asarray(ds.boresight["unit_vector"][pos], np.float64),
            truth=[(quaternion_to_matrix(q), r) for q, r in zip(q_true, roll_true)],
            seed=int(ds.config["seed"]),
            info={
                "path": str(ds.root),
                "dataset_id": ds.manifest.get("dataset_id"),
                "split": split,
                "frames": int(len(pos)),
            },
        )


def load_benchmark_prior(checkpoint, data, fr: BenchmarkFrames, warn):
    """(the checkpoint's prior, the frame settings of ``data`` unlike its training data's): refuses a
    checkpoint of another camera; other differences are warned about and reported."""
    from ..model.checkpoint import differences_warning, load_checkpoint
    from .priors import load_prior

    ckpt = load_checkpoint(checkpoint)
    own = ckpt.render_config  # older checkpoints: the benchmark dataset's
    if own and own["camera"] != fr.config["camera"]:
        raise ConfigError(
            f"{checkpoint} was trained for another camera than dataset {data} "
            f"({own['camera']} vs {fr.config['camera']}); benchmark it on frames of its camera"
        )
    diffs = ckpt.config_differences(fr.config)
    if diffs:
        warn(differences_warning(str(data), diffs, str(checkpoint)))
    return load_prior(ckpt, None if own else dict(fr.config)), diffs


def build_solvers(ctx, solvers: list[str]) -> tuple[dict, dict]:
    """({name: solver} to run, {name: (first, second)} composed from two of them): a chain ``a>b`` whose
    parts are both scored is composed from their per-frame answers instead of solving twice."""
    from .registry import get

    built, composite = {}, {}
    for name in solvers:
        if name == "learned":
            continue
        parts = name.split(">")
        if len(parts) == 2 and all(p in solvers for p in parts):
            composite[name] = tuple(parts)
        else:
            built[name] = get(ctx, name)
    return built, composite


def track_hint(m_true: np.ndarray, angle_deg: float, seed: int, frame_index: int) -> np.ndarray:
    """A tracking cell's hint: the true camera -> ICRS matrix turned by ``angle_deg`` about a random axis of the
    camera frame (one draw per (dataset seed, frame), the same for every solver and every angle)."""
    from scipy.spatial.transform import Rotation

    rng = corr.stage_rng(seed, frame_index, "track_hint/benchmark")
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    return np.asarray(m_true) @ Rotation.from_rotvec(np.radians(angle_deg) * axis).as_matrix()


def tracking_zero_point(solver, fr: BenchmarkFrames) -> float | None:
    """The photometric zero point tracking cells give as ``hint_zero_point``: the median over the frames of the
    zero point ``solver`` (the fine stage) measures on all of a frame's detections at its true attitude (a 0.05 deg
    hint) -- what a tracker that has solved earlier frames of this camera knows; None if no frame gives one.
    :func:`frame_zero_points` gives each frame's."""
    zps = frame_zero_points(solver, fr)
    return float(np.median(zps)) if len(zps) else None


def frame_zero_points(solver, fr: BenchmarkFrames) -> np.ndarray:
    """Each frame's zero point as :func:`tracking_zero_point` measures it (frames that give none left out)."""
    zps = []
    for j, t in enumerate(fr.tables):
        r = solver.solve(Detections.from_table(t), fr.camera, None, hint=fr.truth[j][0], hint_sigma_deg=0.05)
        if isinstance(r, Solution) and r.extra.get("zero_point") is not None:
            zps.append(r.extra["zero_point"])
    return np.asarray(zps, np.float64)


def solve_all(solver, dets: list, fr: BenchmarkFrames, hint_deg: float = 0.0) -> tuple[list, list]:
    """(answers, seconds) of ``solver`` on each frame's detections; the benchmark's truth-ranked priors
    receive each frame's probabilities; ``hint_deg`` > 0: tracking, each frame's :func:`track_hint` with a
    1-sigma error of ``hint_deg``."""
    from .priors import OraclePrior

    oracle = getattr(solver, "prior", None)
    oracle = oracle if isinstance(oracle, OraclePrior) else None
    results, secs = [], []
    for j, d in enumerate(dets):
        kw = {"probabilities": oracle.probabilities_for(fr.v_true[j], int(fr.index[j]))} if oracle is not None else {}
        if hint_deg > 0:
            kw = {"hint": track_hint(fr.truth[j][0], hint_deg, fr.seed, int(fr.index[j])), "hint_sigma_deg": hint_deg}
            if fr.zero_point is not None:
                kw["hint_zero_point"] = fr.zero_point
        t0 = time.perf_counter()
        results.append(solver.solve(d, fr.camera, fr.images[j], **kw))
        secs.append(time.perf_counter() - t0)
    return results, secs


def warm_up(built: dict, fr: BenchmarkFrames) -> None:
    """One untimed solve per solver on the first frame: compiling the fine stage's loops (numba) and loading
    its pair index take seconds once per process, which would otherwise be the first cell's p99."""
    if fr.tables:
        for solver in built.values():
            solve_all(solver, [Detections.from_table(fr.tables[0])], fr)


def score_cell(cell: dict, fr: BenchmarkFrames, built: dict, composite: dict, learned, correct: tuple) -> dict:
    """One row of the report: every solver on the cell's (corrupted, brightest-N) detections. ``learned``:
    None, or (prior, its K centroids, true region labels, true fine-region labels or None, regions searched)
    for the ``learned`` column; ``correct``: (correct_deg, correct_roll_deg)."""
    cam = fr.camera
    dets = [
        corrupt(t, cell["corruption"], cell["severity"], fr.seed, int(i), cam.width_px, cam.height_px).brightest(
            cell["n"]
        )
        for t, i in zip(fr.tables, fr.index)
    ]
    removed = 0
    if fr.defects is not None:  # the brightest N, then the sensor's known defects dropped (as a tracker's map does)
        dets, counts = zip(*(m.remove(d) for m, d in zip(fr.defects, dets)))
        dets, removed = list(dets), int(sum(counts))
    row = {**cell, "mean_detections": float(np.mean([len(d) for d in dets])), "solvers": {}}
    if fr.defects is not None:
        row["defects_removed"] = removed
    answers = {}
    hint_deg = float(cell.get("track_hint_deg") or 0.0)
    for name, solver in built.items():
        results, secs = answers[name] = solve_all(solver, dets, fr, hint_deg)
        row["solvers"][name] = _summary(results, fr.truth, secs, *correct)
    for name, (a, b) in composite.items():
        (ra, sa), (rb, sb) = answers[a], answers[b]
        first = [isinstance(x, Solution) for x in ra]
        row["solvers"][name] = _summary(
            [x if ok else y for x, y, ok in zip(ra, rb, first)],
            fr.truth,
            [x if ok else x + y for x, y, ok in zip(sa, sb, first)],
            *correct,
        )
    if learned is not None and not hint_deg:
        prior, centroids, labels, search_labels, top_k = learned
        row["solvers"]["learned"] = _learned_cell(
            prior, dets, fr.images, labels, fr.v_true, centroids, search_labels, top_k
        )
    return row


def _run_benchmark(data, out: Path, checkpoint, solvers: list[str], st: dict, log, warn) -> dict:
    """run_benchmark once its arguments are checked and it holds the lock of ``out``: load the frames and the
    prior, build the solvers, score every cell, write the outputs."""
    from .registry import make_context
    from .tetra import Tetra3Solver

    t_start = time.perf_counter()
    fr = load_frames(data, st["split"], st["frames"], with_images=bool(checkpoint))
    tetra = Tetra3Solver(fr.camera, log=log)
    prior, notes, diffs = None, [], {}
    if checkpoint:
        prior, diffs = load_benchmark_prior(checkpoint, data, fr, warn)
        centroids = prior.centroids
    else:
        centroids = default_centroids()
        dropped = [s for s in solvers if needs_learned_prior(s)]
        if dropped:
            notes.append(f"{', '.join(dropped)}: skipped, no --checkpoint given (pending a trained model)")
        solvers = [s for s in solvers if not needs_learned_prior(s)]
    ctx = make_context(
        fr.camera,
        prior=prior,
        search=st["search"],
        search_k=st["top_k"],
        focal_tol=st["focal_tol"],
        tetra=tetra,
        search_centroids=None if prior is not None else centroids,
        k_flag="--top-k",
        max_hypotheses=st.get("max_hypotheses"),
    )
    level = getattr(ctx.prior, "level", "coarse")
    built, composite = build_solvers(ctx, solvers)
    warm_up(built, fr)
    if st.get("known_defects"):
        from .defects import from_dataset_tables, leave_one_out

        fr.defects = leave_one_out(from_dataset_tables(fr.tables))
    if st["track_hint_deg"]:
        from .registry import get

        zps = frame_zero_points(get(ctx, "whole-sky"), fr)
        if len(zps):
            fr.zero_point = float(np.median(zps))
            # the frame-to-frame scatter a tracker's zero point has (robust: 1.4826 x the median absolute deviation)
            fr.zero_point_scatter = float(1.4826 * np.median(np.abs(zps - fr.zero_point)))
    labels = np.argmax(fr.v_true @ centroids.T, axis=1)
    search_labels = np.argmax(fr.v_true @ ctx.search_centroids.T, axis=1)
    learned = (
        (prior, centroids, labels, search_labels if level == "fine" else None, ctx.top_k)
        if "learned" in solvers
        else None
    )
    cells = grid(
        st["n_values"], st["corruption_n"], st["corruptions"], st["severities"], st["track_hint_deg"], st["track_n"]
    )
    log(f"benchmark: {len(fr.tables)} frames x {len(cells)} cells; solvers: {', '.join(solvers)}")
    rows = []
    for ci, cell in enumerate(cells):
        rows.append(score_cell(cell, fr, built, composite, learned, (st["correct_deg"], st["correct_roll_deg"])))
        log(_cell_line(rows[-1], ci, len(cells)))
    report = {
        "dataset": fr.info,
        "camera": {
            "width_px": fr.camera.width_px,
            "height_px": fr.camera.height_px,
            "fov_deg": list(fr.camera.fov_deg),
        },
        "checkpoint": str(checkpoint) if checkpoint else None,
        "solvers": list(built) + list(composite) + (["learned"] if "learned" in solvers else []),
        "correct_definition": f"boresight error <= {st['correct_deg']} deg and roll error <= "
        f"{st['correct_roll_deg']} deg",
        "region_count": int(len(centroids)),
        "search": {
            "level": level,
            "regions": int(len(ctx.search_centroids)),
            "top_k": ctx.top_k,
            "chain_top_k": ctx.chain_top_k,  # what learned+fine>whole-sky searches before the sky
            "focal_tol": st["focal_tol"],
            "max_hypotheses": st.get("max_hypotheses"),  # None: the fine stage's default budget
        },
        "top_k": ctx.top_k,
        "notes": notes,
        "known_defects": bool(st.get("known_defects")),
        "tracking_zero_point": fr.zero_point,
        "tracking_zero_point_scatter": fr.zero_point_scatter,
        "config_differences": diffs,
        "cells": rows,
        "hardware": hardware_line() + ", one process",
        "tetra3rs_version": tetra.t3.__version__,
        "wall_time_s": time.perf_counter() - t_start,
    }
    write_outputs(report, out, log)
    return report


def write_outputs(report: dict, out: Path, log) -> None:
    """benchmark.json, benchmark.md and the plots into ``out``."""
    write_json(out / "benchmark.json", report)
    atomic_write_text(out / "benchmark.md", markdown(report))
    plot(report, out)
    log(f"wrote {out / 'benchmark.json'}, benchmark.md and plots ({report['wall_time_s']:.0f} s)")


def _learned_cell(prior, dets, images, labels, v_true, centroids, search_labels, search_k) -> dict:
    """The model's regions alone: top-1 / top-3 of its K regions, angular error of the top-1 centroid, and
    (``search_labels`` given) how often the true fine region is among the ``search_k`` searched."""
    t, probs, fine = [], [], []
    for d, im in zip(dets, images):
        t0 = time.perf_counter()
        c, f = prior.both(d, im)
        t.append(time.perf_counter() - t0)
        probs.append(c)
        fine.append(f)
    p = np.array(probs)
    order = np.argsort(-p, axis=1)
    top1 = order[:, 0] == labels
    top3 = (order[:, :3] == labels[:, None]).any(axis=1)
    err = np.degrees(np.arccos(np.clip(np.sum(v_true * centroids[order[:, 0]], axis=1), -1, 1)))
    out = {
        "frames": len(dets),
        "top1": float(top1.mean()),
        "top3": float(top3.mean()),
        "angular_error_deg": {"median": float(np.median(err)), "p95": float(np.percentile(err, 95))},
        "ms_per_frame": 1e3 * float(np.mean(t)),
    }
    if search_labels is not None and fine[0] is not None:
        fo = np.argsort(-np.array(fine), axis=1)[:, :search_k]
        out[f"fine_top{search_k}"] = float((fo == search_labels[:, None]).any(axis=1).mean())
    return out


def _cell_name(c: dict) -> str:
    if c.get("track_hint_deg"):
        return f"track, hint {c['track_hint_deg']:g}° off"
    return "clean" if c["corruption"] is None else f"{c['corruption']}={c['severity']:g}"


def _is_clean(row: dict) -> bool:
    return row["corruption"] is None and not row.get("track_hint_deg")


def _cell_line(row: dict, i: int, n: int) -> str:
    parts = []
    for name, s in row["solvers"].items():
        parts.append(
            f"{name} {100 * s['correct']:.0f}%/{100 * s['wrong']:.0f}%"
            if "correct" in s
            else f"{name} top1 {100 * s['top1']:.0f}%"
        )
    return f"[{i + 1}/{n}] {_cell_name(row)} N={row['n']}: " + ", ".join(parts)


def markdown(r: dict) -> str:
    full = [s for s in r["solvers"] if s != "learned"]
    lines = [
        f"# Solver benchmark on `{r['dataset']['path']}` ({r['dataset']['split']}, {r['dataset']['frames']} frames)",
        "",
        f"Camera {r['camera']['width_px']} x {r['camera']['height_px']} px, field "
        f"{r['camera']['fov_deg'][0]:.2f} x {r['camera']['fov_deg'][1]:.2f} deg; {r['region_count']} regions; "
        f"{_search_text(r)}; tetra3rs {r['tetra3rs_version']}; {r['hardware']}; "
        f"{r['wall_time_s']:.0f} s in all.",
        "",
        f"**correct** = {r['correct_definition']}; **wrong** = any other returned attitude; **refused** = no "
        "attitude returned. Each entry: correct / wrong / refused (%), then ms per frame (mean; p50 / p95 / p99, "
        "every call timed, refusals included).",
        "",
    ]
    setup = []
    if r.get("known_defects"):
        removed = sum(c.get("defects_removed", 0) for c in r["cells"])
        setup.append(
            f"known defects (`--known-defects`): {removed} detections at static hot pixels dropped over all cells "
            "after the brightest N were kept (each frame's map learned from the other frames)"
        )
    if r.get("tracking_zero_point") is not None:
        scatter = r.get("tracking_zero_point_scatter")
        setup.append(
            f"tracking cells: hint zero point {r['tracking_zero_point']:.3f} mag (the frames' median"
            + (f"; frame to frame it scatters {scatter:.3f} mag" if scatter is not None else "")
            + ")"
        )
    lines += [f"- {n}" for n in setup + r["notes"]] + ([""] if setup or r["notes"] else [])
    head = (
        "| cell | N | mean det. | "
        + " | ".join(full)
        + (" | learned top-1 / top-3 |" if "learned" in r["solvers"] else "")
    )
    lines += [head.rstrip(" |") + " |", "|" + "---|" * (3 + len(full) + ("learned" in r["solvers"]))]
    for row in r["cells"]:
        cols = []
        for name in full:
            s = row["solvers"][name]
            cols.append(
                f"{100 * s['correct']:.0f} / {100 * s['wrong']:.0f} / {100 * s['refused']:.0f} "
                f"({s['ms_per_frame']:.1f} ms; {_tail_text(s)})"
            )
        if "learned" in r["solvers"]:
            s = row["solvers"]["learned"]
            k = [key for key in s if key.startswith("top") and key != "top1"][0]
            fk = [key for key in s if key.startswith("fine_top")]
            fine = f"; fine top-{fk[0][8:]} {100 * s[fk[0]]:.0f}" if fk else ""
            cols.append(
                f"{100 * s['top1']:.0f} / {100 * s[k]:.0f}{fine} (median err {s['angular_error_deg']['median']:.1f}°)"
            )
        lines.append(f"| {_cell_name(row)} | {row['n']} | {row['mean_detections']:.1f} | " + " | ".join(cols) + " |")
    lines += [
        "",
        "Attitude errors of returned solutions (median boresight / median roll, arcsec), clean cells:",
        "",
        "| N | " + " | ".join(full) + " |",
        "|---|" + "---|" * len(full),
    ]
    for row in r["cells"]:
        if _is_clean(row):
            cols = []
            for name in full:
                s = row["solvers"][name]
                b, o = s["boresight_error_arcsec"], s["roll_error_arcsec"]
                cols.append("–" if b is None else f"{b['median']:.1f} / {o['median']:.1f}")
            lines.append(f"| {row['n']} | " + " | ".join(cols) + " |")
    return "\n".join(lines + _certificate_lines(r, full)) + "\n"


def _tail_text(s: dict) -> str:
    """p50 / p95 / p99 of one cell's timings (older reports: the median only)."""
    med, p95, p99 = (s.get(f"ms_per_frame_{k}") for k in ("median", "p95", "p99"))
    if med is None:
        return "median –"
    return f"{med:.1f} / {p95:.1f} / {p99:.1f}" if p99 is not None else f"median {med:.1f}"


def _certificate_lines(r: dict, full: list) -> list:
    """The refusals by status, and each solution's certificate checked against the truth: the wrong answers
    its false-match probabilities expect (their sum) beside those counted, and how often the true error of
    a correct answer lies within 1 / 2 sigma of its covariance (68 / 95 % if calibrated)."""
    if not any("refusals_by_status" in row["solvers"].get(n, {}) for row in r["cells"] for n in full):
        return []
    lines = [
        "",
        "Refusals by status (frames), and the certificate of the answers: wrong answers counted / expected "
        "(the sum of their false-match probabilities); correct answers whose true error lies within 1σ / 2σ "
        "of their covariance, cross-boresight (x and y pooled) and roll (68 / 95 % if calibrated):",
        "",
        "| cell | N | solver | refusals by status | wrong / expected | cross 1σ / 2σ | roll 1σ / 2σ |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in r["cells"]:
        for name in full:
            s = row["solvers"][name]
            if "refusals_by_status" not in s:
                continue
            by = ", ".join(f"{k} {v}" for k, v in s["refusals_by_status"].items()) or "–"
            wrong = round(s["wrong"] * s["frames"])
            c = s.get("coverage")
            cross = "–" if c is None else f"{100 * c['cross_1sigma']:.0f} / {100 * c['cross_2sigma']:.0f} %"
            roll = "–" if c is None else f"{100 * c['roll_1sigma']:.0f} / {100 * c['roll_2sigma']:.0f} %"
            lines.append(
                f"| {_cell_name(row)} | {row['n']} | {name} | {by} | {wrong} / "
                f"{s['false_match_probability_sum']:.2g} | {cross} | {roll} |"
            )
    return lines


def _search_text(r: dict) -> str:
    se = r.get("search") or {"level": "coarse", "regions": r["region_count"], "top_k": r["top_k"], "focal_tol": 0.0}
    what = "fine regions" if se["level"] == "fine" else "regions"
    return (
        f"coarse-to-fine solvers search the top {se['top_k']} of {se['regions']} {what}, focal length "
        f"within ±{100 * se['focal_tol']:g} %"
    )


def plot(r: dict, out: Path) -> None:
    from ..plots import _figure, _save

    plt = _figure()
    full = [s for s in r["solvers"] if s != "learned"]
    clean = [row for row in r["cells"] if _is_clean(row)]
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
                y = ([100 * base[0]["solvers"][s]["correct"]] if base else []) + [
                    100 * row["solvers"][s]["correct"] for row in sub
                ]
                ax.plot(sev, y, "o-", label=f"{s}, N={n}")
        ax.set_xlabel(f"{name} ({corr.get(name).unit})")
        ax.set_ylabel("% correct")
        ax.set_ylim(-2, 102)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
        _save(fig, out / f"success_vs_{name}.png")
        plt.close(fig)
