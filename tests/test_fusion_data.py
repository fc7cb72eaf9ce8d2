"""Input pipeline: ordering, padding and mask, sparse frames, normalisation, heatmap, workers."""

import numpy as np
import pytest
import torch

from fusion.errors import DatasetError
from fusion.model.heatmap import rasterise
from fusion.model.inputs import FrameGeometry, encode_detections, normalise_image
from fusion.model.shards import FrameDataset, count_sparse_frames, make_loader, read_sample, split_positions
from fusion.testing import render_small, small_dataset
from fusion.train.augment import Augmenter
from skygen.datasets.shards import open_dataset


@pytest.fixture(scope="module")
def uniform():
    with open_dataset(small_dataset("uniform")) as ds:
        yield ds


@pytest.fixture(scope="module")
def sparse_path(tmp_path_factory):
    """Frames with 0, 1 or a few detections: a very high detection threshold."""
    return render_small(
        tmp_path_factory.mktemp("sparse") / "ds",
        [
            "n_frames=40",
            "output.shard_size=40",
            "camera.width_px=256",
            "camera.height_px=256",
            "camera.fov_deg=20",
            "output.image_size_px=64",
            "detection.threshold_sigma=150",
            "output.split_fractions=[0.5, 0.25, 0.25]",
        ],
    )


def test_rows_are_the_brightest_detections_brightest_first(uniform):
    geo = FrameGeometry.from_render_config(uniform.config)
    for i in range(5):
        det = uniform.detections(i)
        s = read_sample(uniform, i, geo)
        coords, mask = encode_detections(s, geo, 6, 3.0)
        n = min(len(det["flux_adu"]), 6)
        assert mask.sum() == n and mask[:n].all()
        flux = 10 ** (coords[:n, 2] + 3.0) - 1
        assert np.all(np.diff(flux) <= 1e-3 * flux[:-1])  # brightest first
        top = np.sort(det["flux_adu"])[::-1][:n]
        np.testing.assert_allclose(flux, top, rtol=1e-4)
        # positions: sensor edges at -1 / +1, pixel centres inside
        w = uniform.sensor_shape[1]
        order = np.argsort(-det["flux_adu"], kind="stable")[:n]
        np.testing.assert_allclose(coords[:n, 0], (det["x_px"][order] + 0.5) / (w / 2) - 1, atol=1e-6)
        np.testing.assert_allclose(coords[:n, 1], (det["y_px"][order] + 0.5) / (w / 2) - 1, atol=1e-6)
        assert np.all(np.abs(coords[:n, :2]) < 1)


def test_padding_rows_are_zero_and_masked(sparse_path):
    with open_dataset(sparse_path) as ds:
        pos = np.arange(len(ds))
        fd = FrameDataset(ds, pos, np.zeros(len(pos), int), max_stars=6)
        nd = ds.frames["n_detections"]
        assert (nd < 2).any() and (nd >= 2).any(), "fixture should hold sparse and non-sparse frames"
        for j in range(len(pos)):
            item = fd[j]
            n = min(int(nd[j]), 6)
            assert item["mask"].sum().item() == n
            assert torch.all(item["coords"][n:] == 0)
            assert int(item["n_detections"]) == nd[j]


def test_frames_with_fewer_than_two_detections_are_kept_and_counted(sparse_path):
    with open_dataset(sparse_path) as ds:
        pos = split_positions(ds, "train")
        expected = int((ds.frames["n_detections"][pos] < 2).sum())
        assert expected > 0
        assert count_sparse_frames(ds, pos) == expected
        fd = FrameDataset(ds, pos, np.zeros(len(pos), int))
        assert len(fd) == len(pos)  # nothing dropped


def test_empty_split_is_a_clear_error(tmp_path):
    path = render_small(
        tmp_path / "ds",
        [
            "n_frames=4",
            "camera.width_px=64",
            "camera.height_px=64",
            "camera.fov_deg=20",
            "output.image_size_px=32",
            "output.split_fractions=[1.0, 0.0, 0.0]",
        ],
    )
    with open_dataset(path) as ds:
        with pytest.raises(DatasetError, match="split 'val' .* holds no frames"):
            split_positions(ds, "val")


def test_image_normalisation_is_the_documented_log_stretch(uniform):
    geo = FrameGeometry.from_render_config(uniform.config)
    adu = np.array([0, geo.bias_adu, geo.bias_adu + 8, geo.max_adu], np.float32)
    x = normalise_image(adu, geo, 8.0)
    np.testing.assert_allclose(x, [0, 0, np.log1p(1) / np.log1p((geo.max_adu - geo.bias_adu) / 8), 1], rtol=1e-6)
    img = FrameDataset(uniform, np.arange(3), np.zeros(3, int))[0]["image"]
    assert img.shape == (1,) + uniform.image_shape and img.dtype == torch.float32
    assert 0 <= img.min() and img.max() <= 1


