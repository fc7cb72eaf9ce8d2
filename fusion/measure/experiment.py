"""``fusion experiment``: the paper's tables re-measured, and the experiments it lists as missing.

One command renders (or reuses) the preset's dataset, trains every run it needs with
several seeds (validation split for early stopping only), evaluates each on the
independent test split, runs the robustness sweeps and the latency timing, and writes
``REPORT.md`` plus the raw JSON/CSV beside it. Every step is skipped when its output
already exists, so an interrupted experiment resumes where it stopped (a killed
training run resumes from its ``last.pt``).

Sections (names usable with ``--sections``):

1. ``table1``   — the paper's Table 1: image-only baselines and Star-Fusion, top-1/3/5;
   ``few_star`` — table 1's runs on frames cut to their brightest N detections (the image whole);
2. ``ablation`` — all 7 non-empty subsets of {image, heatmap, coordinates};
3. ``k_sweep``  — K in the preset's list: top-1 and angular error (median, p95) against K;
4. ``labels``   — hard labels with focal loss vs geometry-aware soft labels (several kappa);
5. ``coords``   — coordinate encoders (MLP, set encoder, transformer), each evaluated with
   the detections in brightness order and shuffled;
6. ``recipe``   — the training recipe's own ablations (e.g. roll-canonical vs raw inputs, the
   sample stream vs the fixed training split at about equal training time), with the
   training time and samples seen of every row;
7. ``robustness`` — every registered corruption for the full, image-only and geometry-only
   models (first seed), one figure per corruption;
8. ``latency``  — ``fusion timing`` of the trained full model, forward and end-to-end.

A preset is a YAML file (``configs/experiments/<name>.yaml``) that names the dataset
(skygen overrides), the training preset, the seeds and each section's variants as lists
of ``key=value`` overrides of the training config. ``sweep_model`` names the table-1 row
whose overrides the K sweep, the label study and the latency timing start from (default
``star_fusion``); ``sweep_overrides`` replaces those overrides where the sweeps should run at
another budget than table 1 (the CPU preset: a 1.6-min geometry-only run, while table 1 compares
every model at about 4 min).

A preset runs the sections it defines (``--sections`` picks among them); ``few_star: [3, 4, ...]``
scores every table-1 run again on the test frames cut to their brightest N detections (the image
whole). A row's override ``config=configs/X.yaml`` trains it from that preset instead of the
preset-wide ``train_config``, so rows of different recipes sit in one table.

Two-stage rows: the override ``model.init_from=row:NAME`` warm-starts a run from the best
checkpoint of table-1 row ``NAME`` with the same seed (trained first when missing). Its training
time and samples seen in the tables are both stages together, so a two-stage row is compared with
one-stage rows at equal total cost.
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from skygen.config import load_config as load_render_config
from skygen.configlib import read_yaml
from skygen.datasets.build import render_dataset
from skygen.datasets.shards import open_dataset
from skygen.runtime import atomic_write_text, hardware, write_json

from ..config import load_config
from ..errors import ConfigError
from ..model.checkpoint import load_checkpoint
from .evaluate import evaluate_checkpoint

SECTIONS = ("table1", "few_star", "ablation", "k_sweep", "labels", "coords", "recipe", "robustness", "latency")
PRESET_DIR = Path(__file__).resolve().parents[2] / "configs" / "experiments"
ROW_REF = "model.init_from=row:"  # a two-stage row: warm start from a table-1 row's run
CONFIG_REF = "config="  # a row's own training preset instead of the preset-wide train_config

# The paper's reported numbers (Hammad & Hammad, Star-Fusion; K = 15, validation split,
# one seed, Stellarium-derived images, SwinV2 from ImageNet weights). Shown beside ours,
# labelled, never mixed into our results.
PAPER_TABLE1 = {"resnet50": (79.4, 88.2, 92.1), "swinv2_tiny": (84.2, 91.5, 95.8), "star_fusion": (93.4, 97.8, 99.2)}
PAPER_ABLATION_TOP1 = {"image+heatmap+coords": 93.4, "image+coords": 90.1, "image+heatmap": 88.9, "image": 84.2}
PAPER_LATENCY = "18.4 ms forward pass, batch 1, FP16, Jetson at 10-15 W (paper; not measured here)"


@dataclass(frozen=True)
class RunSpec:
    """One training run: a name for tables, config overrides and a seed."""

    name: str
    overrides: tuple[str, ...]
    seed: int

    @property
    def key(self) -> str:
        import hashlib

        text = json.dumps(sorted(self.overrides)) + f"|{self.seed}"
        return hashlib.sha256(text.encode()).hexdigest()[:10]


def stage_row(overrides) -> str | None:
    """The table-1 row a two-stage run warm-starts from (``model.init_from=row:NAME``), or None."""
    refs = [o[len(ROW_REF) :] for o in overrides if o.startswith(ROW_REF)]
    return refs[-1] if refs else None


@dataclass
class Preset:
    name: str
    dataset_n: int
    dataset_overrides: list[str]
    train_config: str
    train_overrides: list[str]
    seeds: list[int]
    split: str
    table1: dict[str, list[str]]
    ablation: dict[str, list[str]]
    k_values: list[int]
    soft_kappas: list[float]
    coord_encoders: dict[str, list[str]]
    robustness_models: dict[str, list[str]]
    robustness_frames: int
    robustness_levels: dict[str, list[float]] = field(default_factory=dict)
    timing_iters: int = 50
    notes: list[str] = field(default_factory=list)
    sweep_model: str = "star_fusion"
    recipe: dict[str, list[str]] = field(default_factory=dict)
    sweep_overrides: list[str] | None = None  # None: the sweep model's table-1 overrides
    few_star: list[int] = field(default_factory=list)
    sections: tuple[str, ...] = SECTIONS  # the sections the preset defines

    @property
    def sweep_base(self) -> tuple[str, ...]:
        """Overrides the K sweep, labels, coords, recipe and latency sections start from."""
        return tuple(self.table1[self.sweep_model] if self.sweep_overrides is None else self.sweep_overrides)


def load_preset(name_or_path: str | Path) -> Preset:
    path = Path(name_or_path)
    if not path.suffix:
        path = PRESET_DIR / f"{name_or_path}.yaml"
    if not path.exists():
        names = ", ".join(sorted(p.stem for p in PRESET_DIR.glob("*.yaml")))
        raise ConfigError(f"experiment preset {name_or_path!r} not found; available: {names}")
    raw = read_yaml(path)  # one line, not a traceback, for a file that is not UTF-8 YAML
    try:
        sec = raw["sections"]
        present = tuple(s for s in SECTIONS if s in sec or (s == "labels" and "soft_kappas" in sec))
        rob = sec.get("robustness") or {}
        preset = Preset(
            name=raw.get("name", path.stem),
            dataset_n=int(raw["dataset"]["n_frames"]),
            dataset_overrides=list(raw["dataset"].get("overrides", [])),
            train_config=raw["train_config"],
            train_overrides=list(raw.get("train_overrides", [])),
            seeds=[int(s) for s in raw["seeds"]],
            split=raw.get("split", "test"),
            table1=dict(sec["table1"]),
            ablation=dict(sec.get("ablation") or {}),
            k_values=[int(k) for k in sec.get("k_sweep") or []],
            soft_kappas=[float(k) for k in sec.get("soft_kappas") or []],
            coord_encoders=dict(sec.get("coords") or {}),
            robustness_models=dict(rob.get("models") or {}),
            robustness_frames=int(rob.get("frames", 0)),
            robustness_levels={k: [float(x) for x in v] for k, v in rob.get("levels", {}).items()},
            timing_iters=int((sec.get("latency") or {}).get("iters", 50)),
            notes=list(raw.get("notes", [])),
            sweep_model=str(raw.get("sweep_model", "star_fusion")),
            recipe=dict(sec.get("recipe") or {}),
            sweep_overrides=None if raw.get("sweep_overrides") is None else [str(o) for o in raw["sweep_overrides"]],
            few_star=[int(n) for n in sec.get("few_star") or []],
            sections=present,
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: malformed experiment preset ({type(exc).__name__}: {exc})") from None
    if preset.sweep_model not in preset.table1:
        raise ConfigError(
            f"{path}: sweep_model {preset.sweep_model!r} is not a row of sections.table1 ({', '.join(preset.table1)})"
        )
    if any(n < 1 for n in preset.few_star):
        raise ConfigError(f"{path}: sections.few_star {preset.few_star}: detections kept must be at least 1")
    for ov in [
        [],
        *preset.table1.values(),
        *preset.ablation.values(),
        *preset.coord_encoders.values(),
        *preset.robustness_models.values(),
        *preset.recipe.values(),
        list(preset.sweep_base),
    ]:
        load_run_config(preset, ov)  # validate early
        row = stage_row(ov)
        if row is not None and (row not in preset.table1 or stage_row(preset.table1[row]) is not None):
            raise ConfigError(
                f"{path}: {ROW_REF}{row} must name a one-stage row of sections.table1 "
                f"({', '.join(r for r, o in preset.table1.items() if stage_row(o) is None)})"
            )
    return preset


def load_run_config(preset: Preset, overrides, extra: list[str] = ()):
    """The training config of a run: its own ``config=`` preset or the preset-wide one, then the
    preset-wide ``train_overrides``, the run's overrides and ``extra``."""
    ov = list(preset.train_overrides) + list(overrides) + list(extra)
    own = [o[len(CONFIG_REF) :] for o in ov if o.startswith(CONFIG_REF)]
    base = _repo_path(own[-1] if own else preset.train_config)
    if not base.exists():
        raise ConfigError(f"experiment preset {preset.name!r}: training config {base} not found")
    return load_config(base, [o for o in ov if not o.startswith(CONFIG_REF)])


