"""Training (``fusion train``) as library functions that read top to bottom.

:func:`train` wires the stages: open the data and fit the labels (:func:`prepare_data`),
build the model, optimiser and schedule, then per epoch :func:`train_one_epoch` and
:func:`evaluate` (both return dicts), keep ``best.pt`` (lowest validation loss) and
``last.pt``, rewrite ``metrics.csv`` and the plots, and stop early after
``train.patience`` epochs without a better validation loss.

Reproducibility: every epoch starts from ``torch.manual_seed`` of (seed, epoch); the
data order is a seeded permutation per epoch and augmentations draw from
(seed, epoch, frame) (see :mod:`fusion.data`). So a run killed after epoch e and
resumed with ``--resume`` continues exactly as the uninterrupted run would (bit for bit
on CPU with the same thread count).

Schedule: AdamW; the learning rate rises linearly over ``optim.warmup_epochs`` (counted
in optimiser steps) and then follows a cosine from ``optim.lr`` to ``optim.min_lr`` at
the end of ``train.epochs``; it is stepped after every optimiser step.

Multi-GPU: under ``torchrun`` the model is wrapped in DDP, each process sees
``batch_size / world`` samples per step from its shard of the epoch's permutation, the
validation predictions of all processes are gathered so metrics are exact, and rank 0
writes every file.
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import yaml

from skygen.io import Dataset as SkyDataset
from skygen.io import open_dataset, verify_checksums

from skygen.configlib import flatten

from . import distributed as D
from .checkpoint import (atomic_save_numpy, atomic_write_text, load_checkpoint, load_matching_state, load_model_state,
                         prepare_run_folder, rng_state, save_checkpoint, set_rng_state, versions, write_json)
from .config import FusionConfig, build_config, config_dict
from .data import (FrameDataset, boresight_vectors, count_sparse_frames, make_loader, split_positions)
from .errors import CheckpointError, ConfigError, FusionError
from .labels import KMeansResult, assign, class_weights, soft_targets, spherical_kmeans
from .losses import FocalLoss, focal_loss
from .metrics import topk_accuracy
from .models import StarFusion, create_model, parameter_counts, resolve_model_config
from .plots import plot_loss_curves, plot_lr_schedule

METRIC_COLUMNS = ("epoch", "train_loss", "train_top1", "val_loss", "val_top1", "val_top3", "val_top5", "lr",
                  "epoch_time_s", "best")
RESUMABLE_KEYS = ("data.path", "train.workers", "train.progress", "train.device", "train.threads", "train.epochs")


# --------------------------------------------------------------------------- data and labels
@dataclass
class PreparedData:
    ds: SkyDataset
    centroids: np.ndarray                 # (K, 3)
    train: FrameDataset
    val: FrameDataset
    alpha: np.ndarray                     # (K,)
    kmeans: KMeansResult | None           # None when the centroids came from a checkpoint
    sparse_frames: dict                   # split -> frames with < 2 detections
    fine_centroids: np.ndarray | None = None   # (F, 3) with labels.fine_k
    fine_groups: np.ndarray | None = None      # (F,) region of each fine region


def prepare_data(cfg: FusionConfig, centroids: np.ndarray | None = None,
                 fine_centroids: np.ndarray | None = None) -> PreparedData:
    """Open the dataset, fit (or reuse) the centroids on the training split, label both splits.

    With ``labels.fine_k`` also the fine regions (spherical K-means on the same directions)
    and the region each belongs to (the region of its centroid)."""
    if not cfg.data.path:
        raise ConfigError("data.path: no dataset given; pass --data DIR (a folder written by `skygen render`)")
    ds = open_dataset(cfg.data.path)
    verify_checksums(ds, log=print)
    d, lab = cfg.data, cfg.labels
    pos = {name: split_positions(ds, getattr(d, f"{name}_split"), d.max_frames) for name in ("train", "val")}
    vec = {name: boresight_vectors(ds, p) for name, p in pos.items()}
    km = None
    if centroids is None:
        km = spherical_kmeans(vec["train"], lab.k, lab.seed, lab.n_init, lab.max_iter, lab.tol_deg)
        centroids = km.centroids
    elif len(centroids) != lab.k:
        raise CheckpointError(f"the checkpoint's centroids define K={len(centroids)} classes but labels.k={lab.k}")
    labels = {name: assign(v, centroids) for name, v in vec.items()}
    groups = fine = None
    if lab.fine_k:
        if fine_centroids is None:
            if lab.fine_k > len(vec["train"]):
                raise ConfigError(f"labels.fine_k={lab.fine_k} exceeds the {len(vec['train'])} training directions")
            fine_centroids = spherical_kmeans(vec["train"], lab.fine_k, lab.seed, lab.n_init, lab.max_iter,
                                              lab.tol_deg).centroids
        groups = assign(fine_centroids, centroids)
        empty = sorted(set(range(lab.k)) - set(groups.tolist()))
        if empty:
            raise ConfigError(f"labels.fine_k={lab.fine_k}: regions {empty} contain no fine-region centroid; "
                              "raise labels.fine_k")
        fine = {name: assign(v, fine_centroids) for name, v in vec.items()}
    soft = {name: (soft_targets(v, centroids, lab.kappa) if lab.soft_labels else None) for name, v in vec.items()}
    common = dict(max_stars=d.max_stars, norm_scale_adu=d.norm_scale_adu, log_flux_offset=d.log_flux_offset)
    train = FrameDataset(ds, pos["train"], labels["train"], soft=soft["train"], aug=cfg.aug, seed=cfg.train.seed,
                         fine=None if fine is None else fine["train"], **common)
    val = FrameDataset(ds, pos["val"], labels["val"], soft=soft["val"], aug=None, seed=cfg.train.seed, **common)
    return PreparedData(ds, np.asarray(centroids, np.float64), train, val,
                        class_weights(labels["train"], lab.k, cfg.loss.alpha), km,
                        {name: count_sparse_frames(ds, p) for name, p in pos.items()},
                        None if fine_centroids is None else np.asarray(fine_centroids, np.float64), groups)


# --------------------------------------------------------------------------- optimisation
class WarmupCosine:
    """LambdaLR factor: linear warm-up over ``warmup`` steps, then cosine to ``floor`` at ``total`` steps."""

    def __init__(self, warmup: int, total: int, floor: float):
        self.warmup, self.total, self.floor = int(warmup), max(int(total), 1), float(floor)

    def __call__(self, step: int) -> float:
        if step < self.warmup:
            return (step + 1) / self.warmup
        span = max(self.total - self.warmup, 1)
        t = min((step - self.warmup) / span, 1.0)
        return self.floor + (1.0 - self.floor) * 0.5 * (1.0 + math.cos(math.pi * t))


def build_optimizer(model: torch.nn.Module, lr: float, betas: tuple[float, float], weight_decay: float):
    """AdamW; no weight decay on biases and normalisation weights (1-D parameters)."""
    decay = [p for p in model.parameters() if p.requires_grad and p.ndim > 1]
    no_decay = [p for p in model.parameters() if p.requires_grad and p.ndim <= 1]
    return torch.optim.AdamW([{"params": decay, "weight_decay": weight_decay},
                              {"params": no_decay, "weight_decay": 0.0}], lr=lr, betas=betas)


def planned_lr(schedule: WarmupCosine, lr: float) -> np.ndarray:
    return np.array([lr * schedule(s) for s in range(schedule.total)])


def autocast_dtype(amp: str, device: torch.device) -> torch.dtype | None:
    """Mixed-precision dtype on CUDA; None (full precision) on CPU or when off."""
    if device.type != "cuda" or amp == "off":
        return None
    if amp == "auto":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    return {"bf16": torch.bfloat16, "fp16": torch.float16}[amp]


def _autocast(device: torch.device, dtype: torch.dtype | None):
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


def _inputs(batch: dict, device: torch.device) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]:
    nb = device.type == "cuda"
    image = batch.get("image")     # the detections stream has none (geometry-only models)
    return (None if image is None else image.to(device, non_blocking=nb), batch["coords"].to(device, non_blocking=nb),
            batch["mask"].to(device, non_blocking=nb))


def _target(batch: dict, device: torch.device, soft: bool) -> torch.Tensor:
    return (batch["soft"] if soft else batch["label"]).to(device, non_blocking=device.type == "cuda")


def _bar(iterable, enabled: bool, desc: str, total: int | None = None):
    if not (enabled and sys.stderr.isatty()):
        return iterable
    from tqdm import tqdm
    return tqdm(iterable, desc=desc, total=total, leave=False, dynamic_ncols=True)


# --------------------------------------------------------------------------- one epoch
def train_one_epoch(model: torch.nn.Module, loader, loss_fn: torch.nn.Module, optimizer, scheduler, scaler,
                    device: torch.device, *, amp_dtype: torch.dtype | None = None,
                    grad_clip_norm: float | None = None, soft: bool = False, progress: bool = False,
                    desc: str = "train") -> dict:
    """One pass over ``loader``; returns mean loss, top-1 on the (augmented) batches, last lr, time."""
    model.train()
    t0 = time.perf_counter()
    total_loss, n, hits = 0.0, 0, 0
    bar = _bar(loader, progress, desc, len(loader))
    for step, batch in enumerate(bar):
        image, coords, mask = _inputs(batch, device)
        target = _target(batch, device, soft)
        with _autocast(device, amp_dtype):
            if "label_fine" in batch:     # fine regions: cross-entropy on them, regions by log-sum-exp
                fine = model(image, coords, mask, fine=True)
                logits = getattr(model, "module", model).coarse_logits(fine)
            else:
                logits = model(image, coords, mask)
        if "label_fine" in batch:
            loss = torch.nn.functional.cross_entropy(fine.float(), batch["label_fine"].to(device))
        else:
            loss = loss_fn(logits.float(), target)
        if not torch.isfinite(loss):
            raise FusionError(f"training loss became {loss.item()}; lower optim.lr or enable optim.grad_clip_norm")
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(loss).backward()
        if grad_clip_norm:
            scaler.unscale_(optimizer)
            torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip_norm)
        scaler.step(optimizer)
        scaler.update()
        scheduler.step()
        b = len(target)
        total_loss += float(loss.detach()) * b   # .item()-like sync once per step: cheap next to the step
        hits += int((logits.detach().argmax(1).cpu() == batch["label"]).sum())
        n += b
        if step % 10 == 0 and hasattr(bar, "set_postfix"):
            bar.set_postfix(loss=f"{total_loss / n:.3f}", top1=f"{hits / n:.3f}",
                            samples_s=f"{n / (time.perf_counter() - t0):.0f}")
    return {"loss": total_loss / max(n, 1), "top1": hits / max(n, 1), "n": n,
            "lr": scheduler.get_last_lr()[0], "time_s": time.perf_counter() - t0}


@torch.no_grad()
def predict(model: torch.nn.Module, loader, device: torch.device, *, amp_dtype: torch.dtype | None = None,
            progress: bool = False, desc: str = "eval") -> dict:
    """Logits, labels, soft targets (if any) and frame indices of this process's share of ``loader``."""
    model.eval()
    out = {"logits": [], "label": [], "index": [], "soft": []}
    for batch in _bar(loader, progress, desc, len(loader)):
        image, coords, mask = _inputs(batch, device)
        with _autocast(device, amp_dtype):
            logits = model(image, coords, mask)
        out["logits"].append(logits.float().cpu())
        out["label"].append(batch["label"])
        out["index"].append(batch["index"])
        if "soft" in batch:
            out["soft"].append(batch["soft"])
    cat = lambda xs: torch.cat(xs).numpy() if xs else None
    return {k: cat(v) for k, v in out.items()}


