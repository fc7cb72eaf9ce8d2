"""Evaluation (``fusion evaluate``): a checkpoint on one split, as JSON, Markdown and a PNG.

The checkpoint carries everything needed: the model config, K and the centroids fitted
on its training split; the split's frames are labelled against those centroids (max
cosine). Reported (angles in degrees, see :mod:`fusion.model.metrics` for definitions):

* top-1/3/5 accuracy;
* angular error of the prediction ``arccos(v . c_pred)`` — mean, median, p95 — and the
  *quantisation floor*, the same statistics for ``arccos(v . c_true)``: the error a
  perfect classifier still makes because it answers with a centroid;
* per-class accuracy and the confusion matrix (rows true, columns predicted; PNG too);
* the share of errors between neighbouring clusters (Voronoi neighbours on the sphere).

Outputs ``eval-<split>.json``, ``eval-<split>.md`` and ``confusion-<split>.png`` in
``out`` (default: the checkpoint's folder), which is created and tested for writing before
any work. The JSON records the hardware (:func:`skygen.runtime.hardware`).

Data rendered with other frame settings than the checkpoint's training data (any key of
``camera``, ``optics``, ``photometry``, ``sensor``, ``corruptions``, ``detection``,
``catalog``, or ``epoch_yr``: :func:`fusion.model.checkpoint.frame_config_differences`;
not ``seed``, ``n_frames``, ``attitude``, ``output``, ``render``) is scored, since a
robustness study does it on purpose, but a one-line WARNING naming the keys (training ->
data) goes to stderr before the work and again after the result, the summary line and the
Markdown say so, and the JSON lists them under ``config_differences``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from skygen.datasets.shards import open_dataset, verify_checksums
from skygen.runtime import atomic_write_text, hardware, pick_device, write_json

from ..errors import ConfigError, DatasetError
from ..model.checkpoint import Checkpoint, differences_text, differences_warning, load_checkpoint, resolve_checkpoint
from ..model.inference import autocast_dtype, predict_batches
from ..model.metrics import (
    angular_error_deg,
    confusion_matrix,
    error_stats,
    neighbour_error_share,
    per_class_accuracy,
    topk_accuracy,
    voronoi_neighbours,
)
from ..model.regions import assign
from ..model.shards import FrameDataset, boresight_vectors, count_sparse_frames, make_loader, split_positions
from ..plots import plot_confusion

NEIGHBOUR_DEFINITION = (
    "clusters whose Voronoi cells on the sphere share a boundary arc (edges of the spherical "
    "Delaunay triangulation of the centroids, from their convex hull)"
)


def report_from_predictions(logits: np.ndarray, labels: np.ndarray, v: np.ndarray, centroids: np.ndarray) -> dict:
    """All metrics of one split from its logits, true labels and true boresight vectors."""
    k = len(centroids)
    pred = np.argmax(logits, axis=1)
    cm = confusion_matrix(labels, pred, k)
    adj = voronoi_neighbours(centroids)
    return {
        "n_frames": int(len(labels)),
        "num_classes": k,
        "chance_top1": 1.0 / k,
        **topk_accuracy(logits, labels),
        "angular_error": error_stats(angular_error_deg(v, centroids, pred)),
        "quantisation_floor": error_stats(angular_error_deg(v, centroids, labels)),
        "per_class": per_class_accuracy(cm),
        "confusion_matrix": cm.tolist(),
        "n_errors": int((pred != labels).sum()),
        "neighbour_error_share": neighbour_error_share(labels, pred, adj),
        "neighbour_definition": NEIGHBOUR_DEFINITION,
        "neighbour_pairs": int(adj.sum() // 2),
    }


def check_no_training_frames(ckpt: Checkpoint, ds, pos: np.ndarray, split: str, allow_overlap: bool, warn) -> int:
    """Frames of ``pos`` the checkpoint was trained on (by frame identity); refuses them unless ``allow_overlap``."""
    if ckpt.train_frame_ids is None:
        warn(
            "warning: this checkpoint predates training-frame records; cannot check that the evaluated frames "
            "were not among its training frames"
        )
        return 0
    ids = ds.frames["frame_id"][pos].view(np.int64)
    seen = np.isin(ids, ckpt.train_frame_ids)
    n = int(seen.sum())
    if n and not allow_overlap:
        first = int(ds.frames["index"][pos[np.argmax(seen)]])
        raise DatasetError(
            f"{n} of the {len(pos)} frames of split {split!r} of {ds.root} are frames the checkpoint "
            f"was trained on (equal frame identities, e.g. frame {first}); the score would be "
            "optimistic. Evaluate on frames rendered with another --seed, or pass --allow-overlap "
            "to score them anyway"
        )
    if n:
        warn(
            f"WARNING: {n} of the {len(pos)} evaluated frames were TRAINING frames of this checkpoint; "
            "the result is optimistic (--allow-overlap)"
        )
    return n


def frame_settings_check(ckpt: Checkpoint, ds, warn) -> dict:
    """The render settings that change frames and differ between ``ckpt``'s training data and ``ds``
    (:meth:`Checkpoint.config_differences`); a one-line warning on ``warn`` when there are any. A warning,
    not a refusal: scoring a model on frames of another sensor is what a robustness study does on purpose."""
    diffs = ckpt.config_differences(ds.config)
    if diffs:
        warn(differences_warning(str(ds.root), diffs, ckpt.source))
    return diffs


def prepare_out(out: Path, default: bool) -> bool:
    """Create ``out`` and check that files can be written there, before any work; True when it was created
    here. ConfigError naming the folder (and ``--out``) otherwise."""
    from skygen.runtime import check_output_folder

    return check_output_folder(out, "--out" if not default else "the checkpoint's folder (the default of --out)")


def evaluate_checkpoint(
    checkpoint: str | Path | Sequence[str | Path],
    data: str | Path,
    split: str = "test",
    out: str | Path | None = None,
    *,
    batch_size: int = 64,
    workers: int = 0,
    device: str = "auto",
    max_frames: int | None = None,
    allow_overlap: bool = False,
    keep_brightest: int | None = None,
    overrides: Sequence[str] = (),
    log=print,
    warn=None,
) -> dict:
    """Evaluate ``checkpoint`` (a file or a run folder) on ``split`` of dataset ``data``; write and return the report.

    Several checkpoints are scored as one ensemble: the mean of their log-probabilities (a product
    of experts, each model reading the frame as it was trained to); they must label the sky with the
    same regions, and ``out`` is required (the report belongs to none of them).
    Refuses (DatasetError) frames a checkpoint was trained on unless ``allow_overlap``;
    ``warn`` (default: print to stderr) receives the warnings. ``keep_brightest`` = N scores
    few-star frames: each frame keeps its brightest N detections (the image is untouched), and
    the files are named ``eval-<split>-brightest<N>.*``. ``overrides`` (``key=value``) change config keys
    no trained weight depends on (:data:`fusion.model.checkpoint.INFERENCE_KEYS`) in every checkpoint
    before it is scored; the report records them.
    """
    import sys

    warn = warn or (lambda msg: print(msg, file=sys.stderr))
    for name, value, lo in (
        ("--batch-size", batch_size, 1),
        ("--workers", workers, 0),
        ("--max-frames", max_frames, 1),
        ("--brightest", keep_brightest, 1),
    ):
        if value is not None and value < lo:
            raise ConfigError(f"{name} {value}: must be at least {lo}")
    t0 = time.perf_counter()
    paths = [resolve_checkpoint(c) for c in ([checkpoint] if isinstance(checkpoint, (str, Path)) else checkpoint)]
    if not paths:
        raise ConfigError("no checkpoint given")
    if len(paths) > 1 and out is None:
        raise ConfigError(
            f"{len(paths)} checkpoints are scored as one ensemble, whose report belongs to none of "
            "their run folders: pass --out DIR"
        )
    out_dir = Path(out) if out is not None else paths[0].parent
    created = prepare_out(out_dir, default=out is None)  # before minutes of work, not after
    try:
        report = _evaluate(
            paths,
            data,
            split,
            batch_size=batch_size,
            workers=workers,
            device=device,
            max_frames=max_frames,
            allow_overlap=allow_overlap,
            keep_brightest=keep_brightest,
            overrides=list(overrides),
            log=log,
            warn=warn,
        )
    except BaseException:
        if created and not any(out_dir.iterdir()):
            out_dir.rmdir()  # a failed evaluation leaves no empty folder behind
        raise
    report["wall_time_s"] = time.perf_counter() - t0
    stem = split if keep_brightest is None else f"{split}-brightest{keep_brightest}"
    write_json(out_dir / f"eval-{stem}.json", report)
    atomic_write_text(out_dir / f"eval-{stem}.md", markdown_report(report))
    plot_confusion(
        np.array(report["confusion_matrix"]),
        out_dir / f"confusion-{stem}.png",
        f"{report['model']} on {stem} (K={report['num_classes']})",
    )
    log(summary_line(report))
    log(f"wrote {out_dir / f'eval-{stem}.json'}, eval-{stem}.md, confusion-{stem}.png")
    if _all_differences(report):  # said again beside the result, where it is read
        warn(
            f"WARNING: {report['dataset']['path']} differs from the training data in frame settings "
            f"({differences_text(_all_differences(report))}): read the score above with that in mind"
        )
    return report


def _evaluate(
    paths: list[Path],
    data,
    split: str,
    *,
    batch_size: int,
    workers: int,
    device: str,
    max_frames: int | None,
    allow_overlap: bool,
    keep_brightest: int | None,
    overrides: list[str],
    log,
    warn,
) -> dict:
    """The report of :func:`evaluate_checkpoint` (everything but writing it)."""
    ckpts = [load_checkpoint(p).with_inference_overrides(overrides) for p in paths]
    centroids = ckpts[0].centroids
    for p, c in zip(paths[1:], ckpts[1:]):
        if c.centroids.shape != centroids.shape or not np.allclose(c.centroids, centroids, atol=1e-9):
            raise ConfigError(
                f"{p} labels the sky with other regions than {paths[0]} (K {len(c.centroids)} against "
                f"{len(centroids)}, or other centroids): an ensemble needs the same regions; train its "
                "models with the same labels settings on the same dataset"
            )
    dev = pick_device(device)
    logits, diffs = [], []
    with open_dataset(data) as ds:
        verify_checksums(ds, log=log)
        pos = split_positions(ds, split, max_frames)
        v = boresight_vectors(ds, pos)
        labels = assign(v, centroids)
        for p, ckpt in zip(paths, ckpts):
            diffs.append(frame_settings_check(ckpt, ds, warn))
            if ds.image_shape[0] != ckpt.image_size:
                raise DatasetError(
                    f"{data}: stored images are {ds.image_shape[0]} px but {p} was trained on "
                    f"{ckpt.image_size} px images; render with output.image_size_px="
                    f"{ckpt.image_size} or train on this dataset"
                )
            check_no_training_frames(ckpt, ds, pos, split, allow_overlap, warn)
            logits.append(_predict_split(ckpt, ds, pos, labels, dev, split, batch_size, workers, keep_brightest))
        ids = ds.frames["frame_id"][pos].view(np.int64)
        seen = [c.train_frame_ids for c in ckpts if c.train_frame_ids is not None]
        overlap = int(np.isin(ids, np.concatenate(seen)).sum()) if seen else 0
        sparse = count_sparse_frames(ds, pos)
        dataset_info = {
            "path": str(ds.root),
            "dataset_id": ds.manifest.get("dataset_id"),
            "split": split,
            "frames_seen_in_training": overlap,
        }
    if len(logits) == 1:
        combined = logits[0]
    else:  # mean log-probability: a product of experts, each model's confidence weighing in
        from scipy.special import log_softmax

        combined = np.mean([log_softmax(lg, axis=1) for lg in logits], axis=0)
    report = report_from_predictions(combined, labels, v, centroids)
    one = len(ckpts) == 1
    report.update(
        {
            "checkpoint": str(paths[0]) if one else " + ".join(map(str, paths)),
            "epoch": ckpts[0].epoch if one else [c.epoch for c in ckpts],
            "model": ckpts[0].model_name if one else " + ".join(c.model_name for c in ckpts),
            "branches": ckpts[0].branches if one else [c.branches for c in ckpts],
            # render settings that change frames, training -> this data ({} when they agree)
            "config_differences": diffs[0] if one else diffs,
            "dataset": dataset_info,
            "frames_with_lt2_detections": sparse,
            "device": str(dev),
            "hardware": hardware(dev),
            "keep_brightest": keep_brightest,
            "overrides": overrides,
        }
    )
    if not one:
        report.update(
            {
                "checkpoints": [str(p) for p in paths],
                "ensemble": "mean of the models' log-softmax (product of experts)",
                "members_top1": [float((np.argmax(lg, axis=1) == labels).mean()) for lg in logits],
            }
        )
    return report


def _predict_split(
    ckpt: Checkpoint,
    ds,
    pos: np.ndarray,
    labels: np.ndarray,
    dev,
    split: str,
    batch_size: int,
    workers: int,
    keep_brightest: int | None,
) -> np.ndarray:
    """The logits of one checkpoint on the frames ``pos`` of ``ds``, in that order."""
    model, cfg = ckpt.build_model(), ckpt.fusion_config
    model.to(dev)
    d = cfg.data
    frames = FrameDataset(
        ds,
        pos,
        labels,
        max_stars=d.max_stars,
        norm_scale_adu=d.norm_scale_adu,
        log_flux_offset=d.log_flux_offset,
        keep_brightest=keep_brightest,
    )
    loader = make_loader(frames, batch_size, shuffle=False, workers=workers, pin_memory=dev.type == "cuda")
    pred = predict_batches(model, loader, dev, amp_dtype=autocast_dtype(cfg.train.amp, dev), progress=True, desc=split)
    if not np.array_equal(pred["index"], pos):
        raise RuntimeError("prediction order does not match the split's frames")  # a bug, not user input
    return pred["logits"]


def _all_differences(r: dict) -> dict:
    """The frame-setting differences of a report, merged over an ensemble's members."""
    d = r.get("config_differences") or {}
    if isinstance(d, list):
        merged = {}
        for one in d:
            merged.update(one)
        return merged
    return d