def test_heatmap_peaks_at_each_detection(uniform):
    geo = FrameGeometry.from_render_config(uniform.config)
    s = read_sample(uniform, 0, geo)
    coords, mask = encode_detections(s, geo, 6, 3.0)
    c = 128
    w = geo.sensor_px
    for j in range(int(mask.sum())):
        only = np.zeros_like(mask)
        only[j] = True
        h = rasterise(torch.from_numpy(coords)[None], torch.from_numpy(only)[None], c, 1.5)[0, 0].numpy()
        yy, xx = np.unravel_index(np.argmax(h), h.shape)
        # canvas coordinate of the detection: same edge convention as the stored image
        u = (s.x_px[j] + 0.5) * c / w - 0.5
        v = (s.y_px[j] + 0.5) * c / w - 0.5
        assert abs(xx - u) <= 0.5 + 1e-6 and abs(yy - v) <= 0.5 + 1e-6
        assert h.max() > 0.75
    h_all = rasterise(torch.from_numpy(coords)[None], torch.from_numpy(mask)[None], c, 1.5)
    assert h_all.shape == (1, 1, c, c) and 0 <= h_all.min() and h_all.max() <= 1


def test_heatmap_ignores_padding_and_handles_empty_frames():
    coords = torch.zeros(2, 6, 3)
    mask = torch.zeros(2, 6, dtype=torch.bool)
    h = rasterise(coords, mask, 32, 1.0)
    assert torch.all(h == 0)
    coords[1, 0, :2] = torch.tensor([0.5, -0.5])
    mask[1, 0] = True
    h = rasterise(coords, mask, 32, 1.0)
    assert torch.all(h[0] == 0) and h[1].max() > 0.5


def test_items_are_identical_with_fork_spawn_and_forkserver_workers():
    """The dataset pickles without HDF5 handles; augmented items depend on (seed, epoch, frame) only."""
    from fusion.config import AugConfig

    with open_dataset(small_dataset("smoke")) as ds:
        pos = np.arange(8)
        fd = FrameDataset(ds, pos, np.zeros(8, int), augment=Augmenter(AugConfig()), seed=3)
        ref = next(iter(make_loader(fd, 8, shuffle=True, seed=1)))
        for method in ("fork", "spawn", "forkserver"):
            batch = next(iter(make_loader(fd, 8, shuffle=True, seed=1, workers=1, start_method=method)))
            for key in ("image", "coords", "mask", "index"):
                assert torch.equal(batch[key], ref[key]), (method, key)


def test_augmented_items_repeat_per_epoch_and_change_between_epochs():
    from fusion.config import AugConfig

    with open_dataset(small_dataset("smoke")) as ds:
        fd = FrameDataset(ds, np.arange(4), np.zeros(4, int), augment=Augmenter(AugConfig()), seed=0)
        a, b, c = fd[(1, 0)], fd[(1, 0)], fd[(1, 1)]
        assert torch.equal(a["image"], b["image"]) and torch.equal(a["coords"], b["coords"])
        assert not torch.equal(a["image"], c["image"])


def test_forked_workers_do_not_deadlock_after_opencv_ran_in_the_parent():
    """OpenCV's thread pool does not survive fork; fusion keeps OpenCV single-threaded."""
    import subprocess
    import sys

    script = (
        "import numpy as np, cv2\n"
        "from fusion.config import AugConfig\n"
        "from fusion.model.shards import FrameDataset, make_loader\n"
        "from fusion.train.augment import Augmenter\n"
        "from skygen.datasets.shards import open_dataset\n"
        "big = np.random.rand(2048, 2048).astype(np.float32)\n"
        "cv2.warpAffine(big, np.array([[0.9, -0.4, 10], [0.4, 0.9, 5]]), (2048, 2048))\n"
        f"ds = open_dataset({str(small_dataset('smoke'))!r})\n"
        "fd = FrameDataset(ds, np.arange(8), np.zeros(8, int), augment=Augmenter(AugConfig()))\n"
        "next(iter(make_loader(fd, 4, shuffle=False, workers=1, start_method='fork')))\n"
        "print('ok')\n"
    )
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and "ok" in res.stdout, res.stderr[-2000:]
