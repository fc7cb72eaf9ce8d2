"""Training: smoke run beats chance, exact resume, run-folder safety, checkpoint checks, DDP on CPU."""

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from fusion.config import load_config
from fusion.errors import CheckpointError, RunFolderError
from fusion.model.checkpoint import load_checkpoint, load_model_state
from fusion.model.networks import create_model
from fusion.testing import Killed, assert_same_run, killing_log, small_dataset
from fusion.train.loop import WarmupCosine
from fusion.train.run import train

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"
quiet = lambda *a, **k: None  # noqa: E731


def smoke_cfg(*overrides):
    return load_config(SMOKE, [f"data.path={small_dataset('smoke')}", *overrides])


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "smoke"
    summary = train(smoke_cfg(), out, log=quiet)
    return out, summary


def test_smoke_training_beats_chance_by_far(smoke_run):
    out, summary = smoke_run
    k = summary["num_classes"]
    assert k == 4
    assert summary["best"]["val_top1"] >= max(0.75, 3 / k)  # chance is 1/K = 0.25
    for name in (
        "best.pt",
        "last.pt",
        "metrics.csv",
        "config.yaml",
        "centroids.npy",
        "summary.json",
        "loss_curves.png",
        "lr_schedule.png",
    ):
        assert (out / name).is_file(), name
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    assert len(rows) == summary["epochs_run"]
    assert {"train_loss", "val_loss", "val_top1", "val_top3", "val_top5", "lr", "epoch_time_s"} <= set(rows[0])
    np.testing.assert_array_equal(np.load(out / "centroids.npy"), load_checkpoint(out / "best.pt").centroids)
    assert "trained from scratch" in (out / "config.yaml").read_text()


def test_checkpoint_is_self_describing(smoke_run):
    out, _ = smoke_run
    raw = torch.load(out / "last.pt", weights_only=True)
    for key in (
        "format",
        "format_version",
        "model",
        "optimizer",
        "scheduler",
        "scaler",
        "epoch",
        "config",
        "centroids",
        "versions",
        "rng",
        "history",
        "best",
        "num_classes",
        "model_name",
        "branches",
        "render_config",
        "dataset",
        "train_frame_ids",
        "fine_centroids",
    ):
        assert key in raw, key
    ckpt = load_checkpoint(out / "last.pt")
    assert sorted(ckpt.to_dict()) == sorted(raw)  # one schema: what is loaded is what is saved
    assert ckpt.finished and ckpt.epoch == ckpt.config["train"]["epochs"]
    model, cfg = ckpt.build_model(), ckpt.fusion_config
    assert cfg.labels.k == 4 and model.num_classes == 4


def test_resume_continues_exactly(tmp_path):
    cfg = smoke_cfg("train.epochs=3")
    full = tmp_path / "full"
    train(cfg, full, log=quiet)

    killed = tmp_path / "killed"
    with pytest.raises(Killed):
        train(cfg, killed, log=killing_log("epoch 2/3"))
    assert load_checkpoint(killed / "last.pt").epoch == 2
    assert not (killed / "summary.json").exists()
    with pytest.raises(RunFolderError, match="unfinished run"):
        train(cfg, killed, log=quiet)
    train(cfg, killed, resume=True, log=quiet)
    assert_same_run(full, killed)


def test_finished_run_is_not_overwritten_without_force(smoke_run, tmp_path):
    out, _ = smoke_run
    with pytest.raises(RunFolderError, match="finished run"):
        train(smoke_cfg("train.epochs=1"), out, log=quiet)
    with pytest.raises(RunFolderError, match="finished run"):
        train(smoke_cfg(), out, resume=True, log=quiet)
    fresh = tmp_path / "fresh"
    with pytest.raises(RunFolderError, match="no last.pt"):
        train(smoke_cfg(), fresh, resume=True, log=quiet)


def test_force_replaces_a_finished_run(tmp_path):
    out = tmp_path / "run"
    train(smoke_cfg("train.epochs=1"), out, log=quiet)
    (out / "notes.txt").write_text("mine")
    train(smoke_cfg("train.epochs=2"), out, force=True, log=quiet)
    assert load_checkpoint(out / "last.pt").epoch == 2
    assert (out / "notes.txt").read_text() == "mine"  # only run files are deleted


