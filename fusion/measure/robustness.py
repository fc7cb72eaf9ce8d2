"""Corruption-robustness sweeps (``fusion robustness``): accuracy against corruption severity.

For each corruption of skygen's registry (:data:`skygen.instrument.corruptions.REGISTRY`) and each
severity of its sweep, the chosen frames of one split are perturbed by
:func:`skygen.render.perturb.perturbed_frames` — the generator's own code, nothing re-implemented
here — and every checkpoint is evaluated on them:

* ``sensor`` and ``scene`` corruptions re-render each frame from its stored seed and
  boresight with the extra severity applied, then run skygen's real detector, so
  corrupted pixels reach the detections as they would on orbit;
* ``detections`` corruptions act on the stored detection table.

Severities are *extra* severities in the corruption's physical unit (hot-pixel fraction,
px rms of centroid noise, deg/s of angular rate, ...), stacked on the dataset's own level
of that corruption (:meth:`skygen.instrument.corruptions.Corruption.stack`); both the extra and the
resulting total are reported. Severity 0 gives the stored frames exactly, so its row
equals ``fusion evaluate`` on the same frames.

Inputs are built exactly as for training and evaluation (:class:`fusion.model.inputs.Preprocessor`)
with each checkpoint's own data settings, and frames
are labelled against each checkpoint's own centroids (max cosine), so every checkpoint is
scored on its own K classes.

Reported per (checkpoint, corruption, severity): top-1/3/5, angular error of the
prediction ``arccos(v . c_pred)`` in degrees (median, mean, p95), mean detections per
frame (before truncation to ``max_stars``) and frames with fewer than two detections.

Determinism: the corruption draws come from skygen's per-frame streams (dataset seed,
frame index, corruption name), independent of ``--workers``; ``--seed`` only picks which
frames are used when ``--n`` is smaller than the split. The same arguments give the same
table, bit for bit on the same machine and thread count.

Outputs (in ``--out``; ``STEM`` is ``robustness-<corruption>`` or ``robustness-all``):
``STEM.json``, ``STEM.csv``, ``STEM.md`` and one ``robustness-<corruption>.png`` per
corruption (top-1 and median angular error against severity, one line per checkpoint).
They are written into a temporary folder once every result exists and then moved into
place, so a failed or interrupted sweep leaves nothing half-written. A sweep holds the
lock of ``--out`` (:class:`skygen.lock.FolderLock`): a second one into the same folder is
refused with one line naming the first. One progress line per corruption and severity
goes to the log as it finishes.
"""

from __future__ import annotations

import csv
import io
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from skygen.config import build_config as build_render_config
from skygen.datasets.shards import Dataset as SkyDataset
from skygen.datasets.shards import open_dataset
from skygen.instrument import corruptions as corr
from skygen.lock import FolderLock
from skygen.render.perturb import perturbed_frames
from skygen.runtime import atomic_write_bytes, atomic_write_text, hardware, pick_device, write_json

from ..config import FusionConfig
from ..errors import CheckpointError, ConfigError
from ..model.checkpoint import differences_text, differences_warning, load_checkpoint
from ..model.inference import autocast_dtype, predict_batches
from ..model.inputs import FrameGeometry, Preprocessor, Sample, sample_from_table
from ..model.metrics import angular_error_deg, error_stats, topk_accuracy
from ..model.networks import StarFusion
from ..model.regions import assign
from ..model.shards import boresight_vectors, split_positions

FORMAT = "fusion-robustness"
FORMAT_VERSION = 1
CSV_COLUMNS = (
    "checkpoint",
    "label",
    "model",
    "branches",
    "num_classes",
    "corruption",
    "stage",
    "unit",
    "severity",
    "total_severity",
    "n_frames",
    "top1",
    "top3",
    "top5",
    "median_error_deg",
    "mean_error_deg",
    "p95_error_deg",
    "mean_detections",
    "frames_lt2_detections",
)


