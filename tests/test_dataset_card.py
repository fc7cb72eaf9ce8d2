"""A rendered dataset travels: Hugging Face `datasets` loads its shards unchanged, and its
Croissant 1.1 card validates with `mlcroissant` and names the columns `datasets` sees."""

import json

import numpy as np
import pytest

from skygen.datasets.shards import open_dataset

datasets = pytest.importorskip("datasets", reason="dev extra: pip install -e '.[dev]'")


@pytest.fixture(scope="module")
def hf_rows(small_dataset, tmp_path_factory):
    files = sorted(str(p) for p in small_dataset.glob("shard-*.h5"))
    return datasets.load_dataset(
        "hdf5", data_files=files, split="train", cache_dir=str(tmp_path_factory.mktemp("hf-cache"))
    )


def test_datasets_loads_shards_with_the_same_rows_as_skygen(small_dataset, hf_rows):
    with open_dataset(small_dataset) as ds:
        assert len(hf_rows) == len(ds) == 50
        for i in (0, 7, 19, 20, 49):  # across shard boundaries (20 frames per shard)
            row = hf_rows[i]
            assert np.array_equal(np.asarray(row["images"], np.uint16), ds.image(i))
            assert row["frames"]["index"] == ds.frames["index"][i]
            assert row["frames"]["frame_id"] == int(ds.frames["frame_id"][i])
            assert row["boresight"]["ra_deg"] == ds.boresight["ra_deg"][i]
            np.testing.assert_array_equal(row["boresight"]["quaternion"], ds.boresight["quaternion"][i])
            det, stars = ds.detections(i), ds.true_stars(i)
            for k in det:
                np.testing.assert_array_equal(np.asarray(row["detections"][k]), det[k], err_msg=k)
            for k in stars:
                np.testing.assert_array_equal(np.asarray(row["stars"][k], stars[k].dtype), stars[k], err_msg=k)
            assert json.loads(row["corruptions"]["log"]) == ds.corruption_log(i)


def test_croissant_card_validates_and_names_the_loaded_columns(small_dataset, hf_rows):
    mlc = pytest.importorskip("mlcroissant")
    meta = mlc.Dataset(jsonld=str(small_dataset / "croissant.json")).metadata
    assert not meta.ctx.issues.errors and not meta.ctx.issues.warnings, meta.ctx.issues.report()
    card = json.loads((small_dataset / "croissant.json").read_text())
    assert card["conformsTo"] == "http://mlcommons.org/croissant/1.1"
    columns = {
        f"{g}/{k}" if isinstance(v, dict) else g
        for g, v in hf_rows.features.items()
        for k in (v if isinstance(v, dict) else [None])
    }
    named = {f["source"]["extract"]["column"] for f in card["recordSet"][0]["field"]}
    assert named <= columns and {"images", "frames/frame_id", "detections/x_px"} <= named


def test_readme_card_says_what_how_camera_splits_licence_and_loading(small_dataset):
    text = (small_dataset / "README.md").read_text()
    for words in (
        "## How it was made",
        "## Camera",
        "## Splits",
        "## Licence",
        "Hipparcos",
        "## How to load",
        "h5py",
        "open_dataset",
        'load_dataset("hdf5"',
        "train 40, val 5, test 5",
    ):
        assert words in text, words
