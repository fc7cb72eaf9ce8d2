"""Evaluation metrics, neighbours on the sphere, and the evaluate report files."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fusion.config import load_config
from fusion.errors import DatasetError
from fusion.measure.evaluate import evaluate_checkpoint, report_from_predictions
from fusion.model.metrics import (
    angular_error_deg,
    confusion_matrix,
    neighbour_error_share,
    per_class_accuracy,
    topk_accuracy,
    voronoi_neighbours,
)
from fusion.model.regions import radec_to_unit, spherical_kmeans
from fusion.testing import render_small, small_dataset
from fusion.train.run import train

ROOT = Path(__file__).resolve().parents[1]
quiet = lambda *a, **k: None  # noqa: E731


def test_topk_counts_hits_among_the_k_largest_logits():
    logits = np.array([[3.0, 2.0, 1.0, 0.0], [0.0, 1.0, 2.0, 3.0], [1.0, 3.0, 2.0, 0.0]])
    labels = np.array([0, 1, 3])
    r = topk_accuracy(logits, labels, ks=(1, 2, 3, 5))
    assert r == {"top1": pytest.approx(1 / 3), "top2": pytest.approx(1 / 3), "top3": pytest.approx(2 / 3), "top5": 1.0}


def test_angular_error_is_the_angle_to_the_predicted_centroid():
    c = radec_to_unit([0, 90], [0, 0])
    v = radec_to_unit([10, 80], [0, 0])
    np.testing.assert_allclose(angular_error_deg(v, c, np.array([0, 1])), [10, 10], atol=1e-9)
    np.testing.assert_allclose(angular_error_deg(v, c, np.array([1, 0])), [80, 80], atol=1e-9)


def test_octahedron_neighbours_are_the_four_adjacent_vertices():
    c = radec_to_unit([0, 90, 180, 270, 0, 0], [0, 0, 0, 0, 90, -90])
    adj = voronoi_neighbours(c)
    assert adj.sum(axis=1).tolist() == [4] * 6  # each vertex touches 4 others, not its antipode
    assert not adj[0, 2] and not adj[4, 5] and adj[0, 1] and adj[0, 4]
    assert (adj == adj.T).all() and not adj.diagonal().any()


def test_neighbours_of_kmeans_centroids_form_a_sphere_triangulation():
    v = np.random.default_rng(0).standard_normal((3000, 3))
    res = spherical_kmeans(v / np.linalg.norm(v, axis=1, keepdims=True), 15, seed=0)
    adj = voronoi_neighbours(res.centroids)
    assert adj.sum() // 2 == 3 * 15 - 6  # Euler: a triangulation of K points has 3K-6 edges
    # the nearest other centroid is always a neighbour
    cos = res.centroids @ res.centroids.T
    np.fill_diagonal(cos, -2)
    assert all(adj[i, np.argmax(cos[i])] for i in range(15))


def test_neighbour_share_confusion_and_per_class():
    adj = np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], bool)
    labels = np.array([0, 0, 1, 2, 2, 2])
    pred = np.array([0, 1, 1, 0, 1, 2])
    assert neighbour_error_share(labels, pred, adj) == pytest.approx(2 / 3)
    cm = confusion_matrix(labels, pred, 3)
    assert cm.tolist() == [[1, 1, 0], [0, 1, 0], [1, 1, 1]]
    pc = per_class_accuracy(cm)
    assert [p["top1"] for p in pc] == [0.5, 1.0, pytest.approx(1 / 3)]
    assert neighbour_error_share(labels, labels, adj) is None


def test_report_quantisation_floor_is_the_error_of_a_perfect_classifier():
    v = np.random.default_rng(1).standard_normal((400, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    res = spherical_kmeans(v, 6, seed=0)
    perfect = np.eye(6)[res.labels] * 10
    r = report_from_predictions(perfect, res.labels, v, res.centroids)
    assert r["top1"] == 1.0 and r["n_errors"] == 0 and r["neighbour_error_share"] is None
    assert r["angular_error"] == r["quantisation_floor"]
    assert 0 < r["quantisation_floor"]["median_deg"] < 90


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval") / "run"
    cfg = load_config(ROOT / "configs" / "smoke.yaml", [f"data.path={small_dataset('smoke')}"])
    train(cfg, out, log=quiet)
    return out


def test_evaluate_writes_json_markdown_and_png(trained, tmp_path):
    r = evaluate_checkpoint(trained / "best.pt", small_dataset("smoke"), "test", tmp_path, log=quiet)
    for name in ("eval-test.json", "eval-test.md", "confusion-test.png"):
        assert (tmp_path / name).is_file()
    saved = json.loads((tmp_path / "eval-test.json").read_text())
    assert saved["top1"] == r["top1"] >= 0.75
    assert saved["num_classes"] == 4 and saved["n_frames"] == 60
    assert np.array(saved["confusion_matrix"]).sum() == 60
    assert saved["angular_error"]["median_deg"] >= 0 and saved["quantisation_floor"]["p95_deg"] >= 0
    md = (tmp_path / "eval-test.md").read_text()
    assert "| top-1 | top-3 | top-5 |" in md and "quantisation floor" in md and "Voronoi" in md


def test_an_ensemble_of_checkpoints_is_scored_as_one(trained, tmp_path):
    """Several checkpoints: the mean of their log-probabilities, each member's own top-1 beside it."""
    import dataclasses

    from fusion.errors import ConfigError
    from fusion.model.checkpoint import load_checkpoint

    data = small_dataset("smoke")
    one = evaluate_checkpoint(trained / "best.pt", data, "test", tmp_path / "one", keep_brightest=2, log=quiet)
    # the same model twice: the product of two equal experts ranks as the model does
    two = evaluate_checkpoint(
        [trained / "best.pt", trained], data, "test", tmp_path / "two", keep_brightest=2, log=quiet
    )
    assert two["top1"] == one["top1"] and two["top3"] == one["top3"]
    assert two["members_top1"] == [one["top1"]] * 2 and len(two["checkpoints"]) == 2
    assert "An ensemble of 2 models" in (tmp_path / "two" / "eval-test-brightest2.md").read_text()
    # a confident wrong member pulls the ensemble: a copy whose classifier says class 0 for every frame
    ck = load_checkpoint(trained / "best.pt")
    state = {k: v.clone() for k, v in ck.model.items()}
    bias = [k for k in state if k.endswith("bias") and state[k].shape == (ck.num_classes,)][-1]
    state[[k for k in state if k.endswith("weight") and state[k].shape[0] == ck.num_classes][-1]].zero_()
    state[bias].zero_()
    state[bias][0] = 50.0
    dataclasses.replace(ck, model=state).save(tmp_path / "class0.pt")
    pulled = evaluate_checkpoint([trained, tmp_path / "class0.pt"], data, "test", tmp_path / "pulled", log=quiet)
    labels0 = np.array(pulled["confusion_matrix"])[0].sum() / pulled["n_frames"]
    assert pulled["members_top1"][1] == pytest.approx(labels0) and pulled["top1"] < pulled["members_top1"][0]
    with pytest.raises(ConfigError, match="--out"):
        evaluate_checkpoint([trained, trained], data, "test", None, log=quiet)
    dataclasses.replace(ck, centroids=-ck.centroids).save(tmp_path / "other-regions.pt")
    with pytest.raises(ConfigError, match="other regions"):
        evaluate_checkpoint([trained, tmp_path / "other-regions.pt"], data, "test", tmp_path / "x", log=quiet)


