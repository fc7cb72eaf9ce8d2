"""The torch backend against the NumPy renderer: same scene, same light, same noise law."""

import dataclasses

import numpy as np
import pytest
import torch

from skygen.config import load_config
from skygen.errors import ConfigError
from skygen.instrument import corruptions as corr
from skygen.render.frame import Renderer
from skygen.render.torch_frames import TorchRenderer, render_batch

CLEAN = [f"corruptions.{name}=0" for name in corr.REGISTRY]
H = W = 256


@pytest.fixture(scope="module")
def small(small_overrides):
    return small_overrides + ["render.backend=torch"]


def numpy_star_light(r: Renderer, scene) -> np.ndarray:
    out = np.zeros((r.cfg.camera.height_px, r.cfg.camera.width_px), np.float32)
    r.deposit(scene.stars, out)
    return out.astype(np.float64)


@pytest.mark.parametrize(
    "extra",
    [
        [],
        ["corruptions.motion_blur=1.0", "corruptions.false_stars=3"],
        ["optics.psf=moffat"],
        ["optics.psf=airy", "corruptions.motion_blur=0.5"],
    ],
)
def test_same_scene_and_same_star_light_as_numpy(small, extra):
    tr = TorchRenderer(load_config(overrides=small + extra))
    ref = Renderer(load_config(overrides=small + extra))
    scenes = tr.scenes([5, 6])
    light = tr.star_light(scenes).view(2, H, W).double().numpy()
    for b, sc in enumerate(scenes):
        own = ref.scene(sc.index)
        for k in ("hip_id", "x_px", "y_px", "electrons"):
            assert np.array_equal(sc.stars[k], own.stars[k]), k
        want = numpy_star_light(ref, own)
        # the same pixel integrals; Gaussian stamps differ only in where faint wings are cut (< 0.01 e-)
        assert np.abs(light[b] - want).max() < 0.02 + 1e-6 * want.max()
        assert abs(light[b].sum() - want.sum()) < 0.05 * max(1, len(sc.stars["x_px"]))


@pytest.mark.parametrize("blur", [0.0, 1.0])
def test_flux_is_conserved(small, blur):
    tr = TorchRenderer(load_config(overrides=small + CLEAN + [f"corruptions.motion_blur={blur}"]))
    scenes = tr.scenes(range(4))
    light = tr.star_light(scenes).view(4, H, W).double()
    for b, sc in enumerate(scenes):
        st = sc.stars
        xs = st["x_px"][:, None] if st["paths"] is None else st["paths"][0]
        ys = st["y_px"][:, None] if st["paths"] is None else st["paths"][1]
        m = tr.radius + 1
        inside = (xs.min(1) > m) & (xs.max(1) < W - 1 - m) & (ys.min(1) > m) & (ys.max(1) < H - 1 - m)
        assert inside.sum() >= 5
        total = float(light[b].sum())
        assert total <= st["electrons"].sum() * (1 + 1e-6)
        assert total >= st["electrons"][inside].sum() * (1 - 1e-6)
        # each fully inside star's light, summed around it, is its flux
        s = int(np.flatnonzero(inside)[0])
        xa, xb = int(np.floor(xs[s].min() + 0.5)) - m, int(np.floor(xs[s].max() + 0.5)) + m + 1
        ya, yb = int(np.floor(ys[s].min() + 0.5)) - m, int(np.floor(ys[s].max() + 0.5)) + m + 1
        assert float(light[b, ya:yb, xa:xb].sum()) >= st["electrons"][s] * (1 - 1e-5)


def quiet(small, **sensor):
    sets = (
        small
        + CLEAN
        + [
            "sensor.fpn_adu=0",
            "sensor.prnu_frac=0",
            "sensor.dead_pixel_fraction=0",
            "sensor.gain_e_per_adu=1.7",
            "sensor.read_noise_e=3.0",
        ]
    )
    return sets + [f"sensor.{k}={v}" for k, v in sensor.items()]


