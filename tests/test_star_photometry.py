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