def _repo_path(p: str) -> Path:
    path = Path(p)
    return path if path.is_absolute() or path.exists() else Path(__file__).resolve().parents[2] / path


# --------------------------------------------------------------------------- planning
def plan(preset: Preset) -> dict[str, list[RunSpec]]:
    """Runs per section (identical runs in several sections share one folder)."""
    seeds = preset.seeds
    runs: dict[str, list[RunSpec]] = {s: [] for s in SECTIONS}
    for label, ov in preset.table1.items():
        runs["table1"] += [RunSpec(label, tuple(ov), s) for s in seeds]
    for label, ov in preset.ablation.items():
        runs["ablation"] += [RunSpec(label, tuple(ov), s) for s in seeds]
    full = preset.sweep_base
    base = load_run_config(preset, full)
    for k in preset.k_values:  # the preset's own K shares the sweep model's runs
        ov = full if k == base.labels.k else full + (f"labels.k={k}",)
        runs["k_sweep"] += [RunSpec(f"K={k}", ov, s) for s in seeds]
    loss = "focal" if base.loss.gamma > 0 else "cross-entropy"
    if "labels" in preset.sections:
        full_coarse = full
        if base.labels.fine_k:  # soft labels and fine regions exclude each other: compare both against hard labels
            runs["labels"] += [RunSpec(f"hard, {loss}, {base.labels.fine_k} fine regions", full, s) for s in seeds]
            full_coarse = full + ("labels.fine_k=null",)
        runs["labels"] += [RunSpec(f"hard, {loss}", full_coarse, s) for s in seeds]
        for kappa in preset.soft_kappas:
            runs["labels"] += [
                RunSpec(f"soft, kappa={kappa:g}", full_coarse + ("labels.soft_labels=true", f"labels.kappa={kappa}"), s)
                for s in seeds
            ]
    for label, ov in preset.coord_encoders.items():
        runs["coords"] += [RunSpec(label, tuple(ov), s) for s in seeds]
    for label, ov in preset.recipe.items():
        runs["recipe"] += [RunSpec(label, tuple(ov), s) for s in seeds]
    for label, ov in preset.robustness_models.items():
        runs["robustness"].append(RunSpec(label, tuple(ov), seeds[0]))
    if "latency" in preset.sections:
        runs["latency"].append(RunSpec(preset.sweep_model, full, seeds[0]))
    if "few_star" in preset.sections:
        runs["few_star"] = list(runs["table1"])
    return runs


