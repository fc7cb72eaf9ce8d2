"""Each augmentation keeps the image and the detections in agreement."""

import numpy as np
import pytest
from scipy import ndimage

from fusion.config import AugConfig
from fusion.model.inputs import FrameGeometry, Sample
from fusion.model.shards import read_sample
from fusion.testing import small_dataset
from fusion.train.augment import _gaussian_stamp, add_noise, augment, drop_stars, inject_false_stars, jitter, rotate
from skygen.datasets.shards import open_dataset

GEO = FrameGeometry(sensor_px=256, image_px=64, factor=4, bias_adu=100.0, max_adu=4095.0, psf_sigma_px=1.2)


def synthetic(xs, ys, fluxes, geo=GEO, bg=103.0):
    """A flat background with Gaussian stars at full-resolution positions, and their detections."""
    img = np.full((geo.image_px, geo.image_px), bg, np.float32)
    sig = np.sqrt(geo.psf_sigma_px**2 + geo.factor**2 / 12) / geo.factor
    for x, y, f in zip(xs, ys, fluxes):
        u, v = geo.to_stored(np.array([x, y]))
        _gaussian_stamp(img, u, v, f / geo.factor**2, sig)
    n = len(xs)
    return Sample(
        img,
        np.asarray(xs, float),
        np.asarray(ys, float),
        np.asarray(fluxes, np.float32),
        np.full(n, 20, np.int32),
        bg,
        0.5,
    ).sorted()


def peak_near(img, u, v, r=2):
    """Position (u, v) of the brightest stored pixel within r pixels of (u, v)."""
    y0, x0 = int(round(v)), int(round(u))
    ys, xs = slice(max(y0 - r, 0), y0 + r + 1), slice(max(x0 - r, 0), x0 + r + 1)
    win = img[ys, xs]
    j, i = np.unravel_index(np.argmax(win), win.shape)
    return xs.start + i, ys.start + j, win.max()


def centroid_near(img, u, v, bg, r=3):
    y0, x0 = int(round(v)), int(round(u))
    ys, xs = slice(max(y0 - r, 0), y0 + r + 1), slice(max(x0 - r, 0), x0 + r + 1)
    w = np.clip(img[ys, xs] - bg, 0, None)
    yy, xx = np.mgrid[ys, xs]
    return (w * xx).sum() / w.sum(), (w * yy).sum() / w.sum()


@pytest.mark.parametrize("theta", [-10.0, -3.3, 7.0, 45.0, 90.0, 180.0])
def test_rotation_moves_image_and_detections_together(theta):
    s = synthetic([40.3, 128.0, 200.7], [60.2, 127.5, 180.1], [20000, 12000, 8000])
    r = rotate(s, theta, GEO)
    assert r.n == 3
    for x, y in zip(r.x_px, r.y_px):
        u, v = GEO.to_stored(np.array([x, y]))
        cu, cv = centroid_near(r.image, u, v, s.background_adu)
        assert abs(cu - u) < 0.15 and abs(cv - v) < 0.15, (theta, cu - u, cv - v)


def test_rotation_by_90_degrees_is_exact_on_the_pixel_grid():
    img = np.full((64, 64), 100.0, np.float32)
    img[10, 20] = 1000.0  # stored (u, v) = (20, 10)
    x, y = GEO.to_full(np.array([20.0, 10.0]))
    s = Sample(img, np.array([x]), np.array([y]), np.array([1000.0], np.float32), np.array([4], np.int32), 100.0, 0.5)
    r = rotate(s, 90.0, GEO)
    u, v = GEO.to_stored(np.array([r.x_px[0], r.y_px[0]]))
    # x' = c - (y - c), y' = c + (x - c) with c = 31.5 in stored pixels
    assert (u, v) == pytest.approx((53.0, 20.0))
    assert np.unravel_index(np.argmax(r.image), r.image.shape) == (20, 53)
    assert r.image[20, 53] == pytest.approx(1000.0)


def test_rotation_drops_detections_that_leave_the_sensor():
    s = synthetic([2.0, 128.0], [2.0, 128.0], [5000, 5000])
    r = rotate(s, 45.0, GEO)
    assert r.n == 1 and r.x_px[0] == pytest.approx(128.0 + (0.5 - 0.5), abs=1.0)


def test_rotation_on_a_real_frame_keeps_stars_on_their_detections():
    with open_dataset(small_dataset("uniform")) as ds:
        geo = FrameGeometry.from_render_config(ds.config)
        s = read_sample(ds, 3, geo)
        r = rotate(s, 8.0, geo)
        assert r.n >= 3
        for x, y in zip(r.x_px[:3], r.y_px[:3]):
            u, v = geo.to_stored(np.array([x, y]))
            pu, pv, peak = peak_near(r.image, u, v, r=1)
            assert np.hypot(pu - u, pv - v) <= 1.5
            assert peak > s.background_adu + 5 * s.noise_adu


