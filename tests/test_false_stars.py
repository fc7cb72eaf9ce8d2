"""False stars with a brightness distribution (corruptions.false_star_slope / _span_mag) and its fit from
real frames (skygen.real.fit_render.fit_false_star_shape), and the sharp-source count behind the fitted
cosmic-ray rate: the parts that let renders of a fitted camera put as many uncatalogued sources among the
brightest detections as the real frames do (issue 35)."""

from __future__ import annotations

import numpy as np
import pytest

from skygen.config import config_dict, load_config
from skygen.identity import content_id
from skygen.instrument.corruptions import false_star_magnitudes
from skygen.real.fit_render import detected_share, fit_false_star_shape, sharp_sources
from skygen.real.frame_stats import nonstar_brightest
from skygen.render.frame import Renderer


def cdf(m, lim, slope, span):
    """The model's CDF of magnitude m (density ~ 10 ** (slope (m - lim)) on [lim - span, lim])."""
    k = slope * np.log(10.0)
    return (np.exp(k * (m - lim)) - np.exp(-k * span)) / (1 - np.exp(-k * span))


def test_slope_zero_is_the_old_uniform_draw_bit_for_bit():
    u = np.random.default_rng(0).random(1000)
    lim = 9.3312345
    assert np.array_equal(false_star_magnitudes(u, lim), (lim - 4.0 + 4.0 * u).astype(np.float32))


def test_a_slope_puts_most_false_stars_near_the_limit_with_the_model_distribution():
    from scipy.stats import kstest

    u = np.random.default_rng(1).random(20000)
    m = false_star_magnitudes(u, 10.0, 0.4, 3.0).astype(np.float64)
    assert m.min() >= 7.0 - 1e-5 and m.max() <= 10.0 + 1e-5
    assert kstest(m, lambda x: cdf(x, 10.0, 0.4, 3.0)).pvalue > 0.01
    # the brightest magnitude holds 10 ** (0.4 * 2) ~ 6 x fewer than the faintest (uniform: half in each half)
    assert np.mean(m < 8.5) == pytest.approx(cdf(8.5, 10.0, 0.4, 3.0), abs=0.01)
    assert np.mean(m < 8.5) < 0.25


def _detected(m, rng):
    """Detection with a soft limit: 50 % at Hp 8.6, as a detector's area and background rules make it."""
    return rng.random(len(m)) < 1.0 / (1.0 + np.exp((m - 8.6) / 0.2))