def test_evaluate_brightest_n_cuts_the_detections_not_the_image(trained, tmp_path):
    """--brightest N: each frame keeps its brightest N detection rows, the image is the same."""
    from fusion.errors import ConfigError
    from fusion.model.shards import FrameDataset, split_positions
    from skygen.datasets.shards import open_dataset

    with open_dataset(small_dataset("smoke")) as ds:
        pos = split_positions(ds, "test")[:8]
        whole = FrameDataset(ds, pos, np.zeros(len(pos)), max_stars=6)
        cut = FrameDataset(ds, pos, np.zeros(len(pos)), max_stars=6, keep_brightest=2)
        for j in range(len(pos)):
            a, b = whole[j], cut[j]
            assert (a["image"] == b["image"]).all()
            n = int(a["mask"].sum())
            assert int(b["mask"].sum()) == min(n, 2)
            assert (b["coords"][:2] == a["coords"][:2]).all() and (b["coords"][2:] == 0).all()
    r = evaluate_checkpoint(trained / "best.pt", small_dataset("smoke"), "test", tmp_path, keep_brightest=2, log=quiet)
    assert r["keep_brightest"] == 2 and (tmp_path / "eval-test-brightest2.json").is_file()
    assert "brightest 2 detections" in (tmp_path / "eval-test-brightest2.md").read_text()
    with pytest.raises(ConfigError, match="--brightest"):
        evaluate_checkpoint(trained / "best.pt", small_dataset("smoke"), "test", tmp_path, keep_brightest=0, log=quiet)


def test_evaluate_refuses_a_dataset_with_another_image_size(trained, tmp_path):
    other = render_small(
        tmp_path / "ds",
        [
            "n_frames=6",
            "camera.width_px=256",
            "camera.height_px=256",
            "camera.fov_deg=20",
            "output.image_size_px=128",
            "output.split_fractions=[0.5, 0.0, 0.5]",
        ],
    )
    with pytest.raises(DatasetError, match="128 px"):
        evaluate_checkpoint(trained / "best.pt", other, "test", tmp_path, log=quiet)


