"""Render a whole dataset: shards, manifest, parallel workers, resume and slices.

Frame i always comes from ``Renderer(cfg).render(i)``, so a dataset is identical
whatever the number of workers, the slicing, or how often it was interrupted. With
``render.backend=torch`` frames are rasterised in device batches of ``render.batch_size``
that start at fixed indices within each shard (:mod:`skygen.render.torch_frames`), so the same
holds on one device type; detection runs on the host as for the NumPy backend.

Progress is recorded in the manifest after every finished shard. A re-run with the same
config skips shards whose file matches the recorded sha256 and renders the rest. A
render sliced for a job array (``slice_index`` of ``num_slices``) writes its own
``manifest.slice-I-of-K.json``; when the last slice finishes, ``manifest.json`` for
the whole dataset is written.

A render holds a lock on its output folder (:mod:`skygen.lock`): the whole folder
without slices; only its own slice with slices, so the slices of a job array share one
folder, and the step combining their manifests runs one slice at a time.
"""

from __future__ import annotations

import errno
import json
import multiprocessing as mp
import os
import re
import time
from pathlib import Path

from skygen.config import RenderConfig, config_dict
from skygen.configlib import flatten
from skygen.datasets.card import CARD_NAME, CROISSANT_NAME, write_card
from skygen.datasets.shards import (
    MANIFEST_FORMAT,
    MANIFEST_NAME,
    SCHEMA_VERSION,
    SPLIT_NAMES,
    config_id,
    library_versions,
    sha256_file,
    shard_name,
    write_json_atomic,
    write_shard,
)
from skygen.errors import ConfigError, DatasetError
from skygen.identity import content_id
from skygen.instrument import corruptions as corr
from skygen.lock import FolderLock
from skygen.runtime import check_stop


def shard_ranges(n_frames: int, shard_size: int) -> list[tuple[int, int]]:
    return [(s, min(s + shard_size, n_frames)) for s in range(0, n_frames, shard_size)]


def config_differences(a: dict, b: dict) -> list[str]:
    """Dotted keys whose values differ between two config dicts."""
    fa, fb = flatten(a), flatten(b)
    return sorted(k for k in set(fa) | set(fb) if fa.get(k, "<missing>") != fb.get(k, "<missing>"))


def _manifests(out: Path) -> list[tuple[Path, dict]]:
    found = []
    for p in sorted(out.glob("manifest*.json")):
        try:
            found.append((p, json.loads(p.read_text())))
        except (OSError, ValueError):
            raise DatasetError(
                f"{p} is unreadable; delete it (its shards will be checked and re-used) and run the same command again"
            ) from None
    return found


def _same_but_newer_keys(old: dict, new: dict) -> bool:
    """The same frames, ``old`` written before keys that :data:`skygen.identity.NEUTRAL_DEFAULTS` lists were
    added (e.g. ``catalog.source``): a render made before them resumes."""
    import copy

    from skygen.identity import drop_neutral

    return not config_differences(drop_neutral(copy.deepcopy(old)), drop_neutral(copy.deepcopy(new)))


def _check_compatible(out: Path, cfg_dict: dict, force: bool) -> list[dict]:
    """Shard entries recorded by earlier runs of the same config in ``out``."""
    entries = []
    for path, man in _manifests(out):
        if man.get("format") != MANIFEST_FORMAT:
            raise DatasetError(f"{path} is not a skygen manifest; choose another --out folder")
        if man.get("dataset_id") != config_id(cfg_dict) and not _same_but_newer_keys(man.get("config", {}), cfg_dict):
            if force:
                continue
            diff = config_differences(man.get("config", {}), cfg_dict)
            raise DatasetError(
                f"{out} already holds a different dataset (config keys differ: "
                f"{', '.join(diff[:12]) or 'schema'}). Use another --out folder, or --force "
                "to replace it."
            )
        entries += man.get("shards", [])
    return entries


def _clean_temporaries(out: Path, shards: list[int] | None = None, manifest: str | None = None) -> None:
    """Remove hidden temporaries left by an interrupted write: all of them, or (a slice rendering
    beside other slices) only those of its ``shards`` and its ``manifest``."""
    if shards is None:
        found = [*out.glob(".shard-*.h5.tmp*"), *out.glob(".manifest*.json.tmp*")]
    else:
        found = [p for k in shards for p in out.glob(f".{shard_name(k)}.tmp*")]
        found += list(out.glob(f".{manifest}.tmp*")) if manifest else []
    for p in found:
        p.unlink(missing_ok=True)


