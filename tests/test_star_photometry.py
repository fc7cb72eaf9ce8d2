"""Stars' photometry on a fitted camera: each star's fixed brightness offset (photometry.star_scatter_mag), the
stars' own vignetting (optics.vignetting, the background's kept apart as optics.sky_vignetting), and the fit of
both from matched stars (skygen.real.fit_render)."""

import numpy as np
import pytest

from skygen.config import load_config
from skygen.instrument.photometry import star_gains
from skygen.real.fit_render import photometric_scatter, star_vignetting
from skygen.render.frame import Renderer

SMALL = ["camera.width_px=256", "camera.height_px=256", "camera.pixel_pitch_um=22.0", "output.image_size_px=64"]


def test_star_gains_are_fixed_per_star_and_have_the_asked_rms():
    ids = np.arange(1, 200_001)
    g = star_gains(ids, 0.3, 1234)
    dm = -2.5 * np.log10(g)
    assert np.std(dm) == pytest.approx(0.3, rel=0.01) and abs(np.mean(dm)) < 0.005
    np.testing.assert_array_equal(star_gains(ids[::-1], 0.3, 1234), g[::-1])  # a star's own, whatever the order
    assert not np.allclose(star_gains(ids, 0.3, 99), g)  # another sensor, other offsets
    np.testing.assert_array_equal(star_gains(ids, 0.0, 1234), np.ones(len(ids)))


def test_a_render_applies_the_offsets_to_the_stars_electrons_and_nowhere_else():
    base = Renderer(load_config(overrides=SMALL))
    spread = Renderer(load_config(overrides=SMALL + ["photometry.star_scatter_mag=0.4"]))
    a, b = base.scene(3).stars, spread.scene(3).stars
    np.testing.assert_array_equal(a["hip_id"], b["hip_id"])
    np.testing.assert_allclose(a["x_px"], b["x_px"])
    ratio = b["electrons"] / a["electrons"]
    np.testing.assert_allclose(ratio, star_gains(a["hip_id"], 0.4, base.cfg.sensor.sensor_seed), rtol=1e-6)
    # the same star, another frame: the same factor
    c, d = base.scene(4).stars, spread.scene(4).stars
    common = np.intersect1d(a["hip_id"], c["hip_id"])
    for h in common[:5]:
        assert ratio[a["hip_id"] == h][0] == pytest.approx((d["electrons"] / c["electrons"])[c["hip_id"] == h][0])


def test_sky_vignetting_shapes_the_background_and_not_the_stars():
    both = Renderer(load_config(overrides=SMALL + ["optics.vignetting=0.5"]))
    apart = Renderer(load_config(overrides=SMALL + ["optics.vignetting=0.1", "optics.sky_vignetting=0.5"]))
    s_both, s_apart = both.scene(1), apart.scene(1)
    bg_both, bg_apart = both.background_map(s_both), apart.background_map(s_apart)
    np.testing.assert_allclose(bg_both, bg_apart)  # the background's fall is sky_vignetting's
    x, y = s_both.stars["x_px"], s_both.stars["y_px"]
    ratio = s_apart.stars["electrons"] / s_both.stars["electrons"]
    np.testing.assert_allclose(ratio, both.vignetting(x, y, 0.1) / both.vignetting(x, y, 0.5), rtol=1e-6)


def _stars(v: float, scatter: float, n: int = 900, seed: int = 2):
    """Matched stars as fit-camera pools them: a vignetting v, a colour term, per-frame zero points, scatter."""
    rng = np.random.default_rng(seed)
    mag = rng.uniform(3, 8, n)
    bv = rng.uniform(-0.2, 1.8, n)
    r2 = rng.uniform(0, 1, n)
    frame = rng.integers(0, 9, n)
    inst = mag - 0.25 * bv + rng.normal(0, 0.1, 9)[frame] + rng.normal(0, scatter, n)
    flux = 10 ** (-0.4 * (inst - 12.0)) * (1 - v * r2)
    return {"flux_adu": flux, "mag": mag, "bv": bv, "r2": r2, "frame": frame, "n": n}


def test_the_stars_vignetting_and_scatter_are_recovered():
    for v in (0.0, 0.3, 0.7):
        s = _stars(v, 0.05)
        assert star_vignetting(s)["v"] == pytest.approx(v, abs=0.03)
        rms, used = photometric_scatter(s["flux_adu"], s["mag"], s["bv"], s["frame"], s["r2"], v, 99.0)
        assert rms == pytest.approx(0.05, rel=0.1) and used == len(s["mag"])
    s = _stars(0.3, 0.05)
    s["r2"] = s["r2"] * 0.1  # all near the centre: not measurable, so not fitted
    assert star_vignetting(s)["v"] is None


