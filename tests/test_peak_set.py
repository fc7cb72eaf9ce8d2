"""The image backbones that keep where the stars are: the peak set (stars read off the pixels as
tokens) and the grid CNN, and model.image_px binning."""

import dataclasses

import numpy as np
import pytest
import torch

from fusion.config import BranchesConfig, DataConfig, ModelConfig, build_config
from fusion.errors import ConfigError
from fusion.model.canonical import canonical_views
from fusion.model.inputs import Preprocessor
from fusion.model.networks import PeakSet, create_model, resolve_model_config
from fusion.model.shards import read_sample
from skygen.datasets.shards import open_dataset


def _star_field(
    size=64,
    stars=((20.3, 30.7, 60.0), (45.6, 12.2, 30.0), (9.8, 50.1, 15.0)),
    hot=((40, 10, 200.0),),
    sigma_psf=1.0,
    noise=2.0,
    bias=100.0,
    seed=0,
):
    """A quantised frame (ADU): Gaussian stars (x, y, peak in noise sigmas), one-pixel hot pixels."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size].astype(np.float64)
    img = bias + rng.normal(0, noise, (size, size))
    for x, y, snr in stars:
        img += snr * noise * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma_psf**2))
    for x, y, snr in hot:
        img[y, x] += snr * noise
    return torch.from_numpy(np.round(img).astype(np.float32))[None, None]


def _norm(u, v, size):
    """Stored pixel (u, v) -> the coordinate branch's normalised (x, y) (pixel edges at -1, +1)."""
    return (u + 0.5) / (size / 2) - 1, (v + 0.5 - size / 2) / (size / 2)


def test_peaks_are_the_stars_at_subpixel_positions_and_hot_pixels_are_dropped():
    img = _star_field()
    rows, mask = PeakSet(16, threshold=5.0).peaks(img)
    got = rows[0, mask[0]]
    assert len(got) == 3  # three stars, no hot pixel, no noise peak
    for (x, y, _), row in zip(((20.3, 30.7, 0), (45.6, 12.2, 0), (9.8, 50.1, 0)), got):  # strongest first
        ex, ey = _norm(x, y, 64)
        # within 0.25 px: a 3 x 3 centroid is pulled towards the peak pixel by up to ~0.2 px
        assert abs(row[0] - ex) < 0.25 * 2 / 64 and abs(row[1] - ey) < 0.25 * 2 / 64
    assert (got[:, 2].diff() < 0).all()  # log flux falls with the star's brightness
    assert ((got[:, 3] > 0.1) & (got[:, 3] < 0.9)).all()  # spread by the PSF
    # the hot pixel is a token when the sharpness cut is off, and it is the sharpest
    rows, mask = PeakSet(16, threshold=5.0, max_sharpness=1.0).peaks(img)
    assert mask[0].sum() == 4 and rows[0, mask[0], 3].max() > 0.9


def test_a_saturated_star_is_one_peak():
    """A star clipped at the ADC's top has a flat plateau whose pixels are all local maxima; it is one
    token, at the plateau's centre, and the faint star beside it (6 px away) is still its own."""
    img = _star_field(stars=((30.0, 30.0, 2000.0), (36.0, 30.0, 40.0), (10.3, 50.2, 30.0)), hot=())
    img = img.clamp(max=float(img.quantile(0.9995)))  # ~2 x 2 to 3 x 3 px flat top
    rows, mask = PeakSet(16, threshold=5.0).peaks(img)
    got = rows[0, mask[0], :2]
    assert len(got) == 3
    ex, ey = _norm(30.0, 30.0, 64)
    assert abs(got[0, 0] - ex) < 0.75 * 2 / 64 and abs(got[0, 1] - ey) < 0.75 * 2 / 64


def test_peak_noise_estimate_works_on_quantised_and_scaled_frames():
    """A stored frame whose noise is below one ADU has a MAD of zero; the peaks must not depend on the
    stretch: the log stretch the model sees and the raw ADU give the same stars."""
    img = _star_field(noise=0.4, stars=((20.0, 30.0, 40.0), (45.0, 12.0, 20.0)), hot=())
    ps = PeakSet(16, threshold=5.0)
    rows_adu, mask_adu = ps.peaks(img)
    assert mask_adu[0].sum() == 2
    stretched = torch.log1p(torch.clamp(img - 100, min=0) / 8.0) / np.log1p(3995 / 8.0)
    rows_log, mask_log = ps.peaks(stretched)
    assert mask_log[0].sum() == 2
    torch.testing.assert_close(rows_log[0, :2, :2], rows_adu[0, :2, :2], atol=0.1 * 2 / 64, rtol=0)


