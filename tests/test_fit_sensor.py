"""skygen fit-camera's sensor: the model's background statistics, the mean-variance line and its refusals, the
direct fit, the frames' fixed pattern, the render check, and a faint 8-bit camera fitted end to end."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from skygen.cli import main
from skygen.instrument.detect import estimate_background
from skygen.real import fit_sensor as S
from skygen.real.fit_pixels import background, fixed_pattern
from skygen.real.frame_stats import check_renders, star_width_px


def _read_out(rng, lam, gain, read, bias, fpn_map, top, shape):
    """skygen's sensor model for a background of ``lam`` e- (scalar or map), drawn with numpy."""
    e = rng.poisson(lam, shape) + read * rng.standard_normal(shape)
    return np.clip(np.floor(e / gain) + bias + fpn_map, 0, top)


# ------------------------------------------------------------------------------ the model
@pytest.mark.parametrize(
    "lam, gain, read, bias, fpn, top",
    [
        (8.4, 4.0, 3.0, 2, 0.3, 255),
        (4.4, 2.0, 2.0, 0, 0.0, 255),
        (1.0, 0.5, 1.0, 0, 0.2, 255),
        (500, 2.65, 5, 7, 1, 4095),
    ],
)
def test_model_background_is_what_the_estimator_measures_on_a_frame(lam, gain, read, bias, fpn, top):
    """Level and sigma of skygen's estimator, computed from the exact distribution (floor, clip at 0 ADU,
    integer FPN), against the same estimator on 400 000 drawn pixels."""
    rng = np.random.default_rng(1)
    shape = (400, 1000)
    img = _read_out(rng, lam, gain, read, bias, np.rint(fpn * rng.standard_normal(shape)), top, shape)
    level, sigma = S.model_background(lam, gain, read, bias, fpn, top)
    got = estimate_background(img, 1)
    assert level == pytest.approx(got[0], abs=0.01 + 2e-4 * got[0])
    assert sigma == pytest.approx(got[1], rel=0.01)


def test_direct_fit_recovers_gain_and_background_when_bias_and_read_noise_are_right():
    for lam, gain, read, bias, fpn in [(8.4, 4.0, 3.0, 2, 0.3), (4.4, 2.0, 2.0, 0, 0.0), (11.0, 6.0, 4.0, 5, 0.5)]:
        level, sigma = S.model_background(lam, gain, read, bias, fpn, 255)
        g, e, f = S.fit_direct(level, sigma, bias, read, fpn, 255)
        assert g == pytest.approx(gain, rel=0.01) and e == pytest.approx(lam, rel=0.01) and f == fpn
        assert S.electrons_at(level, gain, read, bias, fpn, 255) == pytest.approx(lam, rel=1e-3)


def test_direct_fit_drops_an_fpn_larger_than_the_noise():
    level, sigma = S.model_background(6.0, 3.0, 2.0, 1, 0.0, 255)  # sigma ~1 ADU
    _, _, fpn = S.fit_direct(level, sigma, 1, 2.0, 1.2, 255)
    assert fpn == 0.0


# ------------------------------------------------------------------------------ the line and its refusals
def _frames_boxes(lam_centre, drop, gain, read, bias, fpn, top, n=3, shape=(256, 384), seed=0):
    """Background boxes (skygen.real.fit_camera.sensor_boxes) of ``n`` starless frames whose background falls
    by ``drop`` (fraction) from the centre to the corners."""
    from skygen.real.fit_camera import sensor_boxes

    rng = np.random.default_rng(seed)
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    lam = lam_centre * (1 - drop * r2)
    pattern = np.rint(fpn * rng.standard_normal(shape))
    imgs = [_read_out(rng, lam, gain, read, bias, pattern, top, shape) for _ in range(n)]
    return sensor_boxes([background(im, 64) for im in imgs]), imgs


