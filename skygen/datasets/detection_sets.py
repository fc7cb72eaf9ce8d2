"""Detection sets on disk: ``skygen stream --kind detections --out FILE``.

The second file type skygen writes beside the shards, in the shards' own table layout and
field definitions (:data:`~skygen.datasets.shards.DETECTION_FIELDS`, ``STAR_FIELDS``,
``BORESIGHT_FIELDS``), so a reader of shard tables reads these too. Format name
``skygen-detection-stream``; the resolved stream config is stored in the ``config`` attribute.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from skygen.datasets.shards import BORESIGHT_FIELDS, DETECTION_FIELDS, LIBVER, STAR_FIELDS
from skygen.runtime import atomic_path


def write_detection_sets(batches, path: str | Path, config: dict) -> Path:
    """Write detection-stream samples (an iterable of :class:`skygen.stream.samples.DetectionBatch`) to one HDF5 file
    in the
    shard table layout (``detections``/``stars`` flat tables with ``offsets``, ``boresight`` per sample);
    written to a temporary name and renamed, as shards are."""
    parts = list(batches)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w", libver=LIBVER) as f:
            f.attrs["format"] = "skygen-detection-stream"
            f.attrs["config"] = json.dumps(config, sort_keys=True)
            f.attrs["description"] = (
                "detection sets of skygen's detections stream (emulated detector); "
                "tables as in skygen shards: rows of sample j are offsets[j]:offsets[j+1]"
            )
            idx = np.concatenate([b.index for b in parts])
            f.create_dataset("index", data=idx)
            g = f.create_group("boresight")
            g.attrs["frame"] = "ICRS"
            for name, (dtype, _, units, desc) in BORESIGHT_FIELDS.items():
                d = g.create_dataset(name, data=np.concatenate([b.labels[name] for b in parts]).astype(dtype))
                d.attrs["units"], d.attrs["description"] = units, desc
            for group, fields, offs, attr in (
                ("detections", DETECTION_FIELDS, "offsets", "detections"),
                ("stars", STAR_FIELDS, "star_offsets", "stars"),
            ):
                g = f.create_group(group)
                counts = np.concatenate([np.diff(getattr(b, offs)) for b in parts])
                g.create_dataset("offsets", data=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64))
                for name, (dtype, units, desc) in fields.items():
                    cols = [getattr(b, attr).get(name) for b in parts]
                    if any(c is None for c in cols):
                        continue
                    d = g.create_dataset(name, data=np.concatenate(cols).astype(dtype))
                    d.attrs["units"], d.attrs["description"] = units, desc
    return path
