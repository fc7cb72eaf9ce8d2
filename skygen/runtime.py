"""What every command of skygen and fusion needs from its host: safe files, strict JSON, the
hardware record and the choice of a torch device.

Files
    :func:`atomic_path` is the one write-then-rename: a context manager that yields a hidden
    temporary name in the target's folder (``.NAME.tmpPID``), renames it over ``path`` only
    when the block ends without an exception, and removes it otherwise. A crash, Ctrl-C or
    a full disk never leaves a half-written file under the real name.
    :func:`atomic_write_bytes`, :func:`atomic_write_text`, :func:`atomic_save_numpy` and
    :func:`write_json` are built on it.

JSON
    :func:`write_json` and :func:`dumps_json` write *strict* JSON (RFC 8259): NaN and
    infinities become ``null`` (a missing number), NumPy scalars and arrays become plain
    numbers and lists; anything else that is not JSON raises ``TypeError``.

Hardware
    :func:`hardware` records what a figure was measured on: CPU model, cores, memory, OS,
    library versions, load average, and, when a torch device is given, its name (GPU model,
    CUDA capability and memory; Jetson board, L4T release and power mode). Torch is
    imported only when a device is given.

Stopping
    :func:`stop_on_sigterm` turns SIGTERM (a scheduler's stop, ``kill``) into
    :class:`StopRequested` for the block it guards; :func:`check_stop` re-raises a request
    whose exception Python swallowed (inside a destructor) between units of work.

Devices
    :func:`pick_device` has one meaning of ``auto`` for every command: the first CUDA
    device if one is visible, else the CPU. ``cuda`` (or ``cuda:N``) without a visible
    device raises :class:`skygen.errors.ConfigError` naming the option.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import platform
import subprocess
from pathlib import Path
from typing import Iterator

import numpy as np

from skygen.errors import ConfigError


# --------------------------------------------------------------------------- files
@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path``, on failure it is removed.

    ``suffix`` is appended to the temporary name for writers that insist on an extension
    (``numpy.savez`` adds ``.npz`` unless the name has it).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}{suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def print_and_write(text: str, out: str | Path | None) -> None:
    """Print a table (a benchmark's Markdown) and, where ``out`` is given, write it there too: its folder made,
    the file written whole or not at all."""
    print(text)
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out, text + "\n")


def atomic_save_numpy(path: str | Path, array: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, array)
    atomic_write_bytes(path, buf.getvalue())


# --------------------------------------------------------------------------- strict JSON
def _plain(o):
    """``o`` with NumPy values as Python ones and non-finite floats as None (recursively)."""
    if isinstance(o, dict):
        return {k: _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    if isinstance(o, np.ndarray):
        return _plain(o.tolist())
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return float(o) if math.isfinite(o) else None
    return o


def dumps_json(data, **kw) -> str:
    """Strict JSON text of ``data`` (see the module docstring); ``kw`` go to :func:`json.dumps`."""
    return json.dumps(_plain(data), allow_nan=False, **kw)


def write_json(path: str | Path, data) -> None:
    """``data`` as strict, indented, key-sorted JSON, written atomically."""
    atomic_write_text(path, dumps_json(data, indent=1, sort_keys=True) + "\n")


# --------------------------------------------------------------------------- hardware
def _read(path: str) -> str | None:
    try:
        return Path(path).read_text().strip("\x00\n ")
    except OSError:
        return None


def _command(args: list[str]) -> str | None:
    try:
        return subprocess.run(args, capture_output=True, text=True, timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def cpu_model() -> str:
    for line in (_read("/proc/cpuinfo") or "").splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def hardware(device=None) -> dict:
    """What the numbers were measured on; ``device`` (a torch device) adds the accelerator and torch."""
    mem = None
    meminfo = _read("/proc/meminfo")
    if meminfo and meminfo.startswith("MemTotal"):
        mem = round(int(meminfo.split()[1]) / 2**20, 1)
    hw = {
        "cpu_model": cpu_model(),
        "machine": platform.machine(),
        "logical_cores": os.cpu_count(),
        "usable_cores": usable_cores(),
        "memory_gib": mem,
        "os": platform.platform(),
        "python": platform.python_version(),
        "numpy": str(np.__version__),
        "load_average_1m": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }
    if device is not None:
        import cv2
        import timm
        import torch

        hw.update(
            {
                "torch_threads": torch.get_num_threads(),
                "torch": str(torch.__version__),
                "timm": str(timm.__version__),
                "opencv": str(cv2.__version__),
                "device": str(device),
                "device_name": hw["cpu_model"],
            }
        )
        if device.type == "cuda":
            p = torch.cuda.get_device_properties(device)
            hw.update(
                {
                    "device_name": torch.cuda.get_device_name(device),
                    "cuda_capability": f"{p.major}.{p.minor}",
                    "gpu_memory_gib": round(p.total_memory / 2**30, 1),
                    "cuda_runtime": torch.version.cuda,
                    "cudnn": torch.backends.cudnn.version(),
                }
            )
    tegra = _read("/etc/nv_tegra_release")
    if tegra:  # a Jetson: record what docs/jetson.md asks for
        hw.update(
            {
                "jetson_board": _read("/proc/device-tree/model"),
                "l4t_release": tegra.splitlines()[0],
                "nvpmodel": _command(["nvpmodel", "-q"]),
            }
        )
    return hw


def hardware_line(hw: dict | None = None) -> str:
    """One line for a report: machine, CPU model and cores (and the device when it is not the CPU)."""
    hw = hw or hardware()
    line = f"{hw['machine']} {hw['cpu_model']}, {hw['logical_cores']} logical CPUs"
    if str(hw.get("device", "cpu")).startswith("cuda"):
        line += f", {hw['device_name']}"
    return line


# --------------------------------------------------------------------------- devices
def pick_device(name: str = "auto", option: str = "--device", local_rank: int | None = None):
    """The torch device for ``auto``, ``cpu``, ``cuda`` or ``cuda:N`` (one meaning of ``auto`` everywhere).

    ``local_rank`` (torchrun) picks that GPU for ``auto``/``cuda``. ConfigError names
    ``option`` when the device is unknown or not visible here.
    """
    import torch

    name = str(name)
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError):
        raise ConfigError(f"{option}: {name!r} is not a device; use auto, cpu, cuda or cuda:N") from None
    if dev.type == "cpu":
        return dev
    if dev.type != "cuda":
        raise ConfigError(f"{option}: {name!r} is not supported; use auto, cpu, cuda or cuda:N")
    if not torch.cuda.is_available():
        raise ConfigError(f"{option}={name}: no CUDA device is visible on this machine; use {option}=cpu")
    if dev.index is None and local_rank is not None:
        dev = torch.device("cuda", local_rank)
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ConfigError(f"{option}={name}: only {torch.cuda.device_count()} CUDA device(s) here")
    return dev


# --------------------------------------------------------------------------- stopping on SIGTERM
class StopRequested(KeyboardInterrupt):
    """SIGTERM arrived: raised in the main process so that cleanup runs and the resume hint is printed.

    A :class:`KeyboardInterrupt` (so a BaseException): every cleanup that serves Ctrl-C serves a
    scheduler's stop too, and no ``except Exception`` of a long job swallows it. Catch it before
    ``KeyboardInterrupt`` to tell the two apart (exit 143 against 130)."""


_STOP = {"requested": False}


def request_stop(signum=None, frame=None) -> None:
    """SIGTERM handler: remember the request and raise :class:`StopRequested`. A signal that arrives
    inside a destructor or a weakref callback has its exception swallowed by Python; the remembered
    request is raised again by the next :func:`check_stop` of a long loop, so the job still stops."""
    _STOP["requested"] = True
    raise StopRequested()


def check_stop() -> None:
    """Raise :class:`StopRequested` if SIGTERM arrived (call between units of work)."""
    if _STOP["requested"]:
        raise StopRequested()


@contextlib.contextmanager
def stop_on_sigterm() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`StopRequested` in the main thread (:func:`request_stop`);
    the previous handler comes back afterwards. The one SIGTERM handling of both command lines
    (``skygen render``, ``fusion train``). Outside the main thread (where Python delivers no
    signal) it does nothing."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _STOP["requested"] = False
    previous = signal.signal(signal.SIGTERM, request_stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def check_output_file(path: str | Path, option: str, example: str, error=ConfigError) -> None:
    """Refuse (``error``, a ConfigError by default) an output *file* that cannot be written, before any work:
    a folder given where a file is due (``example``: a file name to suggest), or a folder that cannot be made
    or written to. The folder is made (an empty one is left behind when the work fails later)."""
    path = Path(path)
    if path.is_dir():
        raise error(f"{option} {path} is a folder; give a file name such as {path / example}")
    _probe_folder(path.parent, f"{option} {path}", "give a file in a folder you can write to", error)


def check_output_folder(path: str | Path, option: str, error=ConfigError) -> bool:
    """Make the output *folder* ``path`` and check that files can be written there, before any work; True when
    it was created here. ``error`` (a ConfigError by default) names ``option`` otherwise."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise error(f"{option} {path} exists and is not a folder; give a folder for the output files")
    created = not path.exists()
    _probe_folder(path, f"{option} {path}", f"give a folder you can write to with {option} DIR", error)
    return created


def _probe_folder(folder: Path, what: str, advice: str, error) -> None:
    probe = folder / f".write-test-{os.getpid()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe.touch()
        probe.unlink()
    except OSError as exc:
        raise error(f"{what}: cannot write there ({exc.strerror or exc}); {advice}") from None


def describe_os_error(exc: OSError) -> str:
    """One line for a file-system error a command met: what, which file, and what to do for a full disk."""
    import errno as _errno
    import re

    what = exc.strerror or str(exc)
    # a write goes through atomic_path's temporary ".NAME.tmpPID": name the file the user asked for
    where = ""
    if getattr(exc, "filename", None):
        where = ": " + re.sub(r"(^|/)\.([^/]+)\.tmp\d+[^/]*$", r"\1\2", str(exc.filename))
    if getattr(exc, "filename2", None):
        where += f" -> {exc.filename2}"
    hint = ""
    if exc.errno == _errno.ENOSPC:
        hint = "; free space (or choose another --out) and run the same command again"
    elif exc.errno in (_errno.EACCES, _errno.EPERM, _errno.EROFS):
        hint = "; choose a folder you can write to"
    elif exc.errno in (_errno.ENOENT, _errno.ENOTDIR, _errno.EISDIR, _errno.EEXIST):
        hint = "; check the path (its folder must exist and it must not be a folder or a file in the way)"
    return f"{what}{where}{hint}"