def test_the_line_gives_gain_and_bias_over_a_long_lever_arm():
    """288 boxes from 900 down to 420 ADU: the gain to ~1.5 %, the bias (an extrapolation to 0 ADU) to ~8 ADU."""
    boxes, _ = _frames_boxes(2000.0, 0.6, 2.5, 5.0, 100, 1.0, 4095, shape=(512, 768))
    mv = S.mean_variance(boxes["level"], boxes["variance"], boxes["level_noise"], 5.0, 1.0, 4095)
    assert mv["ok"], mv
    assert mv["gain_e_per_adu"] == pytest.approx(2.5, rel=0.05)
    assert mv["bias_adu"] == pytest.approx(100, abs=25) and mv["slope_rse"] < 0.03


def test_a_background_at_the_adc_floor_is_refused():
    boxes, _ = _frames_boxes(6.0, 0.5, 3.0, 3.0, 0, 0.2, 255)
    mv = S.mean_variance(boxes["level"], boxes["variance"], boxes["level_noise"], 5.0, 1.0, 255)
    assert not mv["ok"] and mv["term"] == "gain, bias and read noise"
    assert "within 3 σ of the ADC's floor (0 ADU)" in mv["why"]


def test_a_gain_without_a_lever_arm_is_refused():
    """A flat background 6 ADU above a bias of 5: the levels spread by their own noise only."""
    boxes, _ = _frames_boxes(11.0, 0.0, 6.0, 4.0, 5, 0.5, 255)
    mv = S.mean_variance(boxes["level"], boxes["variance"], boxes["level_noise"], 5.0, 1.0, 255)
    assert not mv["ok"] and mv["term"] == "gain"
    assert mv["why"].startswith("background spans ")


def test_an_impossible_bias_is_refused_and_the_direct_fit_says_what_it_used():
    """A gain of 25 e-/ADU and a read noise of 20 e- read as a line with the start camera's 2 e-: the
    intercept needs a bias far above the background, which is refused."""
    from skygen.config import build_config

    boxes, _ = _frames_boxes(2000.0, 0.5, 25.0, 2.0, 30, 0.3, 4095)
    mv = S.mean_variance(boxes["level"], boxes["variance"], boxes["level_noise"], 200.0, 0.3, 4095)
    assert not mv["ok"] and mv["term"] == "bias", mv
    assert "above the darkest background" in mv["why"] and "impossible" in mv["why"]
    start = build_config({"sensor": {"read_noise_e": 200.0, "fpn_adu": 0.3}}).sensor
    fit, rec = S.fit_sensor(boxes, start, None, 4095, "the start camera's")
    assert fit.method == "direct" and fit.bias_adu == 0
    assert fit.said.startswith("bias not constrained by these frames (the mean–variance line")
    assert "used instead" in fit.said and "bias 0 ADU (no camera file gives one)" in fit.said
    assert rec["direct"]["model_level_adu"] == pytest.approx(rec["level_adu"], rel=0.01)
    assert rec["direct"]["model_sigma_adu"] == pytest.approx(rec["sigma_adu"], rel=0.01)


def test_darks_quieter_than_the_adc_rounding_keep_the_start_cameras_gain_and_say_so():
    """An 8-bit JPEG's crushed blacks: every background box at 0 ADU with no noise. No gain gives a read-out less
    noisy than its own rounding, so the start camera's gain, read noise and FPN are kept and the line says why
    (a first run on such frames fitted a gain of 2e6 e-/ADU and stopped on the config's range check)."""
    from skygen.config import build_config

    n = 200
    boxes = {k: np.zeros(n) for k in ("level", "variance", "level_noise", "sigma")}
    start = build_config({}).sensor
    fit, rec = S.fit_sensor(boxes, start, None, 255, "the start camera's")
    assert fit.method == "kept" and fit.gain_e_per_adu == start.gain_e_per_adu
    assert fit.read_noise_e == start.read_noise_e and rec["method"] == "kept"
    assert "below an ADC's own rounding" in fit.said and "renders will show more background noise" in fit.said
    build_config({"sensor": {"gain_e_per_adu": fit.gain_e_per_adu}})  # a valid camera
    # the same through a correction's targets (renders' noise scaled down towards the frames' 0)
    fit, _ = S.fit_sensor(boxes, start, 0, 255, "as fitted", targets=(0.05, 0.001))
    assert fit.method == "kept"


