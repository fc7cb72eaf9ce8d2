"""A camera processor's tone curve (sensor.tone_gamma, sensor.tone_knee_adu): its shape, how frames render through it,
the configs it refuses, and fit-camera's search for its exponent."""

from __future__ import annotations

import numpy as np
import pytest

from skygen.config import build_config
from skygen.errors import ConfigError

EIGHT_BIT = {"bit_depth": 8, "bias_adu": 5, "gain_e_per_adu": 3.0, "exposure_s": 0.5}


def _curve(gamma=0.4, knee=20.0, **sensor):
    from skygen.instrument.sensor import ToneCurve

    return ToneCurve.of(build_config({"sensor": {**EIGHT_BIT, **sensor, "tone_gamma": gamma,
                                                 "tone_knee_adu": knee}}).sensor)  # fmt: skip


def test_the_curve_is_linear_to_the_knee_and_a_power_law_beyond_it():
    c = _curve(0.4, 20.0)
    raw = np.arange(c.raw_top + 1)
    assert np.array_equal(c.lut[: 5 + 21], raw[: 5 + 21])  # pedestal 5 + knee 20: read as a linear sensor
    assert np.all(np.diff(c.lut.astype(int)) >= 0) and c.lut[-1] == 255
    assert int(np.argmax(c.lut == 255)) >= c.raw_top - 10  # the top is reached at raw_top (~13 read-outs per ADU there)
    assert np.diff(c.lut.astype(int))[25:30].max() == 1  # continuous in slope at the knee: no jump
    # far above the knee, ten times the light is 10^0.4 times the ADU above the pedestal (and knee's offset)
    x = np.array([200.0, 1000.0])
    t = c.lut[(x + 5).astype(int)].astype(float) - 5 - 20 + 20 / 0.4
    assert np.log(t[1] / t[0]) / np.log(5.0) == pytest.approx(0.4, abs=0.02)
    assert _curve(1.0, 0.0) is None  # a linear sensor: no curve


def test_frames_read_the_background_as_a_linear_sensor_and_compress_the_stars():
    from skygen.render.frame import Renderer

    def render(**tone):
        cfg = build_config({"sensor": {**EIGHT_BIT, **tone}, "n_frames": 1, "seed": 5, "output": {"full_res": True},
                            "catalog": {"mag_limit": 9.0},  # the same stars (the curve moves the detection limit)
                            "corruptions": {"hotpixels": 0.0, "cosmic_rays": 0.0}})  # fmt: skip
        r = Renderer(cfg)
        f = r.render(0)
        return f.image_full.astype(float), f.stars

    lin, stars = render()
    bg, sd = np.median(lin), lin[lin < np.percentile(lin, 90)].std()
    knee = bg - 5 + 3 * sd
    toned, _ = render(tone_gamma=0.4, tone_knee_adu=float(knee))
    low = lin < bg + 2 * sd
    assert np.array_equal(lin[low], toned[low])  # same noise draws: below the knee nothing changes
    peaks = (lin > 100) & (lin < 255)
    assert peaks.any() and np.all(toned[peaks] < lin[peaks])  # bright star pixels compressed
    assert (toned == 255).sum() < (lin == 255).sum() / 2  # and far fewer saturate: the curve reaches the top later
    assert toned.max() <= 255 and lin.max() <= 255


def test_bad_tone_settings_are_refused_with_the_fix():
    with pytest.raises(ConfigError, match="tone_knee_adu=0 .* at least 1 ADU"):
        build_config({"sensor": {"tone_gamma": 0.5}})
    with pytest.raises(ConfigError, match="raise the knee or the exponent"):
        build_config({"sensor": {"tone_gamma": 0.2, "tone_knee_adu": 2.0, "bit_depth": 16, "bias_adu": 0}})
    with pytest.raises(ConfigError, match="needs render.backend=numpy"):
        build_config({"sensor": {**EIGHT_BIT, "tone_gamma": 0.5, "tone_knee_adu": 10.0},
                      "render": {"backend": "torch"}})  # fmt: skip
    with pytest.raises(ConfigError):
        build_config({"sensor": {"tone_gamma": 1.2}})


