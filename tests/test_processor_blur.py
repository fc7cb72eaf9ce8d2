"""A camera processor's blur of the read-out (sensor.processor_blur_px): correlated noise, wider stars, and how
fit-camera reads it from frames."""

from __future__ import annotations

import numpy as np
import pytest

from skygen.config import ConfigError, build_config
from skygen.instrument.sensor import (
    blur_correlation,
    blur_for_correlation,
    blur_variance_factor,
    blur_width_variance,
)


def _frames(blur: float, n: int = 2, **sensor) -> list[np.ndarray]:
    from skygen.real.fit_render import renderer_at

    cfg = build_config({"sensor": {"processor_blur_px": blur, "read_noise_e": 20.0, **sensor},
                        "corruptions": {"cosmic_rays": 0.0, "hotpixels": 0.0}})  # fmt: skip
    r = renderer_at(cfg, [(15.0 + 40 * i, 10.0, 0.0) for i in range(n)])
    return [r.render(i).image_full.astype(np.float32) for i in range(n)]


def test_the_kernel_statistics_are_consistent_and_invert():
    s = np.linspace(0.3, 2.5, 12)
    rho = [blur_correlation(x) for x in s]
    assert np.all(np.diff(rho) > 0) and np.all(np.diff([blur_variance_factor(x) for x in s]) < 0)
    for x in (0.5, 0.7, 1.2):
        assert blur_for_correlation(blur_correlation(x)) == pytest.approx(x, abs=2e-3)
    assert blur_correlation(0.0) == 0.0 and blur_variance_factor(0.0) == 1.0 and blur_for_correlation(-0.1) == 0.0
    # a wide kernel's second moment is its sigma squared; a narrow sampled one adds almost nothing
    assert blur_width_variance(1.5) == pytest.approx(1.5**2, rel=0.01) and blur_width_variance(0.3) < 0.01


def test_blurred_renders_correlate_their_noise_and_keep_the_level():
    """The background's neighbour correlation is the kernel's, its variance falls by the kernel's factor, its
    level stays; without the blur the noise is white."""
    from skygen.instrument.detect import estimate_background
    from skygen.real.frame_stats import neighbour_correlation

    white, blurred = _frames(0.0, 1)[0], _frames(0.7, 1)[0]
    rx, ry, _ = neighbour_correlation(white)
    assert abs(rx) < 0.03 and abs(ry) < 0.03
    bx, by, _ = neighbour_correlation(blurred)
    assert bx == pytest.approx(blur_correlation(0.7), abs=0.04) and by == pytest.approx(blur_correlation(0.7), abs=0.04)
    (lw, sw), (lb, sb) = estimate_background(white), estimate_background(blurred)
    assert lb == pytest.approx(lw, abs=0.3)
    quantum = 1 / 12
    assert (sb**2 - quantum) / (sw**2 - quantum) == pytest.approx(blur_variance_factor(0.7), rel=0.1)


def test_stars_widen_in_quadrature():
    """A bright star read out through the blur (no sky, read noise or fixed pattern, so its second moment is the
    light's) is wider by the kernel's second moment in quadrature; its flux is kept."""
    from skygen.instrument.sensor import Exposure, read_out, sensor_maps

    yy, xx = np.mgrid[0:41, 0:41] - 20.0
    star = 2e4 * np.exp(-(xx**2 + yy**2) / (2 * 1.2**2)) / (2 * np.pi * 1.2**2)

    def moments(blur):
        # fine ADU steps, so that rounding cuts no wing
        quiet = {"read_noise_e": 0.0, "fpn_adu": 0.0, "prnu_frac": 0.0, "bias_adu": 0, "full_well_e": 1e6}
        cfg = build_config({"sensor": {"processor_blur_px": blur, **quiet, "bit_depth": 16, "gain_e_per_adu": 0.05}})
        s = cfg.sensor
        maps = sensor_maps(41, 41, 1, 0.0, 0.0, 0, 0.0, 0.0, 0.0)
        img, _ = read_out(Exposure(star, None, [(0, 41, 0, 41)], 0.0), s, maps, np.random.default_rng(0))
        f = img.astype(np.float64) * s.gain_e_per_adu
        tot = f.sum()
        mx, my = (f * xx).sum() / tot, (f * yy).sum() / tot
        return tot, ((f * ((xx - mx) ** 2 + (yy - my) ** 2)).sum() / tot) / 2

    (t0, v0), (t1, v1) = moments(0.0), moments(1.0)
    assert v1 - v0 == pytest.approx(blur_width_variance(1.0), rel=0.05)
    assert t1 == pytest.approx(t0, rel=0.01)


def test_refusals_and_fallbacks():
    with pytest.raises(ConfigError, match="processor_blur_px needs render.backend=numpy"):
        build_config({"sensor": {"processor_blur_px": 0.5}, "render": {"backend": "torch"}})
    with pytest.raises(ConfigError, match="processor_blur_px"):
        build_config({"sensor": {"processor_blur_px": 5.0}})
    from skygen.render.binned import unsupported_reason
    from skygen.render.frame import Renderer

    r = Renderer(build_config({"sensor": {"processor_blur_px": 0.5}, "n_frames": 1}))
    assert "processor_blur_px" in unsupported_reason(r)


