"""``skygen preview``: a PNG grid of stored frames with detections and true stars overlaid.

Frames are shown with an asinh stretch around the background. Circles: detections
(green: matched to a catalog star, red: false). Small crosses: true stars down to half a
magnitude below the detection limit. Positions are
converted from full-resolution to stored pixels with :func:`conventions.full_to_stored`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skygen.conventions import full_to_stored
from skygen.datasets.shards import open_dataset
from skygen.errors import ConfigError, DatasetError


def check_preview_args(out: Path, n: int, start: int) -> None:
    """Refuse what would write nothing useful or somewhere unexpected (ConfigError)."""
    if n < 1:
        raise ConfigError(f"--n {n}: show at least 1 frame")
    if start < 0:
        raise ConfigError(f"--start {start}: must be 0 or more (a position within the split)")
    if out.suffix.lower() != ".png":
        raise ConfigError(f"--out {out}: the preview is a PNG; give a file name ending in .png")
    if not out.parent.is_dir():
        raise ConfigError(f"--out {out}: folder {out.parent} does not exist; create it first or choose another path")


def preview(path, out, n: int = 12, split: str | None = None, start: int = 0) -> Path:
    """Write a PNG grid of ``n`` frames of ``split`` (all frames if None) from position ``start``."""
    out = Path(out)
    check_preview_args(out, n, start)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open_dataset(path) as ds:
        all_idx = ds.indices(split)
        if len(all_idx) == 0:
            raise DatasetError(
                f"{path}: split {split!r} holds no frames (frames per split: "
                f"{ {s: len(ds.indices(s)) for s in ('train', 'val', 'test')} })"
            )
        if start >= len(all_idx):
            raise ConfigError(
                f"--start {start}: the {split or 'whole dataset'} holds only {len(all_idx)} frames "
                f"(positions 0..{len(all_idx) - 1})"
            )
        idx = all_idx[start : start + n]
        cols = min(4, max(1, len(idx)))
        rows = int(np.ceil(len(idx) / cols)) or 1
        fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 4.0 * rows), squeeze=False)
        f = ds.downsample_factor
        for ax in axes.ravel():
            ax.axis("off")
        for ax, i in zip(axes.ravel(), idx):
            img = ds.image(int(i)).astype(np.float32)
            bg = np.median(img)
            noise = max(np.std(img[img < np.percentile(img, 90)]), 0.5)
            ax.imshow(np.arcsinh((img - bg) / (3 * noise)), cmap="gray", vmin=-0.5, vmax=4, origin="upper")
            t = ds.true_stars(int(i))
            lim = ds.manifest.get("detection_limit_mag")
            if lim is not None:  # stars far below the detection limit would only clutter the view
                t = {k: v[t["mag"] <= lim + 0.5] for k, v in t.items()}
            ax.plot(full_to_stored(t["x_px"], f), full_to_stored(t["y_px"], f), "+", color="#4aa3ff", ms=4, mew=0.6)
            d = ds.detections(int(i))
            ok = d["hip_id"] >= 0
            for sel, colour in ((ok, "#3cdc5a"), (~ok, "#ff4040")):
                ax.scatter(
                    full_to_stored(d["x_px"][sel], f),
                    full_to_stored(d["y_px"][sel], f),
                    s=60,
                    facecolors="none",
                    edgecolors=colour,
                    linewidths=0.8,
                )
            b = ds.boresight
            ax.set_title(
                f"#{ds.frames['index'][i]} RA {b['ra_deg'][i]:.1f} Dec {b['dec_deg'][i]:+.1f} "
                f"roll {b['roll_deg'][i]:.0f}\n{len(d['x_px'])} det ({int(ok.sum())} matched), "
                f"{len(t['x_px'])} stars",
                fontsize=7,
            )
            ax.set_xlim(-0.5, img.shape[1] - 0.5)
            ax.set_ylim(img.shape[0] - 0.5, -0.5)
        fig.suptitle(
            f"{path}: green = matched detection, red = false detection, + = true star (to 0.5 mag below the detection "
            f"limit)",
            fontsize=8,
        )
        fig.tight_layout()
        fig.savefig(out, dpi=90)
        plt.close(fig)
    return out
