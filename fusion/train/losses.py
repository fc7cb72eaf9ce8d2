"""Focal loss with class weights, for hard labels and for soft (geometry-aware) targets.

For sample i with target distribution q_i (one-hot for hard labels) and predicted
probabilities p_i = softmax(logits_i), the paper's loss is

    FL_i = - sum_c alpha_c q_ic (1 - p_ic)^gamma log p_ic.

The batch loss is the **weighted mean** ``sum_i FL_i / sum_i sum_c alpha_c q_ic`` — the
normalisation ``torch.nn.functional.cross_entropy(weight=alpha)`` uses. So at gamma = 0
the loss *is* class-weighted cross-entropy, and with uniform alpha it is plain
cross-entropy, whatever the scale of alpha (the paper's alpha sums to 1, which would
otherwise shrink the loss by K). With soft targets it is the weighted cross-entropy
against q (gamma = 0) or its focal version.

Class weights ``alpha`` come from :func:`fusion.labels.class_weights`: balanced
``N/(K n_c)`` L1-normalised (sums to 1), or uniform 1/K.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def focal_loss(
    logits: torch.Tensor, target: torch.Tensor, alpha: torch.Tensor | None = None, gamma: float = 2.0
) -> torch.Tensor:
    """Weighted-mean focal loss. ``target``: (B,) class indices or (B, K) distributions."""
    logp = F.log_softmax(logits.float(), dim=-1)
    k = logits.shape[-1]
    q = F.one_hot(target, k).to(logp.dtype) if target.dim() == 1 else target.to(logp.dtype)
    w = q if alpha is None else q * alpha.to(logp.dtype)[None, :]
    mod = (1.0 - logp.exp()).clamp(min=0.0).pow(gamma) if gamma != 0 else 1.0
    per_sample = -(w * mod * logp).sum(dim=-1)
    return per_sample.sum() / w.sum().clamp(min=torch.finfo(logp.dtype).tiny)


class FocalLoss(nn.Module):
    """:func:`focal_loss` with a fixed ``alpha`` (a buffer, so it follows the model's device)."""

    def __init__(self, alpha: torch.Tensor | None = None, gamma: float = 2.0):
        super().__init__()
        self.gamma = float(gamma)
        self.register_buffer("alpha", None if alpha is None else torch.as_tensor(alpha, dtype=torch.float32))

    def forward(self, logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return focal_loss(logits, target, self.alpha, self.gamma)

    def extra_repr(self) -> str:
        return f"gamma={self.gamma}"