def test_fit_pixels_reads_the_blur_and_undoes_it():
    """processor_blur finds the blur the frames were rendered with and none in white noise; unblurred_boxes turns
    the blurred frames' box noise back into the read-out's; a crushed background is not taken for a blur."""
    from skygen.real.fit_camera import sensor_boxes
    from skygen.real.fit_pixels import background, processor_blur, unblurred_boxes, unblurred_psf

    blurred, white = _frames(0.7), _frames(0.0)
    got = processor_blur(blurred, 3.0)
    assert got["px"] == pytest.approx(0.7, abs=0.06) and "sensor.processor_blur_px" in got["note"]
    assert processor_blur(white, 3.0)["px"] == 0.0
    crushed = processor_blur(blurred, 0.1)
    assert crushed["px"] == 0.0 and "crushed" in crushed["note"]
    bw = sensor_boxes([background(im) for im in white])
    bb = unblurred_boxes(sensor_boxes([background(im) for im in blurred]), got["px"])
    assert np.median(bb["sigma"]) == pytest.approx(np.median(bw["sigma"]), rel=0.1)
    assert np.median(bb["variance"]) == pytest.approx(np.median(bw["variance"]), rel=0.15)
    psf = unblurred_psf({"ok": True, "gaussian_sigma_px": 1.5, "moffat_sigma_px": 1.4, "psf": "gaussian"}, 1.0)
    assert psf["gaussian_sigma_px"] == pytest.approx(np.sqrt(1.5**2 - blur_width_variance(1.0)))


def test_auto_keeps_the_fit_whose_renders_miss_by_less():
    """--processor-blur auto: where a blur is measured, both fits are made and the one whose renders miss their frames
    by less is kept, its messages printed and the choice said; where none is measured, one fit."""
    from skygen.real.fit_camera import _with_or_without_blur

    def check(ratio):
        return [{"ratio": ratio, "tolerance": 0.25, "ok": abs(ratio - 1) <= 0.25}]

    def fake(measured: float, with_ratio: float, without_ratio: float):
        calls = []

        def pixels_and_terms(blur: bool, say):
            calls.append(blur)
            say(f"fit {'with' if blur else 'without'}")
            px = {"meas": {"processor_blur": {"px": measured, "note": "measured"}}}
            return px, {"checks": check(with_ratio if blur else without_ratio)}

        return pixels_and_terms, calls

    for with_ratio, without_ratio, kept in ((1.0, 0.6, True), (4.0, 0.7, False), (1.05, 1.2, True)):
        said: list[str] = []
        run, calls = fake(0.6, with_ratio, without_ratio)
        px, model = _with_or_without_blur(run, said.append)
        assert calls == [False, True] and model["checks"] == check(with_ratio if kept else without_ratio)
        assert said[0] == f"fit {'with' if kept else 'without'}" and ("not kept" in said[-1]) != kept
        assert px["meas"]["processor_blur"]["auto"]["kept"] is kept
    said = []
    run, calls = fake(0.0, 1.0, 0.6)
    _with_or_without_blur(run, said.append)
    assert calls == [False] and said == ["fit without"]


def test_unfitted_false_stars_are_capped_at_the_frames_bright_end(monkeypatch):
    """Where the frames' uncatalogued detections are too few to fit the false stars' brightness (the neutral shape,
    uniform over 4 mag above the limit), their bright end is still checked against the frames' non-catalogue sources
    among the ten brightest detections: renders that put 10 there where the frames put 0 are capped (the 70D's and
    openstartracker's fits of session 37 solved none of their renders before)."""
    from skygen.real import fit_render as F

    def stats(cfg, attitudes, table, sat, skip=0):
        n, span = cfg["false"], cfg["span"]  # the stand-in config: false stars a frame, uniform over span mag
        bright = n * max(span - 3.0, 0.0) / span  # brighter than the tenth star (Hp 5, the limit 8)
        return [{"detections": 20 + n, "nonstar_brightest10": min(bright, 10.0), "_unexplained_flux": np.zeros(0),
                 "_detection_limit_mag": 8.0, "_star_mag": np.zeros(0), "_star_found": np.zeros(0, bool),
                 "_tenth_mag": 5.0} for _ in attitudes]  # fmt: skip

    def fitted(cfg0, cam, meas, exposure, pitch):
        return {"false": meas["faint_sources_per_frame"], "span": meas.get("false_star_shape", {}).get("span_mag", 4)}

    monkeypatch.setattr(F, "_render_stats", stats)
    monkeypatch.setattr(F, "build_fitted", fitted)
    real = [{"detections": 40, "nonstar_brightest10": 0} for _ in range(5)]
    meas: dict = {}
    # two uncatalogued detections only: the shape is not fitted, the number comes from the detection deficit
    cfg, rows = F._faint_sources(None, None, meas, 1.0, None, real, [(0, 0, 0)] * 5, None, 255, 0.0,
                                 faint=(20.0, np.array([1.0, 2.0])))  # fmt: skip
    assert meas["false_star_shape"]["n"] < F.MIN_FALSE_STARS_FITTED
    assert meas["false_star_shape"]["span_mag"] < 4.0 and "bright end capped" in meas["false_star_shape"]["note"]
    # 20 false stars a frame over 4 mag had put 5 a frame above the tenth star; capped at it, none
    assert meas["false_star_shape"]["span_mag"] == pytest.approx(3.0, abs=0.01)
    assert meas["faint_sources_per_frame"] == pytest.approx(20 * 3.0 / 4.0, rel=0.01)
    assert all(r["nonstar_brightest10"] == pytest.approx(0.0, abs=0.01) for r in rows)