# --------------------------------------------------------------------------- arguments
def resolve_corruptions(spec: str | Sequence[str]) -> list[str]:
    """``'all'``, one name, or a comma-separated list -> registry names (unknown ones list the valid)."""
    names = spec.split(",") if isinstance(spec, str) else list(spec)
    names = [n.strip() for n in names if n.strip()]
    if not names:
        raise ConfigError(f"--corruption: give a corruption name or 'all'; valid names: {', '.join(corr.REGISTRY)}")
    if names == ["all"]:
        return list(corr.REGISTRY)
    out = []
    for n in names:
        corr.get(n)  # ConfigError listing the valid names
        if n not in out:
            out.append(n)
    return out


def parse_levels(text: str | Sequence[float] | None) -> tuple[float, ...] | None:
    """``'0,1e-4,5e-4'`` -> (0.0, 0.0001, 0.0005); None stays None (use the registry's sweep)."""
    if text is None:
        return None
    items = text.split(",") if isinstance(text, str) else list(text)
    out = []
    for item in items:
        try:
            v = float(item)
        except (TypeError, ValueError):
            raise ConfigError(
                f"--levels: {item!r} is not a number; give comma-separated severities, e.g. --levels 0,1e-4,1e-3"
            ) from None
        if not np.isfinite(v):
            raise ConfigError(f"--levels: {item!r} is not a finite number")
        out.append(v)
    if not out:
        raise ConfigError("--levels: no severity given")
    return tuple(dict.fromkeys(out))


def sweep_levels(names: list[str], levels: tuple[float, ...] | None, render_config: dict) -> dict[str, tuple]:
    """The severities of each corruption, validated against the dataset's config before any work."""
    if levels is not None and len(names) > 1:
        raise ConfigError(
            "--levels applies to a single --corruption (each corruption has its own unit); "
            "leave it out to use each corruption's default sweep"
        )
    base = build_render_config(render_config)
    out = {}
    for name in names:
        c = corr.get(name)
        chosen = levels if levels is not None else c.sweep
        for lvl in chosen:
            if lvl < 0:
                raise ConfigError(
                    f"--levels: severity {lvl:g} of {name} is negative; severities are "
                    f"extra {c.unit} stacked on the dataset's own, 0 = none"
                )
            try:
                corr.with_extra(base, name, lvl)
            except ConfigError as exc:
                raise ConfigError(f"severity {lvl:g} {c.unit} of {name} is out of range: {exc}") from None
        out[name] = tuple(float(v) for v in chosen)
    return out


# --------------------------------------------------------------------------- checkpoints
@dataclass
class SweepModel:
    """A checkpoint ready for the sweep: model, its config and centroids, a plot label."""

    path: Path
    model: StarFusion
    cfg: FusionConfig
    centroids: np.ndarray
    model_name: str
    branches: dict
    image_size: int
    label: str = ""
    config_differences: dict | None = None  # frame settings of the sweep's data unlike the training data's

    @property
    def num_classes(self) -> int:
        return len(self.centroids)

    @property
    def branch_text(self) -> str:
        return "+".join(k for k, on in self.branches.items() if on)


def load_sweep_model(path: str | Path, ds: SkyDataset, warn=None) -> SweepModel:
    """Load a checkpoint and check that it can be evaluated on ``ds`` (CheckpointError otherwise); frame settings
    of ``ds`` unlike those of the checkpoint's training data are recorded and warned about on ``warn``."""
    path = Path(path)
    ckpt = load_checkpoint(path)
    model, cfg = ckpt.build_model(), ckpt.fusion_config
    centroids, k = ckpt.centroids, ckpt.num_classes
    if centroids.shape != (k, 3):
        raise CheckpointError(
            f"{path}: holds {centroids.shape[0]} centroids of shape {centroids.shape[1:]} but "
            f"K={k} classes; the checkpoint is damaged or was edited"
        )
    if model.num_classes != k:
        raise CheckpointError(f"{path}: the model has {model.num_classes} outputs but the checkpoint's K is {k}")
    size = ckpt.image_size
    if ds.image_shape[0] != size:
        raise CheckpointError(
            f"{path} was trained on {size} x {size} images but dataset {ds.root} stores "
            f"{ds.image_shape[0]} x {ds.image_shape[1]}; render the sweep dataset with "
            f"output.image_size_px={size} or use a checkpoint trained at this size"
        )
    diffs = ckpt.config_differences(ds.config)
    if diffs and warn is not None:
        warn(differences_warning(str(ds.root), diffs, str(path)))
    return SweepModel(path, model, cfg, centroids, ckpt.model_name, dict(ckpt.branches), size, config_differences=diffs)