def test_blank_frame_gives_an_empty_set_and_finite_features():
    ps = PeakSet(8)
    rows, mask = ps.peaks(torch.full((2, 1, 32, 32), 100.0))
    assert not mask.any() and (rows == 0).all()
    assert torch.isfinite(ps(torch.full((2, 1, 32, 32), 100.0))).all()


def test_peaks_on_a_rendered_frame_are_its_detections(small_dataset):
    """On skygen's own stored frame the bright detections (full-resolution centroids, encoded by the
    preprocessor) each have a peak within one stored pixel."""
    ds = open_dataset(small_dataset)
    pre = Preprocessor.from_configs(ds.config, DataConfig(), max_stars=5)
    hits = total = 0
    for i in range(10):
        s = read_sample(ds, i, pre.geo, None)
        coords, m = pre.coords(s)
        rows, mask = PeakSet(64, threshold=5.0).peaks(torch.from_numpy(pre.image(s.image))[None, None])
        size = pre.geo.image_px
        for c in coords[m]:
            d = np.hypot(*(rows[0, mask[0], :2].numpy() - c[:2]).T).min() if mask.any() else np.inf
            hits += d < 2 / size
            total += 1
    assert total >= 20 and hits / total >= 0.9


def test_peak_tokens_are_rotated_with_the_detections():
    """model.canonical.image with the peak set: tokens come from the image as stored and are rotated
    by the same angle as the detections, so a star's token and its detection stay together."""
    img = _star_field(stars=((20.3, 30.7, 60.0), (45.6, 12.2, 30.0), (9.8, 50.1, 15.0)), hot=())
    pos = [_norm(x, y, 64) for x, y in ((20.3, 30.7), (45.6, 12.2), (9.8, 50.1))]
    coords = torch.tensor([[[x, y, 1.0 - 0.3 * i] for i, (x, y) in enumerate(pos)]], dtype=torch.float32)
    mask = torch.ones(1, 3, dtype=torch.bool)
    cfg = build_config(
        {
            "model": {
                "image_backbone": "peak_set",
                "branches": {"image": True, "heatmap": False, "coords": False},
                "canonical": {"mode": "brightest", "image": True},
                "peaks": {"max_peaks": 8},
            }
        }
    )
    model = create_model("star_fusion", 15, cfg.model, image_size=64).eval()
    seen = {}
    enc = model.image.backbone.encoder
    enc.register_forward_hook(lambda mod, args, out: seen.update(rows=args[0], mask=args[1]))
    with torch.no_grad():
        model(img, coords, mask)
    cv, mv, _, _ = canonical_views(coords, mask, "brightest", 1, 0.05, False)
    tokens = seen["rows"][0, seen["mask"][0], :2]
    torch.testing.assert_close(tokens, cv[0, :, :2], atol=0.25 * 2 / 64, rtol=0)


def test_grid_cnn_with_image_px_binning_and_bad_binning():
    cfg = dataclasses.replace(
        ModelConfig(image_backbone="grid_cnn", image_px=32), branches=BranchesConfig(True, False, False)
    )
    model = create_model("star_fusion", 5, cfg, image_size=64)
    assert model.image.bin == 2
    out = model(torch.rand(2, 1, 64, 64), torch.zeros(2, 4, 3), torch.zeros(2, 4, dtype=torch.bool))
    assert out.shape == (2, 5) and torch.isfinite(out).all()
    with pytest.raises(ConfigError, match="integer binning"):
        create_model("star_fusion", 5, dataclasses.replace(cfg, image_px=48), image_size=64)


def test_peak_set_has_no_imagenet_weights():
    with pytest.raises(ConfigError, match="no ImageNet weights"):
        resolve_model_config(ModelConfig(image_backbone="peak_set", pretrained="resnet50.a1_in1k"))
    with pytest.raises(ConfigError):
        build_config({"model": {"peaks": {"max_sharpness": 0.0}}})
