"""Training (``fusion train``): the run in named steps that read top to bottom.

:func:`train` prepares the run folder and calls :func:`run`, which wires the steps: set up
torch (:func:`setup_torch`), open the data and fit the regions
(:func:`fusion.train.data.prepare_data`), build the model (:func:`build_model`), the training
loader (:func:`train_loader`: shards or a stream) and the optimisation
(:func:`build_optimisation`), resume if asked (:func:`resume_state`), then per epoch
:func:`fusion.train.loop.train_one_epoch` and :func:`fusion.train.loop.validate` (both return
dicts), keep ``best.pt`` (lowest validation loss) and ``last.pt``, rewrite ``metrics.csv`` and
the plots (:func:`write_epoch`), and stop early after ``train.patience`` epochs without a
better validation loss.

Reproducibility: every epoch starts from ``torch.manual_seed`` of (seed, epoch); the data
order is a seeded permutation per epoch and augmentations draw from (seed, epoch, frame)
(see :mod:`fusion.model.shards`). So a run killed after epoch e and resumed with
``--resume`` continues exactly as the uninterrupted run would (bit for bit on CPU with the
same thread count).

Multi-GPU: under ``torchrun`` the model is wrapped in DDP, each process sees
``batch_size / world`` samples per step from its shard of the epoch's permutation, the
validation predictions of all processes are gathered so metrics are exact, and rank 0
writes every file.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from skygen.runtime import atomic_save_numpy, hardware, write_json

from ..config import FusionConfig
from ..errors import ConfigError
from ..model.checkpoint import Checkpoint, load_checkpoint, load_matching_state, load_model_state, versions
from ..model.inference import autocast_dtype
from ..model.networks import StarFusion, create_model, parameter_counts, resolve_model_config
from ..model.shards import make_loader
from ..plots import plot_loss_curves, plot_lr_schedule
from . import distributed as D
from .data import PreparedData, prepare_data
from .loop import WarmupCosine, build_optimizer, planned_lr, train_one_epoch, validate
from .losses import FocalLoss
from .runfolder import (
    check_resume_config,
    lock_run_folder,
    prepare_run_folder,
    rng_state,
    set_rng_state,
    write_config_yaml,
    write_metrics_csv,
)


def train(cfg: FusionConfig, out: str | Path, *, resume: bool = False, force: bool = False, log=print) -> dict:
    """Train ``cfg`` into run folder ``out``; returns the summary (also written to summary.json)."""
    out = Path(out)
    info, device = D.init(cfg.train.device)
    say = log if info.is_main else (lambda *a, **k: None)
    lock = None
    try:
        cfg = replace(cfg, model=resolve_model_config(cfg.model))
        # rank 0 holds the run folder's lock for the whole run: a second `fusion train --out` into it
        # (which would interleave checkpoints, or --force-delete them) is refused, naming this one
        lock = _broadcast_error(lambda: lock_run_folder(out), info)
        _broadcast_error(lambda: prepare_run_folder(out, resume=resume, force=force, epochs=cfg.train.epochs), info)
        D.barrier(info)
        ckpt = None
        if resume:
            ckpt = load_checkpoint(out / "last.pt")
            cfg = check_resume_config(cfg, ckpt)
        return run(cfg, out, ckpt, info, device, say)
    finally:
        if lock is not None:
            lock.release()
        D.shutdown(info)


def _broadcast_error(fn, info: D.DistInfo):
    """Run ``fn`` on rank 0 and share its result, or its exception, with every rank."""
    result, error = None, None
    if info.is_main:
        try:
            result = fn()
        except Exception as exc:  # re-raised below on every rank
            error = exc
    error = D.broadcast_object(error, info)
    if error is not None:
        raise error
    return result


# --------------------------------------------------------------------------- the steps
def setup_torch(cfg: FusionConfig, info: D.DistInfo, device: torch.device) -> None:
    """Batch divisibility, determinism, threads and the global seeds (before anything draws)."""
    tc = cfg.train
    if tc.batch_size % info.world:
        raise ConfigError(
            f"train.batch_size ({tc.batch_size}) must be divisible by the number of processes ({info.world})"
        )
    if tc.deterministic:
        if device.type == "cuda":  # cuBLAS needs this before its first call to be deterministic
            os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
        torch.backends.cudnn.benchmark = False
    if tc.threads:
        torch.set_num_threads(tc.threads)
    torch.manual_seed(tc.seed)
    np.random.seed(tc.seed)


def loader_workers(asked: int, say=None) -> int:
    """``train.workers``, but no more than the cores this process may use (more only thrash)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if asked > cores and say is not None:
        say(f"train.workers={asked} but this machine gives the process {cores} core(s): {cores} loader worker(s)")
    return min(asked, cores)


