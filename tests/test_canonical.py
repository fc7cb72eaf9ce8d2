"""Roll handling: canonical orientation and the rotation-invariance property of the models."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fusion.config import build_config
from fusion.model.canonical import canonical_views, reference_rows, rotate_image, rotate_rows
from fusion.model.networks import create_model


def _rotate(coords: torch.Tensor, ang: float) -> torch.Tensor:
    c, s = math.cos(ang), math.sin(ang)
    x, y = coords[..., 0], coords[..., 1]
    return torch.stack([c * x - s * y, s * x + c * y, coords[..., 2]], -1)


def _inputs(b=6, m=20, seed=0):
    g = torch.Generator().manual_seed(seed)
    coords = torch.rand(b, m, 3, generator=g) * 1.2 - 0.6
    coords[..., 2] = torch.sort(torch.rand(b, m, generator=g), dim=1, descending=True).values  # brightest first
    n = torch.tensor([m, 12, 5, 2, 1, 0])[:b]
    mask = torch.arange(m)[None, :] < n[:, None]
    return coords * mask[..., None], mask


def test_reference_skips_the_centre_and_padding():
    coords = torch.tensor([[[0.01, 0.0, 3.0], [0.5, 0.5, 2.0], [-0.3, 0.2, 1.0], [0.9, 0.9, 0.5]]])
    mask = torch.tensor([[True, True, True, False]])
    rows, valid = reference_rows(coords, mask, 3, min_radius=0.05)
    assert rows.tolist() == [[1, 2, 1]] and valid.tolist() == [[True, True, False]]
    cv, _, theta, views = canonical_views(coords, mask, "brightest", 3, 0.05, training=False)
    assert views == 1
    np.testing.assert_allclose(cv[0, 1, :2].numpy(), [math.sqrt(0.5), 0.0], atol=1e-6)  # reference on +x


def test_nearest_reference_ignores_photometry():
    """mode=nearest: the reference is the detection nearest the centre beyond min_radius, so a new
    brightness order (magnitude noise reordering the rows) leaves the canonical frame where it was,
    while mode=brightest turns it to the new brightest star."""
    coords, mask = _inputs(b=5)
    cv, _, theta, views = canonical_views(coords, mask, "nearest", 3, 0.1, training=True)
    assert views == 1
    r = torch.linalg.vector_norm(coords[..., :2], dim=-1).masked_fill(~mask | (coords[..., :2].norm(dim=-1) < 0.1), 9)
    ref = r.argmin(dim=1)
    for b in range(4):  # samples with an eligible detection: their reference lands on +x at its own radius
        np.testing.assert_allclose(cv[b, ref[b], :2].numpy(), [r[b, ref[b]].item(), 0.0], atol=1e-5)
    # reorder the rows (a new brightness order, brightest first as the loaders give them): same stars, same frame
    g = torch.Generator().manual_seed(3)
    perm = torch.randperm(coords.shape[1], generator=g)
    shuffled = coords[:, perm].clone()
    shuffled[..., 2] = torch.sort(torch.rand(shuffled.shape[:2], generator=g), dim=1, descending=True).values
    smask = mask[:, perm]
    _, _, theta2, _ = canonical_views(shuffled, smask, "nearest", 3, 0.1, training=False)
    np.testing.assert_allclose(theta2[:4].numpy(), theta[:4].numpy(), atol=1e-6)
    _, _, tb1, _ = canonical_views(coords, mask, "brightest", 1, 0.1, training=False)
    _, _, tb2, _ = canonical_views(shuffled, smask, "brightest", 1, 0.1, training=False)
    assert not torch.allclose(tb1[:3], tb2[:3])  # the brightest reference moved with the order


def test_rotate_rows_and_image_agree():
    theta = torch.tensor([0.7])
    img = torch.zeros(1, 1, 65, 65)
    # a bright pixel at normalised (x, y) = (0.5 cos 0.7, 0.5 sin 0.7)
    px = (0.5 * math.cos(0.7) + 1) * 65 / 2 - 0.5
    py = (0.5 * math.sin(0.7) + 1) * 65 / 2 - 0.5
    img[0, 0, round(py), round(px)] = 1.0
    out = rotate_image(img, theta)
    yy, xx = np.unravel_index(out[0, 0].argmax().item(), (65, 65))
    xn, yn = (xx + 0.5) * 2 / 65 - 1, (yy + 0.5) * 2 / 65 - 1
    row = rotate_rows(torch.tensor([[[0.5 * math.cos(0.7), 0.5 * math.sin(0.7), 0.0]]]), theta)
    assert abs(xn - row[0, 0, 0].item()) < 0.05 and abs(yn - row[0, 0, 1].item()) < 0.05


@pytest.mark.parametrize("encoder", ["mlp", "set", "transformer"])
@pytest.mark.parametrize("mode", ["brightest", "nearest", "multi"])
def test_canonical_models_are_rotation_invariant(encoder, mode):
    cfg = build_config(
        {
            "model": {
                "coord_encoder": encoder,
                "branches": {"image": False},
                "canonical": {"mode": mode, "n_refs": 3},
                "heatmap": {"channels": [8, 16], "out_dim": 32},
            }
        }
    )
    torch.manual_seed(0)
    model = create_model("star_fusion", 15, cfg.model, max_stars=20).eval()
    coords, mask = _inputs()
    with torch.no_grad():
        ref = model(None, coords, mask)
        assert torch.isfinite(ref).all()
        for ang in (0.4, 1.9, math.pi, -2.5, 5.0):
            out = model(None, _rotate(coords, ang) * mask[..., None], mask)
            # rows with a usable reference are exactly invariant (float rounding only)
            ok = mask.sum(1) >= 1
            torch.testing.assert_close(out[ok], ref[ok], atol=2e-5, rtol=1e-5)


def test_raw_inputs_are_not_invariant():
    cfg = build_config({"model": {"coord_encoder": "transformer", "branches": {"image": False, "heatmap": False}}})
    torch.manual_seed(0)
    model = create_model("star_fusion", 15, cfg.model, max_stars=20).eval()
    coords, mask = _inputs()
    with torch.no_grad():
        assert (
            model(None, _rotate(coords, 1.0) * mask[..., None], mask) - model(None, coords, mask)
        ).abs().max() > 1e-3


def test_multi_view_output_is_a_probability_average():
    cfg = build_config(
        {
            "model": {
                "coord_encoder": "set",
                "branches": {"image": False, "heatmap": False},
                "canonical": {"mode": "multi", "n_refs": 3},
            }
        }
    )
    model = create_model("star_fusion", 15, cfg.model, max_stars=20).eval()
    coords, mask = _inputs()
    with torch.no_grad():
        p = torch.softmax(model(None, coords, mask), -1)
    torch.testing.assert_close(p.sum(-1), torch.ones(len(p)), atol=1e-5, rtol=0)
    # training mode draws one reference per sample: one view, same batch size
    model.train()
    assert model(None, coords, mask).shape == (len(coords), 15)


def test_canonical_image_branch_runs():
    cfg = build_config(
        {
            "model": {
                "image_backbone": "tiny_cnn",
                "coord_encoder": "transformer",
                "canonical": {"mode": "multi", "image": True},
                "heatmap": {"channels": [8, 16], "out_dim": 32},
            }
        }
    )
    model = create_model("star_fusion", 15, cfg.model, image_size=64, max_stars=20).eval()
    coords, mask = _inputs()
    with torch.no_grad():
        out = model(torch.rand(len(coords), 1, 64, 64), coords, mask)
    assert out.shape == (len(coords), 15) and torch.isfinite(out).all()


@pytest.mark.parametrize("encoder", ["mlp", "transformer"])
def test_relative_flux_models_ignore_the_flux_scale(encoder):
    """model.relative_flux: multiplying every flux by one factor (exposure, gain, 12-bit data stored
    x16) leaves the logits unchanged; without it the model sees the change."""
    coords, mask = _inputs()
    shifted = coords.clone()
    shifted[..., 2] = torch.where(mask, coords[..., 2] + math.log10(16.0), coords[..., 2])
    for relative in (True, False):
        cfg = build_config(
            {
                "model": {
                    "coord_encoder": encoder,
                    "branches": {"image": False},
                    "relative_flux": relative,
                    "canonical": {"mode": "brightest"},
                    "heatmap": {"channels": [8, 16], "out_dim": 32},
                }
            }
        )
        torch.manual_seed(0)
        model = create_model("star_fusion", 15, cfg.model, max_stars=20).eval()
        with torch.no_grad():
            a, b = model(None, coords, mask), model(None, shifted, mask)
        assert torch.isfinite(a).all()
        if relative:
            torch.testing.assert_close(a, b, atol=2e-5, rtol=1e-5)
        else:
            assert (a - b).abs().max() > 1e-3


def test_rotate_image_is_affine_grid_written_out():
    """rotate_image builds F.affine_grid's grid itself (ONNX has affine_grid only from opset 20): same grid."""
    import torch.nn.functional as F

    from fusion.model.canonical import rotate_image

    torch.manual_seed(0)
    img, th = torch.randn(4, 2, 32, 48), torch.randn(4)
    c, s = torch.cos(th), torch.sin(th)
    mat = torch.stack([torch.stack([c, -s, torch.zeros_like(c)], -1), torch.stack([s, c, torch.zeros_like(c)], -1)], 1)
    ref = F.grid_sample(
        img,
        F.affine_grid(mat, list(img.shape), align_corners=False),
        mode="bilinear",
        padding_mode="zeros",
        align_corners=False,
    )
    torch.testing.assert_close(rotate_image(img, th), ref, atol=1e-4, rtol=0)
    smooth = torch.linspace(0, 1, 48).repeat(1, 1, 32, 1)  # a smooth image: grids differ by an ulp
    torch.testing.assert_close(
        rotate_image(smooth, th[:1]),
        F.grid_sample(smooth, F.affine_grid(mat[:1], list(smooth.shape), align_corners=False), align_corners=False),
        atol=1e-5,
        rtol=0,
    )


