"""skygen.stream.samples: determinism, sample identity, bad input, and the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from skygen.cli import main
from skygen.config import build_config, config_dict, load_config
from skygen.errors import ConfigError, DatasetError
from skygen.render.frame import Renderer
from skygen.sky.attitude import attitude_matrices
from skygen.sky.attitude import matrices_to_quaternions as quaternions
from skygen.stream import emulator as emu
from skygen.stream.samples import SampleStream, partition


@pytest.fixture(scope="module")
def det_stream():
    return SampleStream(load_config(), "detections")


def _same(a: dict, b: dict) -> bool:
    keys = set(a["detections"]) | set(b["detections"])
    return (
        a["ra_deg"] == b["ra_deg"]
        and a["roll_deg"] == b["roll_deg"]
        and all(np.array_equal(a["detections"][k], b["detections"][k]) for k in keys)
    )


def test_detection_sample_is_pure_function_of_index(det_stream):
    alone = det_stream.sample(777)
    in_batch = det_stream.batch([3, 777, 12, 5000]).sample(1)
    reversed_batch = det_stream.batch(np.arange(800, 700, -1)).sample(23)  # index 777
    fresh = SampleStream(load_config(), "detections").sample(777)
    assert _same(alone, in_batch) and _same(alone, reversed_batch) and _same(alone, fresh)
    assert not _same(alone, det_stream.sample(778))


def test_worker_and_rank_splits_cover_the_stream_once(det_stream):
    ranks = [list(x for _, x in zip(range(50), partition(100, r, 3))) for r in range(3)]
    flat = sorted(i for r in ranks for i in r)
    assert flat == list(range(100, 250))
    # restarting at any index reproduces the same samples
    whole = det_stream.batch(np.arange(100, 140))
    restarted = det_stream.batch(np.arange(120, 140))
    for j in range(20):
        assert _same(whole.sample(20 + j), restarted.sample(j))


def test_detection_sets_look_like_the_default_camera(det_stream):
    b = det_stream.batch(np.arange(400))
    n = np.diff(b.offsets)
    assert 20 <= np.median(n) <= 40  # real detector: median 30 (docs/skygen.md)
    assert n.max() <= 64  # detection.max_detections
    # brightest first within every sample
    f = b.detections["flux_adu"]
    for j in range(len(b)):
        seg = f[b.offsets[j] : b.offsets[j + 1]]
        assert np.all(np.diff(seg) <= 0)
    # labels are consistent: quaternion <-> unit vector
    R = attitude_matrices(b.labels["ra_deg"], b.labels["dec_deg"], b.labels["roll_deg"])
    np.testing.assert_allclose(R[:, :, 2], b.labels["unit_vector"], atol=1e-12)
    np.testing.assert_allclose(quaternions(R), b.labels["quaternion"], atol=1e-12)


def test_stream_never_repeats_dataset_frames():
    cfg = load_config(overrides=["n_frames=50"])
    dataset = Renderer(cfg)
    frames = SampleStream(cfg, "frames")
    dets = SampleStream(cfg, "detections").batch(np.arange(50))
    for i in range(0, 50, 10):
        a, b = dataset.render(i), frames.frame(i)
        assert (a.ra_deg, a.dec_deg) != (b.ra_deg, b.dec_deg)
        assert (a.ra_deg, a.dec_deg) != (dets.labels["ra_deg"][i], dets.labels["dec_deg"][i])
    # frames-stream sample i is the tagged render of frame i, deterministic
    again = SampleStream(cfg, "frames").frame(20)
    assert np.array_equal(frames.frame(20).image, again.image)


def test_level_ranges_are_per_sample_and_applied(det_stream):
    cfg = load_config()
    s = SampleStream(cfg, "detections", level_ranges={"dropout": (0.5, 0.5), "false_stars": (3, 3)})
    base = det_stream.batch(np.arange(300))
    hard = s.batch(np.arange(300))
    assert np.all(hard.levels["dropout"] == 0.5)
    ratio = len(hard.detections["x_px"]) / len(base.detections["x_px"])
    assert 0.45 < ratio < 0.62  # half dropped, a few false stars added
    false_src = (hard.stars["hip_id"] < 0).sum() / len(hard)
    assert 2.5 < false_src < 3.5
    varied = SampleStream(cfg, "detections", level_ranges={"centroid_noise": (0, 2)}).batch(np.arange(200))
    lv = varied.levels["centroid_noise"]
    assert lv.min() < 0.2 and lv.max() > 1.8


def test_light_fixed_on_the_sensor_is_in_every_frame_and_sample():
    """sensor.fixed_sources: a round Gaussian of the given rate at fixed pixels. Rendered frames detect it there
    with the flux its electrons make, whatever the attitude; the detections stream places it too, with about the
    same flux, and needs no new detector calibration (the stream adds it, as it adds false stars); the binned
    renderer, which cannot paint it, is not used; bad sources are refused by name."""
    src = (800.0, 300.0, 2.0e5, 2.0)  # px, px, e-/s, px
    cfg = load_config(overrides=[f"sensor.fixed_sources=[{list(src)}]", "n_frames=3", "output.full_res=true"])
    r = Renderer(cfg)
    fluxes = []
    for i in range(3):
        d = r.render(i).detections
        k = int(np.argmin(np.hypot(d["x_px"] - src[0], d["y_px"] - src[1])))
        assert np.hypot(d["x_px"][k] - src[0], d["y_px"][k] - src[1]) < 0.2
        fluxes.append(float(d["flux_adu"][k]))
    electrons_adu = src[2] * cfg.sensor.exposure_s / cfg.sensor.gain_e_per_adu
    assert 0.8 < np.median(fluxes) / electrons_adu <= 1.0  # the detector's footprint holds most of it
    assert emu.calibration_key(config_dict(cfg)) == emu.calibration_key(config_dict(load_config()))
    batch = SampleStream(cfg, "detections").batch(np.arange(4))
    plain = SampleStream(load_config(), "detections").batch(np.arange(4))
    for j in range(4):
        d, d0 = batch.sample(j)["detections"], plain.sample(j)["detections"]
        gap = np.hypot(np.asarray(d["x_px"]) - src[0], np.asarray(d["y_px"]) - src[1])
        assert gap.min() < 0.5 and len(d["x_px"]) == len(d0["x_px"]) + 1
        assert 0.8 < float(np.asarray(d["flux_adu"])[np.argmin(gap)]) / np.median(fluxes) < 1.25
    binned = SampleStream(load_config(overrides=[f"sensor.fixed_sources=[{list(src)}]"]), "frames")
    assert binned.frames_renderer == "full"
    with pytest.raises(ConfigError, match=r"sensor.fixed_sources\[0\].*must lie on the"):
        load_config(overrides=["sensor.fixed_sources=[[5000.0, 1.0, 1.0, 1.0]]"])
    with pytest.raises(ConfigError, match=r"sensor.fixed_sources\[0\].*sigma"):
        load_config(overrides=["sensor.fixed_sources=[[5.0, 1.0, 1.0, 0.0]]"])
    with pytest.raises(ConfigError, match="needs render.backend=numpy"):
        load_config(overrides=["sensor.fixed_sources=[[5.0, 1.0, 1.0, 1.0]]", "render.backend=torch"])


def test_bad_input_is_refused_before_streaming(tmp_path):
    cfg = load_config()
    with pytest.raises(ConfigError, match="unknown; choose one of"):
        SampleStream(cfg, "pixels")
    s = SampleStream(cfg, "detections")
    with pytest.raises(ConfigError, match=">= 0"):
        s.batch([-1])
    with pytest.raises(ConfigError, match=">= 0"):
        next(partition(-5))
    # a calibration for another camera: the differing keys are named
    other = build_config({"camera": {"fov_deg": 12.0}})
    with pytest.raises(ConfigError, match="camera.fov_deg"):
        SampleStream(other, "detections")
    # damaged, foreign and missing calibration files
    body = json.loads(emu.default_calibration_path().read_text())
    body["threshold_e"] *= 1.01
    bad = tmp_path / "edited.json"
    bad.write_text(json.dumps(body))
    with pytest.raises(DatasetError, match="checksum"):
        SampleStream(cfg, "detections", calibration=bad)
    foreign = tmp_path / "foreign.json"
    foreign.write_text(json.dumps({"hello": 1}))
    with pytest.raises(DatasetError, match="not a skygen detector calibration"):
        SampleStream(cfg, "detections", calibration=foreign)
    garbage = tmp_path / "garbage.json"
    garbage.write_bytes(b"\x00\x01{not json")
    with pytest.raises(DatasetError, match="not a readable"):
        SampleStream(cfg, "detections", calibration=garbage)
    with pytest.raises(DatasetError, match="not found"):
        SampleStream(cfg, "detections", calibration=tmp_path / "nope.json")
    # a config that detects nothing
    dark = load_config(overrides=["sensor.exposure_s=1e-7"])
    with pytest.raises(ConfigError, match="detects no star"):
        SampleStream(dark, "frames")
    with pytest.raises(ConfigError, match="only false_stars, dropout"):
        SampleStream(cfg, "detections", level_ranges={"hotpixels": (0, 1e-3)})


def test_stream_cli(tmp_path, capsys):
    out = tmp_path / "sets.h5"
    assert main(["stream", "--kind", "detections", "--n", "300", "--out", str(out), "--range", "dropout=0:0.2"]) == 0
    text = capsys.readouterr().out
    assert "samples/s" in text and "detections per sample" in text
    import h5py

    with h5py.File(out) as f:
        assert len(f["index"]) == 300
        assert f["detections/offsets"][-1] == len(f["detections/x_px"])
    assert main(["stream", "--kind", "frames", "--n", "2", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["samples"] == 2
    assert main(["stream", "--kind", "detections", "--n", "10", "--start", "-1"]) == 2
    assert main(["stream", "--n", "10", "--range", "dropout=0.3"]) == 2
    assert "NAME=LO:HI" in capsys.readouterr().err