def test_jitter_scales_image_signal_and_fluxes_alike():
    s = synthetic([100.0], [100.0], [30000])
    j = jitter(s, 1.3, 2.0, GEO)
    assert j.flux_adu[0] == pytest.approx(1.3 * s.flux_adu[0])
    u, v = GEO.to_stored(np.array([100.0, 100.0]))
    box = (slice(int(v) - 4, int(v) + 5), slice(int(u) - 4, int(u) + 5))
    sig0 = (s.image[box] - s.background_adu).sum()
    sig1 = (j.image[box] - j.background_adu).sum()
    assert sig1 / sig0 == pytest.approx(1.3, rel=1e-4)
    assert j.background_adu == pytest.approx(GEO.bias_adu + 1.3 * (s.background_adu - GEO.bias_adu) + 2.0)


def test_noise_leaves_detections_and_adds_the_stated_sigma():
    s = synthetic([100.0], [100.0], [30000])
    n = add_noise(s, 3.0, np.random.default_rng(0))
    np.testing.assert_array_equal(n.x_px, s.x_px)
    np.testing.assert_array_equal(n.flux_adu, s.flux_adu)
    assert np.std(n.image - s.image) == pytest.approx(3.0, rel=0.05)


@pytest.mark.parametrize("erase", [False, True])
def test_dropout_removes_detections_and_optionally_the_star(erase):
    s = synthetic([40.0, 128.0, 200.0, 60.0], [40.0, 128.0, 200.0, 190.0], [30000, 20000, 10000, 9000])
    d = drop_stars(s, 0.5, np.random.default_rng(1), GEO, erase_image=erase)
    kept = {(round(x, 3), round(y, 3)) for x, y in zip(d.x_px, d.y_px)}
    dropped = [(x, y) for x, y in zip(s.x_px, s.y_px) if (round(x, 3), round(y, 3)) not in kept]
    assert 0 < len(dropped) < 4
    for x, y in zip(d.x_px, d.y_px):  # kept stars still visible where the list says
        u, v = GEO.to_stored(np.array([x, y]))
        assert peak_near(d.image, u, v)[2] > s.background_adu + 50
    for x, y in dropped:
        u, v = GEO.to_stored(np.array([x, y]))
        peak = peak_near(d.image, u, v)[2]
        if erase:
            assert peak < s.background_adu + 6 * s.noise_adu
        else:
            assert peak > s.background_adu + 50


def test_false_stars_appear_in_image_and_list_brightest_first():
    s = synthetic([128.0], [128.0], [3000])
    f = inject_false_stars(s, 3, (50.0, 200.0), np.random.default_rng(2), GEO)
    assert f.n == 4
    assert np.all(np.diff(f.flux_adu) <= 0)
    labels, _ = ndimage.label(f.image > s.background_adu + 3 * s.noise_adu)
    for x, y, flux in zip(f.x_px, f.y_px, f.flux_adu):
        u, v = GEO.to_stored(np.array([x, y]))
        cu, cv = centroid_near(f.image, u, v, s.background_adu)
        assert abs(cu - u) < 0.3 and abs(cv - v) < 0.3
        # the painted signal integrates to the listed flux (stored pixels are block means)
        box = (slice(int(v) - 5, int(v) + 6), slice(int(u) - 5, int(u) + 6))
        if flux != s.flux_adu[0]:
            painted = (f.image[box] - s.image[box]).sum() * GEO.factor**2
            assert painted == pytest.approx(flux, rel=0.02)


def test_full_augmentation_keeps_every_detection_on_a_star():
    with open_dataset(small_dataset("uniform")) as ds:
        geo = FrameGeometry.from_render_config(ds.config)
        cfg = AugConfig(dropout_prob=0.2, false_star_rate=2.0, rotation_max_deg=10.0)
        for i in range(6):
            s = read_sample(ds, i, geo)
            a = augment(s, cfg, np.random.default_rng([0, i]), geo)
            assert np.all(np.diff(a.flux_adu) <= 0)
            for x, y in zip(a.x_px[:4], a.y_px[:4]):
                u, v = geo.to_stored(np.array([x, y]))
                pu, pv, peak = peak_near(a.image, u, v, r=1)  # r=1: hot pixels and cosmic rays lie about
                assert np.hypot(pu - u, pv - v) <= 1.5
                assert peak > a.background_adu + 3 * a.noise_adu


def test_each_switch_turns_its_augmentation_off():
    with open_dataset(small_dataset("uniform")) as ds:
        geo = FrameGeometry.from_render_config(ds.config)
        s = read_sample(ds, 0, geo)
        off = AugConfig(rotation=False, jitter=False, noise=False, dropout=False, false_stars=False)
        a = augment(s, off, np.random.default_rng(0), geo)
        np.testing.assert_array_equal(a.image, s.image)
        np.testing.assert_array_equal(a.x_px, s.x_px)
