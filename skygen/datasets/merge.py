"""``skygen merge``: combine datasets without copying frame data.

Two cases:

* **Slices of one dataset** (job-array renders into separate folders, same config):
  their shards are united by index into the complete dataset.
* **Different datasets** (other seeds, other teams) whose configs differ only in keys
  that do not change what a frame means (:data:`MERGEABLE_KEYS`): their shards are
  listed one after the other; each entry keeps its own ``dataset_id`` and the manifest
  lists every source config under ``sources``. Datasets that share frames (equal frame
  identities: same seed and render settings, e.g. ``--n 1000`` and ``--n 2000`` of seed 0)
  are refused.

The merged folder holds only ``manifest.json``, whose shard entries point at the
original files by relative path (copy the folders together when sharing). Checksums and
sizes are carried over, so ``skygen validate`` checks the merged dataset like any other.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from skygen.datasets.build import _manifests, config_differences, write_failed
from skygen.datasets.card import write_card
from skygen.datasets.shards import (
    MANIFEST_FORMAT,
    MANIFEST_NAME,
    SCHEMA_VERSION,
    SPLIT_NAMES,
    config_id,
    library_versions,
    write_json_atomic,
)
from skygen.errors import DatasetError
from skygen.identity import dataset_frame_ids
from skygen.lock import FolderLock

MERGEABLE_KEYS = {
    "seed",
    "n_frames",
    "output.shard_size",
    "output.compression",
    "output.compression_level",
    "output.full_res",
}


def _load_inputs(inputs: list[Path]) -> list[tuple[Path, dict, list[dict]]]:
    found = []
    for folder in inputs:
        if not folder.is_dir():
            raise DatasetError(f"{folder}: no such dataset folder")
        mans = _manifests(folder)
        if not mans:
            raise DatasetError(f"{folder}: no manifest*.json; is it a skygen dataset?")
        for path, man in mans:
            if man.get("format") != MANIFEST_FORMAT:
                raise DatasetError(f"{path}: not a skygen manifest")
            if int(str(man.get("schema_version", "0")).split(".")[0]) != int(SCHEMA_VERSION.split(".")[0]):
                raise DatasetError(f"{path}: schema {man.get('schema_version')} cannot be merged with {SCHEMA_VERSION}")
        # one folder = one dataset; its entries from all its manifests
        ids = {m.get("dataset_id") for _, m in mans}
        if len(ids) > 1:
            raise DatasetError(f"{folder}: holds manifests of several datasets; merge folders holding one each")
        entries = {}
        for _, man in mans:
            for e in man.get("shards", []):
                entries[e["index"]] = {**e, "file": str(folder / e["file"])}
        found.append((folder, mans[0][1], sorted(entries.values(), key=lambda e: e["index"])))
    return found


def _refuse_shared_frames(datasets: list[tuple[Path, dict]]) -> None:
    """Refuse datasets that hold the same frames (equal frame identities, see :mod:`skygen.identity`)."""
    seen: list[tuple[Path, np.ndarray]] = []
    for folder, cfg in datasets:
        ids = dataset_frame_ids(cfg)
        for other, other_ids in seen:
            shared = np.intersect1d(ids, other_ids)
            if len(shared):
                raise DatasetError(
                    f"cannot merge {other} and {folder}: {len(shared)} of their frames are the same "
                    "frames (same seed and render settings, so equal frame identities; a merged "
                    "dataset would repeat them, possibly across splits). Re-render one of them "
                    "with another --seed"
                )
        seen.append((folder, ids))


def merge_datasets(inputs: list[str | Path], out: str | Path) -> dict:
    """Write ``out/manifest.json`` combining ``inputs``; returns the manifest."""
    inputs = [Path(p) for p in inputs]
    out = Path(out)
    if len(inputs) < 2:
        raise DatasetError("merge needs at least two dataset folders")
    seen: dict = {}
    for p in inputs:
        key = p.resolve()
        if key in seen:
            raise DatasetError(f"{p}: given twice (as {seen[key]} too); each dataset folder once")
        seen[key] = p
    loaded = _load_inputs(inputs)
    by_id: dict[str, list] = {}
    for folder, man, entries in loaded:
        by_id.setdefault(man["dataset_id"], []).append((folder, man, entries))
    first_cfg = loaded[0][1]["config"]
    for folder, man, _ in loaded[1:]:
        bad = [k for k in config_differences(first_cfg, man["config"]) if k not in MERGEABLE_KEYS]
        if bad:
            raise DatasetError(
                f"cannot merge {inputs[0]} and {folder}: their configs differ in {', '.join(bad)} "
                "(frames would not mean the same thing)"
            )
    _refuse_shared_frames([(g[0][0], g[0][1]["config"]) for g in by_id.values()])
    sources, shards = [], []
    for dsid, group in by_id.items():
        cfg = group[0][1]["config"]
        n_shards = group[0][1].get("n_shards")
        union: dict[int, dict] = {}
        for folder, _, entries in group:
            for e in entries:
                if e["index"] in union and union[e["index"]]["sha256"] != e["sha256"]:
                    raise DatasetError(
                        f"shard {e['index']} of dataset {dsid} exists twice with different "
                        f"contents ({union[e['index']]['file']} and {e['file']})"
                    )
                union[e["index"]] = e
        if n_shards is not None and len(union) != n_shards:
            missing = sorted(set(range(n_shards)) - set(union))
            raise DatasetError(f"dataset {dsid} is incomplete: shard(s) {missing[:10]} missing from the inputs")
        sources.append({"dataset_id": dsid, "config": cfg, "folders": [str(g[0]) for g in group]})
        shards += [{**e, "dataset_id": dsid} for _, e in sorted(union.items())]
    try:
        out.mkdir(parents=True, exist_ok=True)
        with FolderLock(out, what="skygen merge"):  # two merges (or a render) into one folder: one refused
            return _write_merged(out, shards, sources, first_cfg)
    except DatasetError:
        raise
    except OSError as exc:  # disk full, quota, read-only folder: one line, not a traceback
        raise write_failed(exc, Path(exc.filename) if exc.filename else out / MANIFEST_NAME) from None


def _write_merged(out: Path, shards: list[dict], sources: list[dict], first_cfg: dict) -> dict:
    if (out / MANIFEST_NAME).exists():
        raise DatasetError(f"{out / MANIFEST_NAME} exists; choose an empty --out folder")
    start = 0
    for e in shards:
        e["file"] = os.path.relpath(e["file"], out)
        e["frame_start"] = start
        start += e["n_frames"]
    single = len(sources) == 1
    cfg = dict(first_cfg) if not single else sources[0]["config"]
    if not single:
        cfg = json.loads(json.dumps(cfg))
        cfg["n_frames"] = start
    man = {
        "format": MANIFEST_FORMAT,
        "schema_version": SCHEMA_VERSION,
        "dataset_id": sources[0]["dataset_id"]
        if single
        else "merged-" + config_id({"sources": sorted(s["dataset_id"] for s in sources)}),
        "complete": True,
        "n_frames": start,
        "n_shards": len(shards),
        "config": cfg,
        "splits": {s: sum(e["splits"][s] for e in shards) for s in SPLIT_NAMES},
        "shards": shards,
        "sources": sources if not single else [],
        "versions": library_versions(),
    }
    write_json_atomic(out / MANIFEST_NAME, man)
    write_card(out, man)
    return man
