"""Models: output shapes, branch switches, set-encoder invariance, no NaNs, registry, weights loading."""

import dataclasses

import pytest
import torch

from fusion.config import BranchesConfig, ModelConfig, build_config
from fusion.errors import ConfigError
from fusion.model.networks import (
    MODELS,
    CoordMLP,
    SetEncoder,
    create_backbone,
    create_model,
    parameter_counts,
    resolve_model_config,
)

TINY = ModelConfig(
    image_backbone="tiny_cnn",
    coord_hidden=32,
    heatmap=dataclasses.replace(ModelConfig().heatmap, canvas_px=32, channels=(8, 16), out_dim=16),
)


def inputs(b=3, s=64, m=6, n_real=(6, 2, 0)):
    torch.manual_seed(0)
    image = torch.rand(b, 1, s, s)
    coords = torch.rand(b, m, 3) * 2 - 1
    mask = torch.zeros(b, m, dtype=torch.bool)
    for i, n in enumerate(n_real[:b]):
        mask[i, :n] = True
    coords = coords * mask[..., None]
    return image, coords, mask


@pytest.mark.parametrize(
    "image,heatmap,coords", [(1, 1, 1), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1)]
)
def test_every_branch_subset_gives_k_finite_logits(image, heatmap, coords):
    cfg = dataclasses.replace(TINY, branches=BranchesConfig(bool(image), bool(heatmap), bool(coords)))
    model = create_model("star_fusion", 7, cfg, image_size=64)
    assert model.branches == {"image": bool(image), "heatmap": bool(heatmap), "coords": bool(coords)}
    img, c, m = inputs()
    out = model(img if image else None, c, m)
    assert out.shape == (3, 7)
    assert torch.isfinite(out).all()
    out.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    counts = parameter_counts(model)
    assert (counts["image"] > 0) == bool(image) and (counts["heatmap"] > 0) == bool(heatmap)
    assert (counts["coords"] > 0) == bool(coords)
    assert counts["total"] == sum(p.numel() for p in model.parameters())


def test_all_branches_off_is_a_config_error():
    with pytest.raises(ConfigError, match="branches"):
        build_config({"model": {"branches": {"image": False, "heatmap": False, "coords": False}}})


def test_set_encoder_is_permutation_invariant_and_ignores_padding():
    enc = SetEncoder(hidden=32).eval()
    _, coords, mask = inputs(b=3, n_real=(6, 4, 1))
    out = enc(coords, mask)
    perm = torch.randperm(6)
    assert torch.allclose(enc(coords[:, perm], mask[:, perm]), out, atol=1e-6)
    junk = coords.clone()
    junk[~mask] = 5.0  # what sits in padded rows does not matter
    assert torch.allclose(enc(junk, mask), out, atol=1e-6)


def test_coordinate_mlp_depends_on_order_and_ignores_padding():
    mlp = CoordMLP(6, hidden=32).eval()
    _, coords, mask = inputs(b=1, n_real=(4,))
    out = mlp(coords, mask)
    swapped = coords[:, [1, 0, 2, 3, 4, 5]]
    assert not torch.allclose(mlp(swapped, mask), out)
    junk = coords.clone()
    junk[~mask] = 3.0
    assert torch.allclose(mlp(junk, mask), out)


def test_set_encoder_model_invariant_end_to_end():
    cfg = dataclasses.replace(TINY, coord_encoder="set", branches=BranchesConfig(False, True, True))
    model = create_model("star_fusion", 5, cfg).eval()
    _, coords, mask = inputs(b=2, n_real=(5, 3))
    perm = torch.tensor([3, 0, 5, 1, 4, 2])
    assert torch.allclose(model(None, coords[:, perm], mask[:, perm]), model(None, coords, mask), atol=1e-5)


def test_no_nans_for_frames_without_detections():
    model = create_model("star_fusion", 4, dataclasses.replace(TINY, coord_encoder="set"), image_size=64)
    img = torch.zeros(2, 1, 64, 64)
    out = model(img, torch.zeros(2, 6, 3), torch.zeros(2, 6, dtype=torch.bool))
    assert torch.isfinite(out).all()


