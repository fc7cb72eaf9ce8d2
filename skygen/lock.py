"""Output-folder locks: one writer of a folder at a time, a clear line for the second.

Two ``skygen render`` runs into one folder both exited 0 and left an invalid dataset
about one time in four (issue 21): each recorded its own checksum for shards the other
then replaced. :class:`FolderLock` is a lock file in the output folder, created
atomically (``O_CREAT | O_EXCL``), holding JSON: what holds it, host, PID, the command
line and the start time. A second writer is refused with one line naming the first
(:class:`~skygen.errors.FolderInUseError`). A lock left by a process that is gone
(killed with ``kill -9``, a crashed node) is taken over when that can be known: same
host and the PID no longer runs (or now belongs to a newer process) — with a line saying
so. A lock from another host is never taken over (its PID means nothing here); the
message names the file to delete once that job is known to be gone.

What is locked, and why not always the whole folder
---------------------------------------------------
A lock is a name plus an optional *share group*. Locks of different names coexist only
if both carry the same non-empty ``shares`` group; any other live lock in the folder is
a conflict. The check is "create mine, then look at the others", so two conflicting
writers starting together can both be refused, but never both proceed.

* ``skygen render`` without ``--slice``, ``skygen merge`` (and fusion's output folders,
  later): one exclusive lock, ``.skygen.lock``.
* ``skygen render --slice I/K``: slices of a job array render *concurrently into one
  shared folder* — the documented use — and write disjoint shards (index mod K = I) and
  their own ``manifest.slice-I-of-K.json``. So each slice locks only itself
  (``.skygen.render-slice-I-of-K.lock``, group ``render-slices-of-K``): the same slice
  twice is refused, other slices of the same K run, and a render with another K or
  without ``--slice`` (which would write the same shards) is refused. The one step that
  touches files of all slices — combining the slice manifests into ``manifest.json``
  and writing the dataset card — takes a short second lock (``render-finish``, same
  group) and waits for it rather than failing.

Use::

    with FolderLock(out, what="fusion train"):
        ...                       # nothing else that locks `out` runs meanwhile
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
import uuid
from pathlib import Path

from skygen.errors import FolderInUseError

PREFIX = ".skygen"
SUFFIX = ".lock"
#: A lock file that is still empty or unreadable after this long is a leftover of a
#: process that died between creating and writing it.
UNREADABLE_STALE_S = 10.0


def lock_path(folder: str | Path, name: str = "") -> Path:
    """``folder/.skygen.lock``, or ``folder/.skygen.NAME.lock``."""
    return Path(folder) / (f"{PREFIX}.{name}{SUFFIX}" if name else PREFIX + SUFFIX)


def read_lock(path: Path) -> dict | None:
    """The holder recorded in lock file ``path``; None if there is no such file; a dict
    with ``unreadable: True`` and ``age_s`` if it is empty or not JSON (being written, or damaged)."""
    try:
        text = path.read_text()
        age = time.time() - path.stat().st_mtime
    except FileNotFoundError:
        return None
    except OSError:
        return {"unreadable": True, "age_s": 0.0}
    try:
        info = json.loads(text)
        if isinstance(info, dict) and isinstance(info.get("pid"), int):
            return info
    except ValueError:
        pass
    return {"unreadable": True, "age_s": age}


def _proc_stat(pid: int) -> tuple[str, str] | None:
    """(state, start time in clock ticks since boot) of process ``pid`` from Linux /proc;
    None where that cannot be read (not Linux, or /proc hides other users' processes)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return fields[0], fields[19]


def _process_gone(info: dict) -> bool:
    """True when the holder ran on this host and has ended, or its PID now names a newer process."""
    if info.get("host") != socket.gethostname():
        return False
    pid = info["pid"]
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # exists, another user's
        pass
    stat = _proc_stat(pid)
    if stat is None:
        return False  # cannot tell: assume it still runs
    state, ticks = stat
    return state == "Z" or (info.get("start_ticks") is not None and ticks != info["start_ticks"])


def is_stale(info: dict) -> bool:
    """Whether the holder recorded in ``info`` (from :func:`read_lock`) is known to be gone."""
    if info.get("unreadable"):
        return info.get("age_s", 0.0) > UNREADABLE_STALE_S
    return _process_gone(info)


def describe(info: dict, path: Path) -> str:
    """'skygen render (PID 123 on host, started ...: command)' for messages."""
    if info.get("unreadable"):
        return f"a process whose lock file {path} is empty or damaged"
    cmd = str(info.get("command", "?"))
    cmd = cmd if len(cmd) <= 160 else cmd[:157] + "..."
    return (
        f"{info.get('what', '?')} (PID {info.get('pid')} on {info.get('host')}, started "
        f"{info.get('started_utc', '?')}: {cmd})"
    )


class FolderLock:
    """Context manager holding ``folder``'s lock ``name`` (see the module docstring).

    ``what`` names the holder in messages ("skygen render"); ``shares``: the group of
    locks that may hold other names of the same folder at the same time; ``wait_s``:
    keep trying this long before refusing; ``log``: receives the line saying a stale lock
    was taken over (default: stderr). Raises :class:`~skygen.errors.FolderInUseError`.
    The folder must exist. Releasing removes the lock file (only if it is still this one).
    """

    def __init__(
        self,
        folder: str | Path,
        what: str = "skygen",
        *,
        name: str = "",
        shares: str | None = None,
        wait_s: float = 0.0,
        log=None,
    ):
        self.folder = Path(folder)
        self.path = lock_path(folder, name)
        self.what, self.shares, self.wait_s = what, shares, wait_s
        self.log = log or (lambda msg: print(msg, file=sys.stderr))
        self.token: str | None = None

    # -- acquiring ---------------------------------------------------------------
    def acquire(self) -> "FolderLock":
        deadline = time.monotonic() + self.wait_s
        young_unreadable_until = time.monotonic() + 2.0
        while True:
            holder = self._create()
            if holder is None:  # mine; now make sure nothing incompatible runs beside it
                other = self._conflicting_other()
                if other is None:
                    return self
                self.release()
                holder_path, holder = other
            else:
                holder_path = self.path
                if is_stale(holder):
                    self._take_over(holder)
                    continue
            waiting_for_writer = holder.get("unreadable") and time.monotonic() < young_unreadable_until
            if time.monotonic() >= deadline and not waiting_for_writer:
                raise FolderInUseError(self._refusal(holder_path, holder))
            time.sleep(0.05 if waiting_for_writer else 0.2)

    def _create(self) -> dict | None:
        """Create the lock file atomically; None on success, else the current holder."""
        token = uuid.uuid4().hex
        info = {
            "what": self.what,
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "start_ticks": (_proc_stat(os.getpid()) or (None, None))[1],
            "command": " ".join(sys.argv),
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "shares": self.shares,
            "token": token,
        }
        try:
            fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            holder = read_lock(self.path)
            return holder if holder is not None else {"unreadable": True, "age_s": 0.0}  # just released: retry
        try:
            os.write(fd, (json.dumps(info) + "\n").encode())
        except BaseException:
            os.close(fd)
            self.path.unlink(missing_ok=True)
            raise
        os.close(fd)
        self.token = token
        return None

    def _conflicting_other(self) -> tuple[Path, dict] | None:
        for p in sorted(self.folder.glob(f"{PREFIX}*{SUFFIX}")):
            if p == self.path:
                continue
            info = read_lock(p)
            if info is None or is_stale(info):
                continue
            if self.shares is not None and info.get("shares") == self.shares:
                continue
            return p, info
        return None

    def _take_over(self, seen: dict) -> None:
        """Remove the stale lock ``seen``, unless another process replaced it meanwhile.

        A guard file (created with O_EXCL too) makes the check-and-remove atomic among
        processes taking over at the same moment."""
        guard = self.path.with_name(self.path.name + ".takeover")
        try:
            os.close(os.open(guard, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
        except FileExistsError:  # another process is taking over; a guard left by a crash expires
            try:
                if time.time() - guard.stat().st_mtime > UNREADABLE_STALE_S:
                    guard.unlink(missing_ok=True)
            except FileNotFoundError:
                pass
            time.sleep(0.05)
            return
        try:
            now = read_lock(self.path)
            if now is not None and now.get("token") == seen.get("token") and is_stale(now):
                self.path.unlink(missing_ok=True)
                self.log(
                    f"note: {self.folder}: took over the lock of {describe(now, self.path)}, which is no longer running"
                )
        finally:
            guard.unlink(missing_ok=True)

    def _refusal(self, path: Path, info: dict) -> str:
        if info.get("unreadable"):
            return (
                f"{self.folder} is in use: lock file {path} is empty or damaged; if no skygen or fusion "
                f"process writes to {self.folder}, delete {path} and try again"
            )
        if info.get("host") != socket.gethostname():
            hint = f"wait for it to finish; if that job is no longer running, delete {path}"
        else:
            hint = "wait for it to finish, or use another output folder"
        return f"{self.folder} is in use by {describe(info, path)}; {hint}"

    # -- releasing ---------------------------------------------------------------
    def release(self) -> None:
        """Remove the lock file if it is still the one this object created."""
        if self.token is None:
            return
        info = read_lock(self.path)
        if info is not None and info.get("token") == self.token:
            self.path.unlink(missing_ok=True)
        self.token = None

    @property
    def held(self) -> bool:
        return self.token is not None

    def __enter__(self) -> "FolderLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