def test_the_fit_recovers_slope_span_and_number_through_the_renders_completeness():
    rng = np.random.default_rng(2)
    lim, slope, span, per_frame, frames = 9.0, 0.35, 3.2, 30.0, 40
    m = false_star_magnitudes(rng.random(int(per_frame * frames)), lim, slope, span).astype(np.float64)
    seen = m[_detected(m, rng)]  # the real frames' uncatalogued detections
    stars = rng.uniform(4.0, 10.0, 20000)  # catalogue stars in renders, found or not
    fit = fit_false_star_shape(seen, lim, frames, stars, _detected(stars, rng))
    assert fit["slope"] == pytest.approx(slope, abs=0.1)
    assert fit["span_mag"] == pytest.approx(span, abs=0.1)
    assert fit["per_frame"] == pytest.approx(per_frame, rel=0.15)
    assert "slope" in fit["note"] and fit["n"] > 300
    # what renders make themselves (hot pixels, blends) is not added again
    own = seen[: len(seen) // 2]
    less = fit_false_star_shape(seen, lim, frames, stars, _detected(stars, rng), rendered_mags=own)
    assert less["per_frame"] == pytest.approx(per_frame / 2, rel=0.25)


def test_too_few_uncatalogued_detections_keep_the_neutral_shape_and_say_so():
    stars = np.linspace(5, 10, 500)
    fit = fit_false_star_shape(np.array([8.0, 8.2, 8.9]), 9.0, 8, stars, stars < 9.5)
    assert (fit["slope"], fit["span_mag"]) == (0.0, 4.0) and np.isnan(fit["per_frame"])
    assert "too few" in fit["note"]
    assert "not fitted" in fit_false_star_shape(np.array([9.5]), 9.0, 8, stars, stars < 9.5)["note"]


def test_the_detected_share_is_per_bin_and_fills_thin_bins_from_their_neighbours():
    rng = np.random.default_rng(4)
    m = rng.uniform(5.0, 10.0, 20000)
    found = _detected(m, rng)
    edges = np.arange(4.0, 10.01, 0.2)
    share = detected_share(m, found, edges)
    assert share[0] == pytest.approx(share[5], abs=0.02)  # no star brighter than 5: the nearest full bin's
    assert share[edges[:-1] < 7.5].min() > 0.95 and share[-1] < 0.2
    assert np.all(np.diff(share[edges[:-1] >= 7.5]) <= 0.05)  # falls through the limit


def test_sharp_sources_are_unexplained_detections_much_more_concentrated_than_stars():
    n = 30
    flux = np.full(n + 3, 1000.0)
    peak = np.r_[np.full(n, 100.0), 700.0, 110.0, 3500.0]  # stars share 0.1; a hit 0.7; a faint star; saturated
    explained = np.r_[np.ones(n, bool), False, False, False]
    det = {"flux_adu": flux, "peak_adu": peak}
    assert sharp_sources(det, explained, background_adu=100.0, sat=4000.0) == 1  # the saturated one is left out
    assert nonstar_brightest(np.r_[flux[:n], 5000.0, 1.0, 1.0], ~explained, n=10) == 1


def test_rendered_false_stars_follow_the_configured_brightness(small_overrides):
    base = small_overrides + ["corruptions.false_stars=60", "corruptions.cosmic_rays=0"]
    mags = {}
    for slope in (0.0, 0.5):
        r = Renderer(load_config(overrides=base + [f"corruptions.false_star_slope={slope}"]))
        m = np.concatenate([r.render(i).stars["mag"][r.render(i).stars["hip_id"] < 0] for i in range(4)])
        assert len(m) > 150 and m.max() <= r.detection_limit_mag + 1e-4
        mags[slope] = r.detection_limit_mag - m  # magnitudes above the limit
    assert np.median(mags[0.0]) == pytest.approx(2.0, abs=0.3)  # uniform over 4 mag
    assert np.median(mags[0.5]) < 1.0  # most near the limit


def test_the_neutral_shape_keeps_older_datasets_ids():
    cfg = config_dict(load_config())
    assert cfg["corruptions"]["false_star_slope"] == 0.0
    old = {k: dict(v) if isinstance(v, dict) else v for k, v in cfg.items()}
    del old["corruptions"]["false_star_slope"], old["corruptions"]["false_star_span_mag"]
    assert content_id(cfg) == content_id(old)
    cfg["corruptions"]["false_star_slope"] = 0.3
    assert content_id(cfg) != content_id(old)


def test_a_cameras_measured_centroid_error_changes_no_frame_id_and_no_calibration():
    """camera.centroid_sigma_px tells solvers about the real camera (fit-camera writes it); it renders nothing,
    so neither the frames' content id nor the detector calibration's key depend on it."""
    from skygen.stream.emulator import calibration_key

    cfg = config_dict(load_config())
    assert cfg["camera"]["centroid_sigma_px"] is None
    fitted = config_dict(load_config(overrides=["camera.centroid_sigma_px=0.09"]))
    assert fitted["camera"]["centroid_sigma_px"] == 0.09
    assert content_id(fitted) == content_id(cfg)
    assert calibration_key(fitted) == calibration_key(cfg)
    old = {k: dict(v) if isinstance(v, dict) else v for k, v in cfg.items()}
    del old["camera"]["centroid_sigma_px"], old["sensor"]["fixed_sources"]  # a dataset made before the keys
    assert content_id(old) == content_id(cfg)
    glow = config_dict(load_config(overrides=["sensor.fixed_sources=[[10.0, 20.0, 100.0, 2.0]]"]))
    assert content_id(glow) != content_id(cfg)  # light on the sensor is in the frames


def test_the_bright_tail_is_capped_to_what_the_frames_brightest_ten_show():
    """cap_bright_tail: the share of false stars it expects above each frame's tenth-brightest star is the
    renderer's own draw (false_star_magnitudes); it shortens the span until the renders' false-star part matches
    the frames' excess, keeps the density below the cap, and leaves a shape the frames do not contradict."""
    from skygen.real.fit_render import cap_bright_tail

    lim, rng = 8.04, np.random.default_rng(5)
    shape = {"slope": 0.22, "span_mag": 3.55, "per_frame": 87.6, "n": 400, "note": "fitted"}
    tenth = rng.uniform(4.5, 4.8, 9)  # nine frames' tenth-brightest catalogue stars (mag): a wide field's

    def drawn(s: dict) -> float:  # the renderer's draw: false stars above each frame's tenth, summed over frames
        m = false_star_magnitudes(rng.random((4000, int(round(s["per_frame"])))), lim, s["slope"], s["span_mag"])
        return float(np.mean((m[:, None, :] < tenth[None, :, None]).sum(axis=(1, 2))))

    before = drawn(shape)
    assert 4 < before < 20
    own, rendered = 0.5, 0.5 + before  # renders counting every false star above the tenth (the scale cancels)
    capped = cap_bright_tail(shape, lim, tenth, real_count=2, own=own, rendered=rendered)
    assert capped["span_mag"] < shape["span_mag"] and "bright end capped" in capped["note"]
    assert drawn(capped) + own == pytest.approx(2.0, abs=0.15)  # the frames' 2
    # the density of the faint ones is kept: per magnitude at the limit, before and after
    k = 0.22 * np.log(10)
    density = [s["per_frame"] * k / -np.expm1(-k * s["span_mag"]) for s in (shape, capped)]
    assert density[1] == pytest.approx(density[0], rel=1e-9)
    # renders that see a constant share of what the scene holds (saturation) are scaled, not taken literally
    half = cap_bright_tail(shape, lim, tenth, real_count=1, own=own, rendered=own + before / 2)
    assert drawn(half) == pytest.approx(2 * (1 - own), abs=0.15)  # twice the frames' excess in the scene
    # not contradicted (80 % of what renders show; or more): the same shape
    assert cap_bright_tail(shape, lim, tenth, int(0.8 * rendered), own, rendered) is shape
    assert cap_bright_tail(shape, lim, tenth, 20, own, rendered) is shape
    # the frames' own sources account for all they show: no false star above any frame's tenth
    none = cap_bright_tail(shape, lim, tenth, real_count=0, own=0.0, rendered=before)
    assert lim - none["span_mag"] >= tenth.max() - 1e-6 and drawn(none) == 0.0
