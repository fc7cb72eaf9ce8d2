"""What a frame *is*: its random-stream key and its identity across datasets.

Random streams (schema 2)
    Every random draw of a frame comes from a generator keyed by
    ``(seed, split code, index within the split, stage name)`` (:func:`frame_key`), never
    by the frame's global position. So the *j*-th test frame of seed 0 is the same frame
    whatever ``--n`` or ``output.split_fractions`` are, and a training frame of one
    dataset can never reappear as a validation or test frame of another dataset with
    the same seed. Schema 1.x datasets keyed streams by the global index only; two
    seed-0 datasets with different ``--n`` therefore shared frames *across* splits.

Identity
    ``frame_id`` (uint64, stored per frame in schema 2) is a hash of the *content
    config* (the render config without the keys that only say how many frames there
    are and how they are stored, :data:`STORAGE_KEYS`) with the stream key. Equal ids
    mean the same pixels and labels; ``skygen merge`` refuses datasets that share ids
    and ``fusion evaluate`` refuses to score frames a checkpoint was trained on. For a
    1.x dataset the reader derives the ids of its (global-index) keying, so both
    guards work on old data too.
"""

from __future__ import annotations

import copy
import hashlib
import json

import numpy as np

# keys that do not change any frame's pixels or labels under the (split, j) keying (storage, and what a solver
# is told about the real camera)
STORAGE_KEYS = (
    "n_frames",
    "output.shard_size",
    "output.compression",
    "output.compression_level",
    "output.full_res",
    "output.split_fractions",
    "camera.centroid_sigma_px",  # what a solver assumes of the real camera's centroids, not how frames are rendered
    "camera.match_tol_px",  # how closely a solver matches on this camera, likewise
    "camera.shared_sigma_px",  # what a solver assumes of the error bright stars share, likewise
)


# keys added after datasets and calibrations were made, with the value that reproduces the frames made
# before them: at that value they are left out of content ids and calibration keys, so older datasets
# keep their ids and the shipped detector calibration still matches
NEUTRAL_DEFAULTS = {
    "camera.pixel_aspect": 1.0,
    "detection.background_box_px": 0,
    "corruptions.false_star_slope": 0.0,
    "corruptions.false_star_span_mag": 4.0,
    "catalog.source": "hipparcos",
    "photometry.star_scatter_mag": 0.0,
    "optics.sky_vignetting": None,
    "camera.centroid_sigma_px": None,
    "sensor.fixed_sources": [],
    "sensor.black_level_adu": 0,
    "sensor.tone_gamma": 1.0,
    "sensor.tone_knee_adu": 0.0,
    "sensor.processor_blur_px": 0.0,
    "optics.star_jitter_px": 0.0,
    "camera.bright_shift_px": 0.0,
    "camera.match_tol_px": None,
    "camera.bright_shift_from": 1.5,
    "camera.bright_shift_x_px": 0.0,
    "camera.bright_shift_y_px": 0.0,
    "camera.shared_sigma_px": None,
}


def drop_neutral(config: dict) -> dict:
    """``config`` (nested, modified in place) without the :data:`NEUTRAL_DEFAULTS` keys at their neutral value."""
    for key, neutral in NEUTRAL_DEFAULTS.items():
        sec, name = key.split(".")
        if sec in config and name in config[sec] and config[sec][name] == neutral:
            config[sec].pop(name)
    return config


def content_config(config: dict) -> dict:
    """``config`` without :data:`STORAGE_KEYS` (a new dict); the ``render`` section counts
    only when it selects the torch backend (the NumPy renderer's frames do not depend on it)."""
    out = copy.deepcopy(config)
    if out.get("render", {}).get("backend", "numpy") == "numpy":
        out.pop("render", None)
    for key in STORAGE_KEYS:
        node, parts = out, key.split(".")
        for p in parts[:-1]:
            node = node.get(p, {})
        node.pop(parts[-1], None)
    return drop_neutral(out)


def content_id(config: dict) -> str:
    """sha256 (first 16 hex digits) of the canonical JSON of the content config."""
    text = json.dumps(content_config(config), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def split_bounds(n_frames: int, fractions: tuple[float, float, float]) -> tuple[int, int]:
    """Frames [0, a) are train, [a, b) val, [b, n) test (contiguous ranges of the global index)."""
    a = int(round(n_frames * fractions[0]))
    b = int(round(n_frames * (fractions[0] + fractions[1])))
    return a, b


def frame_key(split: int, index_in_split: int) -> tuple[int, int]:
    """The random-stream key of a frame (schema 2): ``(split code, index within the split)``."""
    return int(split), int(index_in_split)


def _hash64(text: str) -> int:
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little")


def frame_ids(config: dict, split: np.ndarray, index_in_split: np.ndarray, index: np.ndarray) -> np.ndarray:
    """uint64 identities of schema-2 frames. With ``attitude.mode=list`` the boresight
    comes from the global index, so that index is part of the identity too."""
    cid = content_id(config)
    listed = config.get("attitude", {}).get("mode") == "list"
    keys = (f"{cid}/{s}/{j}" + (f"/{i}" if listed else "") for s, j, i in zip(split, index_in_split, index))
    return np.fromiter((_hash64(k) for k in keys), np.uint64, count=len(split))


def legacy_frame_ids(config: dict, index: np.ndarray) -> np.ndarray:
    """uint64 identities of schema-1.x frames, whose streams were keyed by the global index."""
    cid = content_id(config)
    return np.fromiter((_hash64(f"{cid}/v1/{i}") for i in index), np.uint64, count=len(index))


def dataset_frame_ids(config: dict) -> np.ndarray:
    """uint64 identities of every frame of the (schema 2) dataset that ``config`` renders, in order."""
    n = int(config["n_frames"])
    a, b = split_bounds(n, tuple(config["output"]["split_fractions"]))
    index = np.arange(n, dtype=np.int64)
    split = np.where(index < a, 0, np.where(index < b, 1, 2))
    return frame_ids(config, split, index - np.array([0, a, b])[split], index)