def test_the_binned_renderer_leaves_a_tone_curve_to_the_full_one():
    from skygen.render.binned import unsupported_reason
    from skygen.render.frame import Renderer

    cfg = build_config({"sensor": {**EIGHT_BIT, "tone_gamma": 0.5, "tone_knee_adu": 20.0}, "n_frames": 1})
    assert "tone_gamma" in unsupported_reason(Renderer(cfg))


def test_the_tone_exponent_is_searched_until_the_renders_respond_as_the_frames():
    """fit_tone_curve on a stand-in for the renders: their flux exponent is the curve's times a linear sensor's."""
    from skygen.real.fit_render import TONE_TOL, fit_tone_curve, tone_gate

    calls = []

    def measure(g):
        calls.append(g)
        return 1.05 * g**1.1, 0.3 * g, {"psf": "gaussian"}  # not exactly proportional: needs more than one step

    out = fit_tone_curve(measure, 0.40, 1.05, 12.0)
    assert abs(1.05 * out["gamma"] ** 1.1 - 0.40) <= TONE_TOL and len(calls) >= 2
    assert out["exposure_s"] == pytest.approx(0.3 * out["gamma"]) and "sensor.tone_gamma" in out["note"]
    # renders that never respond any nearer than the linear ones: no curve
    none = fit_tone_curve(lambda g: (float("nan"), 1.0, None), 0.40, 1.05, 12.0)
    assert none["gamma"] == 1.0 and "none fitted" in none["note"]
    # looked for only where the frames respond with a lower power than the renders, beyond the warning's tolerance,
    # and not where a black level explains the frames
    assert tone_gate({"flux_exponent_real": 0.36, "flux_exponent_rendered": 0.99}, 0) is None
    assert tone_gate({"flux_exponent_real": 0.95, "flux_exponent_rendered": 1.02}, 0)["gamma"] == 1.0
    assert tone_gate({"flux_exponent_real": 1.40, "flux_exponent_rendered": 1.02}, 0)["gamma"] == 1.0
    assert "black level" in tone_gate({"flux_exponent_real": 0.5, "flux_exponent_rendered": 1.0}, 3)["note"]


def test_frames_exposures_from_their_zero_points_are_undone_through_the_curve():
    """A frame's zero point moves as its exposure to the power real / linear flux exponent through a processor's
    curve: the exposure it was rendered at (the zero point's step, a fourth entry) is raised to linear / real."""
    from skygen.real.fit_render import toned_exposures

    att = [(10.0, 20.0, 30.0, 0.5), (11.0, 21.0, 31.0, 2.0)]
    out = toned_exposures(att, 0.5, 1.0)
    assert out[0][:3] == att[0][:3] and out[0][3] == pytest.approx(0.25) and out[1][3] == pytest.approx(4.0)
    assert toned_exposures([(1.0, 2.0, 3.0)], 0.5, 1.0) == [(1.0, 2.0, 3.0)]  # one exposure: nothing to undo
    assert toned_exposures(att, float("nan"), 1.0) == att


def test_the_detection_limit_is_taken_through_the_curve():
    """The detector's threshold is in the frame's ADU: above the knee a star needs more read-out to reach it, so the
    limit is brighter than the linear sensor's; with the threshold below the knee, nothing changes."""
    from skygen.render.frame import Renderer

    def limit(**tone):
        return Renderer(build_config({"sensor": {**EIGHT_BIT, **tone}, "n_frames": 1})).detection_limit_mag

    lin = limit()
    assert limit(tone_gamma=0.3, tone_knee_adu=200.0) == pytest.approx(lin)  # threshold far below the knee
    low = limit(tone_gamma=0.4, tone_knee_adu=3.0)
    assert low < lin - 0.3  # compressed at the threshold: a brighter star needed
    assert low < limit(tone_gamma=0.7, tone_knee_adu=3.0) < lin
