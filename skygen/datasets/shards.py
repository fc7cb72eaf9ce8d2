"""The skygen dataset format: one writer, one reader.

A *dataset* is a folder holding ``manifest.json`` and shards ``shard-00000.h5`` ... .
Each shard is a self-describing HDF5 file (see ``docs/FORMAT.md``) that plain h5py and
Hugging Face ``datasets`` (``load_dataset("hdf5", ...)``) can read: schema 2 stores only
per-frame rows, every dataset with the frame count as its first dimension; the true
stars and detections of a frame are variable-length arrays, one per column. Schema
1.x shards stored those tables flat with an ``offsets`` array (rows of frame i are
``offsets[i]:offsets[i+1]``); this reader still opens them.

Shards are written to a hidden temporary name (``.shard-00000.h5.tmp``) and renamed
only once complete and closed, so a file named ``shard-*.h5`` is always whole; the
manifest records the sha256 of every shard and is itself replaced atomically.

:func:`open_dataset` is the only reader; ``fusion`` reads through it.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from skygen.conventions import CONVENTIONS
from skygen.errors import DatasetError
from skygen.identity import content_id, legacy_frame_ids, split_bounds
from skygen.runtime import atomic_path, write_json

FORMAT_NAME = "skygen-shard"
MANIFEST_FORMAT = "skygen-dataset"
SCHEMA_VERSION = "2.0.0"
SUPPORTED_MAJOR = (1, 2)
MANIFEST_NAME = "manifest.json"
SPLIT_NAMES = ("train", "val", "test")
LIBVER = ("v110", "v114")

STAR_FIELDS = {  # name: (dtype, units, description)
    "hip_id": (
        "i8",
        "",
        "catalog id: HIP number, or with catalog.source=gaia the Gaia DR3 source_id (HIP number for the stars "
        "taken from Hipparcos); -1 for a false star injected in the scene",
    ),
    "x_px": ("f8", "px", "projected position, full-resolution pixels, (0,0) = centre of top-left pixel"),
    "y_px": ("f8", "px", "projected position, full-resolution pixels"),
    "mag": (
        "f4",
        "mag",
        "catalog magnitude (Hp; catalog.source=gaia: Hp, or G + the Hp - G offset for Gaia-only stars)",
    ),
    "bv": ("f4", "mag", "catalog B-V colour (NaN if unknown)"),
    "electrons": ("f4", "e-", "expected photo-electrons collected over the exposure (before noise)"),
}
DETECTION_FIELDS = {
    "x_px": ("f8", "px", "intensity-weighted centroid, full-resolution pixels"),
    "y_px": ("f8", "px", "intensity-weighted centroid, full-resolution pixels"),
    "flux_adu": ("f4", "ADU", "background-subtracted summed signal"),
    "peak_adu": ("f4", "ADU", "background-subtracted peak pixel"),
    "area_px": ("i4", "px", "pixels above threshold"),
    "hip_id": ("i8", "", "catalog id (stars/hip_id) of the matched true star; -1 if false"),
    "star_index": ("i4", "", "row of the matched true star within the frame; -1 if false"),
}
FRAME_FIELDS = {
    "index": ("i8", "", "global frame index within the dataset"),
    "split": ("u1", "", "0 train, 1 val, 2 test (see attribute labels)"),
    "index_in_split": ("i8", "", "position within its split; with the seed, keys the frame's random streams"),
    "frame_id": ("u8", "", "identity of the frame: hash of the content config, split and index_in_split"),
    "n_stars": ("i4", "", "true stars projected inside the sensor"),
    "n_detections": ("i4", "", "detections after detection-level corruptions"),
    "background_adu": ("f4", "ADU", "detector's background estimate"),
    "noise_adu": ("f4", "ADU", "detector's background noise estimate (robust sigma)"),
}
BORESIGHT_FIELDS = {
    "ra_deg": ("f8", (), "deg", "boresight right ascension, ICRS, [0, 360)"),
    "dec_deg": ("f8", (), "deg", "boresight declination, ICRS"),
    "roll_deg": ("f8", (), "deg", "position angle of image up from north through east"),
    "unit_vector": ("f8", (3,), "", "boresight [cos d cos a, cos d sin a, sin d], ICRS"),
    "quaternion": ("f8", (4,), "", "[w, x, y, z], camera frame to ICRS"),
}


def library_versions() -> dict:
    import astropy
    import cv2
    import scipy

    from skygen import __version__

    return {
        "skygen": __version__,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "astropy": astropy.__version__,
        "h5py": h5py.__version__,
        "hdf5": h5py.version.hdf5_version,
        "opencv": cv2.__version__,
    }


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def config_id(config: dict) -> str:
    """Stable identity of a dataset's frames: sha256 of its canonical config JSON.

    The ``render`` section (backend choice) counts only when it selects the torch
    backend, so datasets of the NumPy renderer keep the identity they had before the
    section existed."""
    if config.get("render", {}).get("backend", "numpy") == "numpy":
        config = {k: v for k, v in config.items() if k != "render"}
    text = json.dumps(config, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def shard_name(index: int) -> str:
    return f"shard-{index:05d}.h5"


def _compression(name: str, level: int) -> dict:
    if name == "gzip":
        return {"compression": "gzip", "compression_opts": level, "shuffle": True}
    if name == "lzf":
        return {"compression": "lzf", "shuffle": True}
    if name == "none":
        return {}
    if name in ("blosc-zstd", "blosc-lz4"):
        try:
            import hdf5plugin
        except ImportError:
            raise DatasetError(
                f"compression '{name}' needs the optional package hdf5plugin: "
                "pip install hdf5plugin (or use output.compression=gzip)"
            ) from None
        cname = name.split("-")[1]
        return dict(hdf5plugin.Blosc(cname=cname, clevel=level, shuffle=hdf5plugin.Blosc.BITSHUFFLE))
    raise DatasetError(f"unknown compression {name!r}")


def _write_table(group: h5py.Group, rows: list[dict], fields: dict) -> None:
    """One variable-length array per frame and column: ``group/col[i]`` holds frame i's rows."""
    for name, (dtype, units, desc) in fields.items():
        data = np.empty(len(rows), dtype=object)
        for i, r in enumerate(rows):  # one by one, and passed at creation: rows of equal length
            data[i] = np.asarray(r[name], dtype=dtype)  # must not become a 2-D array
        d = group.create_dataset(name, data=data, shape=(len(rows),), dtype=h5py.vlen_dtype(np.dtype(dtype)))
        d.attrs["units"] = units
        d.attrs["description"] = desc + " (one variable-length array per frame)"