def _label(models: list[SweepModel]) -> None:
    """``model: branches`` labels; the run folder name is added where two would read the same."""
    base = [f"{m.model_name}: {m.branch_text}" for m in models]
    for m, b in zip(models, base):
        m.label = b if base.count(b) == 1 else f"{b} ({m.path.parent.name}/{m.path.name})"


# --------------------------------------------------------------------------- frames -> inputs
def select_frames(ds: SkyDataset, split: str, n: int | None, seed: int, log=None) -> np.ndarray:
    """Positions of the sweep's frames: the whole split, or ``n`` of them drawn with ``seed`` (sorted)."""
    pos = split_positions(ds, split)
    if n is not None and n < 1:
        raise ConfigError(f"--n: {n} frames; give at least 1")
    if n is None or n >= len(pos):
        if n is not None and n > len(pos) and log is not None:
            log(f"--n {n}: the {split} split holds {len(pos)} frames; sweeping all {len(pos)}")
        return pos
    pick = np.random.default_rng([seed, 0x5EED]).choice(len(pos), size=n, replace=False)
    return pos[np.sort(pick)]


def frame_sample(frame: dict, ds: SkyDataset, position: int, geo: FrameGeometry) -> Sample:
    """A perturbed frame (from :func:`perturbed_frames`) as the :class:`Sample` that
    :func:`fusion.model.shards.read_sample` makes of a stored one (brightest first)."""
    return sample_from_table(
        frame["detections"],
        np.asarray(frame["image"]),
        float(ds.frames["background_adu"][position]),
        float(ds.frames["noise_adu"][position]) / geo.factor,
    )


class _Items(torch.utils.data.Dataset):
    """Model-input items of already perturbed frames, as :class:`fusion.model.shards.FrameDataset` makes them."""

    def __init__(
        self, samples: list[Sample], positions: np.ndarray, labels: np.ndarray, geo: FrameGeometry, cfg: FusionConfig
    ):
        self.samples, self.positions, self.labels = samples, positions, labels
        self.pre = Preprocessor(geo, cfg.data.max_stars, cfg.data.log_flux_offset, cfg.data.norm_scale_adu)

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, j: int) -> dict:
        return {
            **self.pre.item(self.samples[j]),
            "label": torch.tensor(self.labels[j]),
            "index": torch.tensor(self.positions[j]),
        }


def score(
    m: SweepModel,
    samples: list[Sample],
    positions: np.ndarray,
    v: np.ndarray,
    geo: FrameGeometry,
    device: torch.device,
    batch_size: int,
) -> dict:
    """Metrics of one checkpoint on one set of (perturbed) frames; ``pred`` holds the predictions."""
    labels = assign(v, m.centroids)
    items = _Items(samples, positions, labels, geo, m.cfg)
    loader = torch.utils.data.DataLoader(items, batch_size=batch_size, shuffle=False)
    out = predict_batches(m.model, loader, device, amp_dtype=autocast_dtype(m.cfg.train.amp, device))
    pred = np.argmax(out["logits"], axis=1)
    err = error_stats(angular_error_deg(v, m.centroids, pred))
    return {
        **topk_accuracy(out["logits"], labels),
        "median_error_deg": err["median_deg"],
        "mean_error_deg": err["mean_deg"],
        "p95_error_deg": err["p95_deg"],
        "pred": pred,
    }