@pytest.mark.parametrize("sampler", ["fast", "exact"])
@pytest.mark.parametrize("lam", [3.0, 40.0])
def test_background_noise_matches_formula(small, sampler, lam):
    """floor((Poisson(lam) + N(0, s)) / g): mean lam/g - 1/2, variance (lam + s^2)/g^2 + 1/12."""
    tr = TorchRenderer(load_config(overrides=quiet(small, sampler=sampler)))
    g = tr.cfg.sensor.gain_e_per_adu
    star = torch.zeros(4, H * W)
    adu, _ = tr.read_out(star, None, torch.tensor(lam), torch.Generator().manual_seed(0))
    x = adu.double().numpy().ravel() - tr.cfg.sensor.bias_adu
    mean, var = lam / g - 0.5, (lam + 9.0) / g**2 + 1 / 12
    assert abs(x.mean() - mean) < 5 * np.sqrt(var / x.size)
    assert abs(x.var() / var - 1) < 5 * np.sqrt(2 / x.size) + 0.01


def test_fast_background_probabilities_are_exact(small):
    """The LUT draw of the uniform background against the exact ADU distribution (chi^2)."""
    from scipy import stats

    from skygen.instrument.sensor import background_sampler

    tr = TorchRenderer(load_config(overrides=quiet(small)))
    smp = background_sampler(12.0, 3.0, 1.7)
    adu = tr._dense_background(12.0, (8, H * W), torch.Generator().manual_seed(3))
    j = adu.numpy().ravel().astype(np.int64) - tr.cfg.sensor.bias_adu - smp.kmin
    counts = np.bincount(j, minlength=len(smp.pmf))
    expected = smp.pmf * j.size
    ok = expected > 50
    chi2 = ((counts[ok] - expected[ok]) ** 2 / expected[ok]).sum()
    assert chi2 < stats.chi2.ppf(0.999, ok.sum() - 1)


@pytest.mark.parametrize("sampler", ["fast", "exact"])
def test_shot_noise_of_star_light_and_prnu(small, sampler):
    """Illuminated pixels: variance = signal * prnu + background + read^2 (in e-, gain 1) + 1/12."""
    tr = TorchRenderer(
        load_config(
            overrides=quiet(
                small, sampler=sampler, gain_e_per_adu=1.0, read_noise_e=2.0, full_well_e=1e6, prnu_frac=0.02
            )
        )
    )
    signal = 500.0
    star = torch.full((4, H * W), signal)
    adu, _ = tr.read_out(star, None, torch.tensor(10.0), torch.Generator().manual_seed(1))
    x = adu.double().numpy().reshape(4, -1) - tr.cfg.sensor.bias_adu
    lam = signal * tr.prnu.double().numpy() + 10.0
    resid = x - (lam - 0.5)  # remove the static PRNU pattern, keep the noise
    assert abs(resid.mean()) < 0.1
    assert abs(resid.var() / (lam.mean() + 4.0 + 1 / 12) - 1) < 0.02


def test_hot_pixels_cosmic_rays_and_saturation(small):
    tr = TorchRenderer(
        load_config(overrides=small + CLEAN + ["corruptions.hotpixels=2e-3", "corruptions.cosmic_rays=20000"])
    )
    scenes = tr.scenes(range(3))
    assert sum(len(sc.cosmic_rays) for sc in scenes) > 3
    charge = tr.cosmic_charge(scenes)
    want = sum(p.sum() for sc in scenes for _, _, p in sc.cosmic_rays)
    assert float(charge.double().sum()) == pytest.approx(want, rel=1e-5)  # tracks are clipped inside already
    full = tr.rasterise(scenes, full_res=True).full.view(3, -1).numpy()
    hot = full[:, tr.base.maps.hot_index]
    assert np.median(hot) > np.median(full) + 50
    # one pixel far above full well: the ADC clips, blooming spreads it along its column only
    star = torch.zeros(1, H * W)
    star[0, 100 * W + 100] = 2e5
    for sampler in ("fast", "exact"):
        t2 = TorchRenderer(load_config(overrides=small + CLEAN + [f"sensor.sampler={sampler}"]))
        adu, bloomed = t2.read_out(star, None, torch.tensor(t2.base.background_e), torch.Generator().manual_seed(2))
        img = adu.view(H, W).numpy()
        assert bloomed == [1]
        assert (
            img[100, 100] == min(2**12 - 1, np.floor(13500 / 3.3) + t2.offset[100 * W + 100].item())
            or img[100, 100] >= 2**12 - 1 - 10
        )
        col = img[:, 100] - np.median(img)
        assert (col > 1000).sum() >= 2e5 / 13500 - 2  # the charge spread over ~15 rows
        assert (img[:, 99] - np.median(img)).max() < 1000  # but not into the next column


