"""Evaluation metrics, neighbours on the sphere, and the evaluate report files."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fusion.config import load_config
from fusion.errors import DatasetError
from fusion.evaluate import evaluate_checkpoint, report_from_predictions
from fusion.labels import radec_to_unit, spherical_kmeans
from fusion.metrics import (angular_error_deg, confusion_matrix, neighbour_error_share, per_class_accuracy,
                            topk_accuracy, voronoi_neighbours)
from fusion.testing import render_small, small_dataset
from fusion.train import train

ROOT = Path(__file__).resolve().parents[1]
quiet = lambda *a, **k: None  # noqa: E731


def test_topk_counts_hits_among_the_k_largest_logits():
    logits = np.array([[3.0, 2.0, 1.0, 0.0], [0.0, 1.0, 2.0, 3.0], [1.0, 3.0, 2.0, 0.0]])
    labels = np.array([0, 1, 3])
    r = topk_accuracy(logits, labels, ks=(1, 2, 3, 5))
    assert r == {"top1": pytest.approx(1 / 3), "top2": pytest.approx(1 / 3), "top3": pytest.approx(2 / 3),
                 "top5": 1.0}


def test_angular_error_is_the_angle_to_the_predicted_centroid():
    c = radec_to_unit([0, 90], [0, 0])
    v = radec_to_unit([10, 80], [0, 0])
    np.testing.assert_allclose(angular_error_deg(v, c, np.array([0, 1])), [10, 10], atol=1e-9)
    np.testing.assert_allclose(angular_error_deg(v, c, np.array([1, 0])), [80, 80], atol=1e-9)


def test_octahedron_neighbours_are_the_four_adjacent_vertices():
    c = radec_to_unit([0, 90, 180, 270, 0, 0], [0, 0, 0, 0, 90, -90])
    adj = voronoi_neighbours(c)
    assert adj.sum(axis=1).tolist() == [4] * 6          # each vertex touches 4 others, not its antipode
    assert not adj[0, 2] and not adj[4, 5] and adj[0, 1] and adj[0, 4]
    assert (adj == adj.T).all() and not adj.diagonal().any()


def test_neighbours_of_kmeans_centroids_form_a_sphere_triangulation():
    v = np.random.default_rng(0).standard_normal((3000, 3))
    res = spherical_kmeans(v / np.linalg.norm(v, axis=1, keepdims=True), 15, seed=0)
    adj = voronoi_neighbours(res.centroids)
    assert adj.sum() // 2 == 3 * 15 - 6                 # Euler: a triangulation of K points has 3K-6 edges
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


def test_evaluate_refuses_a_dataset_with_another_image_size(trained, tmp_path):
    other = render_small(tmp_path / "ds", ["n_frames=6", "camera.width_px=256", "camera.height_px=256",
                                           "camera.fov_deg=20", "output.image_size_px=128",
                                           "output.split_fractions=[0.5, 0.0, 0.5]"])
    with pytest.raises(DatasetError, match="128 px"):
        evaluate_checkpoint(trained / "best.pt", other, "test", tmp_path, log=quiet)


def test_evaluate_refuses_an_unsupported_schema_version(trained, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(small_dataset("smoke"), copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["schema_version"] = "2.0.0"
    (copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match="schema version 2.0.0 is not supported"):
        evaluate_checkpoint(trained / "best.pt", copy, "test", tmp_path, log=quiet)
