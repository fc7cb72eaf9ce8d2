"""The detector emulator tells the truth: emulated versus real detections at the same attitudes.

Fresh frames are rendered in their own random stream (tag ``@emulator-test``, never used
for calibration); the shipped calibration emulates detections of the *same* true stars,
and the statistics the model will see are compared. Tolerances (also in docs/stream.md):

* completeness per 0.5-mag bin with >= 40 stars: within 0.08 absolute;
* centroid error of matched detections (radial): median within 25 %, p90 within 25 %;
* flux ratio ``flux_adu * gain / electrons``: median within 3 %, p10-p90 width within 15 %;
* detections per frame: mean within 5 %, and the 10th and 90th percentiles within 3;
* spurious detections: within 1 percentage point of all detections.
"""

from __future__ import annotations

import numpy as np
import pytest

from skygen import hashrng
from skygen.config import load_config
from skygen.render.frame import Renderer
from skygen.stream import calibration as cal
from skygen.stream import emulator as emu

N_FRAMES = 160


@pytest.fixture(scope="module")
def pairs():
    cfg = cal.calibration_config(load_config())
    r = Renderer(cfg, rng_tag="@emulator-test")
    model = emu.load(emu.default_calibration_path())
    emu.check_compatible(model, __import__("skygen.config", fromlist=["config_dict"]).config_dict(cfg))
    frames = [r.render(i) for i in range(N_FRAMES)]
    # the emulator on the same true stars (sources) of every frame
    st = [f.stars for f in frames]
    fr = np.concatenate([np.full(len(s["x_px"]), k) for k, s in enumerate(st)])
    rows = np.concatenate([np.arange(len(s["x_px"])) for s in st])

    def cat(k):
        return np.concatenate([s[k] for s in st]).astype(np.float64)

    key = hashrng.stream_key(0, "@emulator-test")
    em = model.emulate(key, fr, rows, fr, cat("x_px"), cat("y_px"), cat("electrons"))
    sp = model.spurious_detections(key, np.arange(N_FRAMES), 1 << 40, cfg.camera.width_px, cfg.camera.height_px)
    return cfg, model, frames, st, fr, rows, cat, em, sp


def test_completeness_per_magnitude(pairs):
    cfg, model, frames, st, fr, rows, cat, em, sp = pairs
    mag = cat("mag")
    real = np.concatenate([np.isin(np.arange(len(s["x_px"])), f.detections["star_index"]) for s, f in zip(st, frames)])
    emul = np.zeros(len(fr), bool)
    emul[em["src"]] = True
    checked = 0
    for lo in np.arange(2.0, 7.0, 0.5):
        sel = (mag >= lo) & (mag < lo + 0.5)
        if sel.sum() < 40:
            continue
        checked += 1
        assert abs(real[sel].mean() - emul[sel].mean()) < 0.08, (lo, real[sel].mean(), emul[sel].mean())
    assert checked >= 5


def _real_matched(frames, st):
    dx, ratio = [], []
    for s, f in zip(st, frames):
        d = f.detections
        m = d["star_index"] >= 0
        si = d["star_index"][m]
        dx.append(np.hypot(d["x_px"][m] - s["x_px"][si], d["y_px"][m] - s["y_px"][si]))
        ratio.append(d["flux_adu"][m] / s["electrons"][si])
    return np.concatenate(dx), np.concatenate(ratio)


def test_centroid_and_flux_distributions(pairs):
    cfg, model, frames, st, fr, rows, cat, em, sp = pairs
    real_dr, real_ratio = _real_matched(frames, st)
    src = em["src"]
    emu_dr = np.hypot(em["x_px"] - cat("x_px")[src], em["y_px"] - cat("y_px")[src])
    emu_ratio = em["flux_adu"] / cat("electrons")[src]
    for q in (50, 90):
        a, b = np.percentile(real_dr, q), np.percentile(emu_dr, q)
        assert abs(a - b) / a < 0.25, (q, a, b)
    g = cfg.sensor.gain_e_per_adu
    a, b = np.median(real_ratio) * g, np.median(emu_ratio) * g
    assert abs(a - b) / a < 0.03
    wa = np.subtract(*np.percentile(real_ratio, [90, 10]))
    wb = np.subtract(*np.percentile(emu_ratio, [90, 10]))
    assert abs(wa - wb) / wa < 0.15


