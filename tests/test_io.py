"""Shard format: round trip, attributes, and deliberately broken files."""

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from skygen.datasets.shards import SCHEMA_VERSION, open_dataset, open_shard_file
from skygen.datasets.validate import validate
from skygen.errors import DatasetError


@pytest.fixture
def copy(small_dataset, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(small_dataset, dst)
    return dst


def test_round_trip_and_self_description(small_dataset):
    with open_dataset(small_dataset) as ds:
        assert len(ds) == 50 and ds.image(0).dtype == np.uint16 and ds.image(0).shape == (64, 64)
        d = ds.detections(3)
        assert np.all(np.diff(d["flux_adu"]) <= 0)
        assert set(d) >= {"x_px", "y_px", "flux_adu", "peak_adu", "area_px", "hip_id", "star_index"}
        np.testing.assert_allclose(np.linalg.norm(ds.boresight["unit_vector"], axis=1), 1, atol=1e-12)
    with h5py.File(small_dataset / "shard-00000.h5") as f:
        assert f.attrs["format"] == "skygen-shard" and f.attrs["schema_version"] == SCHEMA_VERSION
        assert "roll" in json.loads(f.attrs["conventions"])
        assert json.loads(f.attrs["config"])["n_frames"] == 50
        assert f["images"].chunks == (1, 64, 64) and f["images"].compression == "gzip"
        assert f["images"].compression_opts == 4 and f["images"].shuffle
        for name in ("boresight/ra_deg", "stars/x_px", "detections/flux_adu", "images"):
            assert "units" in f[name].attrs
        assert f["boresight"].attrs["frame"] == "ICRS"


def test_dataset_pickles_without_open_handles(small_dataset):
    import pickle

    with open_dataset(small_dataset) as ds:
        ds.image(0)
        clone = pickle.loads(pickle.dumps(ds))
        assert all(s.handle is None for s in clone.shards)
        assert np.array_equal(clone.image(21), ds.image(21))


def test_truncated_shard(copy):
    p = copy / "shard-00001.h5"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.raises(DatasetError, match="shard-00001.h5.*(truncated|size)"):
        open_dataset(copy)
    assert not validate(copy).ok


def test_foreign_and_garbage_files(tmp_path):
    with h5py.File(tmp_path / "foreign.h5", "w") as f:
        f["x"] = np.arange(3)
    with pytest.raises(DatasetError, match="foreign.h5: not a skygen shard"):
        open_shard_file(tmp_path / "foreign.h5")
    (tmp_path / "junk.h5").write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(DatasetError, match="junk.h5: not a readable HDF5"):
        open_dataset(tmp_path / "junk.h5")
    with pytest.raises(DatasetError, match="no such dataset"):
        open_dataset(tmp_path / "missing")
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(DatasetError, match="manifest.json is unreadable"):
        open_dataset(tmp_path)


def test_unknown_major_version_is_refused(copy):
    with h5py.File(copy / "shard-00000.h5", "r+") as f:
        f.attrs["schema_version"] = "3.0.0"
    with pytest.raises(DatasetError, match="schema version 3.0.0 is not supported"):
        open_shard_file(copy / "shard-00000.h5")
    man = json.loads((copy / "manifest.json").read_text())
    man["schema_version"] = "9.1.0"
    (copy / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(DatasetError, match="9.1.0"):
        open_dataset(copy)


def test_validate_catches_damage(copy, small_dataset, tmp_path):
    assert validate(copy).ok
    # a flipped byte inside a shard
    p = copy / "shard-00002.h5"
    data = bytearray(p.read_bytes())
    data[len(data) // 2] ^= 0xFF
    p.write_bytes(bytes(data))
    rep = validate(copy)
    assert not rep.ok and any("sha256" in x for x in rep.problems)
    # a missing shard
    (copy / "shard-00001.h5").unlink()
    assert any("missing" in x for x in validate(copy).problems)
    # a shard that the manifest does not list, and a hand-edited manifest
    shutil.copy(small_dataset / "shard-00000.h5", copy / "shard-00009.h5")
    man = json.loads((copy / "manifest.json").read_text())
    man["config"]["seed"] = 99
    (copy / "manifest.json").write_text(json.dumps(man))
    problems = validate(copy).problems
    assert any("does not list" in x for x in problems) and any("edited by hand" in x for x in problems)


def test_validate_catches_shard_from_another_dataset(tmp_path, small_overrides, small_dataset):
    from skygen.config import load_config
    from skygen.datasets.build import render_dataset

    other = tmp_path / "other"
    render_dataset(load_config(overrides=small_overrides + ["n_frames=50", "seed=5"]), other, progress=False)
    mixed = tmp_path / "mixed"
    shutil.copytree(small_dataset, mixed)
    shutil.copy(other / "shard-00001.h5", mixed / "shard-00001.h5")
    man = json.loads((mixed / "manifest.json").read_text())
    om = json.loads((other / "manifest.json").read_text())
    man["shards"][1] = om["shards"][1]  # even with its checksum copied over
    (mixed / "manifest.json").write_text(json.dumps(man))
    assert any("another dataset" in x for x in validate(mixed).problems)


@pytest.mark.parametrize(
    "damage, words",
    [
        (lambda f: f["boresight/ra_deg"].__setitem__(0, np.nan), "NaN"),
        (
            lambda f: (f.__delitem__("frames/split"), f.create_dataset("frames/split", data=np.zeros(20, "f4"))),
            "float32",
        ),
        (lambda f: f.__delitem__("boresight/dec_deg"), "missing"),
    ],
)
def test_damaged_labels_name_file_and_dataset(copy, damage, words):
    with h5py.File(copy / "shard-00001.h5", "r+") as f:
        damage(f)
    man = json.loads((copy / "manifest.json").read_text())
    man["shards"][1]["bytes"] = (copy / "shard-00001.h5").stat().st_size
    (copy / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(DatasetError, match=f"shard-00001.h5.*{words}"):
        open_dataset(copy)


SCHEMA1 = Path(__file__).parent / "data" / "schema1-dataset"  # written by skygen 0.1.0 at commit 8cffe5a


def test_schema1_dataset_still_reads_through_the_one_reader():
    """A 1.x dataset (flat tables + offsets) reads through open_dataset with the 2.x API."""
    with open_dataset(SCHEMA1) as ds:
        assert ds.schema_version.startswith("1.") and len(ds) == 10
        with h5py.File(SCHEMA1 / "shard-00001.h5") as f:  # frame 7 = row 2 of the second shard
            lo, hi = f["detections/offsets"][2:4]
            want = f["detections/x_px"][lo:hi]
            slo, shi = f["stars/offsets"][2:4]
            want_mag = f["stars/mag"][slo:shi]
        np.testing.assert_array_equal(ds.detections(7)["x_px"], want)
        np.testing.assert_array_equal(ds.true_stars(7)["mag"], want_mag)
        assert ds.image(7).shape == (32, 32)
        # identities derived for the 1.x keying (frames drawn from the global index)
        assert ds.frames["frame_id"].dtype == np.uint64 and len(set(ds.frames["frame_id"])) == 10
        assert list(ds.frames["index_in_split"]) == [0, 1, 2, 3, 4, 5, 6, 7, 0, 0]
    assert validate(SCHEMA1).ok, validate(SCHEMA1).text()


@pytest.mark.parametrize("counts", [(0, 0), (3, 3), (2, 0, 5)])
def test_tables_of_empty_or_equal_length_rows_round_trip(tmp_path, counts):
    """Per-frame variable-length rows survive frames without detections and frames of equal counts."""
    from types import SimpleNamespace

    from skygen.config import config_dict, load_config
    from skygen.datasets.shards import DETECTION_FIELDS, STAR_FIELDS, write_shard

    cfg = config_dict(load_config(overrides=["n_frames=3"]))
    table = lambda fields, k: {n: np.arange(k).astype(v[0]) for n, v in fields.items()}  # noqa: E731
    frames = [
        SimpleNamespace(
            index=i,
            split=0,
            index_in_split=i,
            frame_id=i,
            n_stars=k,
            n_detections=k,
            background_adu=0.0,
            noise_adu=1.0,
            ra_deg=0.0,
            dec_deg=0.0,
            roll_deg=0.0,
            unit_vector=np.array([1.0, 0, 0]),
            quaternion=np.array([1.0, 0, 0, 0]),
            image=np.zeros((4, 4), np.uint16),
            image_full=None,
            downsample_factor=1,
            stars=table(STAR_FIELDS, k),
            detections=table(DETECTION_FIELDS, k),
            applied={},
            log={},
        )
        for i, k in enumerate(counts)
    ]
    write_shard(tmp_path / "s.h5", frames, config=cfg, shard_index=0, frame_start=0)
    with h5py.File(tmp_path / "s.h5") as f:
        assert f["detections/x_px"].shape == (len(counts),)
        assert [len(r) for r in f["detections/x_px"][...]] == list(counts)
        assert [len(r) for r in f["stars/mag"][...]] == list(counts)


def test_a_same_size_edit_with_its_mtime_restored_is_caught(copy):
    """The verified-read cache must not trust size + mtime alone: both are easy to restore."""
    import os
    import time

    from skygen.datasets.shards import verify_checksums

    with open_dataset(copy) as ds:
        assert verify_checksums(ds) == len(ds.shards)
        assert verify_checksums(ds) == 0  # remembered
    time.sleep(0.05)  # file timestamps tick coarsely (ms): let the edit's ctime differ
    p = copy / "shard-00001.h5"
    st = p.stat()
    data = bytearray(p.read_bytes())
    data[len(data) // 2] ^= 0xFF
    p.write_bytes(bytes(data))
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns))  # size and mtime as verified
    assert (p.stat().st_size, p.stat().st_mtime_ns) == (st.st_size, st.st_mtime_ns)
    with open_dataset(copy) as ds:
        with pytest.raises(DatasetError, match="shard-00001.h5: sha256 differs"):
            verify_checksums(ds)
    rep = validate(copy)  # validate always hashes
    assert not rep.ok and any("shard-00001.h5: sha256 differs" in x for x in rep.problems)
