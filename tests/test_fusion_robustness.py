"""Robustness sweeps: severity 0 is the clean evaluation, sweeps repeat, bad input writes nothing."""

from __future__ import annotations

import csv
import io
import json

import numpy as np
import pytest
import torch

from fusion import cli as fcli
from fusion.errors import CheckpointError, ConfigError
from fusion.measure import robustness as rob
from fusion.testing import render_small, small_dataset
from skygen.datasets.shards import open_dataset
from skygen.instrument import corruptions as corr
from skygen.render.perturb import perturbed_frames


def cli(argv: list[str]) -> int:
    """``fusion robustness ARGS`` through the real command line."""
    return fcli.main(["robustness", *argv])


def _train(out, overrides=()):
    from fusion.config import load_config
    from fusion.train.run import train

    cfg = load_config("configs/smoke.yaml", [f"data.path={small_dataset('smoke')}", "train.epochs=1", *overrides])
    train(cfg, out, log=lambda *a, **k: None)
    return out / "best.pt"


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory):
    """Two one-epoch smoke checkpoints: full Star-Fusion and geometry only (no image branch)."""
    root = tmp_path_factory.mktemp("ckpts")
    return {"full": _train(root / "full"), "geometry": _train(root / "geo", ["model.branches.image=false"])}


@pytest.fixture(scope="module")
def data():
    return small_dataset("smoke")


def _clean_predictions(ckpt_path, data_path):
    """Predictions on the test split exactly as `fusion evaluate` makes them."""
    from fusion.model.checkpoint import load_checkpoint
    from fusion.model.inference import predict_batches as predict
    from fusion.model.regions import assign
    from fusion.model.shards import FrameDataset, boresight_vectors, make_loader, split_positions

    ckpt = load_checkpoint(ckpt_path)
    model, cfg = ckpt.build_model(), ckpt.fusion_config
    with open_dataset(data_path) as ds:
        pos = split_positions(ds, "test")
        labels = assign(boresight_vectors(ds, pos), ckpt.centroids)
        d = cfg.data
        fd = FrameDataset(
            ds, pos, labels, max_stars=d.max_stars, norm_scale_adu=d.norm_scale_adu, log_flux_offset=d.log_flux_offset
        )
        out = predict(model, make_loader(fd, 64, shuffle=False), torch.device("cpu"))
    return np.argmax(out["logits"], axis=1)


def test_severity_zero_of_every_corruption_is_the_clean_evaluation(ckpts, data, tmp_path):
    from fusion.measure.evaluate import evaluate_checkpoint

    clean = evaluate_checkpoint(ckpts["full"], data, "test", tmp_path / "eval", log=lambda *a: None)
    pred = _clean_predictions(ckpts["full"], data)
    for name in corr.REGISTRY:
        report = rob.run_sweep([ckpts["full"]], data, name, levels="0", progress=False)
        (row,) = report["rows"]
        assert row["severity"] == 0 and row["n_frames"] == clean["n_frames"]
        assert np.array_equal(row["pred"], pred), name
        assert row["top1"] == clean["top1"] and row["top3"] == clean["top3"], name
        assert row["median_error_deg"] == clean["angular_error"]["median_deg"], name


def test_sweep_repeats_exactly_for_a_seed_whatever_the_workers(ckpts, data):
    kw = dict(levels="0,0.002", n=20, seed=3, progress=False)  # 20 frames: two chunks, so 2 processes
    a = rob.run_sweep([ckpts["full"]], data, "hotpixels", workers=1, **kw)
    b = rob.run_sweep([ckpts["full"]], data, "hotpixels", workers=2, **kw)
    assert rob.csv_text(a["rows"]) == rob.csv_text(b["rows"])
    assert all(np.array_equal(x["pred"], y["pred"]) for x, y in zip(a["rows"], b["rows"]))
    assert a["frame_positions"] == b["frame_positions"] and len(a["frame_positions"]) == 20
    other = rob.run_sweep([ckpts["full"]], data, "dropout", levels="0.3", n=6, seed=4, progress=False)
    assert other["frame_positions"] != a["frame_positions"]  # the seed picks the frames
    again = rob.run_sweep([ckpts["full"]], data, "dropout", levels="0.3", n=6, seed=4, progress=False)
    assert rob.csv_text(other["rows"]) == rob.csv_text(again["rows"])