def test_pair_distances_are_the_patterns_own_and_ignore_padding():
    """Each detection's nearest-neighbour distances, nearest first; PAIR_FAR where fewer detections exist;
    padding rows 0 and never anyone's neighbour."""
    from fusion.model.networks import PAIR_FAR, pair_distances

    xy = torch.tensor([[[0.0, 0.0], [0.3, 0.4], [0.0, -0.2], [9.0, 9.0]]])
    mask = torch.tensor([[True, True, True, False]])
    d, pair, near = pair_distances(xy, mask, 3)
    assert d[0, 0, 1] == pytest.approx(0.5) and not pair[0, 0, 0] and not pair[0, 0, 3]
    torch.testing.assert_close(near[0, 0], torch.tensor([0.2, 0.5, PAIR_FAR]))
    torch.testing.assert_close(near[0, 1], torch.tensor([0.5, math.hypot(0.3, 0.6), PAIR_FAR]))
    assert near[0, 3].eq(0).all()
    _, _, ang = pair_distances(_rotate(torch.cat([xy, torch.zeros(1, 4, 1)], -1), 1.1)[..., :2], mask, 3)
    torch.testing.assert_close(ang, near)  # roll does not move them


@pytest.mark.parametrize("mode", ["none", "brightest", "nearest"])
def test_pair_features_keep_the_model_invariant_and_change_its_output(mode):
    """model.transformer.pair_features: a canonical model stays exactly roll-invariant, padding content
    is ignored, and the pattern's distances reach the output (a model without them differs)."""
    cfg = {
        "coord_encoder": "transformer",
        "branches": {"image": False, "heatmap": False},
        "canonical": {"mode": mode},
        "transformer": {"dim": 32, "layers": 2, "heads": 4, "pair_features": True},
    }
    torch.manual_seed(0)
    model = create_model("star_fusion", 15, build_config({"model": cfg}).model, max_stars=20).eval()
    coords, mask = _inputs()
    with torch.no_grad():
        ref = model(None, coords, mask)
        assert torch.isfinite(ref).all()
        junk = coords.clone()
        junk[~mask] = 7.0
        torch.testing.assert_close(model(None, junk, mask), ref, atol=1e-5, rtol=0)
        if mode != "none":
            ok = mask.sum(1) >= 1
            out = model(None, _rotate(coords, 2.2) * mask[..., None], mask)
            torch.testing.assert_close(out[ok], ref[ok], atol=3e-5, rtol=1e-5)
    # the same output in training mode (with gradients) as at inference: torch's fast inference path
    # mishandles a per-head float attention mask, which the pair bias must not take
    torch.testing.assert_close(model.train()(None, coords, mask), ref, atol=1e-5, rtol=0)
    model.eval()
    with torch.no_grad():
        enc = model.coords
        enc.pair_bias[-1].weight.data.zero_()
        enc.pair_bias[-1].bias.data.zero_()
        assert (model(None, coords, mask) - ref)[mask.sum(1) >= 2].abs().max() > 1e-4  # the bias mattered
