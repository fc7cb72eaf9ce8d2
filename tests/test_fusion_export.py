"""ONNX export: onnxruntime reproduces PyTorch, the batch axis is dynamic, a mismatch fails and writes nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fusion import cli as fcli
from fusion.errors import CheckpointError, FusionError
from fusion.measure import export as exp
from fusion.model.checkpoint import load_checkpoint
from skygen.errors import SkygenError

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")


def cli(argv: list[str]) -> int:
    """``fusion export ARGS`` through the real command line."""
    return fcli.main(["export", *argv])


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    from fusion.config import load_config
    from fusion.testing import small_dataset
    from fusion.train.run import train

    out = tmp_path_factory.mktemp("run")
    train(
        load_config("configs/smoke.yaml", [f"data.path={small_dataset('smoke')}", "train.epochs=1"]),
        out,
        log=lambda *a, **k: None,
    )
    return out / "best.pt"


def test_onnx_matches_pytorch_with_a_dynamic_batch(ckpt, tmp_path, capsys):
    from fusion.model.checkpoint import load_checkpoint
    from fusion.testing import small_dataset

    path = tmp_path / "model.onnx"
    assert (
        cli(
            [
                "--checkpoint",
                str(ckpt),
                "--onnx",
                str(path),
                "--opset",
                "17",
                "--data",
                str(small_dataset("smoke")),
                "--report",
                str(tmp_path / "export.json"),
            ]
        )
        == 0
    )
    assert "max abs difference" in capsys.readouterr().out
    report = json.loads((tmp_path / "export.json").read_text())
    v = report["verification"]
    assert v["passed"] and v["max_abs_diff"] <= 1e-4
    assert set(v["by_check"]) == {"random_batch1", "random_batch3", "star_like_batch2", "dataset_frames"}
    assert exp.written_opset(path) == 17 == report["opset"]
    assert report["inputs"] == {"image": ["batch", 1, 64, 64], "coords": ["batch", 6, 3], "mask": ["batch", 6]}
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["image", "coords", "mask"]
    assert all(i.shape[0] == "batch" for i in sess.get_inputs())
    # an independent check at a batch size the export never saw
    model = load_checkpoint(ckpt).build_model()
    rng = np.random.default_rng(7)
    feeds = exp.star_like_inputs(5, 64, 6, rng)
    with torch.inference_mode():
        ref = model(*(torch.from_numpy(feeds[k]) for k in ("image", "coords", "mask"))).numpy()
    got = sess.run(["logits"], feeds)[0]
    assert got.shape == (5, 4) and np.max(np.abs(got - ref)) <= 1e-4
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_mismatch_fails_loudly_and_leaves_the_old_file(ckpt, tmp_path, monkeypatch, capsys):
    path = tmp_path / "model.onnx"
    path.write_bytes(b"previous export")
    real = exp.onnxruntime_logits
    monkeypatch.setattr(exp, "onnxruntime_logits", lambda p, feeds: real(p, feeds) + 1e-3)
    with pytest.raises(exp.ExportError, match=r"exceeds the tolerance 0.0001"):
        exp.export_onnx(ckpt, path)
    assert cli(["--checkpoint", str(ckpt), "--onnx", str(path)]) == 2
    assert "does not match PyTorch" in capsys.readouterr().err
    assert path.read_bytes() == b"previous export"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.onnx"]  # no temporary file left
    assert issubclass(exp.ExportError, FusionError)


def test_verify_catches_a_graph_of_other_weights(ckpt, tmp_path):
    """A real mismatch, not a simulated one: the graph of one model checked against another."""
    from fusion.model.checkpoint import load_checkpoint

    model = load_checkpoint(ckpt).build_model()
    wrapper = exp.ExportWrapper(model.eval())
    feeds = exp.star_like_inputs(2, 64, 6, np.random.default_rng(0))
    exp._export(wrapper, feeds, tmp_path / "a.onnx", 17, "legacy")
    assert exp.verify(tmp_path / "a.onnx", wrapper, {"star_like": feeds})["passed"]
    with torch.no_grad():
        model.head.bias.add_(0.01)
    with pytest.raises(exp.ExportError, match="star_like"):
        exp.verify(tmp_path / "a.onnx", wrapper, {"star_like": feeds})


def test_geometry_only_model_exports_without_an_image_input(tmp_path):
    from fusion.config import load_config
    from fusion.model.networks import create_model

    cfg = load_config("configs/smoke.yaml", ["model.branches.image=false"])
    model = create_model("star_fusion", 4, cfg.model, image_size=64, max_stars=6).eval()
    wrapper = exp.ExportWrapper(model)
    assert wrapper.input_names == ["coords", "mask"]
    rng = np.random.default_rng(1)
    exp._export(wrapper, exp.random_inputs(1, 64, 6, rng), tmp_path / "geo.onnx", 17, "legacy")
    r = exp.verify(tmp_path / "geo.onnx", wrapper, {"random": exp.random_inputs(3, 64, 6, rng)})
    assert r["max_abs_diff"] <= 1e-4
    assert [i.name for i in ort.InferenceSession(str(tmp_path / "geo.onnx")).get_inputs()] == ["coords", "mask"]


def test_float_mask_option_gives_the_same_logits(ckpt, tmp_path):
    r = exp.export_onnx(ckpt, tmp_path / "f.onnx", mask_dtype="float32")
    assert r["input_types"]["mask"] == "float32" and r["verification"]["max_abs_diff"] <= 1e-4
    sess = ort.InferenceSession(str(tmp_path / "f.onnx"), providers=["CPUExecutionProvider"])
    assert sess.get_inputs()[2].type == "tensor(float)"


def test_bad_arguments_are_clear_errors(ckpt, tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        exp.export_onnx(tmp_path / "missing.pt", tmp_path / "m.onnx")
    with pytest.raises(SkygenError, match="--opset"):
        exp.export_onnx(ckpt, tmp_path / "m.onnx", opset=3)
    assert not (tmp_path / "m.onnx").exists()


def _cpu_yaml_model(fine: int = 60):
    """The architecture of configs/cpu.yaml (what `make demo` trains), small widths, random weights."""
    from fusion.config import load_config
    from fusion.model.networks import create_model

    torch.manual_seed(0)
    cfg = load_config(
        "configs/cpu.yaml", ["model.transformer.dim=16", "model.coord_hidden=32", f"labels.fine_k={fine}"]
    )
    assert (cfg.model.coord_encoder, cfg.model.canonical.mode) == ("transformer", "brightest")
    model = create_model(
        "star_fusion", 15, cfg.model, image_size=64, max_stars=cfg.data.max_stars, fine_classes=fine
    ).eval()
    with torch.no_grad():
        model.fine_groups.copy_(torch.arange(fine) % 15)
    return model, cfg


@pytest.fixture(scope="module")
def cpu_yaml_ckpt(tmp_path_factory):
    from fusion.config import config_dict
    from fusion.model.checkpoint import Checkpoint

    model, cfg = _cpu_yaml_model()
    path = tmp_path_factory.mktemp("cpu") / "best.pt"
    Checkpoint(
        model=model.state_dict(),
        config=config_dict(cfg),
        centroids=np.eye(3)[np.arange(15) % 3],
        num_classes=15,
        image_size=64,
        max_stars=cfg.data.max_stars,
        model_name="star_fusion",
        branches=model.branches,
        fine_centroids=np.eye(3)[np.arange(60) % 3],
    ).save(path)
    return path


@pytest.mark.parametrize("exporter,opset", [("legacy", 17), ("dynamo", 18)])
def test_the_cpu_yaml_model_exports_and_matches(cpu_yaml_ckpt, exporter, opset, tmp_path):
    """Fine regions summed per region, roll canonicalisation and the masked transformer all survive
    the export, at every batch size (1 included), also for a sample without any detection."""
    r = exp.export_onnx(cpu_yaml_ckpt, tmp_path / "cpu.onnx", exporter=exporter, opset=opset)
    assert r["verification"]["passed"] and r["inputs"] == {"coords": ["batch", 16, 3], "mask": ["batch", 16]}
    model = load_checkpoint(cpu_yaml_ckpt).build_model()
    wrapper = exp.ExportWrapper(model)
    empty = exp.random_inputs(3, 64, 16, np.random.default_rng(2))
    empty["mask"][1] = False
    empty["coords"][1] = -0.0  # the padding of a sample without detections
    assert exp.verify(tmp_path / "cpu.onnx", wrapper, {"with_empty": empty})["max_abs_diff"] <= 1e-4


def test_a_fine_region_model_needs_opset_16_with_the_legacy_exporter(cpu_yaml_ckpt, tmp_path):
    with pytest.raises(SkygenError, match="--opset 15: .* opset 16"):
        exp.export_onnx(cpu_yaml_ckpt, tmp_path / "m.onnx", opset=15)


def test_export_safe_operations_give_the_same_logits_bit_for_bit():
    """scatter_add sums what index_add summed in the same order, and the guarded atan2 gives
    atan2's angle (signed zeros and ±pi included): trained models keep their exact outputs."""
    from fusion.model.canonical import angles_of

    model, _ = _cpu_yaml_model(fine=1000)
    with torch.no_grad():
        model.fine_groups.copy_(torch.randint(0, 15, (1000,), generator=torch.Generator().manual_seed(1)))
    fine = torch.randn(64, 1000, generator=torch.Generator().manual_seed(2)) * 8
    x = fine.float()
    m = x.max(dim=1, keepdim=True).values
    s = x.new_zeros(64, 15).index_add(1, model.fine_groups, torch.exp(x - m))
    assert torch.equal(model.coarse_logits(fine), torch.log(s.clamp_min(1e-38)) + m)
    xy = torch.tensor(
        [[0.0, 0.0], [-0.0, 0.0], [0.0, -0.0], [-0.0, -0.0], [0.3, -0.0], [-0.3, 0.0], [0.0, 0.2], [0.1, -0.7]]
    )
    coords = torch.cat([xy, torch.ones(len(xy), 1)], dim=1)[:, None, :]  # (B, 1, 3)
    got = angles_of(coords, torch.zeros(len(xy), 1, dtype=torch.long))[:, 0]
    want = torch.atan2(xy[:, 1], xy[:, 0])
    assert torch.equal(got.view(torch.int32), want.view(torch.int32))


def test_an_unwritable_output_is_one_line_before_any_work(ckpt, tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert cli(["--checkpoint", str(ckpt), "--onnx", str(blocker / "model.onnx")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--onnx" in err and "cannot write" in err
    assert (
        cli(["--checkpoint", str(ckpt), "--onnx", str(tmp_path / "m.onnx"), "--report", str(blocker / "r.json")]) == 2
    )
    assert "--report" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file"]
