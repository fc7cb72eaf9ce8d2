"""Output-folder locks (skygen.lock): a second writer is refused naming the first."""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from skygen.datasets.build import _render_lock
from skygen.errors import DatasetError, FolderInUseError
from skygen.lock import FolderLock, lock_path

ROOT = Path(__file__).resolve().parents[1]


def test_a_second_lock_is_refused_naming_the_holder(tmp_path):
    with FolderLock(tmp_path, what="skygen render") as first:
        assert first.held and lock_path(tmp_path).exists()
        with pytest.raises(FolderInUseError) as exc:
            FolderLock(tmp_path, what="skygen merge").acquire()
        msg = str(exc.value)
        assert isinstance(exc.value, DatasetError) and len(msg.splitlines()) == 1
        assert f"is in use by skygen render (PID {os.getpid()} on {socket.gethostname()}" in msg
        assert "wait for it to finish" in msg
    assert not lock_path(tmp_path).exists()  # released: the file is gone
    with FolderLock(tmp_path):  # and the folder can be locked again
        pass


def _lock_left_by_a_dead_process(folder: Path) -> int:
    code = (
        "import os, sys; from skygen.lock import FolderLock; "
        f"FolderLock({str(folder)!r}, what='skygen render').acquire(); os._exit(0)"
    )
    p = subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert p.returncode == 0
    return json.loads(lock_path(folder).read_text())["pid"]


def test_a_lock_left_by_a_dead_process_is_taken_over_with_a_line(tmp_path):
    dead = _lock_left_by_a_dead_process(tmp_path)
    lines = []
    with FolderLock(tmp_path, what="skygen render", log=lines.append):
        assert json.loads(lock_path(tmp_path).read_text())["pid"] == os.getpid()
    assert len(lines) == 1 and "took over the lock" in lines[0] and f"PID {dead} " in lines[0]
    assert "no longer running" in lines[0]
    assert not lock_path(tmp_path).exists()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads process start times from /proc")
def test_a_reused_pid_does_not_keep_a_lock(tmp_path):
    info = {
        "what": "skygen render",
        "host": socket.gethostname(),
        "pid": os.getppid(),
        "start_ticks": "1",
        "command": "skygen render",
        "started_utc": "2000-01-01T00:00:00Z",
        "shares": None,
        "token": "x",
    }
    lock_path(tmp_path).write_text(json.dumps(info))  # the PID runs, but is not the process that locked
    lines = []
    with FolderLock(tmp_path, log=lines.append):
        pass
    assert "took over" in lines[0]


def test_a_lock_from_another_host_is_never_taken_over(tmp_path):
    info = {
        "what": "skygen render --slice 1/4",
        "host": "node-17.elsewhere",
        "pid": 4242,
        "command": "skygen render",
        "started_utc": "2026-01-01T00:00:00Z",
        "shares": None,
        "token": "x",
    }
    lock_path(tmp_path).write_text(json.dumps(info))
    with pytest.raises(
        FolderInUseError,
        match=r"PID 4242 on node-17\.elsewhere.*if that job is no longer running, "
        r"delete .*\.skygen\.lock",
    ):
        FolderLock(tmp_path).acquire()
    assert lock_path(tmp_path).exists()


def test_release_leaves_a_lock_that_is_not_its_own(tmp_path):
    lock = FolderLock(tmp_path).acquire()
    lock_path(tmp_path).write_text(json.dumps({"pid": 1, "token": "someone else"}))
    lock.release()
    assert lock_path(tmp_path).exists()


def test_slices_of_one_job_array_share_a_folder_and_nothing_else_does(tmp_path):
    with _render_lock(tmp_path, 0, 3, None):
        with _render_lock(tmp_path, 1, 3, None):  # another slice of the same array: runs
            pass
        for i, k in ((0, 3), (0, 1), (1, 2)):  # the same slice, no slicing, other K: same shards
            with pytest.raises(FolderInUseError, match=r"in use by skygen render --slice 0/3 \(PID"):
                _render_lock(tmp_path, i, k, None).acquire()
        with pytest.raises(FolderInUseError):
            FolderLock(tmp_path, what="skygen merge").acquire()
    assert not list(tmp_path.iterdir())  # every refused attempt removed its own file


def test_an_unreadable_lock_is_refused_then_expires(tmp_path):
    lock_path(tmp_path).write_text("")
    with pytest.raises(FolderInUseError, match="empty or damaged"):
        FolderLock(tmp_path).acquire()
    os.utime(lock_path(tmp_path), (1, 1))  # a leftover of a process that died while creating it
    with FolderLock(tmp_path, log=lambda m: None):
        pass