def write_shard(
    path: str | Path,
    frames: list,
    *,
    config: dict,
    shard_index: int,
    frame_start: int,
    compression: str = "gzip",
    compression_level: int = 4,
    corruption_names: tuple[str, ...] = (),
) -> dict:
    """Write rendered frames (a list of :class:`skygen.render.frame.Frame`) as one shard.

    The HDF5 file is built in memory (about the size of the shard file; the frames
    themselves are already held) and then written with one plain write to a hidden
    temporary file in the same folder, which is renamed into place, so an interruption
    never leaves a complete-looking shard. HDF5 itself never writes to disk: a full disk
    arrives as a plain ``OSError(ENOSPC)`` from that write, with the temporary removed.
    (Had HDF5 met ENOSPC, it raised RuntimeError on close, kept the half-written file open
    and crashed the interpreter at exit.) Returns the manifest entry.
    """
    path = Path(path)
    n = len(frames)
    buf = io.BytesIO()
    with h5py.File(buf, "w", libver=LIBVER) as f:
        _fill_shard(
            f,
            frames,
            config=config,
            shard_index=shard_index,
            frame_start=frame_start,
            compression=compression,
            compression_level=compression_level,
            corruption_names=corruption_names,
        )
    with atomic_path(path) as tmp:
        _write_bytes(tmp, buf.getbuffer())
    del buf
    splits = np.bincount([fr.split for fr in frames], minlength=3)
    return {
        "file": path.name,
        "index": shard_index,
        "frame_start": frame_start,
        "n_frames": n,
        "bytes": path.stat().st_size,
        "sha256": sha256_file(path),
        "splits": {s: int(c) for s, c in zip(SPLIT_NAMES, splits)},
    }


def _write_bytes(path: Path, data) -> None:
    """Write ``data`` to a new file ``path``; a full disk raises OSError(ENOSPC) here."""
    with open(path, "wb") as fh:
        fh.write(data)