def _merge(parts: list[dict]) -> dict:
    """Concatenate per-rank predictions and restore frame order."""
    merged = {k: (np.concatenate([p[k] for p in parts]) if parts[0][k] is not None else None) for k in parts[0]}
    order = np.argsort(merged["index"], kind="stable")
    return {k: (v[order] if v is not None else None) for k, v in merged.items()}


def evaluate(model: torch.nn.Module, loader, loss_fn: torch.nn.Module, device: torch.device,
             info: D.DistInfo = D.DistInfo(), *, amp_dtype: torch.dtype | None = None, soft: bool = False,
             progress: bool = False) -> dict:
    """Loss and top-1/3/5 over the whole split (predictions of all processes gathered)."""
    t0 = time.perf_counter()
    pred = _merge(D.gather_objects(predict(model, loader, device, amp_dtype=amp_dtype, progress=progress), info))
    logits = torch.from_numpy(pred["logits"])
    target = torch.from_numpy(pred["soft"]) if soft else torch.from_numpy(pred["label"])
    alpha = None if loss_fn.alpha is None else loss_fn.alpha.cpu()
    loss = float(focal_loss(logits, target, alpha, loss_fn.gamma)) if len(logits) else float("nan")
    return {"loss": loss, **topk_accuracy(pred["logits"], pred["label"]), "n": int(len(logits)),
            "time_s": time.perf_counter() - t0, "predictions": pred}


