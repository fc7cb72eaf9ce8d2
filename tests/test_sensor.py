"""Sensor physics: noise variance against the formula, samplers agree, blooming, maps."""

import dataclasses

import numpy as np
import pytest
from scipy import stats

from skygen.config import load_config
from skygen.instrument.photometry import dark_current_e_s
from skygen.instrument.sensor import BackgroundSampler, Exposure, bloom, read_out, sensor_maps

H = W = 256


def quiet_sensor(**kw):
    s = load_config().sensor
    base = dict(fpn_adu=0.0, prnu_frac=0.0, dead_pixel_fraction=0.0, gain_e_per_adu=1.7, read_noise_e=3.0)
    base.update(kw)
    return dataclasses.replace(s, **base)


def maps_for(s, hot=0.0):
    return sensor_maps(
        H, W, s.sensor_seed, s.prnu_frac, s.fpn_adu, s.bias_adu, hot, s.hot_pixel_dark_e_s, s.dead_pixel_fraction
    )


def expected_moments(lam, sigma, g):
    """Mean and variance of floor((Poisson(lam) + N(0, sigma)) / g): x/g - 1/2 and var/g^2 + 1/12."""
    return (lam / g) - 0.5, (lam + sigma**2) / g**2 + 1 / 12


@pytest.mark.parametrize("sampler", ["fast", "exact"])
@pytest.mark.parametrize("lam", [3.0, 40.0])
def test_background_noise_matches_formula(sampler, lam):
    s = quiet_sensor(sampler=sampler)
    exp = Exposure(np.zeros((H, W), np.float32), None, [], lam)
    img, _ = read_out(exp, s, maps_for(s), np.random.default_rng(0))
    x = img.astype(np.float64) - s.bias_adu
    mean, var = expected_moments(lam, s.read_noise_e, s.gain_e_per_adu)
    n = x.size
    assert abs(x.mean() - mean) < 5 * np.sqrt(var / n)
    assert abs(x.var() / var - 1) < 5 * np.sqrt(2 / n) + 0.01  # +1% for the 1/12 approximation


def test_shot_noise_of_illuminated_pixels():
    s = quiet_sensor(read_noise_e=2.0, gain_e_per_adu=1.0, full_well_e=1e6)
    signal = 500.0
    star = np.full((H, W), signal, np.float32)
    exp = Exposure(star, None, [(0, H, 0, W)], 10.0)
    img, _ = read_out(exp, s, maps_for(s), np.random.default_rng(1))
    x = img.astype(np.float64) - s.bias_adu
    mean, var = expected_moments(signal + 10.0, 2.0, 1.0)
    assert abs(x.mean() - mean) < 0.2
    assert abs(x.var() / var - 1) < 0.03


def test_fast_and_exact_samplers_agree_in_distribution():
    s = quiet_sensor()
    exp = Exposure(np.zeros((H, W), np.float32), None, [], 7.5)
    a, _ = read_out(exp, dataclasses.replace(s, sampler="fast"), maps_for(s), np.random.default_rng(2))
    b, _ = read_out(exp, dataclasses.replace(s, sampler="exact"), maps_for(s), np.random.default_rng(3))
    assert stats.ks_2samp(a.ravel()[:40000], b.ravel()[:40000]).pvalue > 1e-3


def test_lut_probabilities_are_exact():
    smp = BackgroundSampler(12.0, 4.0, 2.5)
    rng = np.random.default_rng(4)
    j = smp.sample(400_000, rng)
    counts = np.bincount(j.astype(np.int64), minlength=len(smp.pmf))
    expected = smp.pmf * j.size
    ok = expected > 50
    chi2 = ((counts[ok] - expected[ok]) ** 2 / expected[ok]).sum()
    assert chi2 < stats.chi2.ppf(0.999, ok.sum() - 1)


def test_fixed_seed_regression():
    s = load_config().sensor
    exp = Exposure(np.zeros((H, W), np.float32), None, [], 7.0)
    img, _ = read_out(exp, s, maps_for(s, 1e-3), np.random.default_rng(5))
    img2, _ = read_out(exp, s, maps_for(s, 1e-3), np.random.default_rng(5))
    assert np.array_equal(img, img2)


def test_dark_current_doubles():
    s = load_config().sensor
    d1 = dark_current_e_s(s)
    d2 = dark_current_e_s(dataclasses.replace(s, temperature_c=s.temperature_c + s.dark_doubling_c))
    assert d2 == pytest.approx(2 * d1)
    assert dark_current_e_s(dataclasses.replace(s, temperature_c=s.dark_reference_c)) == s.dark_current_e_s