def test_fixed_pattern_is_the_covariance_frames_share():
    _, imgs = _frames_boxes(20.0, 0.3, 2.0, 3.0, 4, 0.7, 255, n=4)
    bgs = [background(im, 64) for im in imgs]
    got = fixed_pattern(imgs, [b["level_map"] for b in bgs], [b["sigma_map"] for b in bgs], 0.0)
    assert got["pairs"] == 3 and got["fpn_adu"] == pytest.approx(0.7, rel=0.1)
    assert fixed_pattern(imgs[:1], [bgs[0]["level_map"]], [bgs[0]["sigma_map"]], 0.0)["fpn_adu"] is None


# ------------------------------------------------------------------------------ statistics and the check
def test_star_width_skips_saturated_stars_rather_than_giving_nan():
    """The 25 brightest detections saturated, 5 fainter ones not: the width comes from those five."""
    img = np.zeros((200, 200), np.float32)
    yy, xx = np.mgrid[:200, :200]
    xs, ys = [], []
    for k in range(30):
        x, y = 15 + (k % 6) * 30, 15 + (k // 6) * 35
        img += 100 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.2**2))
        xs.append(x)
        ys.append(y)
    peak = np.array([300.0] * 25 + [100.0] * 5)
    det = {"x_px": np.array(xs, float), "y_px": np.array(ys, float), "peak_adu": peak}
    width, n = star_width_px(img, det, 0.0, 255.0)
    assert n == 5 and width == pytest.approx(1.2, rel=0.1)


def test_check_renders_names_each_statistic_off_and_a_nan_with_its_reason():
    real = [{"background_adu": 1.2, "noise_adu": 1.34, "star_sigma_px": 1.9, "detections": 30}] * 3
    rendered = [{"background_adu": 67.0, "noise_adu": 1.40, "star_sigma_px": float("nan"), "detections": 25}] * 3
    checks = {c["stat"]: c for c in check_renders(real, rendered)}
    assert not checks["background_adu"]["ok"] and "55.83 x (tolerance 10 %)" in checks["background_adu"]["why"]
    assert checks["noise_adu"]["ok"] and checks["detections"]["ok"]
    assert not checks["star_sigma_px"]["ok"]
    assert checks["star_sigma_px"]["why"].startswith("star width not measured on the renders (no unsaturated")
    # a background clipped to 0 on the frames: 0 rendered agrees (no ratio needed); anything else is said as is
    black = [{"background_adu": 0.0, "noise_adu": 0.29, "star_sigma_px": 0.9, "detections": 40}] * 3
    assert {c["stat"]: c for c in check_renders(black, black)}["background_adu"]["ok"]
    off = {c["stat"]: c for c in check_renders(black, [{**black[0], "background_adu": 3.0}] * 3)}["background_adu"]
    assert not off["ok"] and off["why"] == "background 3 rendered vs 0 real"


def test_the_check_says_how_much_of_a_ratio_is_the_renders_own_noise():
    """Renders of each frame in passes (fit_render.check_stats): the verdict rests on the median over all of them,
    and says each pass's ratio alone, so that a ratio at the tolerance's edge is seen to be the renders' noise."""
    from skygen.real.frame_stats import repeat_ratios

    real = [{"background_adu": 2.0, "noise_adu": 1.5, "star_sigma_px": 1.3, "detections": 40}] * 5
    base = {"background_adu": 2.0, "noise_adu": 1.5, "star_sigma_px": 1.3}
    per_pass = {0: [44, 46, 48, 50, 52], 1: [50, 52, 54, 56, 58], 2: [54, 56, 58, 60, 62]}  # medians 48, 54, 58
    rendered = [{**base, "detections": d, "render_pass": p} for p, ds in per_pass.items() for d in ds]
    assert repeat_ratios(real, rendered, "detections") == pytest.approx([1.2, 1.35, 1.45])
    det = {c["stat"]: c for c in check_renders(real, rendered)}["detections"]
    assert det["ratio"] == pytest.approx(54 / 40) and not det["ok"]  # the median over all 15 renders
    assert det["passes"] == pytest.approx([1.2, 1.35, 1.45])
    assert det["why"].endswith("(tolerance 25 %; 3 renders of each frame, one by one 1.20-1.45 x)")
    # one render per frame (no passes, as benchmarks give them): nothing to say about it
    assert (
        repeat_ratios(real, rendered[:5], "detections") == []
        and "one by one"
        not in check_renders(real, [{k: v for k, v in r.items() if k != "render_pass"} for r in rendered])[3]["why"]
    )


