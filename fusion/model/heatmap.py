"""Rasterise detected stars as Gaussians on a fixed canvas, in torch, on the model's device.

The canvas (``canvas_px`` x ``canvas_px``) covers the whole sensor: canvas pixel j has
its centre at normalised coordinate ``(j + 0.5) * 2 / C - 1``, the same [-1, 1]
convention as the coordinate rows of :mod:`fusion.data` (sensor pixel edges at -1 and
+1). A star at normalised (x, y) contributes ``exp(-((gx - x)^2 + (gy - y)^2) / (2 s^2))``
with ``s = sigma_px * 2 / C``; overlapping stars combine by maximum, so the heatmap lies in
[0, 1] with value 1 at every star centre that falls on a pixel centre. Masked (padding)
rows contribute nothing. Array order ``[batch, 1, y, x]``.

Because it runs inside the model (:class:`HeatmapRasteriser`), the heatmap always agrees
with the augmented coordinates, costs no loader time, and is part of an exported graph.
"""

from __future__ import annotations

import torch
from torch import nn


def rasterise(coords: torch.Tensor, mask: torch.Tensor, canvas_px: int, sigma_px: float) -> torch.Tensor:
    """(B, M, >=2) normalised positions and (B, M) mask -> (B, 1, C, C) heatmap."""
    c = canvas_px
    grid = (torch.arange(c, device=coords.device, dtype=coords.dtype) + 0.5) * (2.0 / c) - 1.0
    s = sigma_px * 2.0 / c
    x, y = coords[..., 0], coords[..., 1]  # (B, M)
    gx = torch.exp(-((grid[None, None, :] - x[..., None]) ** 2) / (2 * s * s))  # (B, M, C)
    gy = torch.exp(-((grid[None, None, :] - y[..., None]) ** 2) / (2 * s * s))
    g = gy[..., :, None] * gx[..., None, :]  # (B, M, C_y, C_x)
    g = g * mask[..., None, None].to(g.dtype)
    if g.shape[1] == 0:
        return g.new_zeros((g.shape[0], 1, c, c))
    return g.amax(dim=1, keepdim=True)


class HeatmapRasteriser(nn.Module):
    """:func:`rasterise` as a module with a fixed canvas size and sigma (canvas pixels)."""

    def __init__(self, canvas_px: int = 64, sigma_px: float = 1.0):
        super().__init__()
        self.canvas_px, self.sigma_px = int(canvas_px), float(sigma_px)

    def forward(self, coords: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return rasterise(coords, mask, self.canvas_px, self.sigma_px)

    def extra_repr(self) -> str:
        return f"canvas_px={self.canvas_px}, sigma_px={self.sigma_px}"
