"""fusion predict without a model: any sensor size with no storage settings, and an unknown field (--fov-range)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from fusion.cli import main

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "real-frames" / "tetra3-blackfly"


def test_camera_of_any_size_needs_no_storage_settings(tmp_path):
    """770 rows are no multiple of 1024 / 256: a camera file without an output section still predicts."""
    from fusion.solve.predict import Predictor

    cam = tmp_path / "odd.yaml"
    cam.write_text(
        yaml.safe_dump({"camera": {"width_px": 1024, "height_px": 770, "pixel_pitch_um": 6.9, "focal_length_mm": 35.0}})
    )
    pred = Predictor(camera=cam)
    assert (pred.camera.width_px, pred.camera.height_px) == (1024, 770)
    img = np.random.default_rng(0).normal(100, 3, (770, 1024)).astype(np.float32)
    pred.check_shape(img, "x")
    det, _, _ = pred.detect(img)
    assert pred.stored_image(img).shape == (770, 1024)


def test_fitted_camera_background_box_is_the_default(tmp_path):
    from fusion.solve.predict import Predictor

    cam = tmp_path / "c.yaml"
    cam.write_text(
        yaml.safe_dump(
            {
                "camera": {"width_px": 640, "height_px": 480, "pixel_pitch_um": 5.0, "fov_deg": 12.0},
                "detection": {"background_box_px": 64},
            }
        )
    )
    assert Predictor(camera=cam).background_box == 64
    assert Predictor(camera=cam, background_box=0).background_box == 0


@pytest.mark.slow
def test_fov_range_solves_real_frames_and_finds_the_field(tmp_path, capsys):
    pytest.importorskip("tetra3rs")
    with open(REAL / "solutions.csv", newline="") as f:
        listed = {r["file"]: float(r["fov_deg"]) for r in csv.DictReader(f)}
    names = sorted(listed)[2:4]
    out = tmp_path / "p.jsonl"
    assert (
        main(
            [
                "predict",
                *[str(REAL / n) for n in names],
                "--fov-range",
                "10",
                "13",
                "--solve",
                "--background-box",
                "64",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    for n, r in zip(names, recs):
        sol = r["solution"]
        assert sol["status"] == "solved"
        assert sol["fov_deg"] == pytest.approx(listed[n], rel=0.005)


def test_fov_range_refuses_a_checkpoint_and_bad_bounds(tmp_path, capsys):
    assert main(["predict", "x.png", "--fov-range", "20", "10", "--solve"]) == 2
    assert "LO < HI" in capsys.readouterr().err


def test_detections_know_which_stars_are_saturated(tmp_path):
    """A star clipped at the top of an 8-bit frame is flagged saturated, a fainter one is not; the flag follows the
    detections through brightest / take, and the top of a frame's range is read from its data, not its type."""
    from fusion.solve.predict import Predictor, frame_top

    assert frame_top(np.full((4, 4), 120, np.uint16)) == 255  # 8-bit data in a 16-bit array
    assert frame_top(np.full((4, 4), 4000.0)) == 4095
    assert frame_top(np.full((4, 4), 65520, np.uint16)) == 65535  # 12-bit data x 16
    cam = tmp_path / "c.yaml"
    cam.write_text(yaml.safe_dump({"camera": {"width_px": 200, "height_px": 160, "pixel_pitch_um": 5.0, "fov_deg": 5}}))
    yy, xx = np.mgrid[0:160, 0:200]
    img = np.random.default_rng(1).normal(20, 2, (160, 200))
    for x0, y0, amp in ((60.3, 50.6, 900.0), (140.2, 110.1, 90.0)):  # a clipped star, an unsaturated one
        img += amp * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * 1.5**2))
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    det, _, _ = Predictor(camera=cam, background_box=0).detect(img)
    assert len(det) == 2 and det.saturated.tolist() == [True, False]
    assert abs(det.x_px[0] - 60.3) < 0.5 and det.brightest(1).saturated.tolist() == [True]
    assert det.take([1]).saturated.tolist() == [False]