def test_detections_per_frame_and_spurious_rate(pairs):
    cfg, model, frames, st, fr, rows, cat, em, sp = pairs
    cap = cfg.detection.max_detections
    real_n = np.array([len(f.detections["x_px"]) for f in frames])
    emu_n = np.minimum(np.bincount(em["frame"], minlength=N_FRAMES) + np.bincount(sp["frame"], minlength=N_FRAMES), cap)
    assert abs(real_n.mean() - emu_n.mean()) / real_n.mean() < 0.05
    for q in (10, 90):
        assert abs(np.percentile(real_n, q) - np.percentile(emu_n, q)) <= 3
    real_sp = sum(int((f.detections["star_index"] < 0).sum()) for f in frames) / real_n.sum()
    emu_sp = len(sp["frame"]) / emu_n.sum()
    assert abs(real_sp - emu_sp) < 0.01


def test_calibration_round_trip_and_blending(tmp_path, pairs):
    model = pairs[1]
    path = emu.save(model, tmp_path / "c.json")
    again = emu.load(path)
    np.testing.assert_array_equal(again.completeness, model.completeness)
    assert again.key == model.key
    # two equal stars of 10 x threshold: merged when close, resolved when far apart
    thr = model.threshold_e
    key = hashrng.stream_key(1, "blend")
    n = 400
    e = np.full(2 * n, 10 * thr)
    fr = np.repeat(np.arange(n), 2)
    for sep, expect_pairs in ((2.0, False), (11.0, True)):
        x = np.where(np.arange(2 * n) % 2, 500.0 + sep, 500.0)
        out = model.emulate(key, fr, np.tile([0, 1], n), fr, x, np.full(2 * n, 500.0), e)
        per = np.bincount(out["frame"], minlength=n)
        assert per.min() >= 1
        assert (per == 2).mean() > 0.9 if expect_pairs else (per == 1).mean() > 0.9


def test_blending_matches_the_real_detector(pairs):
    """Pairs of equal stars painted into a frame and run through the real detector: the
    separation at which they split into two detections agrees with the emulator's."""
    from skygen.instrument.detect import detect
    from skygen.instrument.psf import add_patch, gaussian_stamps
    from skygen.instrument.sensor import Exposure, read_out

    cfg, model = pairs[0], pairs[1]
    r = Renderer(cfg)
    rng = np.random.default_rng(7)
    for mult in (3.0, 30.0):
        seps = np.arange(3.0, 11.01, 1.0)
        split = []
        for d in seps:
            two = 0
            for _ in range(16):
                img = np.zeros((cfg.camera.height_px, cfg.camera.width_px), np.float32)
                x0, y0, ang = 500 + rng.random(), 500 + rng.random(), rng.uniform(0, np.pi)
                xs, ys = np.array([x0, x0 + d * np.cos(ang)]), np.array([y0, y0 + d * np.sin(ang)])
                boxes = [
                    add_patch(img, y, x, p)
                    for y, x, p in gaussian_stamps(
                        xs, ys, np.full(2, mult * model.threshold_e), cfg.optics.psf_sigma_px
                    )
                ]
                full, _ = read_out(
                    Exposure(img, None, [b for b in boxes if b], r.background_e, None), cfg.sensor, r.maps, rng, 0.0
                )
                det, _, _ = detect(full, cfg.detection.threshold_sigma, cfg.detection.min_area_px, 64)
                two += int((np.hypot(det["x_px"] - x0, det["y_px"] - y0) < d + 4).sum() >= 2)
            split.append(two / 16)
        real_radius = seps[np.argmax(np.array(split) >= 0.5)] - 0.5
        assert abs(real_radius - model.blend_radius_px(mult * model.threshold_e)) <= 1.5, (mult, split)


def test_fit_from_a_dataset_matches_render_fit(tmp_path):
    from skygen.datasets.build import render_dataset

    cfg = load_config(overrides=["n_frames=40", "output.shard_size=40"])
    render_dataset(cfg, tmp_path / "ds", workers=1, progress=False)
    model = cal.calibrate_from_dataset(tmp_path / "ds")
    assert model.info["frames"] == 40
    emu.check_compatible(model, __import__("skygen.config", fromlist=["config_dict"]).config_dict(cfg))
    # the 50 % point of the completeness curve sits near the threshold (u = 0) by construction
    u50 = emu.U_EDGES[np.argmax(model.completeness >= 0.5)]
    assert -0.3 <= u50 <= 0.3
