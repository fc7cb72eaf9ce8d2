"""Roll handling: rotate a detection set about the image centre into a canonical orientation.

A star tracker's roll about its boresight is arbitrary (skygen draws it uniformly in
[0°, 360°)), and the boresight label does not depend on it. A model that sees raw
sensor-frame coordinates must learn that invariance from data. Instead, every input is
rotated about the optical axis (the sensor centre, normalised coordinates (0, 0)) so that
a *reference star* lies on the +x axis. Any rotation of the input then gives the same
canonical rows, so the model's output is invariant to roll by construction (exactly, up to
float rounding; ``tests/test_canonical.py``).

Choice of reference (``model.canonical.mode``)
    ``none``       raw sensor-frame rows (the paper's input; kept for the ablation);
    ``brightest``  the brightest detection at least ``min_radius`` from the centre (a star
                   at the centre defines no direction);
    ``nearest``    the detection nearest the centre at least ``min_radius`` from it: a
                   reference that photometry cannot move. Magnitude noise of a few tenths
                   reorders the brightest stars of most frames (the brightest two of a
                   frame are often within 0.3 mag), and each reorder turns the
                   ``brightest`` frame by the angle between them; the detection nearest the
                   centre changes only when it is itself lost (dropout, the few-star cut) or
                   a false star lands nearer. Centroid noise turns it more (a 1 px error at
                   radius r turns the frame by 1 / r rad), so its ``min_radius`` should be
                   larger than ``brightest``'s (``configs/cpu-few-mag.yaml``: 0.15);
    ``multi``      each of the ``n_refs`` brightest such detections in turn: the model is
                   evaluated once per reference and the class probabilities are averaged.
                   In training one of them is drawn per sample, so the network learns to
                   work from any of them. A reference lost to dropout, or a false star that
                   outshines the real ones, then spoils only one of ``n_refs`` views. But the
                   network must learn ``n_refs`` canonical frames instead of one: at the
                   1 M-sample budget of ``configs/cpu.yaml``, ``brightest`` scored higher on clean
                   *and* on corrupted frames (``results/cpu/presets/presets.md``), so that preset
                   uses it; ``cpu-best.yaml`` uses ``multi``.

Convention: rows are ``[x, y, log_flux]`` with x, y normalised to [-1, 1] over the sensor
(:mod:`fusion.data`; y on the same scale), y growing downwards. Rotating by ``-theta`` (``theta = atan2(y_ref,
x_ref)``) maps the reference onto ``(r_ref, 0)``. The image, when ``model.canonical.image``
is on, is resampled with the same rotation (bilinear, zeros outside), so image, heatmap
and coordinate rows stay in agreement.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

MODES = ("none", "brightest", "nearest", "multi")


def reference_rows(
    coords: torch.Tensor, mask: torch.Tensor, n_refs: int, min_radius: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Row indices (B, n_refs) of the candidate references (brightest first) and their validity (B, n_refs).

    Rows must be sorted brightest first (as :mod:`fusion.data` and the streams give them).
    Invalid references (fewer eligible stars than ``n_refs``) point at the first candidate,
    or at row 0 when there is none.
    """
    r = torch.linalg.vector_norm(coords[..., :2], dim=-1)
    ok = mask & (r >= min_radius)
    m = ok.shape[1]
    # rank of each eligible row among the eligible ones (brightness order = row order)
    rank = torch.cumsum(ok.long(), dim=1) - 1
    big = torch.full_like(rank, m + n_refs + 1)
    key = torch.where(ok, rank, big)  # (B, M)
    targets = torch.arange(n_refs, device=coords.device)
    hit = key[:, :, None] == targets[None, None, :]  # (B, M, R)
    valid = hit.any(dim=1)  # (B, R)
    rows = torch.argmax(hit.to(torch.int8), dim=1)  # first matching row, 0 if none
    first = rows[:, :1].expand_as(rows)
    rows = torch.where(valid, rows, first)
    return rows, valid


def nearest_row(coords: torch.Tensor, mask: torch.Tensor, min_radius: float) -> torch.Tensor:
    """Row index (B, 1) of the detection nearest the centre at least ``min_radius`` from it; row 0
    where no detection qualifies (the padding row of an empty sample, or a star at the centre)."""
    r = torch.linalg.vector_norm(coords[..., :2], dim=-1)
    ok = mask & (r >= min_radius)
    key = torch.where(ok, r, torch.full_like(r, 1e9))  # finite: ArgMin of +inf rows is not portable in ONNX
    return torch.argmin(key, dim=1, keepdim=True)