# --------------------------------------------------------------------------- steps
def ensure_dataset(preset: Preset, data: Path, workers: int, log) -> Path:
    cfg = load_render_config(overrides=preset.dataset_overrides + [f"n_frames={preset.dataset_n}"])
    t0 = time.perf_counter()
    render_dataset(cfg, data, workers=workers, progress=False)
    log(f"dataset {data}: ready ({time.perf_counter() - t0:.0f} s)")
    return data


def run_folder(runs_dir: Path, run: RunSpec) -> Path:
    return runs_dir / f"{run.name.replace(' ', '_').replace(',', '').replace('=', '')}-{run.key}"


def first_stage(preset: Preset, run: RunSpec) -> RunSpec:
    """The table-1 run (same seed) that two-stage ``run`` warm-starts from."""
    row = stage_row(run.overrides)
    return RunSpec(row, tuple(preset.table1[row]), run.seed)


def ensure_run(preset: Preset, run: RunSpec, data: Path, runs_dir: Path, log, *, retrain: bool = False) -> Path:
    """Train (or resume, or skip) one run and evaluate its best checkpoint on the test split (and, with
    ``few_star``, on its frames cut to their brightest N detections) while the checkpoint is at hand."""
    from ..train import train  # experiment is the one measurement that trains (docs/ARCHITECTURE.md)

    folder = run_folder(runs_dir, run)
    ov = [o for o in run.overrides if not o.startswith(ROW_REF)]
    extra = [f"train.seed={run.seed}", f"data.path={data}", "train.progress=false"]
    done = (folder / "summary.json").exists() and not retrain
    if stage_row(run.overrides) is not None and not done:
        spec = first_stage(preset, run)
        first = run_folder(runs_dir, spec)
        again = (first / "summary.json").exists() and not (first / "best.pt").exists()
        if again:
            log(
                f"  {spec.name} seed {spec.seed}: its checkpoint is gone (results copied from another machine?); "
                "training it again for the second stage"
            )
        ensure_run(preset, spec, data, runs_dir, log, retrain=again)
        extra.append(f"model.init_from={first / 'best.pt'}")
    if not done:
        cfg = load_run_config(preset, ov, extra)
        resume = (folder / "last.pt").exists() and not retrain
        t0 = time.perf_counter()
        train(cfg, folder, resume=resume, force=not resume, log=lambda *a, **k: None)
        log(f"  trained {run.name} seed {run.seed} in {time.perf_counter() - t0:.0f} s -> {folder}")
        for old in folder.glob(f"eval-{preset.split}*.json"):
            old.unlink()
    in_table1 = run.overrides in {tuple(v) for v in preset.table1.values()}  # few_star scores table 1's runs
    for n in [None] + (list(preset.few_star) if in_table1 else []):
        if not (folder / eval_name(preset.split, n)).exists():
            if not (folder / "best.pt").exists():
                raise ConfigError(
                    f"{folder}: no best.pt to evaluate (a run folder copied without its checkpoint?); "
                    "delete its summary.json to train it again"
                )
            evaluate_checkpoint(
                folder / "best.pt", data, preset.split, folder, keep_brightest=n, log=lambda *a, **k: None
            )
    return folder