def pace_line(step_s: float, steps: int, epochs_left: int, batch: int, model, device) -> str:
    """What the run will cost at the measured pace; a model too large for a CPU is named with its size."""
    epoch_s = step_s * steps
    total_h = epoch_s * epochs_left / 3600
    n_params = sum(p.numel() for p in model.parameters()) / 1e6
    line = (
        f"pace: {step_s:.2f} s per step of {batch} samples -> ~{epoch_s / 60:.1f} min per epoch, "
        f"~{total_h:.1f} h for the {epochs_left} epoch(s) to go on {device.type}"
    )
    if device.type == "cpu" and total_h > 1.0:
        line += (
            f"; a {n_params:.1f} M-parameter model is a GPU recipe: on a CPU use configs/cpu.yaml "
            "(minutes) or configs/smoke.yaml (seconds)"
        )
    return line


def build_model(cfg: FusionConfig, data: PreparedData, fresh: bool, say) -> StarFusion:
    """The model for ``data``'s regions and image size; a warm start (``model.init_from``) for a fresh run."""
    if (
        cfg.model.branches.image
        and data.ds.image_shape[0] != data.ds.image_shape[1]
        and cfg.model.image_backbone not in ("tiny_cnn", "grid_cnn", "peak_set", "peak_rows")
    ):
        raise ConfigError(
            f"model.image_backbone={cfg.model.image_backbone} takes square images, but this dataset "
            f"stores {data.ds.image_shape[1]} x {data.ds.image_shape[0]} (a non-square sensor); use "
            "model.image_backbone=tiny_cnn or switch the image branch off"
        )
    if cfg.model.branches.image:
        say(f"building {cfg.model.name} with the {cfg.model.image_backbone} image backbone ...")
    model = create_model(
        cfg.model.name,
        cfg.labels.k,
        cfg.model,
        image_size=data.ds.image_shape[0],
        max_stars=cfg.data.max_stars,
        fine_classes=cfg.labels.fine_k,
        pre=data.val.pre,
    )
    if data.regions.fine is not None and model.fine_classes:
        model.fine_groups.copy_(torch.from_numpy(data.regions.groups))
    if cfg.model.init_from and fresh:
        warm = load_matching_state(model, cfg.model.init_from)
        groups = sorted({k.split(".")[0] for k in warm["loaded"]})
        say(
            f"warm start from {cfg.model.init_from}: {len(warm['loaded'])} tensors ({', '.join(groups)}); "
            f"{len(warm['skipped'])} trained from scratch"
            + (
                f"; the fusion head's {'+'.join(warm['head_blocks'])} columns copied, the new branches' columns "
                "start at zero"
                if warm["head_blocks"]
                else ""
            )
        )
    return model


def train_loader(cfg: FusionConfig, data: PreparedData, info: D.DistInfo, device: torch.device, say):
    """The training batches: the shards' training split (``stream.kind=none``) or a skygen stream."""
    tc, sc = cfg.train, cfg.stream
    per_rank = tc.batch_size // info.world
    workers = loader_workers(tc.workers, say if info.is_main else None)
    if sc.kind == "none":
        return make_loader(
            data.train,
            per_rank,
            shuffle=True,
            seed=tc.seed,
            workers=workers,
            rank=info.rank,
            world=info.world,
            pad=True,
            pin_memory=device.type == "cuda",
        )
    from .stream import StreamBatches, make_stream_loader

    batches = StreamBatches.from_config(
        cfg, data.ds.config, data.regions, rank=info.rank, world=info.world, device=device
    )
    if sc.render_backend == "torch" and device.type == "cuda" and workers:
        say("stream.render_backend=torch renders on the GPU in the training process: train.workers set to 0")
        workers = 0
    return make_stream_loader(batches, workers, pin_memory=device.type == "cuda" and workers > 0)