def angles_of(coords: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """Angle (rad) of the reference rows: (B, R).

    A reference at exactly (0, 0) (a sample with no detection: the padding row) has x
    replaced by 1 / x = ±inf of the same sign. ``atan2`` gives the same angle for both
    (IEEE 754: atan2(±0, ±0) = atan2(±0, ±inf)), so PyTorch's result does not change; but
    ONNX has no Atan2, exporters build it from ``Atan(y / x)``, and 0 / 0 = NaN spread
    through the whole sample's logits.
    """
    idx = rows[..., None].expand(-1, -1, coords.shape[-1])
    ref = torch.gather(coords, 1, idx)  # (B, R, F)
    x, y = ref[..., 0], ref[..., 1]
    x = torch.where((x == 0) & (y == 0), torch.reciprocal(x), x)
    return torch.atan2(y, x)


def rotate_rows(coords: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Rotate rows (B, M, F) by ``-theta`` (B,) about the centre; features beyond x, y unchanged."""
    c, s = torch.cos(theta)[:, None], torch.sin(theta)[:, None]
    x, y = coords[..., 0], coords[..., 1]
    xr = c * x + s * y
    yr = -s * x + c * y
    return torch.cat([xr[..., None], yr[..., None], coords[..., 2:]], dim=-1)


def rotate_image(image: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Resample (B, C, H, W) images so that content at angle ``theta`` lands on +x (bilinear)."""
    c, s = torch.cos(theta).to(image.dtype)[:, None, None], torch.sin(theta).to(image.dtype)[:, None, None]
    # output pixel p samples the input at R(theta) p on the align_corners=False normalised grid: what
    # F.affine_grid computes, written out because ONNX has affine_grid only from opset 20 (GridSample: 16)
    h, w = image.shape[-2:]
    xs = ((torch.arange(w, device=image.device, dtype=image.dtype) * 2 + 1) / w - 1)[None, None, :]
    ys = ((torch.arange(h, device=image.device, dtype=image.dtype) * 2 + 1) / h - 1)[None, :, None]
    grid = torch.stack([c * xs - s * ys, s * xs + c * ys], dim=-1)
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def canonical_views(
    coords: torch.Tensor, mask: torch.Tensor, mode: str, n_refs: int, min_radius: float, training: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """The canonical inputs: ``(coords_v, mask_v, theta_v, views)``.

    ``views`` = 1 for ``brightest``, ``nearest`` and for ``multi`` while training (one reference drawn
    per sample with torch's global generator), ``n_refs`` for ``multi`` in evaluation;
    the returned tensors are (B * views, ...), view-major within each sample, and
    ``valid`` views are signalled by ``mask_v`` (an invalid view repeats the first).
    """
    if mode == "nearest":
        rows, training = nearest_row(coords, mask, min_radius), False
    else:
        if mode == "brightest":
            n_refs, training = 1, True
        rows, valid = reference_rows(coords, mask, n_refs, min_radius)
    if training:
        n_valid = valid.sum(dim=1).clamp(min=1)
        pick = (torch.rand(coords.shape[0], device=coords.device) * n_valid).long().clamp(max=n_refs - 1)
        rows = torch.gather(rows, 1, pick[:, None])
    theta = angles_of(coords, rows)  # (B, V)
    views = theta.shape[1]
    b = coords.shape[0]
    cv = coords.repeat_interleave(views, dim=0)
    mv = mask.repeat_interleave(views, dim=0)
    tv = theta.reshape(b * views)
    return rotate_rows(cv, tv), mv, tv, views


def view_weights(coords: torch.Tensor, mask: torch.Tensor, n_refs: int, min_radius: float) -> torch.Tensor:
    """(B, n_refs) weights of the evaluation views: 1 for a real reference, 0 for a repeat
    (a sample with no eligible star keeps its single, arbitrary view)."""
    _, valid = reference_rows(coords, mask, n_refs, min_radius)
    w = valid.to(coords.dtype)
    none = w.sum(dim=1) == 0
    w[none, 0] = 1.0
    return w
