"""Frames of a stored dataset with one corruption made worse: the robustness-sweep input.

* sensor and scene corruptions: the frame is rendered again from the dataset's config
  with the extra severity stacked on the dataset's own (:func:`corruptions.with_extra`).
  Boresight, stars and every other random draw are those of the stored frame, so the
  corrupted pixels go through the real detector as they would on orbit.
* detection corruptions: applied to the stored detections with their own random
  streams (stacked on whatever the dataset already applied).

Extra severity 0 returns the stored image and detections exactly.
"""

from __future__ import annotations

import json
import multiprocessing as mp

import numpy as np

from skygen.config import build_config
from skygen.instrument import corruptions as corr

_CACHE: dict = {}


def _renderer(cfg_dict: dict, name: str, extra: float, legacy: bool = False):
    from skygen.render.frame import Renderer

    key = (json.dumps(cfg_dict, sort_keys=True), name, extra, legacy)
    if key not in _CACHE:
        _CACHE.clear()
        _CACHE[key] = Renderer(corr.with_extra(build_config(cfg_dict), name, extra), legacy_streams=legacy)
    return _CACHE[key]


def _render_some(args) -> list[dict]:
    cfg_dict, name, extra, frame_indices, legacy = args
    r = _renderer(cfg_dict, name, extra, legacy)
    out = []
    for i in frame_indices:
        f = r.render(int(i))
        out.append({"index": int(i), "image": f.image, "detections": f.detections, "log": f.log})
    return out


def perturbed_frames(ds, name: str, extra: float, positions: np.ndarray, workers: int = 1, progress=None) -> list[dict]:
    """Images (stored size) and detections of frames ``positions`` of dataset ``ds``
    (a :class:`skygen.datasets.shards.Dataset`) with ``extra`` severity of corruption ``name``.

    ``progress`` (optional) is called with the number of frames finished so far.
    """
    c = corr.get(name)
    corr.with_extra(build_config(ds.config), name, extra)  # validates the severity
    positions = np.asarray(positions, dtype=np.int64)
    if c.stage == "detections" or extra == 0:
        out = []
        levels = {n: 0.0 for n in corr.REGISTRY}
        levels[name] = float(extra)
        for k, p in enumerate(positions):
            det = ds.detections(int(p))
            idx = int(ds.frames["index"][p])
            det, log = corr.apply_detection_corruptions(det, levels, int(ds.config["seed"]), idx, stream="/sweep")
            out.append({"index": idx, "image": ds.image(int(p)), "detections": det, "log": log})
            if progress:
                progress(k + 1)
        return out
    indices = ds.frames["index"][positions]
    chunks = [indices[i : i + 16] for i in range(0, len(indices), 16)]
    legacy = str(ds.schema_version).startswith("1.")  # 1.x frames: streams keyed by global index
    tasks = [(ds.config, name, float(extra), ch, legacy) for ch in chunks]
    results = []
    if workers <= 1 or len(chunks) == 1:
        for t in tasks:
            results += _render_some(t)
            if progress:
                progress(len(results))
    else:
        for part in _pool(workers).imap(_render_some, tasks):
            results += part
            if progress:
                progress(len(results))
    return results


_POOLS: dict = {}


def _pool(workers: int):
    """One worker pool per process and size, reused across corruptions and severities
    (each worker keeps its Renderer for the last config it saw)."""
    if workers not in _POOLS:
        import atexit

        pool = mp.get_context("spawn").Pool(workers)
        _POOLS[workers] = pool
        atexit.register(pool.terminate)
    return _POOLS[workers]
