"""Dataset rendering: worker-count independence, resume after interruption, slices, safety."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from skygen.config import load_config
from skygen.datasets import build as dsmod
from skygen.datasets.build import render_dataset
from skygen.datasets.shards import open_dataset
from skygen.datasets.validate import validate
from skygen.errors import DatasetError


def contents(path):
    with open_dataset(path) as ds:
        return [
            (ds.image(i).tobytes(), ds.detections(i)["x_px"].tobytes(), ds.true_stars(i)["hip_id"].tobytes())
            for i in range(len(ds))
        ], dict(ds.boresight)


def same_data(a, b) -> bool:
    ca, ba = contents(a)
    cb, bb = contents(b)
    return ca == cb and all(np.array_equal(ba[k], bb[k]) for k in ba)


def test_workers_do_not_change_frames(tmp_path, small_overrides, small_dataset):
    cfg = load_config(overrides=small_overrides + ["n_frames=50"])
    render_dataset(cfg, tmp_path / "w2", workers=2, progress=False)
    assert same_data(small_dataset, tmp_path / "w2")
    assert validate(tmp_path / "w2").ok


def test_resume_after_interrupt_is_identical(tmp_path, small_overrides, small_dataset, monkeypatch):
    cfg = load_config(overrides=small_overrides + ["n_frames=50"])
    real = dsmod._render_shard
    calls = {"n": 0}

    def flaky(task):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(task)

    monkeypatch.setattr(dsmod, "_render_shard", flaky)
    with pytest.raises(KeyboardInterrupt):
        render_dataset(cfg, tmp_path / "r", workers=1, progress=False)
    man = json.loads((tmp_path / "r" / "manifest.json").read_text())
    assert not man["complete"] and len(man["shards"]) == 1
    assert not list((tmp_path / "r").glob(".*tmp*"))  # no half-written file left
    with pytest.raises(DatasetError, match="has not finished"):
        open_dataset(tmp_path / "r")
    monkeypatch.setattr(dsmod, "_render_shard", real)
    render_dataset(cfg, tmp_path / "r", workers=1, progress=False)
    assert same_data(small_dataset, tmp_path / "r")


def test_sigkill_then_resume(tmp_path, small_overrides, small_dataset):
    """A real render process killed with SIGKILL, then resumed, gives identical frames."""
    out = tmp_path / "k"
    args = [sys.executable, "-m", "skygen.cli", "render", "--quiet", "--workers", "1", "--out", str(out), "--n", "50"]
    args += sum((["--set", o] for o in small_overrides), [])
    proc = subprocess.Popen(args)
    deadline = time.time() + 60
    while time.time() < deadline and not list(out.glob("shard-*.h5")):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert subprocess.run(args).returncode == 0
    assert same_data(small_dataset, out)
    assert validate(out).ok


def test_slices_combine_into_one_dataset(tmp_path, small_overrides, small_dataset):
    cfg = load_config(overrides=small_overrides + ["n_frames=50"])
    for i in range(3):
        man = render_dataset(cfg, tmp_path / "s", workers=1, slice_index=i, num_slices=3, progress=False)
    assert man["complete"] and (tmp_path / "s" / "manifest.json").exists()
    assert same_data(small_dataset, tmp_path / "s")


def test_slices_rendered_at_once_into_one_folder(tmp_path, small_overrides, small_dataset):
    """The documented job-array use: each slice locks only itself; the combine step is serialised."""
    out = tmp_path / "s"
    base = [sys.executable, "-m", "skygen.cli", "render", "--quiet", "--workers", "1", "--out", str(out), "--n", "50"]
    base += sum((["--set", o] for o in small_overrides), [])
    procs = [subprocess.Popen(base + ["--slice", f"{i}/3"], stderr=subprocess.PIPE, text=True) for i in range(3)]
    errs = [p.communicate(timeout=120)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0], errs
    assert validate(out).ok and same_data(small_dataset, out)
    assert not list(out.glob(".skygen*"))  # every lock released


def test_other_dataset_in_folder_is_not_overwritten(tmp_path, small_overrides):
    cfg = load_config(overrides=small_overrides + ["n_frames=20"])
    render_dataset(cfg, tmp_path / "d", progress=False)
    before = sorted(p.stat().st_mtime_ns for p in (tmp_path / "d").iterdir())
    other = load_config(overrides=small_overrides + ["n_frames=20", "sensor.exposure_s=0.2"])
    with pytest.raises(DatasetError, match="sensor.exposure_s"):
        render_dataset(other, tmp_path / "d", progress=False)
    assert sorted(p.stat().st_mtime_ns for p in (tmp_path / "d").iterdir()) == before
    render_dataset(other, tmp_path / "d", progress=False, force=True)
    with open_dataset(tmp_path / "d") as ds:
        assert ds.config["sensor"]["exposure_s"] == 0.2


def test_disk_full_leaves_existing_dataset_untouched(tmp_path, small_overrides, monkeypatch):
    import errno

    cfg = load_config(overrides=small_overrides + ["n_frames=40"])
    out = tmp_path / "full"
    render_dataset(cfg, out, progress=False)
    (out / "shard-00001.h5").unlink()  # force one shard to be rendered again
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def no_space(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(dsmod, "write_shard", no_space)
    with pytest.raises(DatasetError, match="No space left"):
        render_dataset(cfg, out, progress=False)
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert after.keys() == before.keys() and after["shard-00000.h5"] == before["shard-00000.h5"]


def _enospc_after(n_ok: int, monkeypatch, module, name: str, partial: bool):
    """Make ``module.name`` fail with ENOSPC from its (n_ok + 1)-th call on, after writing half the bytes."""
    import errno

    real = getattr(module, name)
    calls = {"n": 0}

    def full_disk(path, data, *a, **k):
        calls["n"] += 1
        if calls["n"] <= n_ok:
            return real(path, data, *a, **k)
        if partial:
            Path(path).write_bytes(bytes(data[: len(data) // 2]))
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(module, name, full_disk)


@pytest.mark.parametrize("where", ["shard", "manifest"])
def test_a_full_disk_stops_with_one_line_and_a_rerun_resumes(
    tmp_path, small_overrides, small_dataset, capsys, monkeypatch, where
):
    """Issue 21: ENOSPC printed its line, then the interpreter crashed in HDF5's teardown (exit 139)."""
    from skygen.cli import main
    from skygen.datasets import shards as skio
    from skygen.errors import SkygenError

    out = tmp_path / "full"
    args = ["render", "--n", "50", "--out", str(out), "--workers", "1", "--quiet"]
    args += sum((["--set", o] for o in small_overrides), [])
    if where == "shard":  # the shard writer runs out of space half-way through its third shard
        _enospc_after(2, monkeypatch, skio, "_write_bytes", partial=True)
    else:  # the manifest after the second shard cannot be written
        _enospc_after(2, monkeypatch, dsmod, "write_json_atomic", partial=False)
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "the disk is full" in err and "run the same command again" in err
    with pytest.raises(SkygenError, match="the disk is full"):
        render_dataset(load_config(overrides=small_overrides + ["n_frames=50"]), out, progress=False)
    shards = sorted(out.glob("shard-*.h5"))
    assert shards and all(validate(p).ok for p in shards)  # whatever is named shard-*.h5 is whole
    assert not list(out.glob(".*tmp*"))
    assert not json.loads((out / "manifest.json").read_text())["complete"]
    monkeypatch.undo()  # space freed
    assert main(args) == 0
    assert validate(out).ok and same_data(small_dataset, out)


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores folder permissions")
def test_read_only_output_folder(tmp_path, small_overrides):
    out = tmp_path / "ro"
    out.mkdir()
    out.chmod(0o500)
    try:
        with pytest.raises(DatasetError, match="cannot write"):
            render_dataset(load_config(overrides=small_overrides + ["n_frames=5"]), out, progress=False)
    finally:
        out.chmod(0o700)