# --------------------------------------------------------------------------- the sweep
def _bar(total: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(
        total=total, unit="frame", dynamic_ncols=True, leave=False, disable=not (enabled and sys.stderr.isatty())
    )


def run_sweep(
    checkpoints: Sequence[str | Path],
    data: str | Path,
    corruption: str | Sequence[str] = "all",
    *,
    split: str = "test",
    levels: str | Sequence[float] | None = None,
    n: int | None = None,
    workers: int = 1,
    seed: int = 0,
    batch_size: int = 64,
    device: str = "auto",
    progress: bool = True,
    log=None,
    warn=None,
) -> dict:
    """Evaluate ``checkpoints`` on ``split`` of ``data`` under each corruption and severity.

    Everything the user gave is checked before any frame is rendered. ``log`` (default:
    silent) receives one line per corruption and severity as it finishes; ``warn`` (default:
    stderr) a one-line warning per checkpoint whose training data had other frame settings than
    ``data`` (also in the report: ``checkpoints[i].config_differences``). Returns the report:
    settings, checkpoints, the dataset's own corruption levels and ``rows`` (one per
    checkpoint x corruption x severity, in that nesting, with the fields of
    :data:`CSV_COLUMNS` plus ``pred``, the predicted class of each frame).
    """
    t0 = time.perf_counter()
    warn = warn or (lambda msg: print(msg, file=sys.stderr))
    if isinstance(checkpoints, (str, Path)):
        checkpoints = [checkpoints]
    if not checkpoints:
        raise ConfigError("--checkpoint: give at least one checkpoint")
    if batch_size < 1 or workers < 0:
        raise ConfigError("--batch-size must be >= 1 and --workers >= 0")
    names = resolve_corruptions(corruption)
    levels = parse_levels(levels)
    dev = pick_device(device)
    with open_dataset(data) as ds:
        plan = sweep_levels(names, levels, ds.config)
        models = [load_sweep_model(p, ds, warn) for p in checkpoints]
        _label(models)
        for m in models:
            m.model.to(dev)
        pos = select_frames(ds, split, n, seed, log)
        v = boresight_vectors(ds, pos)
        geo = FrameGeometry.from_render_config(ds.config)
        own = corr.levels_of(build_render_config(ds.config))
        rows: list[dict] = []
        per_model: dict[int, list[dict]] = {j: [] for j in range(len(models))}
        bar = _bar(len(pos) * sum(len(lv) for lv in plan.values()), progress)
        say = (bar.write if not bar.disable else log) if log is not None else None
        steps, step = sum(len(lv) for lv in plan.values()), 0
        try:
            for name in names:
                c = corr.REGISTRY[name]
                for lvl in plan[name]:
                    t_step, step = time.perf_counter(), step + 1
                    bar.set_description(f"{name} {lvl:g}")
                    done = bar.n
                    frames = perturbed_frames(
                        ds,
                        name,
                        lvl,
                        pos,
                        workers=max(workers, 1),
                        progress=lambda k, d=done: bar.update(d + k - bar.n),
                    )
                    samples = [frame_sample(f, ds, int(p), geo) for f, p in zip(frames, pos)]
                    ndet = np.array([s.n for s in samples])
                    common = {
                        "corruption": name,
                        "stage": c.stage,
                        "unit": c.unit,
                        "severity": lvl,
                        "total_severity": c.stack(own[name], lvl),
                        "n_frames": int(len(pos)),
                        "mean_detections": float(ndet.mean()),
                        "frames_lt2_detections": int((ndet < 2).sum()),
                    }
                    for j, m in enumerate(models):
                        with torch.inference_mode():
                            metrics = score(m, samples, pos, v, geo, dev, batch_size)
                        per_model[j].append(
                            {
                                "checkpoint": str(m.path),
                                "label": m.label,
                                "model": m.model_name,
                                "branches": m.branch_text,
                                "num_classes": m.num_classes,
                                **common,
                                **metrics,
                            }
                        )
                    if say is not None:
                        top1 = ", ".join(
                            f"{m.label} {100 * per_model[j][-1]['top1']:.1f}%" for j, m in enumerate(models)
                        )
                        say(
                            f"[{step}/{steps}] {name} {lvl:g} ({c.unit}): {len(pos)} frames in "
                            f"{time.perf_counter() - t_step:.1f} s; top-1 {top1}"
                        )
        finally:
            bar.close()
        for j in range(len(models)):
            rows += per_model[j]
        dataset_info = {
            "path": str(ds.root),
            "dataset_id": ds.manifest.get("dataset_id"),
            "split": split,
            "sensor_px": list(ds.sensor_shape),
            "image_px": list(ds.image_shape),
        }
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "corruptions": names,
        "levels": {k: list(lv) for k, lv in plan.items()},
        "corruption_info": {
            k: {
                "stage": corr.REGISTRY[k].stage,
                "unit": corr.REGISTRY[k].unit,
                "description": corr.REGISTRY[k].description,
                "dataset_level": own[k],
            }
            for k in names
        },
        "checkpoints": [
            {
                "path": str(m.path),
                "label": m.label,
                "model": m.model_name,
                "branches": m.branches,
                "num_classes": m.num_classes,
                "image_size": m.image_size,
                "config_differences": m.config_differences,
            }
            for m in models
        ],
        "dataset": dataset_info,
        "frame_positions": pos.tolist(),
        "seed": int(seed),
        "n_frames": int(len(pos)),
        "device": str(dev),
        "hardware": hardware(dev),
        "wall_time_s": time.perf_counter() - t0,
        "rows": rows,
    }