def test_all_corruptions_write_table_and_one_plot_per_corruption(ckpts, data, tmp_path):
    out = tmp_path / "sweep"
    assert (
        cli(
            [
                "--corruption",
                "all",
                "--checkpoint",
                str(ckpts["full"]),
                str(ckpts["geometry"]),
                "--data",
                str(data),
                "--n",
                "2",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    names = list(corr.REGISTRY)
    files = sorted(p.name for p in out.iterdir())
    assert files == sorted(
        ["robustness-all.json", "robustness-all.csv", "robustness-all.md"] + [f"robustness-{n}.png" for n in names]
    )
    for n in names:
        assert (out / f"robustness-{n}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = json.loads((out / "robustness-all.json").read_text())
    n_rows = 2 * sum(len(c.sweep) for c in corr.REGISTRY.values())
    assert len(report["rows"]) == n_rows and report["corruptions"] == names
    assert {c["label"] for c in report["checkpoints"]} == {
        "star_fusion: image+heatmap+coords",
        "star_fusion: heatmap+coords",
    }
    rows = list(csv.DictReader(io.StringIO((out / "robustness-all.csv").read_text())))
    assert len(rows) == n_rows and tuple(rows[0]) == rob.CSV_COLUMNS
    for r in report["rows"]:
        assert 0 <= r["top1"] <= r["top3"] <= 1 and r["mean_detections"] >= 0 and r["median_error_deg"] >= 0
        assert r["unit"] == corr.REGISTRY[r["corruption"]].unit
    md = (out / "robustness-all.md").read_text()
    assert all(f"## {n} ({corr.REGISTRY[n].unit}" in md for n in names)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left


def test_unknown_corruption_lists_the_valid_names(ckpts, data, tmp_path, capsys):
    out = tmp_path / "out"
    assert (
        cli(["--corruption", "hotpixel", "--checkpoint", str(ckpts["full"]), "--data", str(data), "--out", str(out)])
        == 2
    )
    err = capsys.readouterr().err
    assert "unknown corruption 'hotpixel'" in err and ", ".join(corr.REGISTRY) in err
    assert len(err.strip().splitlines()) == 1 and not out.exists()


@pytest.mark.parametrize(
    "args, match",
    [
        (["--corruption", "dropout", "--levels", "0,1.5"], "corruptions.dropout"),
        (["--corruption", "centroid_noise", "--levels", "0,-1"], "negative"),
        (["--corruption", "all", "--levels", "0,1"], "single --corruption"),
        (["--corruption", "dropout", "--levels", "0,abc"], "not a number"),
    ],
)
def test_bad_severity_is_a_clear_error_and_writes_nothing(ckpts, data, tmp_path, args, match):
    out = tmp_path / "out"
    with pytest.raises(ConfigError, match=match):
        rob.robustness([ckpts["full"]], data, args[1], out, levels=args[3], progress=False, log=lambda *a: None)
    assert not out.exists()
    out.mkdir()
    (out / "keep.txt").write_text("earlier results")
    assert cli([*args, "--checkpoint", str(ckpts["full"]), "--data", str(data), "--out", str(out)]) == 2
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_a_failure_during_the_sweep_leaves_out_untouched(ckpts, data, tmp_path, monkeypatch):
    calls = []

    def failing(*args, **kw):
        calls.append(1)
        if len(calls) > 1:
            raise RuntimeError("interrupted")
        return perturbed_frames(*args, **kw)

    monkeypatch.setattr(rob, "perturbed_frames", failing)
    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="interrupted"):
        rob.robustness([ckpts["full"]], data, "dropout", out, levels="0,0.5", n=3, progress=False)
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_checkpoint_for_another_image_size_is_refused(ckpts, tmp_path):
    other = render_small(
        tmp_path / "ds32",
        [
            "n_frames=6",
            "output.shard_size=6",
            "camera.width_px=128",
            "camera.height_px=128",
            "camera.fov_deg=20",
            "output.image_size_px=32",
            "output.split_fractions=[0.5, 0.0, 0.5]",
        ],
    )
    with pytest.raises(CheckpointError, match=r"trained on 64 x 64 images .* stores 32 x 32"):
        rob.robustness([ckpts["full"]], other, "dropout", tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def _lost_share(clean: dict, new: dict, m: int = 6, radius_px: float = 1.0) -> float:
    """Share of the m brightest clean detections with no new detection among the m brightest within radius."""
    a = np.stack([clean["x_px"][:m], clean["y_px"][:m]], 1)
    b = np.stack([new["x_px"][:m], new["y_px"][:m]], 1)
    if len(a) == 0:
        return 0.0
    if len(b) == 0:
        return 1.0
    return float(np.mean(np.linalg.norm(a[:, None] - b[None], axis=2).min(axis=1) > radius_px))


def test_damage_grows_with_severity_for_every_registered_corruption(data):
    """Image-level: mean |pixel change| from the stored frame; detection-level: brightest stars lost."""
    with open_dataset(data) as ds:
        pos = ds.indices("test")[:8]
        for name, c in corr.REGISTRY.items():
            damage = []
            for lvl in c.sweep:
                frames = perturbed_frames(ds, name, lvl, pos)
                if c.stage == "detections":
                    d = [_lost_share(ds.detections(int(p)), f["detections"]) for f, p in zip(frames, pos)]
                else:
                    d = [np.abs(f["image"].astype(float) - ds.image(int(p))).mean() for f, p in zip(frames, pos)]
                damage.append(float(np.mean(d)))
            assert damage[0] == 0, name
            assert all(b >= a for a, b in zip(damage, damage[1:])) and damage[-1] > 0, (name, damage)


def test_a_sweep_says_where_it_is_and_holds_its_out_folder(ckpts, data, tmp_path, capsys):
    from skygen.errors import FolderInUseError
    from skygen.lock import FolderLock

    out, lines = tmp_path / "out", []
    rob.robustness(
        [ckpts["full"], ckpts["geometry"]], data, "dropout", out, levels="0,0.5", n=3, progress=False, log=lines.append
    )
    progress = [line for line in lines if line.startswith("[")]
    assert [p.split(":")[0] for p in progress] == ["[1/2] dropout 0 (probability)", "[2/2] dropout 0.5 (probability)"]
    assert all("3 frames in" in p and p.count("%") == 2 for p in progress)
    with FolderLock(out, what="fusion robustness"):
        with pytest.raises(FolderInUseError, match="in use by fusion robustness"):
            rob.robustness([ckpts["full"]], data, "dropout", out, levels="0", n=3, progress=False)
        assert (
            cli(
                [
                    "--corruption",
                    "dropout",
                    "--levels",
                    "0",
                    "--n",
                    "3",
                    "--checkpoint",
                    str(ckpts["full"]),
                    "--data",
                    str(data),
                    "--out",
                    str(out),
                ]
            )
            == 2
        )
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_n_above_the_split_says_it_sweeps_the_whole_split(ckpts, data):
    said = []
    report = rob.run_sweep([ckpts["full"]], data, "dropout", levels="0", n=10_000, progress=False, log=said.append)
    n = report["rows"][0]["n_frames"]
    assert n < 10_000 and f"--n 10000: the test split holds {n} frames; sweeping all {n}" in said