def test_splits_are_contiguous_and_complete(small_dataset):
    with open_dataset(small_dataset) as ds:
        assert len(ds.indices("train")) == 40 and len(ds.indices("val")) == 5 and len(ds.indices("test")) == 5
        assert ds.indices("test").min() > ds.indices("val").max() > ds.indices("train").max()


def test_merge_slices_from_separate_folders(tmp_path, small_overrides, small_dataset):
    from skygen.datasets.merge import merge_datasets

    cfg = load_config(overrides=small_overrides + ["n_frames=50"])
    for i in range(2):
        render_dataset(cfg, tmp_path / f"part{i}", workers=1, slice_index=i, num_slices=2, progress=False)
    merge_datasets([tmp_path / "part0", tmp_path / "part1"], tmp_path / "all")
    assert same_data(small_dataset, tmp_path / "all")
    assert validate(tmp_path / "all").ok
    with pytest.raises(DatasetError, match="given twice"):
        merge_datasets([tmp_path / "part0", tmp_path / "part0"], tmp_path / "half")


def test_merge_compatible_datasets_and_refuse_others(tmp_path, small_overrides, small_dataset):
    from skygen.datasets.merge import merge_datasets

    render_dataset(load_config(overrides=small_overrides + ["n_frames=30", "seed=7"]), tmp_path / "b", progress=False)
    man = merge_datasets([small_dataset, tmp_path / "b"], tmp_path / "ab")
    assert man["n_frames"] == 80 and len(man["sources"]) == 2
    assert validate(tmp_path / "ab").ok
    with open_dataset(tmp_path / "ab") as ds:
        assert len(ds) == 80 and len(ds.indices("train")) == 40 + 24
    render_dataset(
        load_config(overrides=small_overrides + ["n_frames=20", "sensor.gain_e_per_adu=2"]),
        tmp_path / "c",
        progress=False,
    )
    with pytest.raises(DatasetError, match="sensor.gain_e_per_adu"):
        merge_datasets([small_dataset, tmp_path / "c"], tmp_path / "ac")