def test_evaluate_refuses_an_unsupported_schema_version(trained, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(small_dataset("smoke"), copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["schema_version"] = "3.0.0"
    (copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match="schema version 3.0.0 is not supported"):
        evaluate_checkpoint(trained / "best.pt", copy, "test", tmp_path, log=quiet)


# ------------------------------------------------------------------ leakage guards
def _smoke_with(tmp_path, name, *overrides):
    from fusion.testing import KINDS

    return render_small(tmp_path / name, [o for o in KINDS["smoke"] if not o.startswith("n_frames")] + list(overrides))


def test_evaluate_refuses_the_checkpoints_training_frames(trained, tmp_path):
    with pytest.raises(DatasetError, match=r"180 of the 180 frames of split 'train'.*--allow-overlap"):
        evaluate_checkpoint(trained, small_dataset("smoke"), "train", tmp_path, log=quiet)
    warnings = []
    r = evaluate_checkpoint(
        trained, small_dataset("smoke"), "train", tmp_path, log=quiet, allow_overlap=True, warn=warnings.append
    )
    assert r["dataset"]["frames_seen_in_training"] == 180
    assert any("WARNING: 180 of the 180 evaluated frames were TRAINING frames" in w for w in warnings)


def test_same_seed_other_n_shares_frames_only_within_a_split(trained, tmp_path):
    """The leak of schema 1.x: with frames keyed by the global index, the test split of a
    200-frame seed-0 dataset (frames 160-199) held frames 160-179 of the 300-frame one's
    training split. Keyed by (split, index in split), it holds none."""
    from skygen.datasets.shards import open_dataset

    other = _smoke_with(tmp_path, "n200", "n_frames=200")
    r = evaluate_checkpoint(trained, other, "test", tmp_path, log=quiet)  # accepted: no shared frame
    assert r["dataset"]["frames_seen_in_training"] == 0
    with open_dataset(other) as b, open_dataset(small_dataset("smoke")) as a:
        tb = b.indices("test")[0]
        assert not np.array_equal(a.image(int(b.frames["index"][tb])), b.image(int(tb)))
        assert np.array_equal(a.image(int(a.indices("test")[0])), b.image(int(tb)))  # same seed, same test frame
    with pytest.raises(DatasetError, match="frames the checkpoint was trained on"):  # train frames 0-119 repeat
        evaluate_checkpoint(trained, other, "train", tmp_path, log=quiet)


def test_evaluate_warns_about_another_camera_and_takes_a_run_folder(trained, tmp_path):
    other = _smoke_with(tmp_path, "cam", "n_frames=20", "camera.fov_deg=24", "seed=9")
    warnings = []
    r = evaluate_checkpoint(trained, other, "test", tmp_path, log=quiet, warn=warnings.append)
    assert r["checkpoint"] == str(trained / "best.pt")
    assert any("other frame settings" in w and "camera.fov_deg 20 -> 24" in w for w in warnings), warnings
    assert r["config_differences"] == {"camera.fov_deg": {"training": 20.0, "data": 24.0}}


def test_evaluate_and_train_refuse_a_shard_changed_after_rendering(trained, tmp_path, monkeypatch, capsys):
    import h5py

    from fusion.cli import main

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    copy = tmp_path / "copy"
    shutil.copytree(small_dataset("smoke"), copy)
    assert main(["evaluate", "--checkpoint", str(trained), "--data", str(copy), "--out", str(tmp_path)]) == 0
    with h5py.File(copy / "shard-00001.h5", "r+") as f:  # an edited detection value, same size
        row = f["detections/flux_adu"][3]
        row[0] += 1000
        f["detections/flux_adu"][3] = row
    assert main(["evaluate", "--checkpoint", str(trained), "--data", str(copy), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "shard-00001.h5: sha256 differs" in err and len(err.splitlines()) == 1
    assert (
        main(
            [
                "train",
                "--data",
                str(copy),
                "--out",
                str(tmp_path / "r"),
                "--config",
                str(ROOT / "configs" / "smoke.yaml"),
            ]
        )
        == 2
    )
    assert "shard-00001.h5: sha256 differs" in capsys.readouterr().err


def test_checksums_are_verified_once_per_size_and_mtime(tmp_path, monkeypatch):
    import os

    from skygen.datasets.shards import open_dataset, verify_checksums

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    with open_dataset(small_dataset("smoke")) as ds:
        assert verify_checksums(ds) == 2
        assert verify_checksums(ds) == 0  # remembered
        p = ds.shards[0].path
        os.utime(p, ns=(p.stat().st_atime_ns, p.stat().st_mtime_ns + 1))
        assert verify_checksums(ds) == 1  # touched: hashed again


def test_an_error_inside_a_dataloader_worker_is_one_line_naming_the_file(tmp_path):
    from fusion.cli import one_line
    from fusion.model.shards import FrameDataset, make_loader
    from skygen.datasets.shards import open_dataset

    copy = tmp_path / "copy"
    shutil.copytree(small_dataset("smoke"), copy)
    ds = open_dataset(copy)
    frames = FrameDataset(ds, np.arange(4), np.zeros(4, np.int64))
    (copy / "shard-00000.h5").unlink()  # vanishes after the dataset was opened
    with pytest.raises(DatasetError) as info:
        next(iter(make_loader(frames, 2, shuffle=False, workers=1)))
    assert "Original Traceback" in str(info.value)  # what torch hands back
    line = one_line(info.value)
    assert "\n" not in line and line.endswith("shard-00000.h5: shard file is missing")