def test_a_response_that_is_not_linear_is_measured_and_warned_about():
    """flux_exponent: detected flux ∝ (catalogue flux)^s recovered from matched stars whatever the zero points,
    colour term and vignetting (s = 1 for a linear sensor, 1.8 for a steep tone curve); fit-camera's warning
    fires where the frames' s differs from the renders' by more than RESPONSE_EXPONENT_TOL, and not within it or
    where either is not measured."""
    from skygen.real.fit_render import RESPONSE_EXPONENT_TOL, flux_exponent, response_warning

    for s_true in (1.0, 1.8):
        s = _stars(0.3, 0.05)
        flux = s["flux_adu"] ** s_true  # a power of the linear flux: the catalogue's to the power s_true
        got = flux_exponent(flux, s["mag"], s["bv"], s["frame"], s["r2"], 0.3 if s_true == 1.0 else 0.0, 99.0)
        assert got == pytest.approx(s_true, abs=0.03 if s_true == 1.0 else 0.1)
    assert np.isnan(flux_exponent(s["flux_adu"][:5], s["mag"][:5], s["bv"][:5], s["frame"][:5], s["r2"][:5], 0, 99))
    assert response_warning({"flux_exponent_real": 1.8, "flux_exponent_rendered": 1.05}).startswith(
        "response not linear"
    )
    tol = RESPONSE_EXPONENT_TOL
    assert response_warning({"flux_exponent_real": 1.05 + 1.1 * tol, "flux_exponent_rendered": 1.05})
    assert response_warning({"flux_exponent_real": 1.05 + 0.9 * tol, "flux_exponent_rendered": 1.05}) is None
    assert response_warning({"flux_exponent_real": float("nan"), "flux_exponent_rendered": 1.05}) is None


def test_the_magnitude_down_to_which_half_the_catalogue_is_detected():
    """half_detected_mag: where the detected share of catalogue stars falls through one half, interpolated between
    bins (a step at 4.0 mag -> 4.0 within a bin; a smooth fall centred at 6.3 -> 6.3); NaN where the share never
    falls below a half or is below it from the brightest bin; fit-camera's warning when the frames' limit is more
    than HALF_DETECTED_TOL_MAG brighter (a response that drops faint stars) or fainter than the renders'."""
    from skygen.real.fit_render import HALF_DETECTED_TOL_MAG, half_detected_mag, half_detected_warning

    rng = np.random.default_rng(5)
    mag = rng.uniform(1, 9, 6000)
    assert half_detected_mag(mag, mag < 4.0) == pytest.approx(4.0, abs=0.15)
    smooth = rng.uniform(size=mag.size) < 1 / (1 + np.exp((mag - 6.3) / 0.2))
    assert half_detected_mag(mag, smooth) == pytest.approx(6.3, abs=0.1)
    assert np.isnan(half_detected_mag(mag, np.ones(mag.size, bool)))  # every star found: no limit in range
    assert np.isnan(half_detected_mag(mag, np.zeros(mag.size, bool)))  # none found
    assert np.isnan(half_detected_mag(mag[:3], mag[:3] < 4))
    w = half_detected_warning(3.0, 6.6)
    assert w and "drops faint stars" in w and "3.00" in w
    assert "fainter stars" in half_detected_warning(7.0, 6.0)
    assert half_detected_warning(6.6 - 0.9 * HALF_DETECTED_TOL_MAG, 6.6) is None
    assert half_detected_warning(float("nan"), 6.6) is None


def test_the_zero_point_leaves_out_detections_far_brighter_than_their_star():
    """zero_point_rows: 45 stars (Hp 2-8, zero point 10.0 +- 0.1 mag, the faintest 0.4 mag above that, as noise
    lifts stars near the detection limit) and 55 detections paired by position with stars of Hp 8-10 they are
    3.5 mag brighter than (non-stars beside faint stars in a wide field): the zero point is the stars' (the plain
    median of all would be ZERO_POINT_CLIP_MAG off and more), the 55 flagged out, the lifted faint stars kept;
    detections fainter than their stars are kept whatever the offset; saturated ones never count."""
    from skygen.real.fit_pixels import ZERO_POINT_CLIP_MAG, zero_point, zero_point_rows

    rng = np.random.default_rng(1)
    mag = np.r_[rng.uniform(2, 8, 45), rng.uniform(8, 10, 55)]
    zp = np.r_[10.0 + rng.normal(0, 0.1, 45) + np.where(mag[:45] > 7.5, 0.4, 0.0), 13.5 + rng.normal(0, 0.3, 55)]
    flux = 10 ** (0.4 * (zp - mag))
    peak, level = flux / 10, np.zeros(100)
    got, rows = zero_point_rows(flux, mag, peak, level, 1e9)
    assert got == pytest.approx(10.0, abs=0.1) and rows[:45].all() and not rows[45:].any()
    assert np.median(zp) > 10.0 + ZERO_POINT_CLIP_MAG  # what the plain median would have said
    short = flux.copy()
    short[45:] = 10 ** (0.4 * (7.0 - mag[45:]))  # the same 55 measured 3 mag short of their stars: kept
    assert zero_point_rows(short, mag, peak, level, 1e9)[1].all()
    peak[:3] = 1e6  # saturated: left out
    assert zero_point(flux, mag, peak, level, 1e6)[1] == 42
