"""The tied image view (model.image_backbone=peak_rows): the image's peaks as a second set of rows
through the coordinate branch and head, fused with the detections as a product of experts."""

import numpy as np
import pytest
import torch

from fusion.config import build_config, load_config
from fusion.errors import ConfigError
from fusion.model.networks import PeakRows, create_model, parameter_counts


def _tied(mode="nearest", **model):
    cfg = build_config(
        {
            "model": {
                "image_backbone": "peak_rows",
                "branches": {"image": True, "heatmap": False, "coords": True},
                "coord_encoder": "transformer",
                "canonical": {"mode": mode, "min_radius": 0.1},
                **model,
            }
        }
    )
    torch.manual_seed(0)
    return create_model("star_fusion", 15, cfg.model, image_size=64, max_stars=8)


def _frame(stars, size=64, noise=2.0, seed=0):
    """Stored image (1, 1, size, size) with Gaussian stars at stored pixels (u, v), and their rows."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size].astype(np.float64)
    img = 100 + rng.normal(0, noise, (size, size))
    for u, v, snr in stars:
        img += snr * noise * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / 2.0)
    half = size / 2
    rows = [[(u + 0.5) / half - 1, (v + 0.5 - half) / half, 1.0 - 0.1 * i] for i, (u, v, _) in enumerate(stars)]
    return torch.from_numpy(img.astype(np.float32))[None, None], torch.tensor([rows], dtype=torch.float32)


STARS = ((20.3, 30.7, 80.0), (45.6, 12.2, 60.0), (9.8, 50.1, 40.0), (50.2, 48.9, 30.0), (33.1, 8.4, 25.0))


def test_the_image_view_has_no_parameters_and_reads_the_peaks_as_flux_free_rows():
    model = _tied()
    assert parameter_counts(model)["image"] == 0 and isinstance(model.image.backbone, PeakRows)
    img, rows = _frame(STARS)
    prow, pmask = model.image.rows(img)
    assert prow.shape == (1, 8, 3) and int(pmask.sum()) == len(STARS)
    assert torch.all(prow[0, pmask[0], 2] == 0)  # no flux: the stretched pixels are not the detector's flux
    for x, y, _ in rows[0]:  # every star has its row within a quarter stored pixel
        d = torch.hypot(prow[0, pmask[0], 0] - x, prow[0, pmask[0], 1] - y).min()
        assert d < 0.25 * 2 / 64


def test_fused_output_is_the_views_mean_log_probability():
    """With an image: log_softmax of the mean of the two views' log-probabilities; without one (the
    detections stream), or with no peak, the detections alone; with no detection, the image alone."""
    model = _tied().eval()
    img, rows = _frame(STARS)
    few = rows[:, :3]
    mask = torch.ones(1, 3, dtype=torch.bool)
    with torch.no_grad():
        fused = model(img, few, mask)
        det = model(None, few, mask)
        prow, pmask = model.image.rows(img)
        view = model(None, prow, pmask)
        want = torch.log_softmax((torch.log_softmax(det, -1) + torch.log_softmax(view, -1)) / 2, -1)
        torch.testing.assert_close(fused, want, atol=1e-5, rtol=0)
        assert not torch.allclose(fused, torch.log_softmax(det, -1), atol=1e-3)  # the image changes the answer
        blank = torch.full_like(img, 100.0)
        torch.testing.assert_close(model(blank, few, mask), torch.log_softmax(det, -1), atol=1e-5, rtol=0)
        none = torch.zeros(1, 3, dtype=torch.bool)
        torch.testing.assert_close(model(img, few, none), torch.log_softmax(view, -1), atol=1e-5, rtol=0)
        fine = _tied(mode="brightest")
        assert fine(img, few, mask).shape == (1, 15)


def test_the_image_views_weight_falls_with_the_detection_count():
    """model.peaks.image_weight (few, many) is linear in the detection count between image_weight_stars:
    at 3 detections the fused output is log_softmax(0.4 det + 0.6 image), at 5 0.35, at 7 or more 0.1."""
    model = _tied(peaks={"image_weight": [0.6, 0.1], "image_weight_stars": [3, 7]}).eval()
    img, rows = _frame(STARS)
    prow, pmask = model.image.rows(img)
    with torch.no_grad():
        view = torch.log_softmax(model(None, prow, pmask), -1)
        for n, a in ((3, 0.6), (5, 0.35)):
            few, mask = rows[:, :n], torch.ones(1, n, dtype=torch.bool)
            det = torch.log_softmax(model(None, few, mask), -1)
            want = torch.log_softmax((1 - a) * det + a * view, -1)
            torch.testing.assert_close(model(img, few, mask), want, atol=1e-5, rtol=0)
    counts = torch.arange(12)[:, None] > torch.arange(12)[None]  # row i: i detections
    a = model.view_weight(counts, torch.ones(12, 4, dtype=torch.bool))
    torch.testing.assert_close(a[1:], torch.tensor([0.6, 0.6, 0.6, 0.475, 0.35, 0.225, 0.1, 0.1, 0.1, 0.1, 0.1]))
    assert a[0] == 1  # no detection: the image alone
    assert model.view_weight(counts, torch.zeros(12, 4, dtype=torch.bool)).eq(0).all()  # no peak: detections
    with pytest.raises(ConfigError, match="image_weight_stars"):
        load_config(None, ["model.peaks.image_weight_stars=[8,4]"])
    with pytest.raises(ConfigError, match="image_weight"):
        load_config(None, ["model.peaks.image_weight=[0.5,1.5]"])


def test_the_image_views_weight_rises_with_the_peaks_no_detection_explains():
    """image_weight_by=unexplained: every peak explained by a detection -> image_weight[1]; most peaks
    unexplained (the frame cut to its brightest two) -> image_weight[0]; the fused output uses that weight."""
    from fusion.model.networks import UNEXPLAINED_TOL_PX, unexplained_share

    peaks = {"image_weight": [0.5, 0.0], "image_weight_by": "unexplained", "image_weight_unexplained": [0.1, 0.2]}
    model = _tied(peaks=peaks).eval()
    img, rows = _frame(STARS)
    prow, pmask = model.image.rows(img)
    tol = UNEXPLAINED_TOL_PX * 2 / 64
    every, two = torch.ones(1, len(STARS), dtype=torch.bool), torch.ones(1, 2, dtype=torch.bool)
    assert float(unexplained_share(prow, pmask, rows, every, tol)) == 0.0
    assert float(unexplained_share(prow, pmask, rows[:, :2], two, tol)) == pytest.approx(3 / 5)
    far = rows.clone()
    far[..., :2] += 10 * tol  # detections nowhere near the peaks explain none of them
    assert float(unexplained_share(prow, pmask, far, every, tol)) == 1.0
    with torch.no_grad():
        view = torch.log_softmax(model(None, prow, pmask), -1)
        for det_rows, mask, a in ((rows, every, 0.0), (rows[:, :2], two, 0.5)):
            det = torch.log_softmax(model(None, det_rows, mask), -1)
            want = torch.log_softmax((1 - a) * det + a * view, -1)
            torch.testing.assert_close(model(img, det_rows, mask), want, atol=1e-5, rtol=0)
    share = torch.tensor([0.0, 0.1, 0.15, 0.2, 0.9])
    a = model.view_weight(torch.ones(5, 3, dtype=torch.bool), torch.ones(5, 4, dtype=torch.bool), share)
    torch.testing.assert_close(a, torch.tensor([0.0, 0.0, 0.25, 0.5, 0.5]))
    with pytest.raises(ConfigError, match="image_weight_unexplained"):
        load_config(None, ["model.peaks.image_weight_unexplained=[0.5,0.2]"])
    with pytest.raises(ConfigError, match="image_weight_by"):
        load_config(None, ["model.peaks.image_weight_by=brightness"])


def test_tied_model_is_roll_invariant():
    """A quarter turn of the image (exact: no resampling) and of the detections gives the same output."""
    model = _tied().eval()
    img, rows = _frame(STARS)
    mask = torch.ones(1, len(STARS), dtype=torch.bool)
    turned = torch.rot90(img, 1, dims=(2, 3))  # (u, v) -> (v, 63 - u): x' = y, y' = -x in normalised units
    trows = torch.stack([rows[..., 1], -rows[..., 0], rows[..., 2]], dim=-1)
    with torch.no_grad():
        torch.testing.assert_close(model(img, rows, mask), model(turned, trows, mask), atol=2e-4, rtol=0)


def test_flux_dropout_zeroes_whole_samples_in_training_only():
    model = _tied(flux_dropout=0.5)
    seen = []
    model.coords.register_forward_hook(lambda mod, args, out: seen.append(args[0].detach().clone()))
    g = torch.Generator().manual_seed(1)
    coords = torch.rand(64, 8, 3, generator=g) + 0.5  # every flux > 0
    mask = torch.ones(64, 8, dtype=torch.bool)
    model.train()
    model(None, coords, mask)
    flux = seen[-1][..., 2]
    dropped = (flux == 0).all(dim=1)
    assert 10 < int(dropped.sum()) < 54 and bool(((flux == 0).any(dim=1) == dropped).all())  # whole samples
    model.eval()
    model(None, coords, mask)
    assert bool((seen[-1][..., 2] > 0).all())


def test_tied_view_config_rules():
    """The detections stream may train a tied model (its image view has nothing of its own to learn);
    it needs a detection branch, and modality dropout would defeat it."""
    cfg = load_config(
        None,
        [
            "stream.kind=detections",
            "model.branches.image=true",
            "model.image_backbone=peak_rows",
            "model.flux_dropout=0.3",
        ],
    )
    assert cfg.model.image_backbone == "peak_rows"
    with pytest.raises(ConfigError, match="stream.kind=detections makes no images"):
        load_config(None, ["stream.kind=detections", "model.branches.image=true", "model.image_backbone=peak_set"])
    with pytest.raises(ConfigError, match="peak_rows"):
        _tied(detections_dropout=0.3)
    with pytest.raises(ConfigError, match="flux_dropout"):
        load_config(None, ["model.flux_dropout=1.0"])


def _pixel_view(scale=8.0, adc=65535.0, share=0.9, factor=4):
    top = float(np.log1p(adc / scale))
    view = PeakRows(8, 5.0, 1.0, stretch=(0.0, scale, top), area=factor**2, log_flux_offset=3.0, max_peak_share=share)
    return view, scale, top


def _stretched(stars, hot=(), size=64, sky=40.0, noise=3.0, sigma=1.0, seed=0, scale=8.0, top=None):
    """A stored frame in ADU above the bias (Gaussian stars of total stored flux F at (u, v), one-pixel
    defects of height A), log-stretched as the preprocessor stores it."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size].astype(np.float64)
    adu = sky + rng.normal(0, noise, (size, size))
    for u, v, flux in stars:
        adu += flux / (2 * np.pi * sigma**2) * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma**2))
    for u, v, a in hot:
        adu[v, u] += a
    x = np.log1p(np.clip(adu, 0, None) / scale) / top
    return torch.from_numpy(x.astype(np.float32))[None, None]