# --------------------------------------------------------------------------- run-folder outputs
def write_metrics_csv(path: Path, history: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=METRIC_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for row in history:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    atomic_write_text(path, buf.getvalue())


def write_config_yaml(path: Path, cfg: FusionConfig) -> None:
    init = (f"image backbone initialised from {cfg.model.pretrained}" if cfg.model.pretrained
            else "image backbone trained from scratch (model.pretrained: null)")
    text = (f"# resolved fusion training config ({init})\n"
            + yaml.safe_dump(config_dict(cfg), sort_keys=False, default_flow_style=None))
    atomic_write_text(path, text)


def check_resume_config(cfg: FusionConfig, ckpt: dict) -> FusionConfig:
    """The checkpoint's config, with only :data:`RESUMABLE_KEYS` taken from ``cfg``; other differences raise."""
    saved, asked = flatten(ckpt["config"]), flatten(config_dict(cfg))
    diff = sorted(k for k in set(saved) | set(asked) if saved.get(k) != asked.get(k) and k not in RESUMABLE_KEYS)
    if diff:
        details = ", ".join(f"{k}: {saved.get(k)!r} -> {asked.get(k)!r}" for k in diff[:8])
        raise CheckpointError(f"--resume: the config differs from the one the run was started with ({details}); "
                              "resume takes the run's config.yaml (only data.path and train.workers/progress/device "
                              "may change): drop those overrides, or start a new run (--force or another --out)")
    data = ckpt["config"]
    for key in RESUMABLE_KEYS:
        section, name = key.split(".")
        data[section][name] = getattr(getattr(cfg, section), name)
    return build_config(data)


# --------------------------------------------------------------------------- the whole run
def _set_epoch(loader, epoch: int) -> None:
    """The epoch of a shard loader's sampler, or of a stream's batches."""
    target = loader.dataset if hasattr(loader.dataset, "set_epoch") else loader.sampler
    target.set_epoch(epoch)


def _seed_epoch(seed: int, epoch: int) -> None:
    torch.manual_seed(seed * 1_000_003 + epoch)


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


def train(cfg: FusionConfig, out: str | Path, *, resume: bool = False, force: bool = False, log=print) -> dict:
    """Train ``cfg`` into run folder ``out``; returns the summary (also written to summary.json)."""
    out = Path(out)
    info, device = D.init(cfg.train.device)
    say = log if info.is_main else (lambda *a, **k: None)
    try:
        cfg = replace(cfg, model=resolve_model_config(cfg.model))
        _broadcast_error(lambda: prepare_run_folder(out, resume=resume, force=force, epochs=cfg.train.epochs), info)
        D.barrier(info)
        ckpt = None
        if resume:
            ckpt = load_checkpoint(out / "last.pt")
            cfg = check_resume_config(cfg, ckpt)
        return _run(cfg, out, ckpt, info, device, say)
    finally:
        D.shutdown(info)


def _run(cfg: FusionConfig, out: Path, ckpt: dict | None, info: D.DistInfo, device: torch.device, say) -> dict:
    t_start = time.perf_counter()
    tc, oc = cfg.train, cfg.optim
    if tc.batch_size % info.world:
        raise ConfigError(f"train.batch_size ({tc.batch_size}) must be divisible by the number of processes "
                          f"({info.world})")
    if tc.deterministic:
        if device.type == "cuda":   # cuBLAS needs this before its first call to be deterministic
            os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
        torch.backends.cudnn.benchmark = False
    if tc.threads:
        torch.set_num_threads(tc.threads)
    torch.manual_seed(tc.seed)
    np.random.seed(tc.seed)

    centroids = None if ckpt is None else ckpt["centroids"].numpy()
    fine_c = None if ckpt is None or ckpt.get("fine_centroids") is None else ckpt["fine_centroids"].numpy()
    data = prepare_data(cfg, centroids, fine_c)
    k, image_size = cfg.labels.k, data.ds.image_shape[0]
    if (cfg.model.branches.image and data.ds.image_shape[0] != data.ds.image_shape[1]
            and cfg.model.image_backbone not in ("tiny_cnn",)):
        raise ConfigError(f"model.image_backbone={cfg.model.image_backbone} takes square images, but this dataset "
                          f"stores {data.ds.image_shape[1]} x {data.ds.image_shape[0]} (a non-square sensor); use "
                          "model.image_backbone=tiny_cnn or switch the image branch off")
    model = create_model(cfg.model.name, k, cfg.model, image_size=image_size, max_stars=cfg.data.max_stars,
                         fine_classes=cfg.labels.fine_k)
    if data.fine_groups is not None:
        model.fine_groups.copy_(torch.from_numpy(data.fine_groups))
    counts = parameter_counts(model)
    if cfg.model.init_from and ckpt is None:
        warm = load_matching_state(model, cfg.model.init_from)
        if info.is_main:
            groups = sorted({k.split(".")[0] for k in warm["loaded"]})
            say(f"warm start from {cfg.model.init_from}: {len(warm['loaded'])} tensors ({', '.join(groups)}); "
                f"{len(warm['skipped'])} trained from scratch")
    model.to(device)
    loss_fn = FocalLoss(torch.as_tensor(data.alpha, dtype=torch.float32), cfg.loss.gamma).to(device)

    per_rank = tc.batch_size // info.world
    pin = device.type == "cuda"
    sc = cfg.stream
    if sc.kind == "none":
        train_loader = make_loader(data.train, per_rank, shuffle=True, seed=tc.seed, workers=tc.workers,
                                   rank=info.rank, world=info.world, pad=True, pin_memory=pin)
    else:
        from .stream import StreamBatches, level_ranges, make_stream_loader
        batches = StreamBatches(data.ds.config, sc.kind, data.centroids,
                                seed=tc.seed if sc.seed is None else sc.seed, batch=per_rank,
                                steps=sc.samples_per_epoch // tc.batch_size, rank=info.rank, world=info.world,
                                max_stars=cfg.data.max_stars, log_flux_offset=cfg.data.log_flux_offset,
                                norm_scale_adu=cfg.data.norm_scale_adu,
                                soft_kappa=cfg.labels.kappa if cfg.labels.soft_labels else None,
                                ranges=level_ranges(sc), calibration=sc.calibration,
                                fine_centroids=data.fine_centroids, few_prob=sc.few_prob,
                                few_stars=sc.few_stars, brightness_mag=sc.brightness_mag,
                                device=str(device) if sc.render_backend == "torch" else None,
                                render_backend=sc.render_backend)
        workers = tc.workers
        if sc.render_backend == "torch" and device.type == "cuda" and workers:
            say("stream.render_backend=torch renders on the GPU in the training process: train.workers set to 0")
            workers = 0
        train_loader = make_stream_loader(batches, workers)
    val_loader = make_loader(data.val, tc.eval_batch_size or 2 * per_rank, shuffle=False, workers=tc.workers,
                             rank=info.rank, world=info.world, pad=False, pin_memory=pin)
    steps = len(train_loader)
    optimizer = build_optimizer(model, oc.lr, oc.betas, oc.weight_decay)
    schedule = WarmupCosine(round(oc.warmup_epochs * steps), tc.epochs * steps, oc.min_lr / oc.lr)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, schedule)
    amp_dtype = autocast_dtype(tc.amp, device)
    scaler = torch.amp.GradScaler(device.type, enabled=amp_dtype == torch.float16)

    start_epoch, history = 0, []
    best = {"epoch": None, "val_loss": float("inf")}
    if ckpt is not None:
        load_model_state(model, ckpt, str(out / "last.pt"))
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])
        schedule.total = max(tc.epochs * steps, 1)   # an extended run stretches the cosine to the new length
        scaler.load_state_dict(ckpt["scaler"])
        start_epoch, history, best = int(ckpt["epoch"]), list(ckpt["history"]), dict(ckpt["best"])
        set_rng_state(ckpt["rng"])
        say(f"resuming {out} at epoch {start_epoch + 1}/{tc.epochs}")

    net = model
    if info.enabled:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None)

    static = {"config": config_dict(cfg), "centroids": torch.from_numpy(data.centroids),
              "fine_centroids": None if data.fine_centroids is None else torch.from_numpy(data.fine_centroids),
              "num_classes": k, "image_size": image_size, "max_stars": cfg.data.max_stars,
              "model_name": cfg.model.name, "branches": model.branches, "versions": versions(),
              "dataset": {"root": str(Path(data.ds.root).resolve()), "dataset_id": data.ds.manifest.get("dataset_id"),
                          "schema_version": data.ds.schema_version, "camera": data.ds.config["camera"]},
              # identities of the frames trained on: `fusion evaluate` refuses to score them
              # (none for a stream-trained model: it never saw a dataset frame)
              "train_frame_ids": (torch.zeros(0, dtype=torch.int64) if cfg.stream.kind != "none" else
                                  torch.from_numpy(data.ds.frames["frame_id"][data.train.positions].view(np.int64))),
              # the camera, sensor, detector and storage the model was trained for: `fusion predict` needs
              # nothing else, from any folder (see fusion.checkpoint.render_config_of)
              "render_config": dict(data.ds.config)}
    if info.is_main:
        write_config_yaml(out / "config.yaml", cfg)
        atomic_save_numpy(out / "centroids.npy", data.centroids)
        if sc.kind == "none":
            say(f"data: {len(data.train)} train / {len(data.val)} val frames, K={k}, "
                f"frames with <2 detections: {data.sparse_frames}")
        else:
            say(f"data: {sc.kind} stream, {steps * tc.batch_size} samples per epoch (never repeated), "
                f"validation on {len(data.val)} rendered {cfg.data.val_split} frames of {data.ds.root}, K={k}")
        if data.kmeans is not None:
            say(f"labels: spherical K-means {'converged' if data.kmeans.converged else 'NOT converged'} "
                f"in {data.kmeans.n_iter} iterations; train class counts "
                f"{np.bincount(data.train.labels, minlength=k).tolist()}")
        say(f"model {cfg.model.name} ({cfg.model.image_backbone if cfg.model.branches.image else 'no image branch'}), "
            f"parameters {counts}; device {device}, {info.world} process(es), amp {amp_dtype}")

    soft = cfg.labels.soft_labels
    stopped_early = False
    for epoch in range(start_epoch, tc.epochs):
        _seed_epoch(tc.seed, epoch)
        _set_epoch(train_loader, epoch)
        t0 = time.perf_counter()
        tr = train_one_epoch(net, train_loader, loss_fn, optimizer, scheduler, scaler, device, amp_dtype=amp_dtype,
                             grad_clip_norm=oc.grad_clip_norm, soft=soft, progress=tc.progress and info.is_main,
                             desc=f"epoch {epoch + 1}/{tc.epochs}")
        # the unwrapped model: ranks see different numbers of validation batches, and a DDP
        # forward may broadcast buffers (a collective every rank must join)
        va = evaluate(model, val_loader, loss_fn, device, info, amp_dtype=amp_dtype, soft=soft,
                      progress=tc.progress and info.is_main)
        improved = va["loss"] < best["val_loss"]
        if improved:
            best = {"epoch": epoch + 1, "val_loss": va["loss"], "val_top1": va["top1"], "val_top3": va["top3"],
                    "val_top5": va["top5"]}
        row = {"epoch": epoch + 1, "train_loss": tr["loss"], "train_top1": tr["top1"], "val_loss": va["loss"],
               "val_top1": va["top1"], "val_top3": va["top3"], "val_top5": va["top5"], "lr": tr["lr"],
               "epoch_time_s": time.perf_counter() - t0, "best": int(improved), "train_samples": tr["n"]}
        history.append(row)
        since_best = epoch + 1 - (best["epoch"] or 0)
        stopped_early = tc.patience is not None and since_best >= tc.patience and epoch + 1 < tc.epochs
        finished = stopped_early or epoch + 1 == tc.epochs
        if info.is_main:
            state = {**static, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
                     "scheduler": scheduler.state_dict(), "scaler": scaler.state_dict(), "epoch": epoch + 1,
                     "history": history, "best": best, "finished": finished, "rng": rng_state()}
            if improved:
                save_checkpoint(out / "best.pt", state)
            save_checkpoint(out / "last.pt", state)
            write_metrics_csv(out / "metrics.csv", history)
            plot_loss_curves(history, out / "loss_curves.png")
            plot_lr_schedule(planned_lr(schedule, oc.lr), steps, history, out / "lr_schedule.png")
            say(f"epoch {epoch + 1}/{tc.epochs}  train loss {tr['loss']:.4f} top1 {tr['top1']:.3f} | val loss "
                f"{va['loss']:.4f} top1 {va['top1']:.3f} top3 {va['top3']:.3f} top5 {va['top5']:.3f} | "
                f"lr {tr['lr']:.3g} | {row['epoch_time_s']:.1f} s, {tr['n'] / max(tr['time_s'], 1e-9):.0f} samples/s | "
                f"best.pt: epoch {best['epoch']} (lowest val loss {best['val_loss']:.4f})"
                f"{'  <- new best' if improved else ''}")
        D.barrier(info)
        if stopped_early:
            say(f"early stopping: no better val loss for {tc.patience} epochs (best: epoch {best['epoch']})")
            break

    summary = {"finished": True, "epochs_run": len(history), "stopped_early": stopped_early, "best": best,
               "last": history[-1] if history else None, "num_classes": k, "parameters": counts,
               "sparse_frames": data.sparse_frames, "frames": {"train": len(data.train), "val": len(data.val)},
               "processes": info.world, "device": str(device), "amp": str(amp_dtype),
               "init": cfg.model.pretrained or "scratch", "wall_time_s": time.perf_counter() - t_start,
               "samples_seen": int(sum(h.get("train_samples", 0) for h in history)),
               "versions": static["versions"], "dataset": static["dataset"]}
    if info.is_main:
        write_json(out / "summary.json", summary)
        say(f"done: best epoch {best['epoch']} val top1 {best.get('val_top1', float('nan')):.3f}; run folder {out}")
    data.ds.close()
    return summary


def load_trained_model(ckpt: dict, source: str = "checkpoint") -> tuple[StarFusion, FusionConfig]:
    """Rebuild the model of a checkpoint from its own config and load its weights (on CPU)."""
    try:
        cfg = build_config(ckpt["config"])
    except ConfigError as exc:
        raise CheckpointError(f"{source}: its config is not valid for this fusion version ({exc})") from None
    model = create_model(cfg.model.name, int(ckpt["num_classes"]), cfg.model, image_size=int(ckpt["image_size"]),
                         fine_classes=cfg.labels.fine_k,
                         max_stars=int(ckpt["max_stars"]), load_pretrained=False)
    load_model_state(model, ckpt, source)
    return model, cfg