def test_resume_with_another_k_is_refused(tmp_path):
    out = tmp_path / "run"
    cfg = smoke_cfg("train.epochs=2")

    def stop(msg, *a, **k):
        if msg.startswith("epoch 1/2"):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(cfg, out, log=stop)
    with pytest.raises(CheckpointError, match="labels.k: 4 -> 5"):
        train(smoke_cfg("train.epochs=2", "labels.k=5"), out, resume=True, log=quiet)


def test_checkpoint_of_another_k_or_model_does_not_load(smoke_run):
    out, _ = smoke_run
    ckpt = load_checkpoint(out / "best.pt")
    cfg = smoke_cfg()
    other_k = create_model("star_fusion", 5, cfg.model, image_size=64)
    with pytest.raises(CheckpointError, match="K=4"):
        load_model_state(other_k, ckpt)
    other_model = create_model("resnet50", 4, cfg.model, image_size=64)
    with pytest.raises(CheckpointError, match="does not fit"):
        load_model_state(other_model, ckpt)


def test_checkpoint_without_newer_keys_still_loads(smoke_run, tmp_path):
    """Format-1 files written before render_config / train_frame_ids / fine_centroids existed load; the
    fields are None and the users of a missing one say what to do."""
    out, _ = smoke_run
    raw = torch.load(out / "best.pt", weights_only=True)
    for key in ("render_config", "train_frame_ids", "fine_centroids", "dataset", "content_sha256"):
        raw.pop(key)
    old = tmp_path / "old.pt"
    torch.save(raw, old)
    ckpt = load_checkpoint(old)
    assert ckpt.render_config is None and ckpt.train_frame_ids is None and ckpt.regions.fine is None
    assert ckpt.build_model().num_classes == 4
    with pytest.raises(CheckpointError, match="predates camera data"):
        ckpt.require_render_config()
    raw["format_version"] = 99
    torch.save(raw, old)
    with pytest.raises(CheckpointError, match="format version 99"):
        load_checkpoint(old)


def test_damaged_and_foreign_checkpoints_are_clear_errors(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(bad)
    foreign = tmp_path / "foreign.pt"
    torch.save({"state_dict": {}}, foreign)
    with pytest.raises(CheckpointError, match="not a fusion checkpoint"):
        load_checkpoint(foreign)


def test_warmup_then_cosine_schedule():
    s = WarmupCosine(warmup=10, total=110, floor=0.01)
    f = np.array([s(i) for i in range(110)])
    assert f[0] == pytest.approx(0.1) and f[9] == pytest.approx(1.0)
    assert np.all(np.diff(f[:10]) > 0) and np.all(np.diff(f[10:]) <= 0)
    assert f[-1] == pytest.approx(0.01, abs=1e-3)


def test_soft_label_training_runs(tmp_path):
    summary = train(
        smoke_cfg("train.epochs=2", "labels.soft_labels=true", "labels.kappa=5"), tmp_path / "soft", log=quiet
    )
    assert np.isfinite(summary["best"]["val_loss"])


def test_ddp_on_cpu_with_gloo_and_two_processes(tmp_path):
    out = tmp_path / "ddp"
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node=2",
        "-m",
        "fusion.cli",
        "train",
        "--data",
        str(small_dataset("smoke")),
        "--out",
        str(out),
        "--config",
        str(SMOKE),
        "train.epochs=2",
        "data.max_frames=59",
        "train.eval_batch_size=1",
    ]  # 30 vs 29 validation batches
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-3000:]
    ckpt = load_checkpoint(out / "last.pt")
    assert ckpt.epoch == 2
    summary = (out / "summary.json").read_text()
    assert '"processes": 2' in summary
    assert res.stdout.count("epoch 2/2") == 1  # only rank 0 reports and writes
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    assert len(rows) == 2 and all(np.isfinite(float(r["val_loss"])) for r in rows)
