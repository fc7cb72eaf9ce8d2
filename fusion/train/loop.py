"""One epoch of training and one validation pass, as functions that return dicts; the schedule.

Schedule: AdamW; the learning rate rises linearly over ``optim.warmup_epochs`` (counted
in optimiser steps) and then follows a cosine from ``optim.lr`` to ``optim.min_lr`` at
the end of ``train.epochs``; it is stepped after every optimiser step.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from ..errors import FusionError
from ..model.inference import autocast, batch_inputs, predict_batches, progress_bar
from ..model.metrics import topk_accuracy
from . import distributed as D
from .losses import focal_loss


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
    return torch.optim.AdamW(
        [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}], lr=lr, betas=betas
    )


def planned_lr(schedule: WarmupCosine, lr: float) -> np.ndarray:
    return np.array([lr * schedule(s) for s in range(schedule.total)])


def train_one_epoch(
    model: torch.nn.Module,
    loader,
    loss_fn: torch.nn.Module,
    optimizer,
    scheduler,
    scaler,
    device: torch.device,
    *,
    amp_dtype: torch.dtype | None = None,
    grad_clip_norm: float | None = None,
    soft: bool = False,
    progress: bool = False,
    desc: str = "train",
    pace=None,
) -> dict:
    """One pass over ``loader``; returns mean loss, top-1 on the (augmented) batches, last lr, time.

    ``pace``: called once as ``pace(seconds_per_step)``, measured over steps 1-10 (or fewer if they
    take over 30 s; the first step, which pays for warm-up, is not counted), so a run can say early
    what it will cost."""
    model.train()
    t0 = time.perf_counter()
    total_loss, n, hits = 0.0, 0, 0
    bar = progress_bar(loader, progress, desc, len(loader))
    nb = device.type == "cuda"
    for step, batch in enumerate(bar):
        image, coords, mask = batch_inputs(batch, device)
        target = (batch["soft"] if soft else batch["label"]).to(device, non_blocking=nb)
        with autocast(device, amp_dtype):
            if "label_fine" in batch:  # fine regions: cross-entropy on them, regions by log-sum-exp
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
        total_loss += float(loss.detach()) * b  # .item()-like sync once per step: cheap next to the step
        hits += int((logits.detach().argmax(1).cpu() == batch["label"]).sum())
        n += b
        if pace is not None:  # steps 1..10 (or 30 s of them): the loader's prefetched batches used up
            if step == 0:
                t_first = time.perf_counter()
            elif step >= 10 or time.perf_counter() - t_first >= 30:
                pace((time.perf_counter() - t_first) / step)
                pace = None
        if step % 10 == 0 and hasattr(bar, "set_postfix"):
            bar.set_postfix(
                loss=f"{total_loss / n:.3f}", top1=f"{hits / n:.3f}", samples_s=f"{n / (time.perf_counter() - t0):.0f}"
            )
    return {
        "loss": total_loss / max(n, 1),
        "top1": hits / max(n, 1),
        "n": n,
        "lr": scheduler.get_last_lr()[0],
        "time_s": time.perf_counter() - t0,
    }


def _merge(parts: list[dict]) -> dict:
    """Concatenate per-rank predictions and restore frame order."""
    merged = {k: (np.concatenate([p[k] for p in parts]) if parts[0][k] is not None else None) for k in parts[0]}
    order = np.argsort(merged["index"], kind="stable")
    return {k: (v[order] if v is not None else None) for k, v in merged.items()}


def validate(
    model: torch.nn.Module,
    loader,
    loss_fn: torch.nn.Module,
    device: torch.device,
    info: D.DistInfo = D.DistInfo(),
    *,
    amp_dtype: torch.dtype | None = None,
    soft: bool = False,
    progress: bool = False,
) -> dict:
    """Loss and top-1/3/5 over the whole validation split (predictions of all processes gathered)."""
    t0 = time.perf_counter()
    pred = _merge(
        D.gather_objects(predict_batches(model, loader, device, amp_dtype=amp_dtype, progress=progress), info)
    )
    logits = torch.from_numpy(pred["logits"])
    target = torch.from_numpy(pred["soft"]) if soft else torch.from_numpy(pred["label"])
    alpha = None if loss_fn.alpha is None else loss_fn.alpha.cpu()
    loss = float(focal_loss(logits, target, alpha, loss_fn.gamma)) if len(logits) else float("nan")
    return {
        "loss": loss,
        **topk_accuracy(pred["logits"], pred["label"]),
        "n": int(len(logits)),
        "time_s": time.perf_counter() - t0,
        "predictions": pred,
    }
