"""What each view of a tied model knows: region top-1 of the fused output, the detections alone and the
image's peaks alone, on whole frames, few-star frames and frames with noisy photometry.

A model with the tied image view (``model.image_backbone=peak_rows``, configs/cpu-views.yaml) reads the
frame twice through one network: its detections, and the strongest peaks of its stored pixels as
flux-free rows; its output is the two views' mean log-probability. This script scores, on the same
test frames:

- ``fused``: what ``fusion evaluate`` scores (both views);
- ``detections``: the model without its image (``model(None, coords, mask)``);
- ``image``: the peaks alone (``model(None, *model.image.rows(image))``; the same in every cell);
- ``detections, no flux``: the detections with every flux feature 0 (the rows ``model.flux_dropout``
  trains on; a model without it has never seen them);
- ``image, pixel flux`` and ``fused, pixel flux`` (a model whose image view has no flux only): a probe,
  the same peaks given a flux measured from the pixels by the model's own code for
  ``model.peaks.pixel_flux`` (:meth:`fusion.model.networks.PeakRows.measure`: the log stretch inverted with
  the preprocessor's constants, the 5 x 5 stored-pixel sum above the frame's median, times the binning
  factor squared: the detector's ADU scale; peaks whose brightest pixel holds more than
  ``--max-peak-share`` of that sum dropped as hot pixels and cosmic-ray hits), and its fusion with the
  detections as the model fuses its views. A model trained with ``pixel_flux`` scores this in its own
  ``image`` and ``fused`` columns;
- ``image weight A`` (``--image-weight A ...``): the views fused with weights 1 - A and A instead of the
  model's own (the image view as in ``fused``, or the probe's).

``--choose-weight`` (a model trained with ``model.peaks.pixel_flux``; run it on the validation split)
also searches ``model.peaks.image_weight`` and ``image_weight_stars`` (the image view's weight at few
and at many detections, linear in the count between) on a grid, by the mean top-1 over the clean cells
(whole frames, the brightest 3 / 4 / 6, and the whole frames of each ``--extra-data`` dataset, e.g.
corrupted frames), with the model's own code (``StarFusion.view_weight``), and prints the best settings
beside the model's own. Several checkpoints pool their frames (e.g. three seeds of one preset).

Cells: whole frames, the brightest 3 / 4 / 6 detections (the image untouched, as ``fusion evaluate
--brightest N``), and the brightest 6 after magnitude noise (each detection's flux scaled by
10^(-0.4 m), m ~ N(0, sigma), then re-ranked, as a detector ranks by measured flux; the pixels are left
as rendered). Prints a Markdown table; ``--out`` also writes it with the command and hardware::

    python benchmarks/tied_views.py --checkpoint runs/views/best.pt --data data/experiment-cpu30 \
        --out results/cpu30/views/tied-views.md
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from fusion.model.checkpoint import load_checkpoint
from fusion.model.networks import UNEXPLAINED_TOL_PX, PeakRows, StarFusion, unexplained_share
from fusion.model.shards import FrameDataset, boresight_vectors, split_positions
from skygen.datasets.shards import open_dataset
from skygen.runtime import hardware_line


def cells(noise: list[float]) -> list[tuple[str, int | None, float]]:
    """(label, brightest N or None, magnitude noise rms)."""
    out: list[tuple[str, int | None, float]] = [("whole frame", None, 0.0)]
    out += [(f"brightest {n}", n, 0.0) for n in (3, 4, 6)]
    out += [(f"brightest 6, {s:g} mag noise", 6, s) for s in noise]
    return out


def batch(fd: FrameDataset, js, n: int | None, sigma: float, seed: int) -> tuple[torch.Tensor, ...]:
    """Images, rows, masks and labels of frames ``js`` for one cell."""
    items = []
    for j in js:
        s = fd.sample(int(j))
        if sigma > 0:
            rng = np.random.default_rng([seed, int(fd.positions[j])])
            s = replace(s, flux_adu=s.flux_adu * 10 ** (-0.4 * rng.normal(0.0, sigma, s.n))).sorted()
        item = fd.pre.item(s)
        if n is not None:
            item["mask"][n:] = False
            item["coords"][n:] = 0.0
        items.append(item)
    image = torch.stack([torch.as_tensor(it["image"]) for it in items])
    coords = torch.stack([torch.as_tensor(it["coords"]) for it in items])
    mask = torch.stack([torch.as_tensor(it["mask"]) for it in items])
    return image, coords, mask, torch.as_tensor(fd.labels[np.asarray(js)])


def pixel_flux_view(model, pre, share: float) -> PeakRows:
    """The tied view of ``model`` with ``model.peaks.pixel_flux`` switched on (the model's own code,
    :meth:`PeakRows.measure`): the probe's peaks measured from the pixels, defects above ``share`` dropped."""
    p = model.image.backbone
    return PeakRows(
        p.max_peaks,
        p.threshold,
        p.max_sharpness,
        stretch=pre.stretch(),
        area=float(pre.geo.factor) ** 2,
        log_flux_offset=pre.log_flux_offset,
        max_peak_share=share,
    )