def _fill_shard(
    f: h5py.File,
    frames: list,
    *,
    config: dict,
    shard_index: int,
    frame_start: int,
    compression: str,
    compression_level: int,
    corruption_names: tuple[str, ...],
) -> None:
    """The datasets and attributes of one shard (layout in docs/FORMAT.md), into open file ``f``."""
    n = len(frames)
    a = f.attrs
    a["format"] = FORMAT_NAME
    a["schema_version"] = SCHEMA_VERSION
    a["config"] = json.dumps(config, sort_keys=True)
    a["dataset_id"] = config_id(config)
    a["versions"] = json.dumps(library_versions(), sort_keys=True)
    a["seed"] = int(config["seed"])
    a["shard_index"] = shard_index
    a["frame_start"] = frame_start
    a["n_frames"] = n
    a["created_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    a["conventions"] = json.dumps(CONVENTIONS, sort_keys=True)
    a["content_id"] = content_id(config)
    comp = _compression(compression, compression_level)
    images = np.stack([fr.image for fr in frames]) if n else np.zeros((0, 1, 1), np.uint16)
    d = f.create_dataset("images", data=images, chunks=(1,) + images.shape[1:] if n else None, **(comp if n else {}))
    d.attrs["units"] = "ADU"
    d.attrs["description"] = "sensor frames area-averaged to the stored size, [frame, y, x]"
    d.attrs["downsample_factor"] = int(frames[0].downsample_factor) if n else 1
    if n and frames[0].image_full is not None:
        full = np.stack([fr.image_full for fr in frames])
        d = f.create_dataset("images_full", data=full, chunks=(1,) + full.shape[1:], **comp)
        d.attrs["units"] = "ADU"
        d.attrs["description"] = "full-resolution sensor frames, [frame, y, x]"
    g = f.create_group("frames")
    for name, (dtype, units, desc) in FRAME_FIELDS.items():
        d = g.create_dataset(name, data=np.array([getattr(fr, name) for fr in frames], dtype=dtype))
        d.attrs["units"] = units
        d.attrs["description"] = desc
    g["split"].attrs["labels"] = json.dumps(SPLIT_NAMES)
    g = f.create_group("boresight")
    g.attrs["frame"] = "ICRS"
    for name, (dtype, shape, units, desc) in BORESIGHT_FIELDS.items():
        data = np.array([getattr(fr, name) for fr in frames], dtype=dtype).reshape((n,) + shape)
        d = g.create_dataset(name, data=data)
        d.attrs["units"] = units
        d.attrs["description"] = desc
    _write_table(f.create_group("stars"), [fr.stars for fr in frames], STAR_FIELDS)
    _write_table(f.create_group("detections"), [fr.detections for fr in frames], DETECTION_FIELDS)
    g = f.create_group("corruptions")
    g.attrs["description"] = "per-frame severity applied for each registered corruption, in its units"
    for name in corruption_names:
        d = g.create_dataset(name, data=np.array([fr.applied.get(name, 0.0) for fr in frames], "f8"))
    log = np.array([json.dumps(fr.log, sort_keys=True) for fr in frames], dtype=object)
    d = g.create_dataset("log", data=log, dtype=h5py.string_dtype())
    d.attrs["description"] = "JSON per frame: what each corruption/defect did (counts, vectors)"


def write_json_atomic(path: str | Path, data: dict) -> None:
    """``data`` as strict JSON (:func:`skygen.runtime.write_json`), written atomically."""
    write_json(path, data)


def read_manifest(folder: str | Path, name: str = MANIFEST_NAME) -> dict:
    path = Path(folder) / name
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(
            f"{path} not found: not a skygen dataset folder, or its render has not "
            "finished (re-run the same `skygen render` command to resume)"
        ) from None
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path} is unreadable or not JSON ({exc}); restore it or re-render") from None
    if not isinstance(data, dict) or data.get("format") != MANIFEST_FORMAT:
        raise DatasetError(
            f"{path} is not a skygen manifest (format={data.get('format') if isinstance(data, dict) else None!r})"
        )
    _check_version(data.get("schema_version"), path)
    return data


def _check_version(version, path) -> None:
    try:
        major = int(str(version).split(".")[0])
    except ValueError:
        raise DatasetError(f"{path}: schema_version {version!r} is not a version number") from None
    if major not in SUPPORTED_MAJOR:
        raise DatasetError(
            f"{path}: schema version {version} is not supported by this skygen "
            f"(reads major version {', '.join(map(str, SUPPORTED_MAJOR))}); "
            "upgrade skygen or re-render the dataset"
        )