def eval_name(split: str, brightest: int | None = None) -> str:
    """The file ``fusion evaluate`` writes for a split (and a brightest-N cut)."""
    return f"eval-{split}.json" if brightest is None else f"eval-{split}-brightest{brightest}.json"


def evaluate_shuffled(checkpoint: Path, data: Path, split: str, seed: int = 0) -> float:
    """Top-1 with the kept detection rows in a random order (same frames, same model)."""
    from ..model.regions import assign
    from ..model.shards import FrameDataset, boresight_vectors, split_positions

    ckpt = load_checkpoint(checkpoint)
    model, cfg = ckpt.build_model(), ckpt.fusion_config
    rng = np.random.default_rng(seed)
    with open_dataset(data) as ds:
        pos = split_positions(ds, split)
        labels = assign(boresight_vectors(ds, pos), ckpt.centroids)
        d = cfg.data
        frames = FrameDataset(
            ds, pos, labels, max_stars=d.max_stars, norm_scale_adu=d.norm_scale_adu, log_flux_offset=d.log_flux_offset
        )
        correct = 0
        with torch.inference_mode():
            for start in range(0, len(frames), 128):
                items = [frames[j] for j in range(start, min(start + 128, len(frames)))]
                coords = torch.stack([it["coords"] for it in items])
                mask = torch.stack([it["mask"] for it in items])
                for b in range(len(items)):
                    n = int(mask[b].sum())
                    coords[b, :n] = coords[b, torch.from_numpy(rng.permutation(n))]
                logits = model(torch.stack([it["image"] for it in items]), coords, mask)
                correct += int((logits.argmax(1).numpy() == labels[start : start + len(items)]).sum())
    return correct / len(pos)


# --------------------------------------------------------------------------- tables
def _eval(folder: Path, split: str, first: Path | None = None) -> dict:
    """A run's evaluation with its training cost; ``first``: the folder of its first stage, whose
    time and samples are added (a two-stage row costs both stages)."""
    ev = json.loads((folder / f"eval-{split}.json").read_text())
    summary = json.loads((folder / "summary.json").read_text()) if (folder / "summary.json").exists() else {}
    ev["train_wall_s"] = summary.get("wall_time_s")
    ev["train_samples"] = summary.get("samples_seen")
    if first is not None and ev["train_wall_s"]:
        if not (first / "summary.json").exists():
            raise ConfigError(f"{folder}: its first stage {first} has no summary.json")
        s0 = json.loads((first / "summary.json").read_text())
        ev["train_stages_s"] = [s0.get("wall_time_s"), ev["train_wall_s"]]
        ev["train_wall_s"] += s0.get("wall_time_s") or 0.0
        ev["train_samples"] = (ev["train_samples"] or 0) + (s0.get("samples_seen") or 0)
    return ev


def _ms(values: list[float], pct: bool = True) -> str:
    v = np.array(values, dtype=float) * (100 if pct else 1)
    if len(v) == 1:
        return f"{v[0]:.1f}"
    return f"{v.mean():.1f} ± {v.std(ddof=1):.1f}"


def _group(
    runs: list[RunSpec], folders: dict[str, Path], split: str, firsts: dict[str, Path] | None = None
) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for r in runs:
        out.setdefault(r.name, []).append(_eval(folders[r.key], split, (firsts or {}).get(r.key)))
    return out


def _train_cost(evs: list[dict]) -> str:
    """Mean training wall time (min) and samples seen of a group of runs."""
    wall = [e["train_wall_s"] for e in evs if e.get("train_wall_s")]
    seen = [e["train_samples"] for e in evs if e.get("train_samples")]
    t = f"{np.mean(wall) / 60:.1f}" if wall else "—"
    stages = [e["train_stages_s"] for e in evs if e.get("train_stages_s") and None not in e["train_stages_s"]]
    if stages and wall:
        t += " (" + " + ".join(f"{np.mean(col) / 60:.1f}" for col in zip(*stages)) + ")"
    n = "—" if not seen else f"{np.mean(seen) / 1000:,.0f} k" if np.mean(seen) >= 10_000 else f"{np.mean(seen):,.0f}"
    return f"{t} | {n}"