def summary_line(r: dict) -> str:
    ae, qf = r["angular_error"], r["quantisation_floor"]
    share = r["neighbour_error_share"]
    cut = "" if r.get("keep_brightest") is None else f" (brightest {r['keep_brightest']} detections)"
    differ = _all_differences(r)
    cut += f" [WARNING: frame settings differ from the training data: {', '.join(differ)}]" if differ else ""
    return (
        f"{r['dataset']['split']}{cut}: {r['n_frames']} frames, K={r['num_classes']}: top-1 {r['top1']:.3f} "
        f"top-3 {r['top3']:.3f} top-5 {r['top5']:.3f} (chance {r['chance_top1']:.3f}); angular error "
        f"mean {ae['mean_deg']:.2f} median {ae['median_deg']:.2f} p95 {ae['p95_deg']:.2f} deg (floor "
        f"median {qf['median_deg']:.2f}); errors between neighbours "
        f"{'n/a' if share is None else f'{100 * share:.1f}%'}"
    )


def _fmt(x, pct: bool = False) -> str:
    if x is None or (isinstance(x, float) and np.isnan(x)):
        return "n/a"
    return f"{100 * x:.1f}%" if pct else f"{x:.2f}"


def markdown_report(r: dict) -> str:
    ae, qf = r["angular_error"], r["quantisation_floor"]
    lines = [
        f"# Evaluation of `{r['checkpoint']}` (epoch {r['epoch']})",
        "",
        f"Model `{r['model']}`, branches {r['branches']}; dataset `{r['dataset']['path']}`, split "
        f"**{r['dataset']['split']}**: {r['n_frames']} frames ({r['frames_with_lt2_detections']} with fewer than "
        f"2 detections), K = {r['num_classes']} (chance top-1 {_fmt(r['chance_top1'], True)})"
        + (
            "."
            if r.get("keep_brightest") is None
            else f"; each frame cut to its brightest {r['keep_brightest']} detections, the image untouched."
        ),
        "",
    ]
    if r.get("overrides"):
        lines += [
            "Scored with inference keys changed from the trained config: "
            + ", ".join(f"`{o}`" for o in r["overrides"])
            + ".",
            "",
        ]
    if _all_differences(r):
        lines += [
            f"**Warning:** the data was rendered with other frame settings than the training data "
            f"({differences_text(_all_differences(r), limit=20)}; training -> this data); the score is not "
            "the model's score on the frames it was trained for.",
            "",
        ]
    lines += [
        "| top-1 | top-3 | top-5 |",
        "|---|---|---|",
        f"| {_fmt(r['top1'], True)} | {_fmt(r['top3'], True)} | {_fmt(r['top5'], True)} |",
        "",
    ]
    if "ensemble" in r:
        lines += [
            f"An ensemble of {len(r['checkpoints'])} models: {r['ensemble']}. Each alone on the same frames, "
            "top-1: " + ", ".join(f"`{c}` {_fmt(t, True)}" for c, t in zip(r["checkpoints"], r["members_top1"])) + ".",
            "",
        ]
    lines += [
        "## Angular error (degrees)",
        "",
        "| | mean | median | p95 |",
        "|---|---|---|---|",
        f"| prediction, arccos(v · c_pred) | {_fmt(ae['mean_deg'])} | {_fmt(ae['median_deg'])} "
        f"| {_fmt(ae['p95_deg'])} |",
        f"| quantisation floor, arccos(v · c_true) | {_fmt(qf['mean_deg'])} | {_fmt(qf['median_deg'])} "
        f"| {_fmt(qf['p95_deg'])} |",
        "",
        f"Errors: {r['n_errors']}; share between neighbouring clusters: {_fmt(r['neighbour_error_share'], True)} "
        f"(neighbours: {r['neighbour_definition']}; {r['neighbour_pairs']} neighbour pairs).",
        "",
        "## Per-class accuracy",
        "",
        "| class | frames | top-1 |",
        "|---|---|---|",
    ]
    lines += [f"| {c['class']} | {c['n']} | {_fmt(c['top1'], True)} |" for c in r["per_class"]]
    stem = r["dataset"]["split"] + ("" if r.get("keep_brightest") is None else f"-brightest{r['keep_brightest']}")
    lines += ["", f"Confusion matrix: `confusion-{stem}.png` (rows true, columns predicted).", ""]
    return "\n".join(lines)
