"""Spherical K-means labels: unit centroids, max-cosine assignment, seeded, fitted on train only."""

import numpy as np
import pytest

from fusion.errors import ConfigError, DatasetError
from fusion.model.regions import (
    angular_distance_deg,
    assign,
    class_weights,
    radec_to_unit,
    soft_targets,
    spherical_kmeans,
)


def random_directions(n, seed=0):
    v = np.random.default_rng(seed).standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def clustered_directions(centres, n_per, spread_deg, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for c in centres:
        p = c + np.radians(spread_deg) * rng.standard_normal((n_per, 3))
        out.append(p / np.linalg.norm(p, axis=1, keepdims=True))
    return np.concatenate(out)


def test_radec_to_unit_matches_the_paper_formula():
    v = radec_to_unit([0, 90, 45], [0, 0, 90])
    np.testing.assert_allclose(v, [[1, 0, 0], [0, 1, 0], [0, 0, 1]], atol=1e-12)


def test_centroids_are_unit_and_assignment_is_max_cosine():
    v = random_directions(2000)
    res = spherical_kmeans(v, 15, seed=3)
    np.testing.assert_allclose(np.linalg.norm(res.centroids, axis=1), 1.0, atol=1e-12)
    cos = v @ res.centroids.T
    np.testing.assert_array_equal(res.labels, np.argmax(cos, axis=1))
    np.testing.assert_array_equal(assign(v, res.centroids), res.labels)
    assert res.converged
    assert len(np.unique(res.labels)) == 15


def test_converged_centroids_are_the_normalised_mean_of_their_members():
    v = random_directions(1500, seed=1)
    res = spherical_kmeans(v, 8, seed=0)
    for k in range(8):
        m = v[res.labels == k].sum(axis=0)
        np.testing.assert_allclose(res.centroids[k], m / np.linalg.norm(m), atol=1e-9)


def test_same_seed_same_centroids_other_seed_may_differ():
    v = random_directions(800, seed=2)
    a = spherical_kmeans(v, 10, seed=7, n_init=1)
    b = spherical_kmeans(v, 10, seed=7, n_init=1)
    np.testing.assert_array_equal(a.centroids, b.centroids)
    np.testing.assert_array_equal(a.labels, b.labels)


def test_recovers_well_separated_clusters():
    centres = radec_to_unit([0, 90, 180, 270, 0, 0], [0, 0, 0, 0, 90, -90])
    v = clustered_directions(centres, 50, spread_deg=3.0)
    res = spherical_kmeans(v, 6, seed=0)
    err = angular_distance_deg(res.centroids[:, None, :], centres[None, :, :]).min(axis=1)
    assert err.max() < 1.0
    # every true cluster maps to exactly one label
    for i in range(6):
        assert len(np.unique(res.labels[i * 50 : (i + 1) * 50])) == 1


def test_too_few_distinct_directions_is_a_clear_error():
    v = np.repeat(radec_to_unit([10, 20], [0, 0]), 5, axis=0)
    with pytest.raises(DatasetError, match="distinct"):
        spherical_kmeans(v, 3)


def test_soft_targets_sum_to_one_and_peak_at_the_hard_label():
    v = random_directions(300, seed=4)
    res = spherical_kmeans(v, 6, seed=0)
    q = soft_targets(v, res.centroids, kappa=20.0)
    np.testing.assert_allclose(q.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(q.argmax(axis=1), assign(v, res.centroids))
    # larger kappa concentrates the mass on the true class
    q_sharp = soft_targets(v, res.centroids, kappa=500.0)
    assert q_sharp.max(axis=1).mean() > q.max(axis=1).mean()


def test_balanced_alpha_is_inverse_frequency_and_sums_to_one():
    labels = np.array([0] * 10 + [1] * 30 + [2] * 60)
    a = class_weights(labels, 3, "balanced")
    assert a.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(a / a[0], [1.0, 10 / 30, 10 / 60])
    np.testing.assert_allclose(class_weights(labels, 3, "uniform"), 1 / 3)


def test_centroids_are_fitted_on_the_training_split_only(tmp_path):
    from fusion.config import load_config
    from fusion.testing import small_dataset
    from fusion.train.data import prepare_data
    from skygen.datasets.shards import open_dataset

    path = small_dataset("uniform")
    cfg = load_config("configs/smoke.yaml", [f"data.path={path}", "labels.k=4"])
    data = prepare_data(cfg)
    with open_dataset(path) as ds:
        v_train = ds.boresight["unit_vector"][ds.indices("train")]
        v_all = ds.boresight["unit_vector"]
    expected = spherical_kmeans(v_train, 4, cfg.labels.seed, cfg.labels.n_init, cfg.labels.max_iter, cfg.labels.tol_deg)
    np.testing.assert_array_equal(data.regions.coarse, expected.centroids)
    with_all = spherical_kmeans(v_all, 4, cfg.labels.seed, cfg.labels.n_init)
    assert not np.allclose(with_all.centroids, data.regions.coarse)
    # validation frames are labelled against the fixed training centroids
    np.testing.assert_array_equal(
        data.val.labels, assign(ds.boresight["unit_vector"][data.val.positions], data.regions.coarse)
    )
    data.ds.close()


def test_assign_with_many_centroids_is_the_largest_cosine():
    """Fine regions go through a k-d tree; the class is still the centroid of largest cosine."""
    rng = np.random.default_rng(5)
    c = rng.normal(size=(1000, 3))
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    v = rng.normal(size=(20000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    got = assign(v, c)
    assert got.dtype == np.int64 and np.array_equal(got, np.argmax(v @ c.T, axis=1))
    assert assign(v[:0], c).shape == (0,)


def test_fine_regions_come_from_the_sky_not_the_dataset(tmp_path):
    """Any fine_k works with any dataset size, and two datasets of one attitude distribution share the
    regions (issue: `fusion train --stream detections --config configs/cpu.yaml` on a small dataset)."""
    from fusion.config import load_config
    from fusion.testing import KINDS, render_small, small_dataset
    from fusion.train.data import prepare_data
    from skygen.datasets import open_dataset

    other = render_small(tmp_path / "other", KINDS["uniform"] + ["n_frames=40", "seed=5"])
    regions = {}
    for kind, path in (("big", small_dataset("uniform")), ("small", other)):
        with open_dataset(path) as ds:
            n_train = len(ds.indices("train"))
        cfg = load_config(
            "configs/smoke.yaml",
            [
                f"data.path={path}",
                "labels.k=4",
                "labels.fine_k=300",
                "stream.kind=detections",
                "labels.n_init=1",
                "model.branches.image=false",
            ],
        )
        assert n_train < 300  # more fine regions than the dataset has training frames
        data = prepare_data(cfg)
        data.ds.close()
        assert data.regions.fine.shape == (300, 3) and set(data.regions.groups) == set(range(4))
        regions[kind] = data.regions
    np.testing.assert_array_equal(regions["big"].fine, regions["small"].fine)
    np.testing.assert_array_equal(regions["big"].coarse, regions["small"].coarse)  # stream: K regions too
    # fitted on the sky: the fine regions' areas are even (largest cell < 2x the mean cell area)
    v = np.random.default_rng(1).standard_normal((50_000, 3))
    counts = np.bincount(assign(v / np.linalg.norm(v, axis=1, keepdims=True), regions["big"].fine), minlength=300)
    assert counts.max() < 2 * counts.mean()


def test_shard_training_keeps_the_k_regions_of_its_training_split():
    from fusion.config import load_config
    from fusion.testing import small_dataset
    from fusion.train.data import prepare_data

    path = small_dataset("uniform")
    cfg = load_config("configs/smoke.yaml", [f"data.path={path}", "labels.k=4", "labels.fine_k=50"])
    data = prepare_data(cfg)
    v_train = data.ds.boresight["unit_vector"][data.ds.indices("train")]
    data.ds.close()
    lab = cfg.labels
    expected = spherical_kmeans(v_train, 4, lab.seed, lab.n_init, lab.max_iter, lab.tol_deg)
    np.testing.assert_array_equal(data.regions.coarse, expected.centroids)


def test_fine_regions_on_a_list_of_pointings_are_refused_with_the_reason():
    from fusion.config import load_config
    from fusion.testing import small_dataset
    from fusion.train.data import prepare_data

    cfg = load_config("configs/smoke.yaml", [f"data.path={small_dataset('smoke')}", "labels.fine_k=300"])
    with pytest.raises(ConfigError, match="8 distinct pointings"):
        prepare_data(cfg)