def test_renders_whose_stars_miss_the_width_take_the_other_fitted_profile_where_its_wings_fit():
    """correct_once on a star width that is off: the Moffat fitted to the same stars where a Gaussian's renders are
    too narrow and the Moffat has wings (beta < WING_BETA), the Gaussian where a Moffat's renders are too wide;
    otherwise (a Moffat no wider than a Gaussian) the PSF's width moves by the difference in quadrature."""
    from skygen.real.fit_render import correct_once

    def off(ratio):
        return [{"stat": "star_sigma_px", "ratio": ratio, "ok": False, "real": 2.0, "rendered": 2.0 * ratio}]

    fitted = {"ok": True, "gaussian_sigma_px": 1.8, "moffat_sigma_px": 1.633, "moffat_beta": 1.54}
    meas = {"psf": {**fitted, "psf": "gaussian"}}
    changed, exposure = correct_once(off(0.87), meas, {}, 1.0, None, 255)
    assert meas["psf"] == {**fitted, "psf": "moffat"} and exposure == 1.0
    assert changed == [
        "PSF profile moffat (as fitted to the stars: σ(FWHM) 1.633 px, β 1.54) for the wider stars of the frames"
    ]
    meas = {"psf": {**fitted, "psf": "moffat"}}  # renders too wide with a Moffat: the Gaussian
    correct_once(off(1.2), meas, {}, 1.0, None, 255)
    assert meas["psf"]["psf"] == "gaussian" and meas["psf"]["gaussian_sigma_px"] == 1.8
    narrow_wings = {**fitted, "moffat_beta": 5.8, "psf": "gaussian"}  # openstartracker's: no wing to gain
    meas = {"psf": dict(narrow_wings)}
    changed, _ = correct_once(off(0.8), meas, {}, 1.0, None, 255)
    # widths add in quadrature: the PSF takes the frames' width less the renders' (2.0 real, 1.6 rendered)
    want = np.sqrt(1.8**2 + 2.0**2 - 1.6**2)
    assert meas["psf"]["psf"] == "gaussian" and meas["psf"]["gaussian_sigma_px"] == pytest.approx(want)
    assert changed == [f"PSF σ {want:.3f} px (the frames' star width less the renders' in quadrature)"]
    meas = {"psf": dict(narrow_wings)}  # far too wide: the quadrature would leave less than half the PSF, so scaled
    correct_once(off(1.6), meas, {}, 1.0, None, 255)
    assert meas["psf"]["gaussian_sigma_px"] == pytest.approx(1.8 / 1.6)


# ------------------------------------------------------------------------------ end to end
FAINT = {
    "camera": {"width_px": 640, "height_px": 480, "pixel_pitch_um": 5.5, "fov_deg": 16.0},
    "optics": {"psf_sigma_px": 1.2, "vignetting": 0.7},
    "photometry": {"sky_mag_arcsec2": 20.8},
    "sensor": {
        "exposure_s": 0.5,
        "gain_e_per_adu": 3.0,
        "read_noise_e": 3.0,
        "bias_adu": 0,
        "fpn_adu": 0.2,
        "bit_depth": 8,
        "dark_current_e_s": 0.0,
        "full_well_e": 10000.0,
    },
    "corruptions": {"cosmic_rays": 0.0, "stray_light": 8.0},
    "detection": {"max_detections": 200},
    "output": {"image_size_px": 160},
}


@pytest.fixture(scope="module")
def faint_frames(tmp_path_factory) -> Path:
    """Four 8-bit frames of a camera whose background is 1-4 ADU (bias 0: its noise clipped at 0 ADU) and a
    start camera file of the right field (1 % off) with no sensor section (skygen's default: bias 100)."""
    from skygen.config import build_config
    from skygen.render.frame import Renderer

    folder = tmp_path_factory.mktemp("faint")
    cfg = build_config({**FAINT, "n_frames": 4, "seed": 6, "output": {**FAINT["output"], "full_res": True}})
    r = Renderer(cfg)
    for i in range(4):
        cv2.imwrite(str(folder / f"frame{i}.png"), r.render(i).image_full.astype(np.uint8))
    start = {"camera": {**FAINT["camera"], "fov_deg": 16.0 * 1.01}, "output": {"image_size_px": 160}}
    (folder / "start.yaml").write_text(yaml.safe_dump(start))
    return folder