def test_skygen_reads_without_torch(small_dataset):
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "from skygen.datasets.shards import open_dataset; from skygen.datasets.validate import validate\n"
        f"ds = open_dataset({str(small_dataset)!r}); ds.image(3); assert validate({str(small_dataset)!r}).ok\n"
    )
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


@pytest.mark.slow
def test_ten_sigkills_then_resume(tmp_path, small_overrides):
    """Kill `skygen render` with SIGKILL at random moments ten times, resuming each time."""
    out = tmp_path / "kills"
    args = [sys.executable, "-m", "skygen.cli", "render", "--quiet", "--workers", "2", "--out", str(out), "--n", "400"]
    args += sum((["--set", o] for o in small_overrides), [])
    rng = np.random.default_rng(0)
    for _ in range(10):
        proc = subprocess.Popen(args)
        time.sleep(rng.uniform(0.5, 3.0))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert not any(p.name.startswith("shard-") and p.suffix != ".h5" for p in out.glob("*"))
    assert subprocess.run(args).returncode == 0
    ref = tmp_path / "ref"
    render_dataset(load_config(overrides=small_overrides + ["n_frames=400"]), ref, workers=2, progress=False)
    assert same_data(ref, out) and validate(out).ok


def test_merge_refuses_datasets_that_share_frames(tmp_path, small_overrides, small_dataset, capsys):
    """Seed 0 with --n 50 and --n 30: the same frames within each split (frame_id equal), so a
    merged dataset would hold them twice; skygen merge refuses, naming the fix."""
    from skygen.cli import main
    from skygen.identity import dataset_frame_ids

    render_dataset(load_config(overrides=small_overrides + ["n_frames=30"]), tmp_path / "b", progress=False)
    assert main(["merge", str(small_dataset), str(tmp_path / "b"), "--out", str(tmp_path / "ab")]) == 2
    err = capsys.readouterr().err
    assert "are the same frames" in err and "another --seed" in err
    assert not (tmp_path / "ab" / "manifest.json").exists()
    with open_dataset(small_dataset) as a, open_dataset(tmp_path / "b") as b:
        shared = np.intersect1d(a.frames["frame_id"], b.frames["frame_id"])
        assert len(shared) == 24 + 3 + 3  # b's whole train, val and test splits
        for split in ("train", "val", "test"):  # never across splits
            ia, ib = a.indices(split), b.indices(split)
            assert np.array_equal(a.image(int(ia[0])), b.image(int(ib[0])))
        assert np.array_equal(dataset_frame_ids(a.config), a.frames["frame_id"])  # ids follow from the config