# --------------------------------------------------------------------------- outputs
def output_stem(names: list[str]) -> str:
    if names == list(corr.REGISTRY) and len(names) > 1:
        return "robustness-all"
    return "robustness-" + "+".join(names)


def _fmt(x, pct: bool = False) -> str:
    if x is None or (isinstance(x, float) and np.isnan(x)):
        return "n/a"
    return f"{100 * x:.1f}%" if pct else f"{x:.2f}"


def csv_text(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()


def markdown_text(report: dict) -> str:
    d = report["dataset"]
    lines = [
        f"# Corruption robustness on `{d['path']}` ({d['split']} split)",
        "",
        f"{report['n_frames']} frames (seed {report['seed']}), sensor {d['sensor_px'][1]} x {d['sensor_px'][0]} px "
        f"stored at {d['image_px'][1]} x {d['image_px'][0]}. Severity is the *extra* severity stacked on the "
        'dataset\'s own level ("total" is the result). Angular error: arccos(v · c_pred), degrees. Detections: '
        "mean per frame, before truncation to the model's max_stars.",
        "",
        "Checkpoints:",
        "",
    ]
    lines += [
        f"- **{c['label']}** — `{c['path']}`, K = {c['num_classes']}"
        + (
            f"; **trained on other frame settings than this data** ({differences_text(c['config_differences'])};"
            " training -> this data)"
            if c.get("config_differences")
            else ""
        )
        for c in report["checkpoints"]
    ]
    for name in report["corruptions"]:
        info = report["corruption_info"][name]
        lines += [
            "",
            f"## {name} ({info['unit']}; {info['stage']} stage)",
            "",
            f"{info['description']}. Dataset's own level: {info['dataset_level']:g} {info['unit']}. "
            f"Plot: `robustness-{name}.png`.",
            "",
            "| severity | total | checkpoint | top-1 | top-3 | median err (deg) | mean detections | frames < 2 det |",
            "|---|---|---|---|---|---|---|---|",
        ]
        rows = sorted(
            (r for r in report["rows"] if r["corruption"] == name),
            key=lambda r: (r["severity"], [c["label"] for c in report["checkpoints"]].index(r["label"])),
        )
        lines += [
            f"| {r['severity']:g} | {r['total_severity']:g} | {r['label']} | {_fmt(r['top1'], True)} | "
            f"{_fmt(r['top3'], True)} | {_fmt(r['median_error_deg'])} | {r['mean_detections']:.2f} | "
            f"{r['frames_lt2_detections']} |"
            for r in rows
        ]
    lines += ["", f"Device {report['device']}; {report['wall_time_s']:.1f} s.", ""]
    return "\n".join(lines)


def plot_corruption(report: dict, name: str) -> bytes:
    """PNG bytes: top-1 and median angular error against severity, one line per checkpoint."""
    from ..plots import _figure

    plt = _figure()
    info = report["corruption_info"][name]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    levels = sorted(report["levels"][name])
    for c in report["checkpoints"]:
        rows = sorted(
            (r for r in report["rows"] if r["corruption"] == name and r["label"] == c["label"]),
            key=lambda r: r["severity"],
        )
        x = [r["severity"] for r in rows]
        ax1.plot(x, [r["top1"] for r in rows], "o-", label=c["label"])
        ax2.plot(x, [r["median_error_deg"] for r in rows], "o-", label=c["label"])
    for k in sorted({c["num_classes"] for c in report["checkpoints"]}):
        ax1.axhline(1.0 / k, color="grey", ls=":", lw=1)
        ax1.text(levels[-1], 1.0 / k, f" chance (K={k})", va="bottom", ha="right", fontsize=7, color="grey")
    positive = [v for v in levels if v > 0]
    if positive and max(positive) / min(positive) > 20:
        for ax in (ax1, ax2):  # severities spanning decades, 0 included
            ax.set_xscale("symlog", linthresh=min(positive))
            ax.set_xlim(left=-0.1 * min(positive), right=max(positive) * 1.5)
    ax1.set_ylim(0, 1.02)
    ax1.set_ylabel("top-1 accuracy")
    ax2.set_ylabel("median angular error (deg)")
    ax2.set_ylim(bottom=0)
    for ax in (ax1, ax2):
        ax.set_xlabel(f"extra {name} severity ({info['unit']})")
        ax.grid(alpha=0.3)
    ax1.legend(fontsize=8)
    fig.suptitle(f"{name} ({info['stage']} stage), {report['n_frames']} {report['dataset']['split']} frames")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def public_report(report: dict) -> dict:
    """The report without the per-frame predictions (what the JSON file holds)."""
    return {**report, "rows": [{k: v for k, v in r.items() if k != "pred"} for r in report["rows"]]}


def write_outputs(report: dict, out: str | Path) -> list[Path]:
    """Write JSON, CSV, Markdown and the PNGs into ``out`` all at once (temporary folder, then moves)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} exists and is not a folder")
    stem = output_stem(report["corruptions"])
    parent = out if out.is_dir() else out.parent
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp", dir=parent))
    try:
        write_json(tmp / f"{stem}.json", public_report(report))
        atomic_write_text(tmp / f"{stem}.csv", csv_text(report["rows"]))
        atomic_write_text(tmp / f"{stem}.md", markdown_text(report))
        for name in report["corruptions"]:
            atomic_write_bytes(tmp / f"robustness-{name}.png", plot_corruption(report, name))
        written = sorted(p.name for p in tmp.iterdir())
        if out.is_dir():
            for fname in written:
                os.replace(tmp / fname, out / fname)
            tmp.rmdir()
        else:
            os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return [out / f for f in written]


def robustness(
    checkpoints: Sequence[str | Path],
    data: str | Path,
    corruption: str | Sequence[str],
    out: str | Path,
    log=print,
    **kw,
) -> dict:
    """:func:`run_sweep` (a progress line per corruption and severity to ``log``) then :func:`write_outputs`,
    holding ``out``'s lock throughout (a second sweep into the same folder is refused, naming the first);
    returns the report (with predictions)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} exists and is not a folder")
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out {out}: cannot create the folder ({exc.strerror or exc})") from None
    try:
        with FolderLock(out, what="fusion robustness"):
            report = run_sweep(checkpoints, data, corruption, log=log, **kw)
            written = write_outputs(report, out)
    except BaseException:
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()  # a failed sweep leaves no empty folder behind
        raise
    log(summary_text(report))
    log(f"wrote {', '.join(str(p) for p in written)}")
    return report


def summary_text(report: dict) -> str:
    lines = []
    for name in report["corruptions"]:
        for c in report["checkpoints"]:
            rows = sorted(
                (r for r in report["rows"] if r["corruption"] == name and r["label"] == c["label"]),
                key=lambda r: r["severity"],
            )
            curve = ", ".join(f"{r['severity']:g}: {100 * r['top1']:.1f}%" for r in rows)
            lines.append(f"{name} [{report['corruption_info'][name]['unit']}] {c['label']}: top-1 {curve}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- command line
