"""``skygen validate``: check a dataset (or one shard) against the format.

Checks the manifest (format, version, completeness, frame counts), that every listed
shard exists with the recorded size and sha256 (always hashed: the checksum cache of
verified reads, :func:`skygen.datasets.shards.verify_checksums`, is not consulted), that no unlisted shard lies beside
them, and inside each shard: format name, schema version, dataset id and config equal to
the manifest's, every documented dataset present with its dtype and shape, per-frame
row counts consistent (offsets, for 1.x shards), frame identities matching the config,
and value ranges (unit vectors of norm 1, RA in [0, 360), Dec in [-90, 90],
quaternions of norm 1, detections and stars inside the sensor, finite numbers, splits
0/1/2, frame indices contiguous).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from skygen.datasets.shards import (
    BORESIGHT_FIELDS,
    DETECTION_FIELDS,
    FORMAT_NAME,
    FRAME_FIELDS,
    MANIFEST_NAME,
    STAR_FIELDS,
    V2_FRAME_FIELDS,
    config_id,
    open_shard_file,
    read_manifest,
    sha256_file,
)
from skygen.errors import DatasetError
from skygen.identity import frame_ids, split_bounds


@dataclass
class Report:
    path: Path
    problems: list[str] = field(default_factory=list)
    checked: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def text(self) -> str:
        head = f"{self.path}: {'OK' if self.ok else 'INVALID'} ({len(self.checked)} item(s) checked)"
        return "\n".join([head] + [f"  problem: {p}" for p in self.problems])


def _check_table(
    f: h5py.File, name: str, fields: dict, n: int, rep: Report, where: str, major: int
) -> tuple[np.ndarray, dict] | None:
    """(row count per frame, all rows of each column concatenated) of table ``name``, or None."""
    if name not in f:
        rep.problems.append(f"{where}: group '{name}' is missing")
        return None
    g = f[name]
    if major == 1:
        if "offsets" not in g:
            rep.problems.append(f"{where}: '{name}/offsets' is missing")
            return None
        off = g["offsets"][...]
        if off.shape != (n + 1,) or off[0] != 0 or np.any(np.diff(off) < 0):
            rep.problems.append(f"{where}: '{name}/offsets' is not a non-decreasing array of {n + 1} starting at 0")
            return None
        counts, shape = np.diff(off), (off[-1],)
    cols = {}
    for col, (dtype, _, _) in fields.items():
        if col not in g:
            rep.problems.append(f"{where}: '{name}/{col}' is missing")
            return None
        d = g[col]
        if major == 1:
            if d.dtype != np.dtype(dtype) or d.shape != shape:
                rep.problems.append(f"{where}: '{name}/{col}' is {d.dtype}{d.shape}, expected {np.dtype(dtype)}{shape}")
                return None
            cols[col] = d[...]
            continue
        base = h5py.check_vlen_dtype(d.dtype)
        if base is None or base != np.dtype(dtype) or d.shape != (n,):
            rep.problems.append(
                f"{where}: '{name}/{col}' is {d.dtype}{d.shape}, expected variable-length {np.dtype(dtype)} ({n},)"
            )
            return None
        rows = d[...]
        lengths = np.array([len(r) for r in rows], np.int64)
        if col == next(iter(fields)):
            counts = lengths
        elif np.any(lengths != counts):
            rep.problems.append(f"{where}: '{name}/{col}' rows differ in length from '{name}/{next(iter(fields))}'")
            return None
        cols[col] = np.concatenate(list(rows)) if n else np.zeros(0, dtype)
    return counts, cols


def _check_shard(path: Path, rep: Report, manifest: dict | None, frame_start: int | None) -> int:
    where = path.name
    try:
        f = open_shard_file(path)
    except DatasetError as exc:
        rep.problems.append(str(exc))
        return 0
    with f:
        try:
            n = int(f.attrs["n_frames"])
            cfg = json.loads(f.attrs["config"])
        except (KeyError, ValueError) as exc:
            rep.problems.append(f"{where}: root attributes damaged ({exc})")
            return 0
        if manifest is not None:
            want_id = manifest.get("expect_id", manifest.get("dataset_id"))
            want_cfg = manifest.get("expect_config", manifest.get("config"))
            if f.attrs.get("dataset_id") != want_id or cfg != want_cfg:
                rep.problems.append(
                    f"{where}: belongs to another dataset (dataset_id {f.attrs.get('dataset_id')} "
                    f"!= manifest {want_id})"
                )
        elif f.attrs.get("dataset_id") != config_id(cfg):
            rep.problems.append(f"{where}: dataset_id does not match its own config")
        try:
            major = int(str(f.attrs["schema_version"]).split(".")[0])
            _check_contents(f, n, cfg, rep, where, frame_start, major)
        except (OSError, KeyError, ValueError) as exc:
            rep.problems.append(f"{where}: unreadable data ({type(exc).__name__}: {exc})")
    rep.checked.append(where)
    return n


def _check_contents(
    f: h5py.File, n: int, cfg: dict, rep: Report, where: str, frame_start: int | None, major: int
) -> None:
    w, h = cfg["camera"]["width_px"], cfg["camera"]["height_px"]
    s = cfg["output"]["image_size_px"]
    sh = h // (w // s)  # stored rows: the sensor rows over the same downsampling factor
    if "images" not in f or f["images"].shape != (n, sh, s) or f["images"].dtype != np.uint16:
        got = (f["images"].dtype, f["images"].shape) if "images" in f else "missing"
        rep.problems.append(f"{where}: 'images' should be uint16 ({n}, {sh}, {s}); got {got}")
    else:
        for j in range(n):  # reading every chunk also verifies the compressed stream
            f["images"][j]
    frame_fields = FRAME_FIELDS if major >= 2 else {k: v for k, v in FRAME_FIELDS.items() if k not in V2_FRAME_FIELDS}
    for grp, fields in (("frames", frame_fields), ("boresight", BORESIGHT_FIELDS)):
        for col, spec in fields.items():
            key = f"{grp}/{col}"
            shape = (n,) + (spec[1] if grp == "boresight" else ())
            if key not in f:
                rep.problems.append(f"{where}: '{key}' is missing")
            elif f[key].shape != shape or f[key].dtype != np.dtype(spec[0]):
                rep.problems.append(
                    f"{where}: '{key}' is {f[key].dtype}{f[key].shape}, expected {np.dtype(spec[0])}{shape}"
                )
    if rep.problems and any(p.startswith(where) for p in rep.problems):
        return
    b = {k: f["boresight"][k][...] for k in BORESIGHT_FIELDS}
    for k, v in b.items():
        if not np.all(np.isfinite(v)):
            rep.problems.append(f"{where}: boresight/{k} holds NaN or infinite values")
    if np.any((b["ra_deg"] < 0) | (b["ra_deg"] >= 360)):
        rep.problems.append(f"{where}: boresight/ra_deg outside [0, 360)")
    if np.any(np.abs(b["dec_deg"]) > 90):
        rep.problems.append(f"{where}: boresight/dec_deg outside [-90, 90]")
    for k in ("unit_vector", "quaternion"):
        if np.any(np.abs(np.linalg.norm(b[k], axis=1) - 1) > 1e-9):
            rep.problems.append(f"{where}: boresight/{k} rows are not of norm 1")
    ra, dec = np.radians(b["ra_deg"]), np.radians(b["dec_deg"])
    uv = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], 1)
    if np.any(np.abs(uv - b["unit_vector"]) > 1e-9):
        rep.problems.append(f"{where}: boresight/unit_vector disagrees with ra_deg/dec_deg")
    fr = {k: f["frames"][k][...] for k in frame_fields}
    if not np.isin(fr["split"], (0, 1, 2)).all():
        rep.problems.append(f"{where}: frames/split holds values other than 0, 1, 2")
    if n and np.any(np.diff(fr["index"]) != 1):
        rep.problems.append(f"{where}: frames/index is not contiguous")
    if frame_start is not None and n and fr["index"][0] != frame_start:
        rep.problems.append(f"{where}: first frame index {fr['index'][0]} != manifest frame_start {frame_start}")
    if major >= 2:
        _check_identity(fr, cfg, rep, where)
    for name, fields, count in (("stars", STAR_FIELDS, None), ("detections", DETECTION_FIELDS, "n_detections")):
        table = _check_table(f, name, fields, n, rep, where, major)
        if table is None:
            continue
        counts, cols = table
        x, y = cols["x_px"], cols["y_px"]
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            rep.problems.append(f"{where}: {name} positions hold NaN or infinite values")
        # detection-level corruptions (centroid noise) may push a centroid slightly outside
        tol = 0.5 + 6 * float(cfg["corruptions"].get("centroid_noise", 0.0)) if name == "detections" else 0.5
        if np.any((x < -tol) | (x > w - 1 + tol) | (y < -tol) | (y > h - 1 + tol)):
            rep.problems.append(f"{where}: {name} positions outside the {w}x{h} sensor")
        if count and np.any(counts != fr[count]):
            rep.problems.append(f"{where}: {name} row counts disagree with frames/{count}")


def _check_identity(fr: dict, cfg: dict, rep: Report, where: str) -> None:
    """index_in_split and frame_id must be those the config gives each frame."""
    bounds = np.array((0, *split_bounds(int(cfg["n_frames"]), tuple(cfg["output"]["split_fractions"]))))
    if np.any(fr["index_in_split"] != fr["index"] - bounds[fr["split"].astype(np.int64)]):
        rep.problems.append(f"{where}: frames/index_in_split disagrees with frames/index and the split fractions")
    elif np.any(fr["frame_id"] != frame_ids(cfg, fr["split"], fr["index_in_split"], fr["index"])):
        rep.problems.append(f"{where}: frames/frame_id disagrees with the config (edited, or another dataset's frames)")


def validate(path: str | Path, checksums: bool = True) -> Report:
    """Validate a dataset folder or a single shard file. Never raises for bad data."""
    path = Path(path)
    rep = Report(path)
    if path.is_file():
        _check_shard(path, rep, None, None)
        return rep
    if not path.is_dir():
        rep.problems.append(f"{path}: no such dataset folder or shard file")
        return rep
    try:
        man = read_manifest(path)
    except DatasetError as exc:
        rep.problems.append(str(exc))
        return rep
    rep.checked.append(MANIFEST_NAME)
    if not man.get("complete"):
        rep.problems.append("manifest says the render is not complete; re-run `skygen render` to finish it")
    sources = {src["dataset_id"]: src["config"] for src in man.get("sources", [])}
    for dsid, cfg in sources.items():
        if dsid != config_id(cfg):
            rep.problems.append(f"merged manifest: source {dsid} does not match its config (edited by hand?)")
    if not sources and man.get("dataset_id") != config_id(man.get("config", {})):
        rep.problems.append("manifest dataset_id does not match its config (edited by hand?)")
    listed = set()
    total = 0
    expected_start = 0
    for e in sorted(man.get("shards", []), key=lambda e: e.get("frame_start", 0)):
        p = path / e["file"]
        listed.add(e["file"])
        if e.get("frame_start") != expected_start:
            rep.problems.append(
                f"{e['file']}: frame_start {e.get('frame_start')} leaves a gap or overlap (expected {expected_start})"
            )
        expected_start = e.get("frame_start", 0) + e.get("n_frames", 0)
        if not p.exists():
            rep.problems.append(f"{e['file']}: listed in the manifest but missing")
            continue
        if p.stat().st_size != e.get("bytes"):
            rep.problems.append(
                f"{e['file']}: size {p.stat().st_size} B, manifest says {e.get('bytes')} B (truncated?)"
            )
            continue
        if checksums and sha256_file(p) != e.get("sha256"):
            rep.problems.append(f"{e['file']}: sha256 differs from the manifest (file changed or corrupted)")
            continue
        expect = man
        if sources:
            expect = {"expect_id": e.get("dataset_id"), "expect_config": sources.get(e.get("dataset_id"))}
        n = _check_shard(p, rep, expect, None if sources else e.get("frame_start"))
        if n != e.get("n_frames"):
            rep.problems.append(f"{e['file']}: holds {n} frames, manifest says {e.get('n_frames')}")
        total += n
    for p in sorted(path.glob("shard-*.h5")):
        if p.name not in listed and not sources:
            rep.problems.append(f"{p.name}: a shard file that the manifest does not list")
    cfg_n = man.get("config", {}).get("n_frames")
    if man.get("complete") and total != cfg_n and not sources:
        rep.problems.append(f"dataset holds {total} readable frames, config n_frames is {cfg_n}")
    if man.get("n_frames") != sum(e.get("n_frames", 0) for e in man.get("shards", [])):
        rep.problems.append("manifest n_frames disagrees with the sum over its shards")
    return rep


__all__ = ["validate", "Report", "FORMAT_NAME"]