def test_blooming_conserves_charge_and_respects_full_well():
    e = np.zeros((40, 5))
    e[20, 2] = 10_000.0
    e[19, 2] = 2_000.0
    total = e.sum()
    assert bloom(e, 1000.0) == 1
    assert e.max() <= 1000.0 + 1e-9
    assert e.sum() == pytest.approx(total)
    assert (e[:, 2] > 0).sum() == 12 and e[:, [0, 1, 3, 4]].sum() == 0  # only the column grew
    edge = np.zeros((6, 1))
    edge[0, 0] = 10_000.0
    bloom(edge, 1000.0)
    assert edge.sum() < 10_000.0  # charge reaching the edge is drained


def test_saturation_clips_at_adc_range():
    s = quiet_sensor(full_well_e=1e9, blooming=False)
    star = np.zeros((H, W), np.float32)
    star[100, 100] = 1e8
    img, _ = read_out(Exposure(star, None, [(100, 101, 100, 101)], 5.0), s, maps_for(s), np.random.default_rng(6))
    assert img[100, 100] == 2**s.bit_depth - 1


def test_hot_pixel_maps_nest_and_scale():
    s = load_config().sensor
    small = maps_for(s, 1e-4)
    large = maps_for(s, 1e-3)
    assert set(small.hot_index) <= set(large.hot_index)
    assert abs(len(large.hot_index) / (H * W) - 1e-3) < 5e-4
    exp = Exposure(np.zeros((H, W), np.float32), None, [], 5.0)
    img, _ = read_out(exp, s, large, np.random.default_rng(7))
    hot = img.ravel()[large.hot_index].astype(float)
    assert np.median(hot) > np.median(img) + 50  # hot pixels stand out


def test_dead_pixels_read_bias_level():
    s = dataclasses.replace(load_config().sensor, dead_pixel_fraction=1e-3, fpn_adu=0.0)
    m = maps_for(s)
    star = np.full((H, W), 1000.0, np.float32)
    img, _ = read_out(Exposure(star, None, [(0, H, 0, W)], 5.0), s, m, np.random.default_rng(8))
    dead = img.ravel()[m.dead_index].astype(float)
    assert len(dead) > 10 and np.all(np.abs(dead - s.bias_adu) < 6 * s.read_noise_e / s.gain_e_per_adu)


@pytest.mark.parametrize("sampler", ["fast", "exact"])
def test_a_black_level_above_the_sky_crushes_the_background_and_erases_faint_stars(sampler):
    """sensor.black_level_adu (a camera's processor): every read-out less it, clipped at 0. Set above the sky the
    background reads 0 everywhere, a star keeps its light above the level, and one whose peak is below it is gone."""
    s = quiet_sensor(sampler=sampler, bias_adu=10, gain_e_per_adu=1.0, read_noise_e=1.0, full_well_e=1e6)
    black = 30  # 20 ADU above bias + sky (a 5 e- sky)
    star = np.zeros((H, W), np.float32)
    star[40, 40] = 200.0  # a bright star's peak: 200 e- above the sky
    star[80, 80] = 15.0  # a faint one: its peak reads ~25 ADU, below the level
    exp = Exposure(star, None, [(39, 42, 39, 42), (79, 82, 79, 82)], 5.0)
    crushed = dataclasses.replace(s, black_level_adu=black)
    maps = sensor_maps(H, W, s.sensor_seed, 0.0, 0.0, s.bias_adu - black, 0.0, s.hot_pixel_dark_e_s, 0.0)
    img, _ = read_out(exp, crushed, maps, np.random.default_rng(2))
    linear, _ = read_out(exp, s, maps_for(s), np.random.default_rng(2))
    assert (linear[100:, 100:] > 0).all() and (img[100:, 100:] == 0).all()  # the background: all 0
    assert img[80, 80] == 0 and linear[80, 80] > 20  # the faint star: gone
    assert img[40, 40] == pytest.approx(float(linear[40, 40]) - black, abs=1)  # the bright one: less the level


def test_the_renderer_draws_the_black_level_and_its_detection_limit_knows_it():
    """The renderer's read-outs carry sensor.black_level_adu (its sensor maps' offset) and its detection limit
    needs a star's peak to clear the level first: brighter by the light the level takes."""
    from skygen.config import build_config
    from skygen.render.frame import Renderer

    base = {"camera": {"width_px": 256, "height_px": 256, "fov_deg": 12.0}, "output": {"image_size_px": 128}}
    plain = Renderer(build_config(base))
    s = plain.cfg.sensor
    sky_adu = s.bias_adu + plain.background_e / s.gain_e_per_adu
    crushed = Renderer(build_config({**base, "sensor": {"black_level_adu": int(sky_adu) + 20}}))
    assert int(crushed.maps.offset_adu.min()) < 0
    assert crushed.detection_limit_mag < plain.detection_limit_mag - 0.5
    f = crushed.render(0)
    assert np.median(f.image_full if f.image_full is not None else f.image) == 0