def open_shard_file(path: str | Path) -> h5py.File:
    """Open one shard read-only, checking that it is a skygen shard of a known version."""
    path = Path(path)
    try:
        f = h5py.File(path, "r")
    except FileNotFoundError:
        raise DatasetError(f"{path}: shard file is missing") from None
    except OSError as exc:
        raise DatasetError(f"{path}: not a readable HDF5 file (truncated or damaged?): {exc}") from None
    fmt, version = f.attrs.get("format"), f.attrs.get("schema_version")
    if fmt != FORMAT_NAME:
        f.close()
        raise DatasetError(f"{path}: not a skygen shard (HDF5 attribute format={fmt!r}, expected {FORMAT_NAME!r})")
    try:
        _check_version(version, path)
    except DatasetError:
        f.close()
        raise
    return f


@dataclass
class _Shard:
    path: Path
    frame_start: int
    n_frames: int
    major: int = 2  # schema major version: 1 = flat tables with offsets
    handle: h5py.File | None = None


@dataclass
class Dataset:
    """A rendered dataset opened for reading. Use :func:`open_dataset`.

    Small per-frame arrays (boresight, split, counts) are loaded on open; images and
    star tables are read lazily from the shards. Safe to pickle into DataLoader
    workers: open HDF5 handles are dropped and re-opened lazily in each process.
    """

    root: Path
    manifest: dict
    shards: list[_Shard]
    boresight: dict = field(repr=False)
    frames: dict = field(repr=False)

    # -- basic facts -------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.frames["index"].shape[0])

    @property
    def config(self) -> dict:
        return self.manifest["config"]

    @property
    def schema_version(self) -> str:
        return self.manifest["schema_version"]

    @property
    def sensor_shape(self) -> tuple[int, int]:
        cam = self.config["camera"]
        return int(cam["height_px"]), int(cam["width_px"])

    @property
    def image_shape(self) -> tuple[int, int]:
        """(rows, columns) of the stored images: the sensor area-averaged by an integer factor."""
        s = int(self.config["output"]["image_size_px"])
        h, w = self.sensor_shape
        return h // (w // s), s

    @property
    def downsample_factor(self) -> int:
        return self.sensor_shape[1] // self.image_shape[1]

    def indices(self, split: str | None = None) -> np.ndarray:
        """Positions (0..len-1) of the frames in ``split`` ('train', 'val', 'test' or None)."""
        if split is None:
            return np.arange(len(self))
        if split not in SPLIT_NAMES:
            raise DatasetError(f"unknown split {split!r}; expected one of {', '.join(SPLIT_NAMES)}")
        return np.flatnonzero(self.frames["split"] == SPLIT_NAMES.index(split))

    # -- lazy access -------------------------------------------------------------
    def _locate(self, i: int) -> tuple[_Shard, h5py.File, int]:
        """The shard holding frame ``i``, its open file (opened on first use) and the row within it."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range for a dataset of {len(self)} frames")
        k = int(np.searchsorted(self._starts, i, side="right") - 1)
        sh = self.shards[k]
        if sh.handle is None:
            sh.handle = open_shard_file(sh.path)
        return sh, sh.handle, i - sh.frame_start

    def __post_init__(self) -> None:
        # first frame of each shard, for the per-frame lookup in _locate (computed once)
        self._starts = np.array([s.frame_start for s in self.shards])

    def image(self, i: int, full_res: bool = False) -> np.ndarray:
        sh, h, j = self._locate(i)
        name = "images_full" if full_res else "images"
        if name not in h:
            raise DatasetError(f"{sh.path}: no '{name}' (render with --full-res to store them)")
        try:
            return h[name][j]
        except OSError as exc:
            raise DatasetError(f"{sh.path}: cannot read {name}[{j}] (damaged shard?): {exc}") from None

    def _table(self, group: str, i: int) -> dict:
        sh, h, j = self._locate(i)
        g = h[group]
        fields = STAR_FIELDS if group == "stars" else DETECTION_FIELDS
        try:
            if sh.major == 1:  # flat columns, rows of frame j at offsets[j]:offsets[j+1]
                lo, hi = g["offsets"][j : j + 2]
                return {k: g[k][lo:hi] for k in fields}
            return {k: np.asarray(g[k][j], dtype=spec[0]) for k, spec in fields.items()}
        except (OSError, KeyError) as exc:
            raise DatasetError(f"{sh.path}: cannot read {group} of frame {j} (damaged shard?): {exc}") from None

    def detections(self, i: int) -> dict:
        """Detections of frame ``i`` (brightest first): x_px, y_px, flux_adu, peak_adu, area_px, hip_id, star_index."""
        return self._table("detections", i)

    def true_stars(self, i: int) -> dict:
        """True stars projected into frame ``i``: hip_id, x_px, y_px, mag, bv, electrons."""
        return self._table("stars", i)

    def corruption_log(self, i: int) -> dict:
        sh, h, j = self._locate(i)
        raw = h["corruptions/log"][j]
        return json.loads(raw.decode() if isinstance(raw, bytes) else raw)

    def close(self) -> None:
        for sh in self.shards:
            if sh.handle is not None:
                sh.handle.close()
                sh.handle = None

    def __enter__(self) -> "Dataset":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["shards"] = [_Shard(s.path, s.frame_start, s.n_frames, s.major) for s in self.shards]
        return state


V2_FRAME_FIELDS = ("index_in_split", "frame_id")  # absent from schema 1.x shards


def _major(f: h5py.File) -> int:
    return int(str(f.attrs["schema_version"]).split(".")[0])


def _read_small(f: h5py.File, path: Path) -> tuple[dict, dict]:
    """Per-frame arrays (boresight labels, splits, counts), checked: dtype, shape, finite."""
    n = int(f.attrs["n_frames"])
    out = []
    frame_fields = (
        FRAME_FIELDS if _major(f) >= 2 else {k: v for k, v in FRAME_FIELDS.items() if k not in V2_FRAME_FIELDS}
    )
    for group, fields in (("boresight", BORESIGHT_FIELDS), ("frames", frame_fields)):
        arrays = {}
        for k, spec in fields.items():
            name = f"{group}/{k}"
            shape = (n, *spec[1]) if group == "boresight" else (n,)  # boresight specs carry a row shape
            try:
                d = f[name]
                if d.dtype != np.dtype(spec[0]) or d.shape != shape:
                    raise DatasetError(
                        f"{path}: '{name}' is {d.dtype}{d.shape}, expected "
                        f"{np.dtype(spec[0])}{shape}; the shard is damaged or foreign"
                    )
                arrays[k] = d[...]
            except KeyError:
                raise DatasetError(f"{path}: '{name}' is missing; the shard is damaged or foreign") from None
            except OSError as exc:
                raise DatasetError(f"{path}: '{name}' is unreadable ({exc}); re-render the shard") from None
            if arrays[k].dtype.kind == "f" and not np.all(np.isfinite(arrays[k])):
                raise DatasetError(
                    f"{path}: '{name}' holds NaN or infinite values; labels must be finite (re-render the shard)"
                )
        out.append(arrays)
    return out[0], out[1]


def _legacy_identity(fr: dict, config: dict) -> None:
    """Fill ``index_in_split`` and ``frame_id`` of a schema 1.x shard (frames keyed by global index)."""
    bounds = np.array((0, *split_bounds(int(config["n_frames"]), tuple(config["output"]["split_fractions"]))))
    fr["index_in_split"] = (fr["index"] - bounds[fr["split"].astype(np.int64)]).astype(np.int64)
    fr["frame_id"] = legacy_frame_ids(config, fr["index"])


def open_dataset(path: str | Path) -> Dataset:
    """Open a dataset folder (or a single shard file) for reading.

    Checks the manifest, each shard's format name and schema major version, and that
    each shard's size matches the manifest (a cheap truncation check; ``skygen
    validate`` also verifies checksums). Use as a context manager.

    Parameters
    ----------
    path : str or Path
        A folder written by ``skygen render`` or ``skygen merge`` (its ``manifest.json``), or one
        ``.h5`` shard.

    Returns
    -------
    Dataset
        Lazy: tables of every frame (``frames``, ``boresight`` in degrees, ICRS) are read at once,
        images (``image(i)``: uint16 ADU, ``[y, x]``), detections and true stars (pixels of the
        full-resolution sensor, ``(0.5, 0.5)`` the centre of the top-left pixel) on demand. HDF5
        files open in the process that reads them, so a ``Dataset`` can cross into DataLoader workers.

    Raises
    ------
    skygen.errors.DatasetError
        A missing or unfinished dataset, a foreign or truncated file, or a newer major schema
        version, each in one line that says what to do.
    """
    path = Path(path)
    if path.is_file():
        with open_shard_file(path) as f:
            config = json.loads(f.attrs["config"])
            n, start = int(f.attrs["n_frames"]), int(f.attrs["frame_start"])
            version = str(f.attrs["schema_version"])
        manifest = {
            "format": MANIFEST_FORMAT,
            "schema_version": version,
            "config": config,
            "shards": [{"file": path.name, "frame_start": start, "n_frames": n}],
        }
        root = path.parent
    elif path.is_dir():
        manifest = read_manifest(path)
        if not manifest.get("complete", False):
            raise DatasetError(
                f"{path}: the render has not finished ({len(manifest.get('shards', []))} of "
                f"{manifest.get('n_shards', '?')} shards); re-run the same `skygen render` "
                "command to resume it"
            )
        root = path
    else:
        raise DatasetError(f"{path}: no such dataset folder or shard file")
    shards, bores, frames = [], [], []
    for entry in manifest["shards"]:
        p = root / entry["file"]
        if "bytes" in entry:
            try:
                size = p.stat().st_size
            except FileNotFoundError:
                raise DatasetError(
                    f"{p}: shard listed in the manifest is missing; "
                    "re-run `skygen render` with the same arguments to restore it"
                ) from None
            if size != entry["bytes"]:
                raise DatasetError(
                    f"{p}: size {size} B differs from the manifest's {entry['bytes']} B "
                    "(truncated or replaced); delete it and re-run `skygen render` to resume"
                )
        with open_shard_file(p) as f:
            if int(f.attrs["n_frames"]) != entry["n_frames"]:
                raise DatasetError(f"{p}: holds {int(f.attrs['n_frames'])} frames, manifest says {entry['n_frames']}")
            b, fr = _read_small(f, p)
            major = _major(f)
            if major == 1:
                _legacy_identity(fr, json.loads(f.attrs["config"]))
        bores.append(b)
        frames.append(fr)
        shards.append(_Shard(p, -1, entry["n_frames"], major))
    start = 0
    for sh in shards:
        sh.frame_start = start
        start += sh.n_frames

    def cat(parts, k):
        return np.concatenate([p[k] for p in parts]) if parts else np.zeros(0)

    bore = {k: cat(bores, k) for k in BORESIGHT_FIELDS}
    frm = {k: cat(frames, k) for k in FRAME_FIELDS}
    return Dataset(root, manifest, shards, bore, frm)


# ----------------------------------------------------------------------- verified reads
def checksum_cache_path() -> Path:
    """Where verified shard checksums are remembered: ``$XDG_CACHE_HOME/skygen`` (default ~/.cache)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "skygen" / "verified-shards.json"


