"""Detector: finds stars, centroids them accurately, and rarely invents any."""

import dataclasses

import numpy as np
import pytest

from skygen.config import load_config
from skygen.instrument.detect import detect, estimate_background, match
from skygen.instrument.psf import add_patch, stamp
from skygen.instrument.sensor import Exposure, read_out, sensor_maps


def frame_with_stars(xs, ys, flux, seed=0, size=512):
    s = dataclasses.replace(load_config().sensor, dead_pixel_fraction=0.0)
    maps = sensor_maps(size, size, s.sensor_seed, s.prnu_frac, s.fpn_adu, s.bias_adu, 0.0, s.hot_pixel_dark_e_s, 0.0)
    star = np.zeros((size, size), np.float32)
    boxes = []
    for x, y in zip(xs, ys):
        y0, x0, p = stamp(x, y, flux, "gaussian", 1.2)
        boxes.append(add_patch(star, y0, x0, p))
    img, _ = read_out(Exposure(star, None, boxes, 7.7), s, maps, np.random.default_rng(seed))
    return img


def test_centroid_recovery_of_bright_stars():
    rng = np.random.default_rng(0)
    gx, gy = np.meshgrid(np.arange(6) * 80 + 40.0, np.arange(5) * 90 + 40.0)  # well separated
    xs, ys = gx.ravel() + rng.uniform(-0.5, 0.5, 30), gy.ravel() + rng.uniform(-0.5, 0.5, 30)
    img = frame_with_stars(xs, ys, 20000.0)
    det, bg, sigma = detect(img)
    idx = match(det["x_px"], det["y_px"], xs, ys, np.ones(30), 2.0)
    assert (idx >= 0).sum() == 30
    err = np.hypot(det["x_px"][idx >= 0] - xs[idx[idx >= 0]], det["y_px"][idx >= 0] - ys[idx[idx >= 0]])
    assert np.sqrt(np.mean(err**2)) < 0.05


def test_background_and_noise_estimate():
    img = frame_with_stars([], [], 0.0)
    s = load_config().sensor
    bg, sigma = estimate_background(img)
    expected = np.sqrt((7.7 + s.read_noise_e**2) / s.gain_e_per_adu**2 + 1 / 12 + s.fpn_adu**2)
    assert abs(bg - (s.bias_adu + 7.7 / s.gain_e_per_adu - 0.5)) < 0.2
    assert abs(sigma / expected - 1) < 0.1


def test_no_detections_on_pure_noise():
    n = sum(len(detect(frame_with_stars([], [], 0.0, seed=k))[0]["x_px"]) for k in range(5))
    assert n <= 1


def test_crushed_blacks_set_no_threshold_below_the_adc_rounding():
    """An 8-bit JPEG's dark sky is one value (0) with compression speckles of 1-3 ADU: its measured noise is ~0, and
    a threshold of five times that would make every speckle a source. The noise estimate stops at the rounding's
    own 1 / sqrt(12) ADU, so the speckles stay below the threshold and the one star is found."""
    rng = np.random.default_rng(2)
    img = np.zeros((256, 256), np.float32)
    spots = rng.integers(0, 256, (300, 2))
    img[spots[:, 0], spots[:, 1]] = 1.0  # isolated one-ADU speckles
    img[10:12, 10:12] = 1.0  # a 2 x 2 one: four pixels at 1 ADU
    y, x = np.mgrid[0:256, 0:256]
    img += np.round(60 * np.exp(-((x - 128.3) ** 2 + (y - 99.6) ** 2) / (2 * 1.5**2)))
    bg, sigma = estimate_background(img)
    assert bg == 0.0 and sigma == pytest.approx(1 / np.sqrt(12))
    det, _, _ = detect(img, max_detections=200)
    assert len(det["x_px"]) == 1 and abs(det["x_px"][0] - 128.3) < 0.1 and abs(det["y_px"][0] - 99.6) < 0.1


def test_brightest_first_and_match_is_one_to_one():
    img = frame_with_stars([100.0, 300.0, 400.0], [100.0, 300.0, 120.0], 5000.0)
    img2 = frame_with_stars([100.0], [100.0], 50000.0, seed=1)
    both = np.maximum(img, img2)
    det, _, _ = detect(both)
    assert np.all(np.diff(det["flux_adu"]) <= 0)
    idx = match(det["x_px"], det["y_px"], np.array([100.0, 100.5]), np.array([100.0, 100.0]), np.array([1.0, 2.0]), 2.0)
    assert sorted(idx[idx >= 0].tolist()) == [1]  # two stars, one detection: brightest claims it