@pytest.mark.parametrize("sampler", ["fast", "exact"])
def test_a_saturating_star_blooms_and_keeps_its_charge(small, sampler):
    tr = TorchRenderer(load_config(overrides=small + CLEAN + [f"sensor.sampler={sampler}"]))
    sc = tr.scenes([2])[0]
    st = sc.stars
    s = int(np.argmin((st["x_px"] - W / 2) ** 2 + (st["y_px"] - H / 2) ** 2))
    flux = 2e6  # the central column alone fills ~47 pixels: the spill runs far beyond the star's stamp
    st["electrons"] = np.where(np.arange(len(st["electrons"])) == s, flux, st["electrons"])
    b = tr.rasterise([sc], torch.Generator().manual_seed(4), full_res=True)
    assert b.logs[0]["blooming"]["columns"] >= 1
    img = b.full[0].double().numpy()
    x = int(round(st["x_px"][s]))
    box = img[:, x - 6 : x + 7] - np.median(img)
    assert (box[:, 6] >= 2**12 - 1 - 200).sum() >= flux / 13500 / 5  # a saturated run along the column
    assert (box[:, 0] < 200).all() and (box[:, -1] < 200).all()  # not spread sideways
    # charge spilled along the columns, not lost (the ADC clips a full pixel at 4095 ADU = 13,184 e-, 2 % low)
    got = box.sum() * tr.cfg.sensor.gain_e_per_adu
    assert 0.9 * flux < got < 1.05 * flux


def test_stored_image_is_the_area_average(small):
    tr = TorchRenderer(load_config(overrides=small))
    b = tr.render_batch([0, 1], full_res=True)
    f = b.full.view(2, 64, 4, 64, 4).double().mean(dim=(2, 4))
    assert torch.allclose(b.images.double(), f, atol=1e-4)
    u16 = tr.render_batch([0, 1], dtype=torch.uint16)
    assert u16.images.dtype == torch.uint16 and u16.images.shape == (2, 64, 64)
    assert np.array_equal(u16.images.to(torch.int32).numpy(), np.round(b.images.numpy()).astype(np.int32))
    cv = tr.base.downsample(b.full[0].to(torch.int32).numpy().astype(np.uint16)).astype(np.int32)
    assert np.abs(cv - np.round(b.images[0].numpy())).max() <= 1  # cv2 INTER_AREA up to rounding


def test_generator_makes_batches_repeatable(small):
    cfg = load_config(overrides=small)
    a = render_batch(cfg, [3, 4], "cpu", torch.Generator().manual_seed(7)).images
    b = render_batch(cfg, [3, 4], "cpu", torch.Generator().manual_seed(7)).images
    c = render_batch(cfg, [3, 4], "cpu", torch.Generator().manual_seed(8)).images
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert torch.equal(render_batch(cfg, [3, 4]).images, render_batch(cfg, [3, 4]).images)  # derived from (seed, 3)
    batch = render_batch(cfg, [3, 4])
    frame = Renderer(cfg).render(4)
    assert np.allclose(batch.unit_vectors[1], frame.unit_vector)
    assert np.array_equal(batch.true_stars(1)["x_px"], frame.stars["x_px"])


def detector_stats(frames, limit: float) -> dict:
    """Completeness of stars brighter than limit - 0.5 and the centroid error of their detections."""
    found, total, err, n_det, false = 0, 0, [], 0, 0
    for f in frames:
        bright = np.flatnonzero((f.stars["mag"] < limit - 0.5) & (f.stars["hip_id"] >= 0))
        d = f.detections
        n_det += len(d["x_px"])
        false += int((d["hip_id"] < 0).sum())
        for s in bright:
            j = np.flatnonzero(d["star_index"] == s)
            total += 1
            if len(j):
                found += 1
                err.append(np.hypot(d["x_px"][j[0]] - f.stars["x_px"][s], d["y_px"][j[0]] - f.stars["y_px"][s]))
    return {
        "completeness": found / total,
        "median_err_px": float(np.median(err)),
        "n_det": n_det,
        "false": false,
        "n_bright": total,
    }