def _fit(folder: Path, out: Path) -> int:
    return main(
        [
            "fit-camera",
            *[str(p) for p in sorted(folder.glob("frame*.png"))],
            "--camera",
            str(folder / "start.yaml"),
            "--out",
            str(out / "fitted.yaml"),
            "--report",
            str(out / "rep"),
        ]
    )


def test_a_faint_8_bit_camera_is_fitted_to_its_background(faint_frames, tmp_path, capsys):
    """About 20 s: the mean-variance line is refused (the background sits at the ADC's floor), saying so on
    the terminal and in the report; the direct fit's renders reproduce the background and its noise."""
    pytest.importorskip("tetra3rs")
    assert _fit(faint_frames, tmp_path) == 0
    err = capsys.readouterr().err
    line = [m for m in err.splitlines() if "read noise not constrained by these frames" in m]
    assert len(line) == 1 and "used instead" in line[0] and "WARNING" not in err
    rec = json.loads((tmp_path / "rep" / "fit.json").read_text())
    assert rec["sensor"]["method"] == "direct" and not rec["warnings"]
    cmp = rec["compare"]
    assert cmp["background_adu"]["fitted"] == pytest.approx(cmp["background_adu"]["real"], rel=0.10)
    assert cmp["noise_adu"]["fitted"] == pytest.approx(cmp["noise_adu"]["real"], rel=0.15)
    assert cmp["star_sigma_px"]["fitted"] == pytest.approx(cmp["star_sigma_px"]["real"], rel=0.10)
    assert cmp["detections"]["fitted"] == pytest.approx(cmp["detections"]["real"], rel=0.25)
    # the check renders each of the four frames four times (fit_render.CHECK_RENDERS), each pass with its own noise
    passes = [r["render_pass"] for r in rec["fitted_stats"]]
    assert passes == [0] * 4 + [1] * 4 + [2] * 4 + [3] * 4
    assert len({r["noise_adu"] for r in rec["fitted_stats"][::4]}) == 4
    assert cmp["catalogue_detections"]["fitted"] <= cmp["detections"]["fitted"]
    rep = (tmp_path / "rep" / "REPORT.md").read_text()
    assert "gain, bias and read noise not constrained by these frames" in rep and "WARNING" not in rep
    assert "each rendered 4 times" in rep and "| of which catalogue stars |" in rep
    # the camera file's bias 100 ADU (skygen's default) is above this background: 0 was used, and said
    assert "the camera file's 100 ADU is above the darkest background" in rep


def test_a_camera_whose_renders_contradict_its_frames_is_written_with_a_warning(
    faint_frames, tmp_path, capsys, monkeypatch
):
    """About 20 s: a fitted term spoiled (20 ADU more bias in every render) and the correction switched
    off: the camera is written, with a WARNING on the terminal, atop the report and in the file."""
    pytest.importorskip("tetra3rs")
    from skygen.real import fit_render

    build = fit_render.build_fitted

    def spoiled(cfg0, cam, meas, exposure, pixel_pitch_um=None):
        return build(cfg0, cam, {**meas, "bias_adu": meas["bias_adu"] + 20}, exposure, pixel_pitch_um)

    monkeypatch.setattr(fit_render, "build_fitted", spoiled)
    monkeypatch.setattr(fit_render, "correct_once", lambda checks, meas, px, exposure, *a: ([], exposure))
    assert _fit(faint_frames, tmp_path) == 0
    err = capsys.readouterr().err
    warn = [m for m in err.splitlines() if m.startswith("fit-camera: WARNING: renders of this camera contradict")]
    assert len(warn) == 1 and "background " in warn[0] and "(tolerance 10 %; 4 renders of each frame" in warn[0]
    rep = (tmp_path / "rep" / "REPORT.md").read_text().splitlines()
    block = [n for n, m in enumerate(rep) if m.startswith("> **WARNING")]
    assert block and block[0] < 6 and any(m.startswith("> - background ") for m in rep)
    head = (tmp_path / "fitted.yaml").read_text().splitlines()[0]
    assert head.startswith("# WARNING: renders of this camera contradict the frames it was fitted on")


