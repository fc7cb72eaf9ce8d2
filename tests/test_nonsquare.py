"""Non-square sensors: config, render, storage, validation; fusion models refuse them clearly (for now)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from skygen.config import load_config
from skygen.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
WIDE = [
    "camera.width_px=256",
    "camera.height_px=192",
    "camera.pixel_pitch_um=22.0",
    "output.image_size_px=64",
    "output.shard_size=10",
    "n_frames=10",
]


def test_config_accepts_non_square_with_an_integer_factor():
    cfg = load_config(overrides=WIDE)
    assert (cfg.camera.width_px, cfg.camera.height_px) == (256, 192)
    with pytest.raises(ConfigError, match="multiple of the downsampling factor"):
        load_config(overrides=["camera.width_px=256", "camera.height_px=190", "output.image_size_px=64"])


def test_camera_presets_load():
    for p in sorted((ROOT / "configs" / "cameras").glob("*.yaml")):
        cfg = load_config(p)
        assert cfg.camera.width_px % cfg.output.image_size_px == 0, p
    bf = load_config(ROOT / "configs" / "cameras" / "blackfly-s-imx265-35mm.yaml")
    from skygen.instrument.camera import Camera

    cam = Camera.from_config(bf.camera)
    assert (cam.width_px, cam.height_px) == (1024, 768)
    assert cam.fov_deg[0] == pytest.approx(11.53, abs=0.01) and cam.fov_deg[1] == pytest.approx(8.66, abs=0.01)


def test_render_store_validate_non_square(tmp_path):
    from skygen.datasets.build import render_dataset
    from skygen.datasets.shards import open_dataset
    from skygen.datasets.validate import validate

    out = tmp_path / "wide"
    render_dataset(load_config(overrides=WIDE), out, workers=1, progress=False)
    with open_dataset(out) as ds:
        assert ds.sensor_shape == (192, 256) and ds.image_shape == (48, 64) and ds.downsample_factor == 4
        img = ds.image(0)
        assert img.shape == (48, 64)
        for i in range(len(ds)):
            det, stars = ds.detections(i), ds.true_stars(i)
            assert np.all((det["y_px"] > -0.5) & (det["y_px"] < 191.5) & (det["x_px"] < 255.5))
            assert np.all(stars["y_px"] < 191.5)
    rep = validate(out)
    assert rep.ok, rep.problems


def test_fusion_geometry_of_a_non_square_sensor():
    """fusion takes non-square sensors (training on them: tests/test_fusion_stream.py)."""
    from fusion.model.inputs import FrameGeometry
    from skygen.config import config_dict

    geo = FrameGeometry.from_render_config(config_dict(load_config(overrides=WIDE)))
    assert (geo.sensor_px, geo.sensor_h, geo.image_px, geo.image_h, geo.factor) == (256, 192, 64, 48, 4)