def non_star_bright_peaks(ds, fd, rows: torch.Tensor, mask: torch.Tensor, js, top: int = 3) -> int:
    """How many of frames ``js`` have, among their ``top`` brightest peaks (``rows``, pixel flux order),
    one with no catalogue star (the dataset's true stars) within 2 full-resolution px."""
    n = 0
    for b, j in enumerate(js):
        ts = ds.true_stars(int(fd.positions[j]))
        tx, ty = fd.geo.normalised(ts["x_px"], ts["y_px"])
        for row in rows[b, mask[b]][:top]:
            d = np.hypot(tx - float(row[0]), ty - float(row[1]))
            if not len(d) or d.min() > 2 * 2 / fd.geo.sensor_px:
                n += 1
                break
    return n


def weight_grid(model, kept: dict[str, list], show: int = 8, by: str = "count") -> list[str]:
    """Markdown lines: the best ``show`` settings of the image view's weight on the kept cells by their mean
    top-1, and the model's own, each fused by the model's ``view_weight``: (image_weight, image_weight_stars)
    with ``by="count"``, (image_weight, image_weight_unexplained) with ``by="unexplained"``."""
    cells = {lab: [torch.cat(parts) for parts in zip(*batches)] for lab, batches in kept.items()}
    keys = ("image_weight_by", "image_weight", "image_weight_stars", "image_weight_unexplained")
    own = {k: getattr(model, k) for k in keys}

    def score(how: str, weight, second) -> list[float]:
        model.image_weight_by, model.image_weight = how, weight
        if how == "count":
            model.image_weight_stars = second
        else:
            model.image_weight_unexplained = second
        out = []
        for det, img, mask, pmask, share, y in cells.values():
            w = model.view_weight(mask, pmask, share)[:, None]
            out.append(100 * float((((1 - w) * det + w * img).argmax(dim=1) == y).float().mean()))
        return out

    grid = []
    if by == "count":
        seconds: list = [(a, b) for a in (3, 4, 5, 6) for b in (4, 6, 8, 10, 12, 16, 20) if b >= a]
    else:
        seconds = [(a, b) for a in (0.0, 0.05, 0.1, 0.15, 0.2) for b in (0.2, 0.3, 0.4, 0.5, 0.6, 0.8) if b > a]
    for few in (0.3, 0.4, 0.5, 0.6, 0.7):
        for many in (0.0, 0.05, 0.1, 0.2, 0.3, 0.5):
            for second in seconds:
                grid.append(((few, many), second, score(by, (few, many), second)))
    own_how = own["image_weight_by"]
    own_second = own["image_weight_stars"] if own_how == "count" else own["image_weight_unexplained"]
    own_row = (own["image_weight"], own_second, score(own_how, own["image_weight"], own_second))
    for k, v in own.items():
        setattr(model, k, v)
    grid.sort(key=lambda g: -float(np.mean(g[2])))
    labels = list(cells)
    col = "image_weight_stars" if by == "count" else "image_weight_unexplained"
    lines = [
        f"Image-view weight searched (`--choose-weight`, by {by}): top-1 (%) per cell, best "
        f"{show} of {len(grid)} settings by their mean, and the model's own "
        f"({own['image_weight_by']}, last row):",
        "",
        f"| image_weight | {col} | " + " | ".join(labels) + " | mean |",
        "|---|---|" + "---|" * (len(labels) + 1),
    ]
    for (few, many), second, sc in [*grid[:show], own_row]:
        lines.append(
            f"| [{few:g}, {many:g}] | [{second[0]:g}, {second[1]:g}] | "
            + " | ".join(f"{v:.1f}" for v in sc)
            + f" | {np.mean(sc):.2f} |"
        )
    return lines