@dataclass
class Optimisation:
    optimizer: torch.optim.Optimizer
    schedule: WarmupCosine
    scheduler: torch.optim.lr_scheduler.LambdaLR
    scaler: torch.amp.GradScaler
    amp_dtype: torch.dtype | None


def build_optimisation(cfg: FusionConfig, model: StarFusion, steps: int, device: torch.device) -> Optimisation:
    oc = cfg.optim
    optimizer = build_optimizer(model, oc.lr, oc.betas, oc.weight_decay)
    schedule = WarmupCosine(round(oc.warmup_epochs * steps), cfg.train.epochs * steps, oc.min_lr / oc.lr)
    amp_dtype = autocast_dtype(cfg.train.amp, device)
    return Optimisation(
        optimizer,
        schedule,
        torch.optim.lr_scheduler.LambdaLR(optimizer, schedule),
        torch.amp.GradScaler(device.type, enabled=amp_dtype == torch.float16),
        amp_dtype,
    )


def resume_state(ckpt: Checkpoint, model: StarFusion, opt: Optimisation, total_steps: int) -> tuple[int, list, dict]:
    """Weights, optimiser, schedule, scaler and generators of ``ckpt``; (start epoch, history, best)."""
    load_model_state(model, ckpt)
    opt.optimizer.load_state_dict(ckpt.optimizer)
    opt.scheduler.load_state_dict(ckpt.scheduler)
    opt.schedule.total = max(total_steps, 1)  # an extended run stretches the cosine to the new length
    opt.scaler.load_state_dict(ckpt.scaler)
    set_rng_state(ckpt.rng)
    return int(ckpt.epoch), list(ckpt.history), dict(ckpt.best)


def checkpoint_template(cfg: FusionConfig, data: PreparedData, model: StarFusion) -> Checkpoint:
    """What every checkpoint of this run holds besides the weights and the training state (schema:
    :mod:`fusion.model.checkpoint`); each epoch's checkpoint is a ``dataclasses.replace`` of it."""
    from ..config import config_dict

    ds = data.ds
    return Checkpoint(
        model={},
        config=config_dict(cfg),
        centroids=data.regions.coarse,
        fine_centroids=data.regions.fine,
        num_classes=cfg.labels.k,
        image_size=ds.image_shape[0],
        max_stars=cfg.data.max_stars,
        model_name=cfg.model.name,
        branches=model.branches,
        versions=versions(),
        dataset={
            "root": str(Path(ds.root).resolve()),
            "dataset_id": ds.manifest.get("dataset_id"),
            "schema_version": ds.schema_version,
            "camera": ds.config["camera"],
        },
        # identities of the frames trained on: `fusion evaluate` refuses to score them
        # (none for a stream-trained model: it never saw a dataset frame)
        train_frame_ids=(
            np.zeros(0, np.int64)
            if cfg.stream.kind != "none"
            else ds.frames["frame_id"][data.train.positions].view(np.int64)
        ),
        # the camera, sensor, detector and storage the model was trained for: `fusion predict` needs
        # nothing else, from any folder
        render_config=dict(ds.config),
    )


def log_start(cfg: FusionConfig, data: PreparedData, steps: int, counts: dict, device, info, amp_dtype, say) -> None:
    k, sc = cfg.labels.k, cfg.stream
    if sc.kind == "none":
        say(
            f"data: {len(data.train)} train / {len(data.val)} val frames, K={k}, "
            f"frames with <2 detections: {data.sparse_frames}"
        )
        if len(data.train) < 20 * k:
            say(
                f"note: {len(data.train)} training frames for K={k} regions ({len(data.train) / k:.1f} per region): "
                "too few to learn from; render more frames or train on the stream (stream.kind=detections)"
            )
    else:
        say(
            f"data: {sc.kind} stream, {steps * cfg.train.batch_size} samples per epoch (never repeated), "
            f"validation on {len(data.val)} rendered {cfg.data.val_split} frames of {data.ds.root}, K={k}"
        )
    if data.kmeans is not None:
        say(
            f"labels: spherical K-means {'converged' if data.kmeans.converged else 'NOT converged'} "
            f"in {data.kmeans.n_iter} iterations; train class counts "
            f"{np.bincount(data.train.labels, minlength=k).tolist()}"
        )
    say(
        f"model {cfg.model.name} ({cfg.model.image_backbone if cfg.model.branches.image else 'no image branch'}), "
        f"parameters {counts}; device {device}, {info.world} process(es), amp {amp_dtype}"
    )
    if device.type == "cpu" and counts["total"] > 10e6:
        say(
            f"{counts['total'] / 1e6:.1f} M parameters on a CPU: expect seconds per step; the pace of this run "
            "follows after its first steps (configs/cpu.yaml trains in minutes)"
        )