def test_local_background_follows_a_sky_gradient():
    """Sky glow rising 80 ADU across the frame (ground frames): one global level loses the stars on
    the dark side under a sea of false pixels on the bright side; the box background finds every star."""
    from skygen.instrument.detect import background_map

    rng = np.random.default_rng(2)
    gx, gy = np.meshgrid(np.arange(6) * 80 + 40.0, np.arange(5) * 90 + 40.0)
    xs, ys = gx.ravel() + rng.uniform(-0.5, 0.5, 30), gy.ravel() + rng.uniform(-0.5, 0.5, 30)
    flat = frame_with_stars(xs, ys, 3000.0)
    ramp = np.linspace(0.0, 80.0, flat.shape[1], dtype=np.float32)[None, :]
    img = flat.astype(np.float32) + ramp
    bg_flat, _ = estimate_background(flat)
    level, sigma = background_map(img, 64)
    assert level.shape == img.shape
    assert np.abs(level - (bg_flat + ramp)).max() < 3.0  # the ramp is followed
    det_global, _, _ = detect(img)
    det_local, _, _ = detect(img, background_box_px=64)
    found = lambda d: (match(d["x_px"], d["y_px"], xs, ys, np.ones(30), 2.0) >= 0).sum()  # noqa: E731
    assert found(det_global) < 25
    assert found(det_local) == 30 and len(det_local["x_px"]) <= 31
    # on a flat frame the local background gives the global detections
    a, _, _ = detect(flat)
    b, _, _ = detect(flat, background_box_px=64)
    assert len(a["x_px"]) == len(b["x_px"]) == 30
    ia, ib = (match(d["x_px"], d["y_px"], xs, ys, np.ones(30), 2.0) for d in (a, b))
    pos = lambda d, i: np.column_stack([d["x_px"], d["y_px"]])[np.argsort(i)]  # noqa: E731  (true-star order)
    np.testing.assert_allclose(pos(b, ib), pos(a, ia), atol=0.05)  # box levels differ by noise


@pytest.mark.parametrize("shape", [(768, 1024), (100, 70), (65, 64)])
def test_separable_background_interpolation_equals_bilinear_map_coordinates(shape):
    """background_map interpolates its box mesh as weights @ mesh @ weights.T: the numbers of
    ndimage.map_coordinates(order=1) at the same fractional indices."""
    from scipy import ndimage

    from skygen.instrument.detect import _linear_weights

    rng = np.random.default_rng(1)
    h, w = shape
    pos_y = np.sort(rng.uniform(0, 9, h))
    pos_x = np.sort(rng.uniform(0, 12, w))
    mesh = rng.normal(100, 5, (10, 13))
    ref = ndimage.map_coordinates(mesh, np.stack(np.meshgrid(pos_y, pos_x, indexing="ij")), order=1, mode="nearest")
    np.testing.assert_allclose(_linear_weights(pos_y, 10) @ mesh @ _linear_weights(pos_x, 13).T, ref, atol=1e-10)


@pytest.mark.parametrize("shape, box", [((256, 320), 64), ((300, 250), 64), ((200, 200), 16), ((130, 97), 40)])
def test_box_backgrounds_at_once_equal_the_per_box_estimates(shape, box):
    """background_map estimates its whole boxes in one vectorised pass: the per-box clipped median/mean and
    noise of estimate_background, up to float32 summation order, including boxes holding a bright star
    (clipped away) and a quantised sky; partial edge boxes still go one at a time."""
    from skygen.instrument.detect import _whole_box_backgrounds, estimate_background

    rng = np.random.default_rng(4)
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.round(200 + 0.03 * xx + rng.normal(0, 3, shape))  # a gradient, integer ADU
    img[h // 3 : h // 3 + 4, w // 2 : w // 2 + 4] += 5000  # a star
    stride = 2 if box >= 32 else 1
    fy, fx = h // box, w // box
    level, sigma = _whole_box_backgrounds(img, box, stride, fy, fx)
    ref = np.array(
        [
            [estimate_background(img[i * box : (i + 1) * box, j * box : (j + 1) * box], stride) for j in range(fx)]
            for i in range(fy)
        ]
    )
    np.testing.assert_allclose(level, ref[..., 0], rtol=1e-6)
    np.testing.assert_allclose(sigma, ref[..., 1], rtol=1e-5)
    assert np.all(np.abs(sigma - 3) < 1.0)  # the star is clipped: the noise stays the sky's


@pytest.mark.parametrize("box", [0, 64])
def test_detect_with_its_background_given_finds_the_same_stars(box):
    """detect(background=...) skips the estimate (fit-camera tries five thresholds per frame): given the very
    estimate it would make, the detections and the returned level and noise are the same; maps of another
    shape are refused."""
    from skygen.instrument.detect import background_map, detect, estimate_background

    rng = np.random.default_rng(7)
    img = rng.normal(300, 6, (256, 320))
    for y, x in rng.uniform(10, 240, (12, 2)):
        img[int(y) - 1 : int(y) + 2, int(x) - 1 : int(x) + 2] += rng.uniform(200, 2000)
    img = np.round(img)
    if box:
        lv, sg = background_map(img, box)
        given = (lv, sg, float(np.median(lv)), float(np.median(sg)))
    else:
        given = estimate_background(img)
    for thr in (3.0, 5.0):
        ref, bg, sigma = detect(img, thr, 3, 100, box)
        got, bg2, sigma2 = detect(img, thr, 3, 100, box, background=given)
        assert (bg2, sigma2) == (bg, sigma) and len(ref["x_px"]) >= 10
        for k in ref:
            np.testing.assert_array_equal(got[k], ref[k])
    if box:
        got, _, _ = detect(img, 5.0, 3, 100, box, background=given[:2])  # the medians are optional
        np.testing.assert_array_equal(got["x_px"], detect(img, 5.0, 3, 100, box)[0]["x_px"])
        with pytest.raises(ValueError, match="shape"):
            detect(img, 5.0, 3, 100, box, background=(lv[:-1], sg[:-1]))