def compare_detections(overrides, n: int, device: str = "cpu") -> tuple[dict, dict]:
    ref = Renderer(load_config(overrides=overrides))
    tr = TorchRenderer(load_config(overrides=overrides + ["render.backend=torch"]), device, renderer=ref)
    a = detector_stats([ref.render(i) for i in range(n)], ref.detection_limit_mag)
    frames = []
    for s in range(0, n, 8):
        frames += tr.frames(tr.render_batch(range(s, min(s + 8, n)), full_res=True))
    b = detector_stats(frames, ref.detection_limit_mag)
    assert abs(a["completeness"] - b["completeness"]) < 0.04, (a, b)
    assert abs(a["median_err_px"] - b["median_err_px"]) < 0.25 * a["median_err_px"] + 0.01, (a, b)
    assert abs(a["n_det"] - b["n_det"]) < 4 * np.sqrt(a["n_det"]) + 0.05 * a["n_det"], (a, b)
    return a, b


def test_detector_sees_the_same_on_both_backends(small_overrides):
    a, b = compare_detections(small_overrides, 24)
    assert a["n_bright"] > 300


@pytest.mark.slow
def test_detector_sees_the_same_on_both_backends_full_size():
    compare_detections([], 40)


def test_device_errors_are_config_errors(small, tmp_path):
    with pytest.raises(ConfigError, match="needs render.backend=torch"):
        load_config(overrides=["render.device=cuda"])
    with pytest.raises(ConfigError, match="render.device"):
        load_config(overrides=["render.backend=torch", "render.device=gpu"])
    with pytest.raises(ConfigError, match="render.backend"):
        load_config(overrides=["render.backend=jax"])
    if not torch.cuda.is_available():
        from skygen.datasets.build import render_dataset

        cfg = load_config(overrides=small + ["render.device=cuda"])
        with pytest.raises(ConfigError, match="CUDA is not available"):
            TorchRenderer(cfg)
        with pytest.raises(ConfigError, match="CUDA is not available"):
            render_dataset(cfg, tmp_path / "never", progress=False)
        assert not (tmp_path / "never").exists()


def test_dataset_with_torch_backend_is_deterministic_and_keeps_numpy_ids(small, tmp_path):
    from skygen.config import config_dict
    from skygen.datasets.build import render_dataset
    from skygen.datasets.shards import config_id, open_dataset

    cfg = load_config(overrides=small + ["n_frames=6", "output.shard_size=4", "render.batch_size=3"])
    m1 = render_dataset(cfg, tmp_path / "a", progress=False)
    render_dataset(cfg, tmp_path / "b", progress=False)
    with open_dataset(tmp_path / "a") as da, open_dataset(tmp_path / "b") as db:
        assert len(da) == 6 and da.image(5).dtype == np.uint16 and len(da.detections(5)["x_px"]) > 5
        for i in range(6):
            assert np.array_equal(da.image(i), db.image(i))
            assert np.array_equal(da.detections(i)["x_px"], db.detections(i)["x_px"])
    numpy_cfg = dataclasses.replace(cfg, render=dataclasses.replace(cfg.render, backend="numpy"))
    d = config_dict(numpy_cfg)
    assert config_id(d) == config_id({k: v for k, v in d.items() if k != "render"}) != m1["dataset_id"]


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_frames_match_cpu_frames_in_distribution(small_overrides):
    cpu = TorchRenderer(load_config(overrides=small_overrides + ["render.backend=torch"]))
    gpu = TorchRenderer(load_config(overrides=small_overrides + ["render.backend=torch", "render.device=cuda"]))
    scenes = cpu.scenes(range(16))
    assert torch.allclose(gpu.star_light(scenes).cpu(), cpu.star_light(scenes), atol=1e-3)
    a = cpu.rasterise(scenes).images
    b = gpu.rasterise(scenes).images.cpu()
    assert abs(a.mean().item() - b.mean().item()) < 0.01
    assert abs(a.std().item() / b.std().item() - 1) < 0.02
    compare_detections(small_overrides, 24, "cuda")