def write_epoch(out: Path, ckpt: Checkpoint, improved: bool, opt: Optimisation, steps: int, lr: float) -> None:
    """best.pt (when improved), last.pt, metrics.csv and the two plots of the run so far."""
    if improved:
        ckpt.save(out / "best.pt")
    ckpt.save(out / "last.pt")
    write_metrics_csv(out / "metrics.csv", ckpt.history)
    plot_loss_curves(ckpt.history, out / "loss_curves.png")
    plot_lr_schedule(planned_lr(opt.schedule, lr), steps, ckpt.history, out / "lr_schedule.png")


# --------------------------------------------------------------------------- the run
def run(cfg: FusionConfig, out: Path, ckpt: Checkpoint | None, info: D.DistInfo, device: torch.device, say) -> dict:
    """The training run of an already prepared run folder (``ckpt``: resume from it)."""
    t_start = time.perf_counter()
    tc = cfg.train
    setup_torch(cfg, info, device)
    data = prepare_data(cfg, None if ckpt is None else ckpt.regions)
    model = build_model(cfg, data, ckpt is None, say if info.is_main else (lambda *a, **k: None))
    counts = parameter_counts(model)
    model.to(device)
    loss_fn = FocalLoss(torch.as_tensor(data.alpha, dtype=torch.float32), cfg.loss.gamma).to(device)
    loader = train_loader(cfg, data, info, device, say)
    val_loader = make_loader(
        data.val,
        tc.eval_batch_size or 2 * (tc.batch_size // info.world),
        shuffle=False,
        workers=loader_workers(tc.workers),
        rank=info.rank,
        world=info.world,
        pad=False,
        pin_memory=device.type == "cuda",
    )
    steps = len(loader)
    opt = build_optimisation(cfg, model, steps, device)

    start_epoch, history, best = 0, [], {"epoch": None, "val_loss": float("inf")}
    if ckpt is not None:
        start_epoch, history, best = resume_state(ckpt, model, opt, tc.epochs * steps)
        say(f"resuming {out} at epoch {start_epoch + 1}/{tc.epochs}")
    net = model
    if info.enabled:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None
        )
    template = checkpoint_template(cfg, data, model)
    if info.is_main:
        write_config_yaml(out / "config.yaml", cfg)
        atomic_save_numpy(out / "centroids.npy", data.regions.coarse)
        log_start(cfg, data, steps, counts, device, info, opt.amp_dtype, say)

    soft = cfg.labels.soft_labels
    warm_val = None
    if ckpt is None and cfg.model.init_from:
        # what the warm start brings before any step: the new branches enter from zero head columns
        warm_val = validate(
            model, val_loader, loss_fn, device, info, amp_dtype=opt.amp_dtype, soft=soft, progress=False
        )
        warm_val = {"val_loss": warm_val["loss"], "val_top1": warm_val["top1"], "val_top3": warm_val["top3"]}
        say(
            f"warm start, before training: val loss {warm_val['val_loss']:.4f} top1 {warm_val['val_top1']:.3f} "
            f"top3 {warm_val['val_top3']:.3f}"
        )
    stopped_early = False
    for epoch in range(start_epoch, tc.epochs):
        torch.manual_seed(tc.seed * 1_000_003 + epoch)
        (loader.dataset if hasattr(loader.dataset, "set_epoch") else loader.sampler).set_epoch(epoch)
        t0 = time.perf_counter()
        pace = (
            (lambda s: say(pace_line(s, steps, tc.epochs - epoch, tc.batch_size, model, device)))
            if epoch == start_epoch and info.is_main
            else None
        )
        tr = train_one_epoch(
            net,
            loader,
            loss_fn,
            opt.optimizer,
            opt.scheduler,
            opt.scaler,
            device,
            amp_dtype=opt.amp_dtype,
            grad_clip_norm=cfg.optim.grad_clip_norm,
            soft=soft,
            progress=tc.progress and info.is_main,
            desc=f"epoch {epoch + 1}/{tc.epochs}",
            pace=pace,
        )
        # the unwrapped model: ranks see different numbers of validation batches, and a DDP
        # forward may broadcast buffers (a collective every rank must join)
        va = validate(
            model,
            val_loader,
            loss_fn,
            device,
            info,
            amp_dtype=opt.amp_dtype,
            soft=soft,
            progress=tc.progress and info.is_main,
        )
        improved = va["loss"] < best["val_loss"]
        if improved:
            best = {
                "epoch": epoch + 1,
                "val_loss": va["loss"],
                "val_top1": va["top1"],
                "val_top3": va["top3"],
                "val_top5": va["top5"],
            }
        row = {
            "epoch": epoch + 1,
            "train_loss": tr["loss"],
            "train_top1": tr["top1"],
            "val_loss": va["loss"],
            "val_top1": va["top1"],
            "val_top3": va["top3"],
            "val_top5": va["top5"],
            "lr": tr["lr"],
            "epoch_time_s": time.perf_counter() - t0,
            "best": int(improved),
            "train_samples": tr["n"],
        }
        history.append(row)
        since_best = epoch + 1 - (best["epoch"] or 0)
        stopped_early = tc.patience is not None and since_best >= tc.patience and epoch + 1 < tc.epochs
        finished = stopped_early or epoch + 1 == tc.epochs
        if info.is_main:
            state = replace(
                template,
                model=model.state_dict(),
                epoch=epoch + 1,
                history=history,
                best=best,
                finished=finished,
                optimizer=opt.optimizer.state_dict(),
                scheduler=opt.scheduler.state_dict(),
                scaler=opt.scaler.state_dict(),
                rng=rng_state(),
            )
            write_epoch(out, state, improved, opt, steps, cfg.optim.lr)
            say(
                f"epoch {epoch + 1}/{tc.epochs}  train loss {tr['loss']:.4f} top1 {tr['top1']:.3f} | val loss "
                f"{va['loss']:.4f} top1 {va['top1']:.3f} top3 {va['top3']:.3f} top5 {va['top5']:.3f} | "
                f"lr {tr['lr']:.3g} | {row['epoch_time_s']:.1f} s, {tr['n'] / max(tr['time_s'], 1e-9):.0f} samples/s | "
                f"best.pt: epoch {best['epoch']} (lowest val loss {best['val_loss']:.4f})"
                f"{'  <- new best' if improved else ''}"
            )
        D.barrier(info)
        if stopped_early:
            say(f"early stopping: no better val loss for {tc.patience} epochs (best: epoch {best['epoch']})")
            break

    summary = {
        "finished": True,
        "epochs_run": len(history),
        "stopped_early": stopped_early,
        "best": best,
        "last": history[-1] if history else None,
        "num_classes": cfg.labels.k,
        "parameters": counts,
        "sparse_frames": data.sparse_frames,
        "frames": {"train": len(data.train), "val": len(data.val)},
        "processes": info.world,
        "device": str(device),
        "amp": str(opt.amp_dtype),
        "init": (
            f"warm start from {cfg.model.init_from}" if cfg.model.init_from else cfg.model.pretrained or "scratch"
        ),
        "warm_start_val": warm_val,
        "wall_time_s": time.perf_counter() - t_start,
        "samples_seen": int(sum(h.get("train_samples", 0) for h in history)),
        "versions": template.versions,
        "dataset": template.dataset,
        "hardware": hardware(device),
    }
    if info.is_main:
        write_json(out / "summary.json", summary)
        say(f"done: best epoch {best['epoch']} val top1 {best.get('val_top1', float('nan')):.3f}; run folder {out}")
    data.ds.close()
    return summary