def test_pixel_flux_is_the_stars_flux_in_sensor_adu_brightest_first_and_defects_are_dropped():
    """model.peaks.pixel_flux: the stretch inverted, the 5 x 5 sum above the sky x the binning factor
    squared is the star's flux in sensor ADU (a sigma = 1 px Gaussian keeps 97.5 % of it in the box);
    rows go brightest first; a one-pixel spike as strong as a star is dropped, and kept with the cut off."""
    view, scale, top = _pixel_view()
    stars = ((20.3, 30.7, 3000.0), (45.6, 12.2, 12000.0), (9.8, 50.1, 800.0), (50.2, 48.9, 5000.0))
    img = _stretched(stars, hot=((33, 40, 2500.0),), top=top)
    rows, mask = view.rows(img)
    assert int(mask.sum()) == len(stars)  # the spike is gone
    got = 10 ** (rows[0, mask[0], 2].double() + 3.0) - 1  # sensor ADU
    want = sorted((f * 16 * 0.975 for *_, f in stars), reverse=True)
    np.testing.assert_allclose(got.numpy(), want, rtol=0.05)
    assert bool((rows[0, ~mask[0]] == 0).all())
    for (x, y, _), f in zip(rows[0, mask[0]].tolist(), want):  # each row at its star
        u, v = (x + 1) * 32 - 0.5, y * 32 + 32 - 0.5
        assert min(abs(u - su) + abs(v - sv) for su, sv, sf in stars if abs(sf * 16 * 0.975 - f) < 1) < 0.5
    keep_all, _, _ = _pixel_view(share=1.0)
    assert int(keep_all.rows(img)[1].sum()) == len(stars) + 1