def verify_checksums(ds: Dataset, log=None) -> int:
    """Check every shard of ``ds`` against the sha256 in its manifest; returns how many were hashed.

    A shard verified before is not hashed again while its path, size, modification time
    and inode change time are unchanged (remembered in :func:`checksum_cache_path`). The
    change time (``st_ctime_ns``) is set by the kernel on every write and cannot be set
    back by ``os.utime`` or ``touch -d``, so a same-size edit with the mtime restored is
    hashed again. (A copy or restore from backup changes it too and costs one re-hash.)
    ``skygen validate`` does not use this cache: it always hashes. Raises DatasetError
    naming the first shard whose checksum differs.
    """
    cache_file = checksum_cache_path()
    try:
        cache = json.loads(cache_file.read_text())
        cache = cache if isinstance(cache, dict) else {}
    except (OSError, ValueError):
        cache = {}
    hashed = 0
    for sh, entry in zip(ds.shards, ds.manifest["shards"]):
        want = entry.get("sha256")
        if want is None:  # a single shard opened without a manifest: nothing to compare with
            continue
        st = sh.path.stat()
        key = f"{sh.path.resolve()}|{st.st_size}|{st.st_mtime_ns}|{st.st_ctime_ns}"
        if cache.get(key) == want:
            continue
        if log and hashed == 0:
            log(f"verifying sha256 of the shards of {ds.root} (once; remembered in {cache_file})")
        hashed += 1
        if sha256_file(sh.path) != want:
            raise DatasetError(
                f"{sh.path}: sha256 differs from {ds.root / MANIFEST_NAME} (the file changed or is "
                "corrupted); delete it and re-run the same `skygen render` to restore it"
            )
        cache[key] = want
    if hashed:
        try:
            cache_file.parent.mkdir(parents=True, exist_ok=True)
            write_json_atomic(cache_file, cache)
        except OSError:
            pass  # an unwritable cache only costs hashing again next time
    return hashed