def write_failed(exc: OSError, what: Path) -> DatasetError:
    """The one-line error for a failed write of ``what`` (a shard, manifest or card).

    A full disk (ENOSPC, or EDQUOT: over quota) says so and how to go on: the shards
    already renamed into place are whole and recorded, so the same command resumes."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        why = "the disk is full" if exc.errno == errno.ENOSPC else "the disk quota is exceeded"
        return DatasetError(
            f"cannot write {what}: {why} ({exc.strerror}); free space on the disk holding "
            f"{what.parent} and run the same command again to resume (finished shards are kept)"
        )
    return DatasetError(f"cannot write {what}: {exc.strerror or exc}")


def _manifest(cfg_dict: dict, entries: list[dict], n_shards: int, complete: bool, extra: dict) -> dict:
    entries = sorted(entries, key=lambda e: e["index"])
    splits = {s: sum(e["splits"][s] for e in entries) for s in SPLIT_NAMES}
    return {
        "format": MANIFEST_FORMAT,
        "schema_version": SCHEMA_VERSION,
        "dataset_id": config_id(cfg_dict),
        "content_id": content_id(cfg_dict),
        "complete": complete,
        "n_frames": sum(e["n_frames"] for e in entries),
        "n_shards": n_shards,
        "splits": splits,
        "shards": entries,
        "config": cfg_dict,
        "versions": library_versions(),
        "updated_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **extra,
    }


# ----------------------------------------------------------------------- workers
_WORKER: dict = {}


def _exit_when_orphaned(parent_pid: int, interval_s: float = 0.2) -> None:
    """In a pool worker: a daemon thread that ends the process once its parent is gone.

    After a kill -9 of ``skygen render`` the pool's workers would otherwise live on
    (re-parented to init) and keep writing shards. Exiting leaves at most a hidden
    ``.shard-*.h5.tmp*`` file, which the next run removes.
    """
    import threading

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(interval_s)
        os._exit(1)

    threading.Thread(target=watch, name="skygen-parent-watch", daemon=True).start()


def _init_worker(cfg: RenderConfig, counter, parent_pid: int | None = None, threads: int | None = 1) -> None:
    import signal

    import cv2

    cv2.setNumThreads(1)
    if parent_pid is not None:  # a pool worker: the parent handles Ctrl-C and SIGTERM, and may die
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        _exit_when_orphaned(parent_pid)
    from skygen.render.frame import Renderer

    _WORKER["renderer"] = Renderer(cfg)
    _WORKER["counter"] = counter
    _WORKER.pop("torch", None)
    if cfg.render.backend == "torch":
        import torch

        from skygen.render.torch_frames import TorchRenderer

        if threads:  # pool workers: one thread each, as cv2
            torch.set_num_threads(threads)
        _WORKER["torch"] = TorchRenderer(cfg, renderer=_WORKER["renderer"])


def _frames(start: int, stop: int):
    """Frames start..stop-1: one by one (NumPy) or in device batches of render.batch_size
    (torch; batches start at multiples of the batch size within the shard, so a frame's
    noise depends only on (config, index))."""
    r = _WORKER["renderer"]
    tr = _WORKER.get("torch")
    if tr is None:
        for i in range(start, stop):
            check_stop()  # a SIGTERM whose exception Python swallowed still stops the job
            yield r.render(i)
        return
    bs = r.cfg.render.batch_size
    for a in range(start, stop, bs):
        yield from tr.frames(tr.render_batch(range(a, min(a + bs, stop)), full_res=True))


def _render_shard(args: tuple[int, int, int, str]) -> dict:
    k, start, stop, out = args
    r = _WORKER["renderer"]
    counter = _WORKER.get("counter")
    frames = []
    for frame in _frames(start, stop):
        frames.append(frame)
        if counter is not None:
            with counter.get_lock():
                counter.value += 1
    o = r.cfg.output
    try:
        return write_shard(
            Path(out) / shard_name(k),
            frames,
            config=config_dict(r.cfg),
            shard_index=k,
            frame_start=start,
            compression=o.compression,
            compression_level=o.compression_level,
            corruption_names=tuple(corr.REGISTRY),
        )
    except OSError as exc:
        raise write_failed(exc, Path(out) / shard_name(k)) from None


def render_dataset(
    cfg: RenderConfig,
    out: str | Path,
    workers: int = 1,
    slice_index: int = 0,
    num_slices: int = 1,
    force: bool = False,
    progress: bool = True,
    warn=None,
) -> dict:
    """Render (or resume) the dataset of ``cfg`` into folder ``out``; returns the manifest.

    Raises DatasetError when ``out`` holds a different dataset (unless ``force``) or a
    shard cannot be written (a full disk included); FolderInUseError when another render
    or merge is writing ``out`` (other slices of the same job array may); ConfigError for
    more slices than shards. Interrupting leaves only whole shards and a valid manifest.
    ``warn`` (default: print to stderr) receives warnings about the physics, e.g. an
    exposure that saturates every pixel. Also writes the dataset card (README.md and
    croissant.json, :mod:`skygen.datasets.card`) once the dataset is complete.
    """
    import sys

    from skygen.render.frame import Renderer

    warn = warn or (lambda msg: print(msg, file=sys.stderr))
    if workers < 1:
        raise ConfigError(f"--workers {workers}: need at least 1 worker process")
    if not 0 <= slice_index < num_slices:
        raise DatasetError(f"slice {slice_index} is not in 0..{num_slices - 1}")
    n_shards = len(shard_ranges(cfg.n_frames, cfg.output.shard_size))
    if num_slices > n_shards:  # some slices would render nothing and exit 0: refuse them all, up front
        size = -(-cfg.n_frames // num_slices)
        raise ConfigError(
            f"--slice {slice_index}/{num_slices}: slices are whole shards of output.shard_size="
            f"{cfg.output.shard_size} frames, and {cfg.n_frames} frames make {n_shards} shard(s), so "
            f"this --n allows at most {n_shards} slice(s); use K <= {n_shards}, or --set "
            f"output.shard_size={size} for {num_slices} slices"
        )
    if cfg.render.backend == "torch":  # fail before any work if the device is not usable
        from skygen.render.torch_frames import resolve_device

        resolve_device(cfg.render.device)
    probe_renderer = Renderer(cfg)  # refuses configs it cannot render (ConfigError) before any file is made
    for message in (
        probe_renderer.saturation_warning(),
        probe_renderer.sparse_warning(),
        probe_renderer.depth_warning(),
    ):
        if message:
            warn(f"warning: {message}")
    extra = {
        "detection_limit_mag": round(probe_renderer.detection_limit_mag, 4),
        "mag_limit": round(probe_renderer.mag_limit, 4),
        "stars_in_catalog_index": len(probe_renderer.sky),
        "catalog": probe_renderer.sky.table.source,
        "shard_size": cfg.output.shard_size,
    }
    del probe_renderer
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-test-{os.getpid()}"
        probe.touch()
        probe.unlink()
    except OSError as exc:
        raise DatasetError(f"cannot write to output folder {out}: {exc.strerror or exc}") from None
    try:
        with _render_lock(out, slice_index, num_slices, warn):
            return _render_into(cfg, out, workers, slice_index, num_slices, force, progress, extra, warn)
    except DatasetError:
        raise
    except OSError as exc:  # a manifest, card or shard could not be written: disk full, quota, I/O error
        raise write_failed(exc, Path(exc.filename) if exc.filename else out) from None


def _render_into(
    cfg: RenderConfig,
    out: Path,
    workers: int,
    slice_index: int,
    num_slices: int,
    force: bool,
    progress: bool,
    extra: dict,
    warn,
) -> dict:
    """render_dataset once its arguments are checked, ``out`` exists and this render holds its lock."""
    cfg_dict = config_dict(cfg)
    ranges = shard_ranges(cfg.n_frames, cfg.output.shard_size)
    mine = [k for k in range(len(ranges)) if k % num_slices == slice_index]
    name = MANIFEST_NAME if num_slices == 1 else f"manifest.slice-{slice_index}-of-{num_slices}.json"
    recorded = _check_compatible(out, cfg_dict, force)
    if force:
        _remove_other_dataset(out, cfg_dict, recorded, set(mine), len(ranges), num_slices)
    own = None if num_slices == 1 else mine  # concurrent slices: touch only this slice's temporaries
    _clean_temporaries(out, own, name)
    done = {}
    for e in recorded:
        p = out / e["file"]
        if (
            e["index"] in mine
            and e["index"] not in done
            and p.exists()
            and p.stat().st_size == e["bytes"]
            and sha256_file(p) == e["sha256"]
        ):
            done[e["index"]] = e
    todo = [k for k in mine if k not in done]

    def save(complete: bool) -> dict:
        man = _manifest(cfg_dict, list(done.values()), len(ranges), complete, extra)
        write_json_atomic(out / name, man)
        return man

    save(not todo)
    n_todo = sum(ranges[k][1] - ranges[k][0] for k in todo)
    bar = None
    if progress and n_todo:
        from tqdm import tqdm

        bar = tqdm(total=n_todo, unit="frame", desc=f"render {out}", smoothing=0.1)
    tasks = [(k, ranges[k][0], ranges[k][1], str(out)) for k in todo]
    try:
        if workers <= 1 or len(tasks) <= 1:
            _init_worker(cfg, None, None, threads=None)
            for t in tasks:
                done[t[0]] = _render_shard(t)
                save(False)
                if bar:
                    bar.update(t[2] - t[1])
        else:
            _run_pool(cfg, tasks, workers, done, save, bar)
    except BaseException:
        _clean_temporaries(out, own, name)
        raise
    finally:
        if bar:
            bar.close()
    man = save(True)
    if num_slices == 1:
        write_card(out, man)
        return man
    # the one step that reads and writes files of every slice: one slice at a time (waits, does not fail)
    with FolderLock(
        out,
        what=f"skygen render --slice {slice_index}/{num_slices} (combining the slice manifests)",
        name="render-finish",
        shares=_slice_group(num_slices),
        wait_s=120,
        log=warn,
    ):
        for p in out.glob("." + MANIFEST_NAME + ".tmp*"):  # left by a combine that was cut short
            p.unlink(missing_ok=True)
        man = _maybe_combine_slices(out, cfg_dict, len(ranges), extra) or man
        if man.get("complete") and (out / MANIFEST_NAME).exists():
            write_card(out, json.loads((out / MANIFEST_NAME).read_text()))
    return man


def _slice_group(num_slices: int) -> str:
    """The lock share group of the slices of a K-slice job array (:mod:`skygen.lock`)."""
    return f"render-slices-of-{num_slices}"


def _render_lock(out: Path, slice_index: int, num_slices: int, warn) -> FolderLock:
    """Without --slice the whole folder; with --slice I/K only slice I (other slices of K run beside it)."""
    if num_slices == 1:
        return FolderLock(out, what="skygen render", log=warn)
    return FolderLock(
        out,
        what=f"skygen render --slice {slice_index}/{num_slices}",
        name=f"render-slice-{slice_index}-of-{num_slices}",
        shares=_slice_group(num_slices),
        log=warn,
    )


def _remove_other_dataset(
    out: Path, cfg_dict: dict, recorded: list[dict], mine: set[int], n_shards: int, num_slices: int
) -> None:
    """--force: delete the manifests, unrecorded shards and card of the dataset being replaced.

    A slice deletes only unrecorded shard files of its own indices (or beyond this
    dataset's last shard): another slice of the same job array may have just renamed its
    shard into place and not yet recorded it."""
    for path, man in _manifests(out):
        if man.get("dataset_id") != config_id(cfg_dict):
            path.unlink(missing_ok=True)  # another slice with --force may have been first
    keep = {e["file"] for e in recorded}
    for p in out.glob("shard-*.h5"):
        m = re.fullmatch(r"shard-(\d+)\.h5", p.name)
        k = int(m.group(1)) if m else -1
        if p.name not in keep and (num_slices == 1 or k in mine or k >= n_shards or k < 0):
            p.unlink(missing_ok=True)
    if not recorded:  # the card described the replaced dataset; a new one comes with completion
        for name in (CARD_NAME, CROISSANT_NAME):
            (out / name).unlink(missing_ok=True)


def _run_pool(cfg, tasks, workers, done, save, bar) -> None:
    ctx = mp.get_context("spawn")
    counter = ctx.Value("q", 0)
    seen = 0
    with ctx.Pool(min(workers, len(tasks)), initializer=_init_worker, initargs=(cfg, counter, os.getpid())) as pool:
        pending = [pool.apply_async(_render_shard, (t,)) for t in tasks]
        try:
            while pending:
                time.sleep(0.2)
                check_stop()
                for res in [p for p in pending if p.ready()]:
                    pending.remove(res)
                    entry = res.get()  # re-raises a worker's exception
                    done[entry["index"]] = entry
                    save(False)
                if bar:
                    now = counter.value
                    bar.update(now - seen)
                    seen = now
        except BaseException:
            pool.terminate()
            raise


def _maybe_combine_slices(out: Path, cfg_dict: dict, n_shards: int, extra: dict) -> dict | None:
    entries = {}
    for path, man in _manifests(out):
        if path.name != MANIFEST_NAME and man.get("dataset_id") == config_id(cfg_dict):
            for e in man["shards"]:
                entries[e["index"]] = e
    if len(entries) < n_shards:
        return None
    man = _manifest(cfg_dict, list(entries.values()), n_shards, True, extra)
    write_json_atomic(out / MANIFEST_NAME, man)
    return man