def score(path: str, a: argparse.Namespace) -> tuple[list[str], StarFusion, dict[str, list]]:
    """The table's lines for one checkpoint, its model, and (``--choose-weight``) its clean cells'
    per-frame view log-probabilities."""
    ckpt = load_checkpoint(path)
    model, cfg = ckpt.build_model().eval(), ckpt.fusion_config
    tied = bool(getattr(model, "tied_view", False))

    def frames(data: str) -> FrameDataset:
        ds = open_dataset(data)
        pos = split_positions(ds, a.split, a.frames)
        return FrameDataset(
            ds,
            pos,
            ckpt.regions.assign(boresight_vectors(ds, pos)),
            max_stars=ckpt.max_stars,
            norm_scale_adu=cfg.data.norm_scale_adu,
            log_flux_offset=cfg.data.log_flux_offset,
        )

    fd = frames(a.data)
    ds, pos = fd.ds, fd.positions
    todo = [(label, fd, n, sigma) for label, n, sigma in cells(a.noise)]
    todo += [(f"whole frame, {Path(d).name}", frames(d), None, 0.0) for d in a.extra_data]
    views = ["detections", "detections, no flux"]
    probe = None
    if tied and not model.image.backbone.pixel_flux:
        probe = pixel_flux_view(model, fd.pre, a.max_peak_share)
        views = ["fused", "detections", "image", "detections, no flux", "image, pixel flux", "fused, pixel flux"]
    elif tied:  # the model's own image view measures pixel fluxes: no probe
        views = ["fused", "detections", "image", "detections, no flux"]
    if tied:
        views += [f"image weight {w:g}" for w in a.image_weight]
    if a.choose_weight and not (tied and model.image.backbone.pixel_flux):
        raise SystemExit(
            "--choose-weight: the checkpoint's image view must measure pixel fluxes (model.peaks.pixel_flux)"
        )
    rows = []
    kept: dict[str, list] = {}  # clean cells, for --choose-weight: (det log-p, image log-p, mask, peak mask, y)
    non_star = 0
    with torch.no_grad():
        for label, fd, n, sigma in todo:
            hits: dict[str, list] = {v: [] for v in views}
            for start in range(0, len(fd), 64):
                image, coords, mask, y = batch(fd, range(start, min(start + 64, len(fd))), n, sigma, a.seed)
                flat = torch.cat([coords[..., :2], torch.zeros_like(coords[..., 2:3]), coords[..., 3:]], dim=-1)
                out = {"detections": model(None, coords, mask), "detections, no flux": model(None, flat, mask)}
                if tied:
                    out["fused"] = model(image, coords, mask)
                    rows0, mask0 = model.image.rows(image)  # the tied view's peaks, read once per batch
                    out["image"] = model(None, rows0, mask0)
                    prow, pmask = (rows0, mask0) if probe is None else probe.measure(image, rows0, mask0)
                    if probe is not None:
                        out["image, pixel flux"] = model(None, prow, pmask)
                        lp = torch.log_softmax(out["detections"], -1) + torch.log_softmax(out["image, pixel flux"], -1)
                        out["fused, pixel flux"] = lp
                    img = torch.log_softmax(out["image" if probe is None else "image, pixel flux"], -1)
                    for w in a.image_weight:
                        out[f"image weight {w:g}"] = (1 - w) * torch.log_softmax(out["detections"], -1) + w * img
                    if a.choose_weight and sigma == 0:
                        det = torch.log_softmax(out["detections"], -1)
                        tol = UNEXPLAINED_TOL_PX * 2.0 / image.shape[-1]
                        share = unexplained_share(prow, pmask, coords, mask, tol)
                        kept.setdefault(label, []).append((det, img, mask, pmask, share, y))
                    if label == "whole frame" and (probe is not None or model.image.backbone.pixel_flux):
                        js = range(start, min(start + 64, len(pos)))
                        non_star += non_star_bright_peaks(ds, fd, prow, pmask, js)
                for v in views:
                    hits[v].append((out[v].argmax(dim=1) == y).numpy())
            rows.append((label, {v: 100 * float(np.concatenate(h).mean()) for v, h in hits.items()}))
    lines = [
        f"Region top-1 (%) of `{path}` (K = {ckpt.num_classes}) on the {len(pos)} {a.split} frames of `{a.data}`:",
        "",
        "| cell | " + " | ".join(views) + " |",
        "|---|" + "---|" * len(views),
    ]
    lines += [f"| {lab} | " + " | ".join(f"{r[v]:.1f}" for v in views) + " |" for lab, r in rows]
    if tied and (probe is not None or model.image.backbone.pixel_flux):
        lines += [
            "",
            f"Frames with a peak among their three brightest (pixel flux) that no catalogue star explains "
            f"(none within 2 px): {non_star} of {len(pos)}.",
        ]
    return lines + [""], model, kept


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--checkpoint",
        required=True,
        nargs="+",
        help="fusion checkpoints (best.pt), each scored in its own table; --choose-weight pools their frames",
    )
    ap.add_argument("--data", required=True, help="a skygen dataset of the checkpoint's camera")
    ap.add_argument("--split", default="test", help="split to score (default test)")
    ap.add_argument("--frames", type=int, help="first N frames of the split (default all)")
    ap.add_argument("--noise", type=float, nargs="*", default=[0.25, 0.5], help="magnitude noise cells, mag rms")
    ap.add_argument("--seed", type=int, default=0, help="seed of the magnitude noise")
    ap.add_argument(
        "--image-weight",
        type=float,
        nargs="*",
        default=[],
        metavar="A",
        help="also score (1 - A) x the detections' log-probability + A x the image view's (the model fuses with "
        "A = 0.5; the image view: the model's own, or the probe's when it has no pixel flux)",
    )
    ap.add_argument(
        "--max-peak-share",
        type=float,
        default=0.9,
        help="the probe's defect cut (model.peaks.max_peak_share; default 0.9)",
    )
    ap.add_argument(
        "--choose-weight",
        action="store_true",
        help="also grid-search model.peaks.image_weight / image_weight_stars by the mean top-1 of the clean cells "
        "(a pixel-flux model; use --split val)",
    )
    ap.add_argument(
        "--weight-by",
        choices=("count", "unexplained"),
        default="count",
        help="--choose-weight: what the searched weight moves with (model.peaks.image_weight_by)",
    )
    ap.add_argument(
        "--extra-data",
        nargs="*",
        default=[],
        metavar="DIR",
        help="more datasets of the checkpoint's camera (e.g. corrupted frames), whose whole frames of the same "
        "split are one more cell each (and count in --choose-weight)",
    )
    ap.add_argument("--out", type=Path, help="also write the table (Markdown) here")
    a = ap.parse_args(argv)
    lines, kept, model = [], {}, None
    for path in a.checkpoint:
        text, model, cells_kept = score(path, a)
        lines += text
        for label, batches in cells_kept.items():  # pooled over checkpoints: the same frames once per model
            kept.setdefault(label, []).extend(batches)
    if a.choose_weight:
        lines += weight_grid(model, kept, by=a.weight_by) + [""]
    lines += [
        "command: `python benchmarks/tied_views.py " + " ".join(argv or sys.argv[1:]) + "`",
        f"hardware: {hardware_line()} (top-1 does not depend on it)",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
