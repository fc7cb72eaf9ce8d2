"""Training on skygen's streams: batch identity, encoding, exact resume, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from fusion.config import load_config
from fusion.errors import ConfigError
from fusion.model.checkpoint import load_checkpoint, load_matching_state
from fusion.model.inputs import FrameGeometry, Sample, encode_batch, encode_detections
from fusion.testing import Killed, assert_same_run, killing_log, small_dataset
from fusion.train.run import train
from fusion.train.stream import StreamBatches, make_stream_loader
from skygen.config import build_config as build_render_config
from skygen.datasets.shards import open_dataset
from skygen.errors import SkygenError
from skygen.stream import calibration as calib
from skygen.stream import emulator as emu

ROOT = Path(__file__).resolve().parents[1]
quiet = lambda *a, **k: None  # noqa: E731


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    """The smoke dataset and a detector calibration for its (small) camera."""
    path = small_dataset("smoke")
    with open_dataset(path) as ds:
        config = ds.config
    cal = tmp_path_factory.mktemp("cal") / "smoke-detector.json"
    emu.save(calib.calibrate_from_renders(build_render_config(config), 150), cal)
    return path, config, cal


def _batches(smoke, **kw):
    path, config, cal = smoke
    args = dict(seed=3, batch=16, steps=6, max_stars=8, calibration=str(cal))
    args.update(kw)
    return StreamBatches(config, "detections", np.eye(3), **args)


def test_stream_batches_are_disjoint_and_worker_independent(smoke):
    seen = set()
    for epoch in (0, 1):
        for rank in (0, 1):
            b = _batches(smoke, rank=rank, world=2)
            b.set_epoch(epoch)
            for step in range(b.steps):
                idx = b.indices(step)
                assert not seen & set(idx.tolist())
                seen |= set(idx.tolist())
    assert len(seen) == 2 * 2 * 6 * 16
    b0 = _batches(smoke)
    direct = [b0.make_batch(s) for s in range(b0.steps)]
    for workers in (0, 2):
        got = list(make_stream_loader(_batches(smoke), workers))
        assert len(got) == len(direct)
        for a, b in zip(direct, got):
            assert torch.equal(a["coords"], b["coords"]) and torch.equal(a["index"], b["index"])


def test_encode_batch_matches_the_shard_encoder(smoke):
    path, config, cal = smoke
    geo = FrameGeometry.from_render_config(config)
    b = _batches(smoke).stream().batch(np.arange(20))
    coords, mask, counts = encode_batch(b.offsets, b.detections, geo, 8, 3.0)
    for j in range(20):
        d = b.sample(j)["detections"]
        s = Sample(np.zeros((2, 2), np.float32), d["x_px"], d["y_px"], d["flux_adu"], d["area_px"], 0.0, 1.0)
        c, m = encode_detections(s, geo, 8, 3.0)
        np.testing.assert_allclose(coords[j], c, atol=1e-6)
        assert np.array_equal(mask[j], m) and counts[j] == len(d["x_px"])


def test_few_star_training_keeps_the_brightest_few(smoke):
    plain = _batches(smoke, max_stars=30).make_batch(0)
    few = _batches(smoke, max_stars=30, few_prob=0.5, few_stars=(3, 5))
    got = few.make_batch(0)
    n_all, n = plain["n_detections"].numpy(), got["n_detections"].numpy()
    cut = n < np.minimum(n_all, 30)
    assert 0.2 < cut.mean() < 0.8  # about half the samples are cut ...
    assert np.all(n[cut] >= 3) and np.all(n[cut] <= 5)  # ... to 3-5 detections
    assert np.array_equal(got["mask"].sum(1).numpy(), np.minimum(n, 30))
    for j in range(len(n)):  # the kept rows are the brightest of the full set
        k = int(got["mask"][j].sum())
        assert torch.equal(got["coords"][j, :k], plain["coords"][j, :k])
        assert not got["mask"][j, k:].any()
    assert torch.equal(got["label"], plain["label"])
    assert torch.equal(few.make_batch(0)["coords"], got["coords"])  # a pure function of the index
    with pytest.raises(ConfigError, match="stream.few_stars"):
        _cfg(smoke, "stream.few_stars=[6, 3]")


def test_brightness_offset_shifts_every_log_flux_of_a_sample(smoke):
    plain = _batches(smoke).make_batch(0)
    got = _batches(smoke, brightness_mag=(-1.0, 2.0)).make_batch(0)
    m = plain["mask"]
    d = got["coords"][..., 2] - plain["coords"][..., 2]
    assert torch.equal(got["coords"][..., :2], plain["coords"][..., :2]) and torch.equal(got["mask"], m)
    assert torch.all(d[~m] == 0)
    for j in range(len(d)):  # one offset per sample, in [-2.5 * 2, 2.5 * 1] / 2.5
        v = d[j][m[j]]
        assert torch.allclose(v, v[0].expand_as(v), atol=1e-5) and -0.8 - 1e-5 <= float(v[0]) <= 0.4 + 1e-5
    assert d[m].std() > 0.1  # and it differs between samples


def _cfg(smoke, *extra):
    path, config, cal = smoke
    return load_config(
        ROOT / "configs" / "smoke.yaml",
        [
            f"data.path={path}",
            "stream.kind=detections",
            f"stream.calibration={cal}",
            "stream.samples_per_epoch=256",
            "stream.dropout=[0, 0.2]",
            "stream.false_stars=[0, 1]",
            "model.branches.image=false",
            "model.coord_encoder=transformer",
            "model.transformer.dim=16",
            "model.transformer.layers=1",
            "model.transformer.heads=2",
            "model.coord_hidden=32",
            "model.canonical.mode=multi",
            "train.batch_size=64",
            "train.epochs=3",
            "data.max_stars=8",
            *extra,
        ],
    )


def test_stream_training_learns_and_resumes_exactly(smoke, tmp_path):
    cfg = _cfg(smoke)
    full = tmp_path / "full"
    summary = train(cfg, full, log=quiet)
    assert summary["epochs_run"] == 3 and np.isfinite(summary["best"]["val_loss"])

    killed = tmp_path / "killed"
    with pytest.raises(Killed):
        train(cfg, killed, log=killing_log("epoch 2/3"))
    train(cfg, killed, resume=True, log=quiet)
    assert_same_run(full, killed)


def test_stream_bad_input(smoke, tmp_path):
    with pytest.raises(ConfigError, match="model.branches.image"):
        _cfg(smoke, "model.branches.image=true")
    with pytest.raises(SkygenError, match="another camera"):
        train(_cfg(smoke, f"stream.calibration={emu.default_calibration_path()}"), tmp_path / "a", log=quiet)
    with pytest.raises(SkygenError, match="not found"):
        train(_cfg(smoke, f"stream.calibration={tmp_path / 'missing.json'}"), tmp_path / "b", log=quiet)
    with pytest.raises(ConfigError, match=r"stream.dropout"):
        _cfg(smoke, "stream.dropout=[0.5, 0.1]")
    with pytest.raises(ConfigError, match="samples_per_epoch"):
        train(_cfg(smoke, "stream.samples_per_epoch=10"), tmp_path / "c", log=quiet)


def test_frames_stream_three_branch_warm_start(smoke, tmp_path):
    """The recipe of configs/cpu-fusion.yaml in miniature: geometry on the detections stream,
    then the three-branch model fine-tuned on the frames stream from that checkpoint."""
    geo = tmp_path / "geo"
    train(
        _cfg(
            smoke,
            "train.epochs=1",
            "model.branches.heatmap=true",
            "model.heatmap.channels=[4,8]",
            "model.heatmap.out_dim=16",
            "model.heatmap.canvas_px=32",
        ),
        geo,
        log=quiet,
    )
    lines = []
    full = _cfg(
        smoke,
        "train.epochs=1",
        "stream.kind=frames",
        "stream.samples_per_epoch=64",
        "model.branches.image=true",
        "model.image_backbone=tiny_cnn",
        "model.canonical.image=true",
        "model.branches.heatmap=true",
        "model.heatmap.channels=[4,8]",
        "model.heatmap.out_dim=16",
        "model.heatmap.canvas_px=32",
        f"model.init_from={geo / 'best.pt'}",
    )
    summary = train(full, tmp_path / "full", log=lambda m, *a, **k: lines.append(m))
    assert summary["epochs_run"] == 1 and np.isfinite(summary["best"]["val_loss"])
    warm = next(m for m in lines if m.startswith("warm start"))
    assert "coords" in warm and "heatmap" in warm and "coords+heatmap columns copied" in warm
    before = next(m for m in lines if m.startswith("warm start, before training"))
    assert summary["warm_start_val"]["val_top1"] == pytest.approx(float(before.split("top1 ")[1].split()[0]), abs=1e-3)
    assert summary["init"].startswith("warm start from")
    geo_ck, full_ck = load_checkpoint(geo / "best.pt"), load_checkpoint(tmp_path / "full" / "best.pt")
    a = geo_ck.model
    assert any(k.startswith("image.") for k in full_ck.model)
    assert "coords.embed.0.weight" in a
    # the fusion head, block by block: the geometry run's LayerNorm and head columns land on the
    # columns of its branches (heatmap, coords), the image's columns start at zero (scale 1, shift 0)
    model = full_ck.build_model()
    info = load_matching_state(model, geo / "best.pt")
    assert info["head_blocks"] == ["coords", "heatmap"]
    n_img = model.image.out_dim
    w, hw = model.head.weight.detach(), a["head.weight"]
    assert w.shape[1] == n_img + hw.shape[1]
    assert torch.equal(w[:, :n_img], torch.zeros_like(w[:, :n_img])) and torch.equal(w[:, n_img:], hw)
    assert torch.equal(model.norm.weight.detach()[n_img:], a["norm.weight"])
    assert torch.equal(model.norm.weight.detach()[:n_img], torch.ones(n_img))
    assert torch.equal(model.norm.bias.detach()[:n_img], torch.zeros(n_img))
    # the other way round (a three-branch checkpoint into a geometry model) copies branches by name only
    small = geo_ck.build_model()
    assert load_matching_state(small, tmp_path / "full" / "best.pt")["head_blocks"] == []


def test_frames_stream_on_the_torch_renderer(smoke, tmp_path):
    """stream.render_backend=torch: each batch rasterised by skygen.render.torch_frames (here on the
    CPU device), detections from the real detector; the same training step."""
    b = _batches(smoke)
    path, config, cal = smoke
    tb = StreamBatches(
        config, "frames", np.eye(3), seed=3, batch=4, steps=2, max_stars=8, render_backend="torch", device="cpu"
    )
    nb = StreamBatches(config, "frames", np.eye(3), seed=3, batch=4, steps=2, max_stars=8)
    t, n = tb.make_batch(0), nb.make_batch(0)
    assert torch.equal(t["index"], n["index"]) and torch.equal(t["label"], n["label"])  # same scenes
    assert t["image"].shape == n["image"].shape and t["image"].dtype == torch.float32
    # same stars, independent noise: the images agree closely but not exactly
    assert 0 < (t["image"] - n["image"]).abs().mean() < 0.05
    del b
    summary = train(
        _cfg(
            smoke,
            "train.epochs=1",
            "stream.kind=frames",
            "stream.samples_per_epoch=64",
            "stream.render_backend=torch",
            "model.branches.image=true",
            "model.image_backbone=tiny_cnn",
        ),
        tmp_path / "t",
        log=quiet,
    )
    assert summary["epochs_run"] == 1


def test_non_square_sensor_trains_on_shards_and_stream(tmp_path):
    """A 256 x 192 sensor (stored 64 x 48): shard training with augmentations and the image,
    and stream training with a calibration made for that camera."""
    from fusion.testing import render_small

    ds = render_small(
        tmp_path / "ns",
        [
            "n_frames=120",
            "output.shard_size=60",
            "camera.width_px=256",
            "camera.height_px=192",
            "camera.fov_deg=20",
            "output.image_size_px=64",
            "output.split_fractions=[0.5, 0.25, 0.25]",
        ],
    )
    with open_dataset(ds) as d:
        config = d.config
        assert d.image_shape == (48, 64)
    geo = FrameGeometry.from_render_config(config)
    x, y = geo.normalised(np.array([-0.5, 255.5, 127.5]), np.array([-0.5, 191.5, 95.5]))
    np.testing.assert_allclose(x, [-1, 1, 0])
    np.testing.assert_allclose(y, [-0.75, 0.75, 0])  # one scale for both axes
    base = [
        f"data.path={ds}",
        "labels.k=3",
        "model.image_backbone=tiny_cnn",
        "model.canonical.mode=multi",
        "model.canonical.image=true",
        "model.coord_encoder=transformer",
        "model.transformer.dim=16",
        "model.transformer.layers=1",
        "model.transformer.heads=2",
        "model.coord_hidden=32",
        "model.heatmap.channels=[4,8]",
        "model.heatmap.out_dim=16",
        "model.heatmap.canvas_px=32",
        "train.epochs=1",
        "train.batch_size=16",
        "train.workers=0",
        "data.max_stars=8",
    ]
    s = train(load_config(ROOT / "configs" / "smoke.yaml", base), tmp_path / "shards", log=quiet)
    assert np.isfinite(s["best"]["val_loss"])
    cal = tmp_path / "ns-detector.json"
    emu.save(calib.calibrate_from_renders(build_render_config(config), 60), cal)
    s = train(
        load_config(
            ROOT / "configs" / "smoke.yaml",
            base
            + [
                "stream.kind=detections",
                f"stream.calibration={cal}",
                "stream.samples_per_epoch=64",
                "model.branches.image=false",
            ],
        ),
        tmp_path / "stream",
        log=quiet,
    )
    assert np.isfinite(s["best"]["val_loss"])


def test_fine_regions_head(smoke, tmp_path):
    """labels.fine_k: trained on finer regions, predicting the K regions by log-sum-exp; the
    checkpoint reloads with its grouping and its region probabilities sum to one."""
    cfg = _cfg(smoke, "train.epochs=1", "labels.fine_k=8")
    s = train(cfg, tmp_path / "fine", log=quiet)
    assert np.isfinite(s["best"]["val_loss"])
    ck = load_checkpoint(tmp_path / "fine" / "best.pt")
    model = ck.build_model()
    groups = model.fine_groups.numpy()
    assert set(groups.tolist()) == set(range(4)) and len(groups) == 8
    c, m = torch.rand(3, 8, 3) - 0.5, torch.ones(3, 8, dtype=torch.bool)
    with torch.no_grad():
        coarse, fine = model.eval()(None, c, m), model(None, c, m, fine=True)
    torch.testing.assert_close(torch.softmax(coarse, -1).sum(-1), torch.ones(3))
    # a region's probability is the sum of its fine regions'
    pf = torch.softmax(fine, -1)
    want = torch.stack([pf[:, torch.from_numpy(groups == g)].sum(-1) for g in range(4)], -1)
    torch.testing.assert_close(torch.softmax(coarse, -1), want, atol=1e-5, rtol=1e-4)
    # the prior the coarse-to-fine search uses: fine regions, consistent with the K regions
    from fusion.solve.base import Detections
    from fusion.solve.priors import load_prior

    fine_prior = load_prior(tmp_path / "fine" / "best.pt", level="fine")
    coarse_prior = fine_prior.at_level("coarse")
    assert fine_prior.level == "fine" and fine_prior.centroids.shape == (8, 3)
    assert coarse_prior.centroids.shape == (4, 3) and coarse_prior.model is fine_prior.model
    rng = np.random.default_rng(0)
    det = Detections(rng.uniform(0, 63, 6), rng.uniform(0, 63, 6), rng.uniform(1e3, 1e4, 6))
    pf, pc = fine_prior.probabilities(det), coarse_prior.probabilities(det)
    assert pf.shape == (8,) and pf.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(pc, [pf[groups == g].sum() for g in range(4)], atol=1e-6)
    with pytest.raises(ConfigError, match="must exceed"):
        _cfg(smoke, "labels.fine_k=3")


def test_geometry_prior_traced_gives_the_eager_probabilities(smoke, tmp_path):
    """A prior without an image branch runs traced (TorchScript, frozen) after its first frame: the same
    coarse and fine probabilities as the eager model (``fast=False``) on frames of 3 to 12 detections (the
    traced forward is not fixed to the first frame's count)."""
    from fusion.solve.base import Detections
    from fusion.solve.priors import load_prior

    cfg = _cfg(smoke, "train.epochs=1", "labels.fine_k=8", "model.branches.image=false")
    train(cfg, tmp_path / "geo", log=quiet)
    fast, eager = (load_prior(tmp_path / "geo" / "best.pt", level="fine", fast=f) for f in (True, False))
    rng = np.random.default_rng(1)
    for n in (5, 3, 4, 8, 12, 3):
        det = Detections(rng.uniform(0, 63, n), rng.uniform(0, 63, n), rng.uniform(1e3, 1e4, n))
        (cf, ff), (ce, fe) = fast.both(det), eager.both(det)
        np.testing.assert_allclose(cf, ce, atol=1e-5)
        np.testing.assert_allclose(ff, fe, atol=1e-5)
    assert isinstance(fast._traced, torch.jit.ScriptModule) and eager._traced is False


def test_frames_stream_binned_by_default_full_selectable():
    """stream.frames_renderer: binned (default) draws the stored image directly, full renders
    it; both give the Preprocessor the same scenes (labels, indices) and images that agree in
    distribution (same stars, independent noise), at any stored size the sensor bins to."""
    from skygen.config import config_dict
    from skygen.config import load_config as render_config

    assert load_config().stream.frames_renderer == "binned"
    assert load_config(overrides=["stream.frames_renderer=full"]).stream.frames_renderer == "full"
    with pytest.raises(ConfigError):
        load_config(overrides=["stream.frames_renderer=fast"])
    config = config_dict(render_config(overrides=["output.image_size_px=128"]))
    kw = dict(seed=5, batch=8, steps=1, max_stars=8)
    binned = StreamBatches(config, "frames", np.eye(3), **kw)
    full = StreamBatches(config, "frames", np.eye(3), frames_renderer="full", **kw)
    assert binned.stream().binned is not None and full.stream().binned is None
    a, b = binned.make_batch(0), full.make_batch(0)
    assert torch.equal(a["index"], b["index"]) and torch.equal(a["label"], b["label"])
    assert a["image"].shape == b["image"].shape == (8, 1, 128, 128)
    assert 0 < (a["image"] - b["image"]).abs().mean() < 0.05
    assert abs(float(a["image"].mean() - b["image"].mean())) < 0.01


def test_frames_batches_send_stored_adu_for_a_gpu(smoke, tmp_path):
    """stream.image_transfer: 'adu' hands the loader's stored uint16 ADU over (half the bytes of
    float32) and batch_inputs stretches them on the training device into the image the 'float'
    path makes in the loader; 'auto' picks adu only for a CUDA device; the training step takes
    either."""
    from fusion.model.inference import batch_inputs

    path, config, cal = smoke
    kw = dict(seed=3, batch=4, steps=2, max_stars=8)
    flt = StreamBatches(config, "frames", np.eye(3), **kw).make_batch(1)
    adu = StreamBatches(config, "frames", np.eye(3), adu_images=True, **kw).make_batch(1)
    assert "image" not in adu and adu["image_adu"].dtype == torch.uint16
    assert adu["image_adu"].element_size() * 2 == flt["image"].element_size()
    image, coords, mask = batch_inputs(adu, torch.device("cpu"))
    assert image.shape == flt["image"].shape and image.dtype == torch.float32
    torch.testing.assert_close(image, flt["image"], rtol=0, atol=1e-6)
    assert torch.equal(coords, flt["coords"]) and torch.equal(mask, flt["mask"])
    assert torch.equal(adu["label"], flt["label"])
    cfg = load_config(overrides=["stream.kind=frames"])
    assert cfg.stream.image_transfer == "auto"
    with pytest.raises(ConfigError, match="image_transfer"):
        load_config(overrides=["stream.image_transfer=int8"])
    from fusion.train.data import prepare_data

    cfg = _cfg(smoke, "stream.kind=frames", "model.branches.image=true", "model.image_backbone=tiny_cnn")
    data = prepare_data(cfg)
    for dev, sent in (("cpu", False), ("cuda", True)):
        assert StreamBatches.from_config(cfg, data.ds.config, data.regions, device=torch.device(dev)).adu_images is sent
    summary = train(
        _cfg(
            smoke,
            "train.epochs=1",
            "stream.kind=frames",
            "stream.samples_per_epoch=64",
            "stream.image_transfer=adu",
            "model.branches.image=true",
            "model.image_backbone=tiny_cnn",
        ),
        tmp_path / "adu",
        log=quiet,
    )
    assert summary["epochs_run"] == 1


@pytest.mark.parametrize("pixel_flux", [False, True])
def test_a_tied_model_trains_on_the_detections_stream_and_its_views_are_scored(smoke, tmp_path, pixel_flux):
    """model.image_backbone=peak_rows on the detections stream (no images in training; validation scores
    the fused output on the dataset's frames), and benchmarks/tied_views.py's fused column is exactly what
    `fusion evaluate` scores, whole and with three detections; with model.peaks.pixel_flux the checkpoint
    rebuilds its view with the training data's stretch (from the render config it carries)."""
    import importlib.util

    from fusion.measure.evaluate import evaluate_checkpoint
    from fusion.model.inputs import Preprocessor

    run = tmp_path / "tied"
    train(
        _cfg(
            smoke,
            "model.branches.image=true",
            "model.image_backbone=peak_rows",
            "model.canonical.mode=brightest",
            f"model.flux_dropout={0.0 if pixel_flux else 0.3}",
            f"model.peaks.pixel_flux={str(pixel_flux).lower()}",
            "train.epochs=2",
        ),
        run,
        log=quiet,
    )
    ckpt = load_checkpoint(run / "best.pt")
    view = ckpt.build_model().image.backbone
    assert ckpt.build_model().tied_view and view.pixel_flux == pixel_flux
    if pixel_flux:
        with open_dataset(smoke[0]) as d:
            pre = Preprocessor.from_configs(d.config, ckpt.fusion_config.data)
        assert (view.scale, view.top) == pre.stretch()[1:] and view.area == pre.geo.factor**2
    spec = importlib.util.spec_from_file_location("tied_views", ROOT / "benchmarks" / "tied_views.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "views.md"
    assert mod.main(["--checkpoint", str(run / "best.pt"), "--data", str(smoke[0]), "--out", str(out)]) == 0
    table = {
        line.split("|")[1].strip(): [float(x) for x in line.split("|")[2:-1]]
        for line in out.read_text().splitlines()
        if line.startswith("| whole") or line.startswith("| brightest 3 |")
    }
    whole = evaluate_checkpoint(run / "best.pt", smoke[0], "test", tmp_path / "e", log=quiet)
    three = evaluate_checkpoint(run / "best.pt", smoke[0], "test", tmp_path / "e3", log=quiet, keep_brightest=3)
    assert table["whole frame"][0] == pytest.approx(100 * whole["top1"], abs=0.051)  # the table has 0.1 %
    assert table["brightest 3"][0] == pytest.approx(100 * three["top1"], abs=0.051)
    assert table["whole frame"][2] == table["brightest 3"][2]  # the image view sees the whole frame in both
    if not pixel_flux:
        return
    # the views' weights are inference keys: `fusion evaluate --set` changes them on the trained model
    # (image weight 0: the detections view alone), other keys are refused
    alone = evaluate_checkpoint(
        run / "best.pt",
        smoke[0],
        "test",
        tmp_path / "w",
        log=quiet,
        overrides=["model.peaks.image_weight=[0,0]"],
    )
    assert alone["top1"] == pytest.approx(table["whole frame"][1] / 100, abs=0.00051)
    assert alone["overrides"] == ["model.peaks.image_weight=[0,0]"]
    assert "model.peaks.image_weight=[0,0]" in (tmp_path / "w" / "eval-test.md").read_text()
    with pytest.raises(ConfigError, match="cannot change on a trained model"):
        evaluate_checkpoint(run / "best.pt", smoke[0], "test", tmp_path / "x", log=quiet, overrides=["labels.k=3"])
    # --choose-weight scores the model's own setting as `fusion evaluate` does
    grid = tmp_path / "grid.md"
    args = ["--checkpoint", str(run / "best.pt"), "--data", str(smoke[0]), "--noise", "--choose-weight"]
    mod.main([*args, "--out", str(grid)])
    own = [line for line in grid.read_text().splitlines() if line.startswith("| [0.5, 0.5] | [3, 8] |")]
    assert float(own[-1].split("|")[3]) == pytest.approx(100 * whole["top1"], abs=0.051)