def test_baselines_are_image_only():
    assert {"star_fusion", "swinv2_tiny", "resnet50"} <= set(MODELS)
    for name, backbone in [("swinv2_tiny", "swinv2_tiny_window8_256"), ("resnet50", "resnet50")]:
        cfg = resolve_model_config(dataclasses.replace(ModelConfig(), name=name))
        assert cfg.image_backbone == backbone
        assert cfg.branches == BranchesConfig(True, False, False)
    with pytest.raises(ConfigError, match="unknown model"):
        create_model("nope", 3)


def test_resnet50_baseline_forward():
    model = create_model("resnet50", 15, ModelConfig(), image_size=64)
    out = model(torch.rand(2, 1, 64, 64))
    assert out.shape == (2, 15) and torch.isfinite(out).all()


def test_star_fusion_paper_size_and_swinv2_forward():
    model = create_model("star_fusion", 15, ModelConfig(), image_size=256)
    counts = parameter_counts(model)
    assert model.image.out_dim == 768
    assert 27.5e6 < counts["image"] < 27.7e6  # timm swinv2_tiny_window8_256, num_classes=0
    assert abs(counts["total"] - 29.8e6) < 0.5e6  # the paper reports 29.8 M
    small = create_model("star_fusion", 15, ModelConfig(), image_size=128)  # same net at 128 px: fast on CPU
    img, c, m = inputs(b=2, s=128)
    out = small(img, c, m)
    assert out.shape == (2, 15) and torch.isfinite(out).all()


def test_pretrained_weights_from_a_file_with_in_chans_handling(tmp_path):
    import timm

    src = timm.create_model("resnet18", num_classes=0)
    path = tmp_path / "weights.pth"
    torch.save(src.state_dict(), path)
    three = create_backbone("resnet18", in_chans=3, img_size=64, pretrained=str(path))
    assert torch.equal(three.conv1.weight, src.conv1.weight)
    one = create_backbone("resnet18", in_chans=1, img_size=64, pretrained=str(path))
    assert torch.allclose(one.conv1.weight, src.conv1.weight.sum(dim=1, keepdim=True), atol=1e-6)
    # a pretrained model defaults to 3 replicated channels with ImageNet statistics
    cfg = dataclasses.replace(ModelConfig(), name="resnet50", image_backbone="resnet18", pretrained=str(path))
    model = create_model("resnet50", 3, cfg, image_size=64)
    assert model.image.in_chans == 3 and model.image.imagenet_norm
    assert torch.isfinite(model(torch.rand(2, 1, 64, 64))).all()


def test_bad_pretrained_values_are_clear_errors():
    with pytest.raises(ConfigError, match="neither an existing file nor a hub name"):
        create_backbone("resnet18", pretrained="/no/such/file.pth")
    with pytest.raises(ConfigError, match="no ImageNet weights"):
        resolve_model_config(dataclasses.replace(TINY, pretrained="timm"))
    with pytest.raises(ConfigError, match="neither a timm model"):
        create_backbone("no_such_backbone")


def test_detections_dropout_zeroes_the_detection_branches_of_some_training_samples():
    """model.detections_dropout: in training a share of the samples keep only their image features
    (the heatmap and coordinate columns zeroed); evaluation sees every branch; it needs an image
    branch and a detection branch."""
    cfg = dataclasses.replace(TINY, detections_dropout=0.5)
    model = create_model("star_fusion", 7, cfg, image_size=64)
    img, c, m = inputs(b=64, n_real=(6,) * 64)
    n_img = model.image.out_dim
    torch.manual_seed(1)
    z = model.train().forward_features(img, c, m)
    dropped = (z[:, n_img:] == 0).all(dim=1)
    assert 16 <= int(dropped.sum()) <= 48  # ~half of 64 samples (binomial, p 0.5: ±4 sigma)
    assert not (z[:, :n_img] == 0).all(dim=1).any()  # the image features are never touched
    ev = model.eval().forward_features(img, c, m)
    assert not (ev[:, n_img:] == 0).all(dim=1).any()  # evaluation: every branch, every sample
    assert torch.allclose(ev[~dropped], z[~dropped].detach(), atol=1e-5)  # the kept samples: their features as they are
    for branches in (BranchesConfig(False, True, True), BranchesConfig(True, False, False)):
        with pytest.raises(ConfigError, match="detections_dropout"):
            create_model("star_fusion", 7, dataclasses.replace(cfg, branches=branches), image_size=64)