def table_topk(groups: dict[str, list[dict]], paper: dict | None = None) -> list[str]:
    head = "| model | top-1 (%) | top-3 (%) | top-5 (%) | median error (deg) | seeds | training (min) | samples seen |"
    if paper:
        head += " paper top-1/3/5 (%) |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, evs in groups.items():
        row = (
            f"| {name} | {_ms([e['top1'] for e in evs])} | {_ms([e['top3'] for e in evs])} | "
            f"{_ms([e['top5'] for e in evs])} | {_ms([e['angular_error']['median_deg'] for e in evs], False)} | "
            f"{len(evs)} | {_train_cost(evs)} |"
        )
        if paper:
            p = paper.get(name)
            row += (
                " "
                + (
                    " / ".join(f"{x:.1f}" for x in p)
                    if isinstance(p, tuple)
                    else (f"{p:.1f} (top-1)" if p is not None else "—")
                )
                + " |"
            )
        lines.append(row)
    return lines


def table_k(groups: dict[str, list[dict]]) -> list[str]:
    lines = [
        "| K | top-1 (%) | top-3 (%) | median error (deg) | p95 error (deg) | floor median (deg) | chance top-1 (%) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, evs in groups.items():
        lines.append(
            f"| {name.split('=')[1]} | {_ms([e['top1'] for e in evs])} | {_ms([e['top3'] for e in evs])} | "
            f"{_ms([e['angular_error']['median_deg'] for e in evs], False)} | "
            f"{_ms([e['angular_error']['p95_deg'] for e in evs], False)} | "
            f"{_ms([e['quantisation_floor']['median_deg'] for e in evs], False)} | "
            f"{100 * evs[0]['chance_top1']:.1f} |"
        )
    return lines


def _plot_k(groups: dict[str, list[dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ks = [int(n.split("=")[1]) for n in groups]
    top1 = [np.mean([e["top1"] for e in evs]) * 100 for evs in groups.values()]
    med = [np.mean([e["angular_error"]["median_deg"] for e in evs]) for evs in groups.values()]
    p95 = [np.mean([e["angular_error"]["p95_deg"] for e in evs]) for evs in groups.values()]
    fig, ax = plt.subplots(1, 2, figsize=(8, 3.2))
    ax[0].plot(ks, top1, "o-")
    ax[0].set_xscale("log")
    ax[0].set_xlabel("K")
    ax[0].set_ylabel("top-1 (%)")
    ax[1].plot(ks, med, "o-", label="median")
    ax[1].plot(ks, p95, "s--", label="p95")
    ax[1].set_xscale("log")
    ax[1].set_yscale("log")
    ax[1].set_xlabel("K")
    ax[1].set_ylabel("angular error (deg)")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _git_revision() -> str:
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=Path(__file__).parent,
            timeout=10,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain"], capture_output=True, text=True, cwd=Path(__file__).parent, timeout=10
        ).stdout.strip()
        return rev + (" (uncommitted changes)" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _hardware() -> str:
    h = hardware(torch.device("cuda" if torch.cuda.is_available() else "cpu"))
    return ", ".join(f"{k}: {v}" for k, v in h.items() if v)


# --------------------------------------------------------------------------- main
def _ensure_run_job(args) -> str:
    preset, run, data, runs_dir = args
    return str(ensure_run(preset, run, data, runs_dir, lambda *a, **k: print(*a, **k, flush=True)))


def train_runs(preset: Preset, todo: list[RunSpec], data: Path, runs_dir: Path, jobs: int, log) -> dict[str, Path]:
    """Train and evaluate every run of ``todo`` (finished ones are skipped), ``jobs`` processes at a
    time; a run folder per run, so processes never share one. Returns the folders by run key."""
    if jobs <= 1 or len(todo) <= 1:
        return {r.key: ensure_run(preset, r, data, runs_dir, log) for r in todo}
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    # two waves: the one-stage runs (and every first stage), then the two-stage runs, so no two
    # processes ever train the same first stage
    firsts = {f.key: f for r in todo if stage_row(r.overrides) is not None for f in [first_stage(preset, r)]}
    wave1 = list({**{r.key: r for r in todo if stage_row(r.overrides) is None}, **firsts}.values())
    wave2 = [r for r in todo if stage_row(r.overrides) is not None]
    folders: dict[str, Path] = {}
    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
        for wave in (wave1, wave2):
            done = pool.map(_ensure_run_job, [(preset, r, data, runs_dir) for r in wave])
            folders.update({r.key: Path(f) for r, f in zip(wave, done)})
    return folders


def run_experiment(
    preset_name: str | Path,
    out: str | Path,
    *,
    sections: tuple[str, ...] | None = None,
    workers: int | None = None,
    data_dir: str | Path | None = None,
    runs_dir: str | Path | None = None,
    jobs: int = 1,
    log=print,
) -> Path:
    """Run the preset's sections; small results and REPORT.md go to ``out``, the dataset to
    ``data_dir`` (default data/experiment-<preset>) and the run folders with checkpoints to
    ``runs_dir`` (default runs/experiment-<preset>), both ignored by git. ``jobs`` trainings run
    at a time in separate processes (each with the preset's ``train.threads``). ``sections``: default
    every section the preset defines."""
    t_start = time.perf_counter()
    revision = _git_revision()  # the code that runs, not the code at the end
    preset = load_preset(preset_name)
    sections = _checked_sections(preset, sections)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    workers = workers or os.cpu_count() or 1
    data = ensure_dataset(preset, Path(data_dir or f"data/experiment-{preset.name}"), workers, log)
    default_runs_dir = Path(f"runs/experiment-{preset.name}")
    runs_dir = Path(runs_dir or default_runs_dir)
    runs = plan(preset)
    todo = list({r.key: r for s in sections for r in runs[s]}.values())
    log(f"{len(todo)} training runs ({len(preset.seeds)} seeds), {jobs} at a time")
    folders = train_runs(preset, todo, data, runs_dir, jobs, log)
    firsts = {r.key: run_folder(runs_dir, first_stage(preset, r)) for r in todo if stage_row(r.overrides)}
    results: dict = {"preset": preset.name, "sections": {}}
    md = [f"# Star-Fusion experiments — preset `{preset.name}`", ""]
    md += _header(preset, data)
    for name in SECTIONS:  # in the report's order
        if name not in sections:
            continue
        if name in GROUP_SECTIONS:
            md += _group_section(name, preset, runs[name], folders, firsts, out, results)
        elif name == "few_star":
            md += _few_star_section(preset, runs["few_star"], folders, results)
        elif name == "coords":
            md += _coords_section(preset, runs["coords"], folders, firsts, data, results)
        elif name == "robustness":
            md += _robustness_section(preset, runs["robustness"], folders, data, out, results, log)
        elif name == "latency":
            md += _latency_section(preset, folders[runs["latency"][0].key], data, out, results, log)
    wall = time.perf_counter() - t_start
    cmd = [f"fusion experiment --preset {preset.name}"]
    cmd += [f"--sections {','.join(sections)}"] if tuple(sections) != tuple(preset.sections) else []
    cmd += [f"--data-dir {data_dir}"] if data_dir else []
    cmd += [f"--runs-dir {runs_dir}"] if runs_dir != default_runs_dir else []
    cmd += [f"--jobs {jobs}"] if jobs != 1 else []
    md += [
        "## Provenance",
        "",
        f"- command: `{' '.join(cmd)} --out {out}`",
        f"- git revision at start: {revision}",
        f"- hardware: {_hardware()}",
        f"- wall time of this invocation: {wall / 60:.1f} min (finished steps are skipped on re-runs)",
        f"- training: {len(todo)} runs, {_summed_train_min(folders):.0f} min of training wall time in all "
        f"({jobs} at a time; evaluation, robustness and latency come on top)",
        f"- raw results: `results.json` here; each run's config, metrics, checkpoints and `eval-{preset.split}.json` "
        f"under `{runs_dir}/` and the dataset in `{data}/` (not committed)",
        "",
    ]
    results["wall_time_s"] = wall
    write_json(out / "results.json", results)
    atomic_write_text(out / "REPORT.md", "\n".join(md) + "\n")
    log(f"wrote {out / 'REPORT.md'}")
    return out / "REPORT.md"


def _checked_sections(preset: Preset, sections) -> tuple[str, ...]:
    """The sections to run: every one the preset defines by default; unknown or undefined ones refused."""
    sections = preset.sections if sections is None else tuple(sections)
    bad = [s for s in sections if s not in SECTIONS]
    if bad:
        raise ConfigError(f"unknown section(s) {', '.join(bad)}; choose from {', '.join(SECTIONS)}")
    missing = [s for s in sections if s not in preset.sections]
    if missing:
        raise ConfigError(
            f"preset {preset.name!r} defines no section {', '.join(missing)}; it has {', '.join(preset.sections)}"
        )
    return sections


# the sections that are one table of top-k over their runs: title and the lines under it
GROUP_SECTIONS = {
    "table1": ("## 1. Table 1: baselines and Star-Fusion", None),
    "ablation": ("## 2. Branch ablation (all 7 subsets)", []),
    "k_sweep": (
        "## 3. Number of clusters K",
        [
            "Angular error = arccos(v · c_pred); the floor is the error if the true "
            "class were always predicted (the quantisation of the sphere into K "
            "cells).",
            "",
        ],
    ),
    "labels": ("## 4. Hard labels vs geometry-aware soft labels q_k ∝ exp(κ v·c_k)", None),
    "recipe": (
        "## 6. Recipe ablations",
        [
            "Each row changes one thing of the preset's recipe (overrides in "
            "`results.json` and the preset file). Training time is wall time on this "
            "machine; compare rows at equal time, not equal epochs.",
            "",
        ],
    ),
}


def _group_section(
    name: str, preset: Preset, runs: list[RunSpec], folders: dict[str, Path], firsts: dict, out: Path, results: dict
) -> list[str]:
    """One of GROUP_SECTIONS: its runs evaluated, grouped by row, as a table (table 1 and the ablation
    beside the paper's numbers, the K sweep with its plot and angular errors)."""
    if name == "recipe" and not runs:
        return []
    g = _group(runs, folders, preset.split, firsts)
    results["sections"][name] = g
    title, intro = GROUP_SECTIONS[name]
    if name == "table1":
        intro = [
            f"Test split, mean ± std over seeds {preset.seeds}. Right column: the paper's reported numbers "
            "(K = 15, its validation split, one seed, its own data) — for orientation, not a like-for-like "
            "comparison.",
            "",
        ]
        return [title, "", *intro] + table_topk(g, PAPER_TABLE1) + [""]
    if name == "labels":
        intro = [
            f"Model: {_sweep_text(preset)}. Soft labels replace fine regions (the two "
            "cannot be combined), so they are compared with hard labels on the K regions themselves.",
            "",
        ]
    if name == "ablation":
        return [title, "", *intro] + table_topk(g, PAPER_ABLATION_TOP1) + [""]
    if name == "k_sweep":
        _plot_k(g, out / "k_sweep.png")
        return [title, "", *intro] + table_k(g) + ["", "![K sweep](k_sweep.png)", ""]
    return [title, "", *intro] + table_topk(g) + [""]


def _coords_section(
    preset: Preset, runs: list[RunSpec], folders: dict[str, Path], firsts: dict, data: Path, results: dict
) -> list[str]:
    """The coordinate encoders, scored on the test frames as they are and with the rows shuffled."""
    g = _group(runs, folders, preset.split, firsts)
    shuffled: dict = {}
    for r in runs:
        shuffled.setdefault(r.name, []).append(
            evaluate_shuffled(folders[r.key] / "best.pt", data, preset.split, r.seed)
        )
    results["sections"]["coords"] = {"ordered": g, "shuffled_top1": shuffled}
    md = [
        "## 5. Coordinate encoders: MLP over the ordered list, set encoder, transformer",
        "",
        "Shuffled: the same test frames with the kept detection rows in a random order at evaluation time.",
        "",
        "| encoder | top-1 ordered (%) | top-1 shuffled (%) | seeds |",
        "|---|---|---|---|",
    ]
    for name, evs in g.items():
        md.append(f"| {name} | {_ms([e['top1'] for e in evs])} | {_ms(shuffled[name])} | {len(evs)} |")
    return md + [""]


def _few_star_section(preset: Preset, runs: list[RunSpec], folders: dict[str, Path], results: dict) -> list[str]:
    """Table 1's runs on the test frames cut to their brightest N detections (the image whole)."""
    split, ns = preset.split, preset.few_star
    table: dict[str, dict[str, list[float]]] = {}
    k = set()
    for r in runs:
        row = table.setdefault(r.name, {})
        for n in [None] + ns:
            ev = json.loads((folders[r.key] / eval_name(split, n)).read_text())
            row.setdefault("all" if n is None else str(n), []).append(ev["top1"])
            k.add(ev["num_classes"])
    results["sections"]["few_star"] = table
    cols = ["all"] + [str(n) for n in ns]
    lines = [
        "## 1b. Few-star frames: top-1 by detections kept",
        "",
        f"The same test frames with each frame's detections cut to its brightest N (the image untouched: "
        f"the pixels still show every star), top-1 (%) at K = {' / '.join(map(str, sorted(k)))}, "
        f"mean ± std over seeds {preset.seeds}. Training time: table 1.",
        "",
        "| model | " + " | ".join("whole frame" if c == "all" else f"N = {c}" for c in cols) + " |",
        "|---|" + "---|" * len(cols),
    ]
    for name, row in table.items():
        lines.append(f"| {name} | " + " | ".join(_ms(row[c]) for c in cols) + " |")
    return lines + [""]


def _summed_train_min(folders: dict[str, Path]) -> float:
    total = 0.0
    for f in folders.values():
        try:
            total += float(json.loads((Path(f) / "summary.json").read_text()).get("wall_time_s") or 0)
        except (OSError, ValueError):
            pass
    return total / 60


def _sweep_text(preset: Preset) -> str:
    if preset.sweep_overrides is None:
        return f"the `{preset.sweep_model}` row of table 1"
    ov = ", ".join(f"`{o}`" for o in preset.sweep_overrides)
    return f"`{preset.train_config}` with the preset-wide `train_overrides`" + (f" and {ov}" if ov else "")


def _header(preset: Preset, data: Path) -> list[str]:
    with open_dataset(data) as ds:
        n = {s: len(ds.indices(s)) for s in ("train", "val", "test")}
        shape = ds.image_shape
    lines = [
        "How our setup differs from the paper's, plainly:",
        "",
        "- data: our physically-based generator (skygen, Hipparcos-2, full sensor model), not Stellarium "
        f"renders; {n['train']} train / {n['val']} val / {n['test']} test frames, stored at "
        f"{shape[0]}×{shape[1]} px; all numbers below are on the independent **test** split (the paper "
        "reports its validation split);",
        "- no ImageNet weights (no network on our machines): every image backbone is trained from scratch;",
        f"- seeds {preset.seeds}, mean ± sample standard deviation.",
    ]
    lines += [f"- {n}" for n in preset.notes]
    return lines + [""]


def _robustness_section(preset, runs, folders, data, out, results, log) -> list[str]:
    from .robustness import robustness

    rdir = out / "robustness"
    ckpts = [folders[r.key] / "best.pt" for r in runs]
    report_path = rdir / "robustness-all.json"
    rep = json.loads(report_path.read_text()) if report_path.exists() else None
    if rep is not None and {r["checkpoint"] for r in rep["rows"]} != {str(c) for c in ckpts}:
        log(f"{report_path}: made with other checkpoints than this plan's; recomputing")
        rep = None
    if rep is None:
        log(
            f"robustness: {len(ckpts)} models x every corruption on {preset.robustness_frames} frames "
            f"(the CPU preset: ~5 min on 2 cores)"
        )
        t0 = time.perf_counter()
        robustness(
            ckpts,
            data,
            "all",
            rdir,
            split=preset.split,
            n=preset.robustness_frames,
            workers=os.cpu_count() or 1,
            seed=0,
            progress=False,
            log=lambda *a, **k: None,
            levels=None,
        )
        rep = json.loads(report_path.read_text())
        log(f"robustness: done ({time.perf_counter() - t0:.0f} s)")
    results["sections"]["robustness"] = {"report": str(report_path.relative_to(out))}
    names = {str(folders[r.key] / "best.pt"): r.name for r in runs}
    models = [r.name for r in runs]
    lines = [
        "## 7. Robustness to controlled corruptions",
        "",
        f"Top-1 (%) on {preset.robustness_frames} test frames per severity, models of the first seed. "
        "Severities are *extra*, in the corruption's physical unit, stacked on the dataset's own; sensor "
        "and scene corruptions re-render the frames and re-run the detector. Mean detections per frame in "
        "the last column. Full tables (top-3, angular error): `robustness/robustness-all.md`.",
        "",
        "| corruption | severity | " + " | ".join(models) + " | detections |",
        "|---|---|" + "---|" * (len(models) + 1),
    ]
    table: dict = {}
    for row in rep["rows"]:
        table.setdefault((row["corruption"], row["severity"], row["unit"]), {})[
            names.get(row["checkpoint"], row["label"])
        ] = row
    for (name, sev, unit), per in table.items():
        first = next(iter(per.values()))
        lines.append(
            f"| {name} | {sev:g} {unit} | "
            + " | ".join(f"{100 * per[m]['top1']:.1f}" if m in per else "—" for m in models)
            + f" | {first['mean_detections']:.1f} |"
        )
    lines.append("")
    for png in sorted(rdir.glob("robustness-*.png")):
        lines.append(f"![{png.stem}](robustness/{png.name})")
    return lines + [""]


def _stale_timing(rec: dict, checkpoint: Path | None) -> bool:
    """Does a cached timing JSON describe another CPU, or another checkpoint than ``checkpoint`` (its path,
    or the same path retrained since: a run folder of an older plan with the same key)?"""
    if rec.get("hardware", {}).get("cpu_model") != hardware().get("cpu_model"):
        return True
    if checkpoint is None:
        return False
    when = rec.get("model", {}).get("checkpoint_mtime")
    return (
        rec.get("model", {}).get("checkpoint") != str(checkpoint)
        or when is None
        or abs(float(when) - Path(checkpoint).stat().st_mtime) > 1e-3
    )


def _latency_section(preset, folder, data, out, results, log) -> list[str]:
    from .timing import summary_text, timing

    k = load_checkpoint(folder / "best.pt").num_classes
    # the paper-size model runs on frames of the default camera (its own 256 px input)
    jobs = {"trained": dict(checkpoint=folder / "best.pt", data=data), "paper-size": dict(overrides=(f"labels.k={k}",))}
    text = {}
    for name, kw in jobs.items():
        path = out / "timing" / f"{name}-cpu-fp32-b1.json"
        if path.exists() and _stale_timing(json.loads(path.read_text()), kw.get("checkpoint")):
            path.unlink()  # timed on another machine, or another (or an older) checkpoint: time again
        if not path.exists():
            timing(
                path,
                device="cpu",
                precision="fp32",
                batch=1,
                iters=preset.timing_iters,
                mode="both",
                log=lambda *a, **k: None,
                **kw,
            )
        text[name] = summary_text(json.loads(path.read_text()))
    results["sections"]["latency"] = {n: f"timing/{n}-cpu-fp32-b1.json" for n in jobs}
    return [
        "## 8. Latency on this machine's CPU",
        "",
        "`fusion timing --mode both`, batch 1, fp32, raw JSON in `timing/`. End-to-end starts from a raw "
        "full-resolution frame (background, detection, coordinate encoding, downsampling, forward). "
        f"*Trained*: {_sweep_text(preset)}. *Paper-size*: the default Star-Fusion architecture "
        f"(SwinV2-Tiny at 256x256, random weights; latency does not depend on them). Paper, for reference: "
        f"{PAPER_LATENCY}.",
        "",
        "Trained model:",
        "",
        "```",
        text["trained"],
        "```",
        "",
        "Paper-size model:",
        "",
        "```",
        text["paper-size"],
        "```",
        "",
    ]
