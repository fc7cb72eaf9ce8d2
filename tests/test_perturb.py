"""Robustness-sweep inputs: severity 0 is the stored frame; severity changes frames deterministically."""

import numpy as np
import pytest

from skygen.datasets.shards import open_dataset
from skygen.instrument import corruptions as corr
from skygen.render.perturb import perturbed_frames


@pytest.mark.parametrize("name", list(corr.REGISTRY))
def test_zero_extra_reproduces_stored_frames(small_dataset, name):
    with open_dataset(small_dataset) as ds:
        pos = ds.indices("test")
        for f, p in zip(perturbed_frames(ds, name, 0.0, pos), pos):
            assert np.array_equal(f["image"], ds.image(int(p)))
            stored = ds.detections(int(p))
            assert all(np.array_equal(f["detections"][k], stored[k]) for k in stored)


def test_rerendered_clean_equals_stored_and_extra_changes_it(small_dataset):
    with open_dataset(small_dataset) as ds:
        pos = ds.indices("val")[:3]
        a = perturbed_frames(ds, "cosmic_rays", 2000.0, pos)
        b = perturbed_frames(ds, "cosmic_rays", 2000.0, pos, workers=2)
        assert all(np.array_equal(x["image"], y["image"]) for x, y in zip(a, b))
        assert any(not np.array_equal(x["image"], ds.image(int(p))) for x, p in zip(a, pos))
        d = perturbed_frames(ds, "dropout", 0.5, pos)
        assert sum(len(x["detections"]["x_px"]) for x in d) < sum(len(ds.detections(int(p))["x_px"]) for p in pos)


def test_out_of_range_severity_is_refused(small_dataset):
    from skygen.errors import ConfigError

    with open_dataset(small_dataset) as ds, pytest.raises(ConfigError, match="corruptions.dropout"):
        perturbed_frames(ds, "dropout", 1.5, ds.indices("test"))
