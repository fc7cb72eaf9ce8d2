"""Figures of a run (the paper's Figure 4 a/b) and of an evaluation (confusion matrix).

Matplotlib with the non-interactive Agg backend; every PNG is written atomically.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from skygen.runtime import atomic_write_bytes


def _figure():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())


def plot_loss_curves(history: list[dict], path: str | Path) -> None:
    """Loss per epoch (left) and accuracy in percent (right, its own readable axis), with the
    epoch kept as ``best.pt`` (lowest validation loss) marked in both (Figure 4a)."""
    plt = _figure()
    ep = [h["epoch"] for h in history]
    best = [h["epoch"] for h in history if h.get("best")]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    ax.plot(ep, [h["train_loss"] for h in history], "o-", label="train loss")
    ax.plot(ep, [h["val_loss"] for h in history], "s-", label="val loss")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss")
    ax.set_title("loss")
    top1 = [100 * h["val_top1"] for h in history]
    ax2.plot(ep, [100 * h["train_top1"] for h in history], "o-", label="train top-1")
    ax2.plot(ep, top1, "s-", label="val top-1")
    ax2.plot(ep, [100 * h["val_top3"] for h in history], "^:", label="val top-3")
    lo = min(top1 + [100 * h["train_top1"] for h in history])
    ax2.set_ylim(max(0.0, lo - 5), 100)
    ax2.set_xlabel("epoch")
    ax2.set_ylabel("accuracy (%)")
    ax2.set_title("accuracy")
    if best:
        b = best[-1]
        for a in (ax, ax2):
            a.axvline(b, color="0.5", ls="--", lw=1, label=f"best.pt (epoch {b}, lowest val loss)")
    for a in (ax, ax2):
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    _save(fig, path)
    plt.close(fig)


def plot_lr_schedule(planned_lr: np.ndarray, steps_per_epoch: int, history: list[dict], path: str | Path) -> None:
    """The planned learning rate per optimiser step, with the applied value at each epoch end (Figure 4b)."""
    plt = _figure()
    fig, ax = plt.subplots(figsize=(6, 4))
    x = (np.arange(len(planned_lr)) + 1) / max(steps_per_epoch, 1)
    ax.plot(x, planned_lr, "-", label="planned (warm-up + cosine)")
    ax.plot([h["epoch"] for h in history], [h["lr"] for h in history], "o", label="applied (end of epoch)")
    ax.set_xlabel("epoch")
    ax.set_ylabel("learning rate")
    ax.set_yscale("log")
    ax.legend()
    ax.set_title("learning-rate schedule")
    _save(fig, path)
    plt.close(fig)


def plot_confusion(cm: np.ndarray, path: str | Path, title: str = "confusion matrix") -> None:
    """Row-normalised confusion matrix (row = true class), counts annotated when K is small."""
    plt = _figure()
    k = len(cm)
    rows = cm.sum(axis=1, keepdims=True)
    norm = np.divide(cm, rows, out=np.zeros(cm.shape, float), where=rows > 0)
    size = min(4 + 0.35 * k, 16)
    fig, ax = plt.subplots(figsize=(size, size))
    im = ax.imshow(norm, vmin=0, vmax=1, cmap="viridis")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="share of true class")
    if k <= 20:
        for i in range(k):
            for j in range(k):
                if cm[i, j]:
                    ax.text(
                        j,
                        i,
                        str(cm[i, j]),
                        ha="center",
                        va="center",
                        fontsize=7,
                        color="black" if norm[i, j] > 0.5 else "white",
                    )
    ax.set_xlabel("predicted class")
    ax.set_ylabel("true class")
    ax.set_title(title)
    _save(fig, path)
    plt.close(fig)
