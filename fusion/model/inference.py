"""Batched inference: logits of a model over a DataLoader of input dicts, with optional mixed precision.

Used by training (validation), evaluation and robustness sweeps alike, so every figure
comes from the same forward pass. Batches are the dicts :class:`fusion.model.inputs.Preprocessor`
items collate to (``image`` optional: geometry-only models and the detections stream have none).
"""

from __future__ import annotations

import contextlib
import sys

import torch


def autocast_dtype(amp: str, device: torch.device) -> torch.dtype | None:
    """Mixed-precision dtype on CUDA (``train.amp``: auto, bf16, fp16, off); None (full precision) on CPU."""
    if device.type != "cuda" or amp == "off":
        return None
    if amp == "auto":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    return {"bf16": torch.bfloat16, "fp16": torch.float16}[amp]


def autocast(device: torch.device, dtype: torch.dtype | None):
    """``torch.autocast`` for ``dtype``, or a no-op context when None."""
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


def batch_inputs(batch: dict, device: torch.device) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]:
    """(image or None, coords, mask) of a collated batch, on ``device``; a stream batch's stored ADU
    (``image_adu`` + ``image_stretch``, ``stream.image_transfer``) are stretched there."""
    nb = device.type == "cuda"
    image = batch.get("image")
    if image is not None:
        image = image.to(device, non_blocking=nb)
    elif "image_adu" in batch:
        from .inputs import stretch_torch

        image = stretch_torch(batch["image_adu"].to(device, non_blocking=nb), *batch["image_stretch"].tolist())
    return image, batch["coords"].to(device, non_blocking=nb), batch["mask"].to(device, non_blocking=nb)


def progress_bar(iterable, enabled: bool, desc: str, total: int | None = None):
    """tqdm over ``iterable`` when enabled and stderr is a terminal; the iterable itself otherwise."""
    if not (enabled and sys.stderr.isatty()):
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, desc=desc, total=total, leave=False, dynamic_ncols=True)


@torch.no_grad()
def predict_batches(
    model: torch.nn.Module,
    loader,
    device: torch.device,
    *,
    amp_dtype: torch.dtype | None = None,
    progress: bool = False,
    desc: str = "eval",
) -> dict:
    """Logits, labels, soft targets (if any) and frame indices of ``loader`` (numpy arrays; None when absent)."""
    model.eval()
    out = {"logits": [], "label": [], "index": [], "soft": []}
    for batch in progress_bar(loader, progress, desc, len(loader)):
        image, coords, mask = batch_inputs(batch, device)
        with autocast(device, amp_dtype):
            logits = model(image, coords, mask)
        out["logits"].append(logits.float().cpu())
        out["label"].append(batch["label"])
        out["index"].append(batch["index"])
        if "soft" in batch:
            out["soft"].append(batch["soft"])

    def cat(xs):
        return torch.cat(xs).numpy() if xs else None

    return {k: cat(v) for k, v in out.items()}
