"""Latency timing: the JSON schema, FLOPs = 2 x MACs, and end-to-end preprocessing equal to the data pipeline."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fusion import cli as fcli
from fusion.errors import ConfigError
from fusion.measure import timing as tim

STAT_KEYS = {"median_ms", "p90_ms", "p99_ms", "mean_ms", "min_ms", "max_ms", "std_ms", "n", "throughput_per_s"}


def cli(argv: list[str]) -> int:
    """``fusion timing ARGS`` through the real command line."""
    return fcli.main(["timing", *argv])


def _check_stats(s: dict, iters: int) -> None:
    assert STAT_KEYS <= set(s)
    assert s["n"] == iters
    assert 0 < s["min_ms"] <= s["median_ms"] <= s["p90_ms"] <= s["p99_ms"] <= s["max_ms"]
    assert s["throughput_per_s"] > 0


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("timing") / "smoke.json"
    assert (
        cli(
            [
                "--config",
                "configs/smoke.yaml",
                "--image-size",
                "64",
                "--iters",
                "4",
                "--warmup",
                "1",
                "--batch",
                "2",
                "--mode",
                "both",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    return json.loads(out.read_text())


def test_json_has_every_section_with_positive_numbers(report):
    assert report["format"] == "fusion-timing" and report["format_version"] == 1
    assert report["settings"] == {
        **report["settings"],
        "device": "cpu",
        "precision": "fp32",
        "batch": 2,
        "iters": 4,
        "warmup": 1,
        "mode": "both",
    }
    m = report["model"]
    assert m["name"] == "star_fusion" and m["image_backbone"] == "tiny_cnn" and m["image_size"] == 64
    p = report["parameters"]
    assert set(p) == {"image", "heatmap", "coords", "head", "total"}
    assert all(v > 0 for v in p.values()) and p["total"] == sum(v for k, v in p.items() if k != "total")
    hw = report["hardware"]
    for key in ("cpu_model", "logical_cores", "torch", "device_name", "python", "os"):
        assert hw[key], key
    _check_stats(report["forward"], 4)
    e = report["end2end"]
    _check_stats(e["total"], 4)
    assert e["stage_order"] == [
        "detect",
        "downsample_normalise",
        "encode_coords",
        "to_device",
        "forward",
        "heatmap_rasterise",
    ]
    for stage in e["stage_order"]:
        _check_stats(e["stages"][stage], 4)
    # the stages cover the chain: their medians add up to about the total (rasterisation is inside forward)
    parts = sum(e["stages"][s]["median_ms"] for s in e["stage_order"] if s != "heatmap_rasterise")
    assert 0.5 * e["total"]["median_ms"] < parts < 1.5 * e["total"]["median_ms"]
    assert e["frame"]["sensor_px"] == [1024, 1024] and e["frame"]["downsample_factor"] == 16
    assert e["frame"]["probabilities_shape"] == [2, 4]


def test_flops_are_twice_the_macs_and_add_up_over_branches(report):
    f = report["flops"]
    assert f["per_image_flops"] > 0 and f["per_image_flops"] == 2 * f["per_image_macs"]
    assert f["per_image_gflops"] == pytest.approx(2 * f["per_image_gmacs"])
    assert sum(f["by_branch_flops"].values()) == f["per_image_flops"]
    assert all(f["by_branch_flops"][k] == 2 * f["by_branch_macs"][k] for k in f["by_branch_flops"])
    assert "MACs = FLOPs / 2" in f["note"]


def test_flop_count_matches_a_hand_count_for_a_linear_layer():
    """The counter's convention: 2 FLOPs per multiply-add (a Linear(a, b) on one row: 2ab)."""
    from fusion.model.networks import StarFusion

    model = StarFusion(3, coords=_Coords()).eval()
    f = tim.count_flops(model, 8, 6, torch.device("cpu"), torch.float32)
    # coords: Linear(24, 16); head: Linear(16, 3)
    assert f["by_branch_flops"]["coords"] == 2 * 24 * 16 and f["by_branch_flops"]["head"] == 2 * 16 * 3
    assert f["per_image_macs"] == 24 * 16 + 16 * 3


class _Coords(torch.nn.Module):
    out_dim = 16

    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(24, 16)

    def forward(self, coords, mask):
        return self.lin(torch.cat([coords, mask[..., None].to(coords.dtype)], -1).flatten(1))


def test_end_to_end_preprocessing_reproduces_the_stored_training_inputs():
    """Raw frame -> detect -> downsample/normalise -> rows equals what skygen stored for that frame."""
    from fusion.config import load_config
    from fusion.model.inputs import FrameGeometry, encode_detections, normalise_image
    from fusion.model.shards import read_sample
    from fusion.testing import small_dataset
    from skygen.datasets.shards import open_dataset

    path = small_dataset("smoke")
    cfg = load_config("configs/smoke.yaml")
    with open_dataset(path) as ds:
        frames, used, _ = tim.raw_frames(ds.config, ds.image_shape[0], 2)
        pre = tim.EndToEnd(used, cfg, 6)
        geo = FrameGeometry.from_render_config(ds.config)
        for i, full in enumerate(frames):
            stored = read_sample(ds, i, geo)
            assert np.array_equal(pre.downsample_normalise(full), normalise_image(ds.image(i), geo, 8.0))
            got = pre.encode(pre.detect(full))
            want = encode_detections(stored, geo, 6, cfg.data.log_flux_offset)
            assert np.array_equal(got[1], want[1]) and np.allclose(got[0], want[0], atol=1e-6)


def test_reduced_precision_casts_the_model():
    r = tim.run_timing(config="configs/smoke.yaml", image_size=64, precision="bf16", iters=2, warmup=1, mode="forward")
    assert r["settings"]["precision"] == "bf16" and "bfloat16" in r["settings"]["precision_note"]
    assert "end2end" not in r and r["forward"]["median_ms"] > 0


def test_a_checkpoint_is_timed_on_frames_of_its_own_training_camera(tmp_path):
    from fusion.config import load_config
    from fusion.testing import small_dataset
    from fusion.train.run import train

    data = small_dataset("smoke")
    train(
        load_config("configs/smoke.yaml", [f"data.path={data}", "train.epochs=1"]),
        tmp_path / "run",
        log=lambda *a, **k: None,
    )
    r = tim.run_timing(checkpoint=tmp_path / "run" / "best.pt", iters=2, warmup=1)
    assert r["model"]["checkpoint"] == str(tmp_path / "run" / "best.pt") and r["model"]["num_classes"] == 4
    assert r["end2end"]["frame"]["sensor_px"] == [256, 256] and r["end2end"]["frame"]["downsample_factor"] == 4
    assert r["forward"]["median_ms"] > 0


def test_bad_requests_are_clear_errors(tmp_path):
    with pytest.raises(ConfigError, match="not both"):
        tim.run_timing(checkpoint="x.pt", config="configs/smoke.yaml")
    with pytest.raises(ConfigError, match="--iters"):
        tim.run_timing(config="configs/smoke.yaml", iters=0)
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA device"):
            tim.run_timing(config="configs/smoke.yaml", device="cuda")
    assert cli(["--config", "configs/smoke.yaml", "--iters", "0", "--out", str(tmp_path / "t.json")]) == 2
    assert not (tmp_path / "t.json").exists()