def test_pixel_flux_on_rendered_frames_matches_the_detectors_flux(small_dataset):
    """On skygen's own frames a detection's peak gets, from the pixels, the detector's flux to within a
    few tens of per cent (different apertures: 5 x 5 stored pixels against the detector's; on the cpu30
    camera the median is -0.03 dex): the stretch, the sky and the binning factor are undone."""
    from fusion.config import DataConfig
    from fusion.model.inputs import Preprocessor
    from fusion.model.shards import read_sample
    from skygen.datasets.shards import open_dataset

    with open_dataset(small_dataset) as ds:
        pre = Preprocessor.from_configs(ds.config, DataConfig(), max_stars=8)
        view = PeakRows(
            24, 5.0, 0.9, stretch=pre.stretch(), area=float(pre.geo.factor) ** 2, log_flux_offset=pre.log_flux_offset
        )
        diffs = []
        for i in range(12):
            s = read_sample(ds, i, pre.geo, None)
            coords, m = pre.coords(s)
            rows, mask = view.rows(torch.from_numpy(pre.image(s.image))[None, None])
            got = rows[0, mask[0]].numpy()
            for c in coords[m]:
                d = np.hypot(got[:, 0] - c[0], got[:, 1] - c[1]) if len(got) else np.array([np.inf])
                if d.min() < 2 / pre.geo.image_px:
                    diffs.append(got[d.argmin(), 2] - c[2])
    diffs = np.array(diffs)
    assert len(diffs) >= 30
    assert abs(np.median(diffs)) < 0.2 and np.mean(np.abs(diffs) < 0.3) > 0.8  # a wrong f^2 is 1.2 dex


def test_pixel_flux_config_rules():
    with pytest.raises(ConfigError, match="pixel_flux"):
        load_config(None, ["model.peaks.pixel_flux=true", "model.image_backbone=peak_set"])
    cfg = load_config(
        None, ["model.branches.image=true", "model.image_backbone=peak_rows", "model.peaks.pixel_flux=true"]
    )
    with pytest.raises(ConfigError, match="render config"):
        create_model("star_fusion", 15, cfg.model, image_size=64, max_stars=8)  # no Preprocessor given
    with pytest.raises(ConfigError, match="max_peak_share"):
        load_config(None, ["model.peaks.max_peak_share=0"])
