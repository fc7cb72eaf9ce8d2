"""ONNX export: onnxruntime reproduces PyTorch, the batch axis is dynamic, a mismatch fails and writes nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fusion import cli as fcli
from fusion.measure import export as exp
from fusion.errors import CheckpointError, FusionError
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
    train(load_config("configs/smoke.yaml", [f"data.path={small_dataset('smoke')}", "train.epochs=1"]), out,
          log=lambda *a, **k: None)
    return out / "best.pt"


def test_onnx_matches_pytorch_with_a_dynamic_batch(ckpt, tmp_path, capsys):
    from fusion.model.checkpoint import load_checkpoint
    from fusion.testing import small_dataset
    path = tmp_path / "model.onnx"
    assert cli(["--checkpoint", str(ckpt), "--onnx", str(path), "--opset", "17", "--data", str(small_dataset("smoke")),
                "--report", str(tmp_path / "export.json")]) == 0
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
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.onnx"]          # no temporary file left
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