def test_renders_that_miss_the_noise_are_corrected_once(faint_frames, tmp_path, capsys, monkeypatch):
    """About 25 s: the first direct fit spoiled (3 x the gain: renders too quiet); the check finds the noise
    off, the sensor is fitted once more to the frames, and the camera written matches without a warning."""
    pytest.importorskip("tetra3rs")
    calls = []
    fit = S.fit_direct

    def first_spoiled(*a, **k):
        g, lam, fpn = fit(*a, **k)
        calls.append(g)
        return (3 * g, 3 * lam, fpn) if len(calls) == 1 else (g, lam, fpn)

    monkeypatch.setattr(S, "fit_direct", first_spoiled)
    assert _fit(faint_frames, tmp_path) == 0
    err = capsys.readouterr().err
    assert len(calls) == 2 and "WARNING" not in err
    said = [m for m in err.splitlines() if m.startswith("fit-camera: renders of the fitted camera missed the frames")]
    assert len(said) == 1 and "background σ" in said[0] and "corrected once: gain" in said[0]
    rec = json.loads((tmp_path / "rep" / "fit.json").read_text())
    assert rec["correction"]["kept"] and not rec["warnings"]
    cmp = rec["compare"]
    assert cmp["noise_adu"]["fitted"] == pytest.approx(cmp["noise_adu"]["real"], rel=0.15)
    assert "Corrected once" in (tmp_path / "rep" / "REPORT.md").read_text()


@pytest.mark.parametrize("shape", [(256, 320), (300, 250)])
def test_box_statistics_at_once_equal_the_per_box_ones(shape):
    """fit_pixels.background estimates every whole box's level (even rows) and difference noise (odd rows)
    in one vectorised pass: the same numbers as the one-box functions (float32 summation order aside), a box
    with a star included, partial edge boxes one at a time."""
    from skygen.instrument.detect import estimate_background
    from skygen.real import fit_pixels as P

    rng = np.random.default_rng(3)
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.round(150 + 0.05 * xx + rng.normal(0, 2.5, shape))
    img[h // 2 : h // 2 + 3, w // 3 : w // 3 + 3] += 3000
    got = P.background(img, 64)
    ys, xs = np.arange(32, h, 64), np.arange(32, w, 64)
    boxes = [img[max(y - 32, 0) : y + 32, max(x - 32, 0) : x + 32] for y in ys for x in xs]
    ref = np.array([estimate_background(b[0::2], 1) for b in boxes])
    np.testing.assert_allclose(got["box_level"], ref[:, 0], rtol=1e-6)
    np.testing.assert_allclose(got["box_clip_sigma"], ref[:, 1], rtol=1e-5)
    np.testing.assert_allclose(got["box_sigma"], [P._difference_sigma(b[1::2]) for b in boxes], rtol=1e-12)
    assert np.all(np.abs(got["box_sigma"] - 2.5) < 0.4)  # the star is clipped from the noise


def test_frame_noise_is_the_noise_the_detector_thresholds_on():
    """A sky-glow gradient is not noise where the detector takes a local background: frame_stats' noise_adu is then
    the boxes' median sigma (~ the pixel noise drawn), and the frame's clipped sigma only without boxes."""
    from skygen.real.frame_stats import frame_stats

    rng = np.random.default_rng(5)
    h, w = 480, 640
    glow = 12.0 * (np.arange(w)[None, :] / w) ** 2 * np.ones((h, 1))  # a curved glow, 12 ADU edge to edge
    img = (40.0 + glow + rng.normal(0.0, 1.5, (h, w))).astype(np.float32)
    local, _ = frame_stats(img, 5.0, 3, 64, 255.0)
    whole, _ = frame_stats(img, 5.0, 3, 0, 255.0)
    assert local["noise_adu"] == pytest.approx(1.5, rel=0.08)
    assert whole["noise_adu"] > 1.3 * local["noise_adu"]  # the glow counted as noise by a global sigma
