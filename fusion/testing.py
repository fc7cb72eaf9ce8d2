"""Small rendered datasets for tests and examples, rendered once per process.

``small_dataset("smoke")`` renders (or returns the cached path of) a tiny dataset into a
temporary folder removed at interpreter exit. The kinds:

* ``smoke`` — 300 frames, 256 x 256 sensor stored at 64 x 64, boresights cycling through 8
  fixed directions (roll 0–20 deg): a learnable toy problem for K = 4 in seconds.
* ``uniform`` — 120 frames over the whole sky, 512 x 512 sensor stored at 128 x 128.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

SMOKE_DIRECTIONS = {"ra_deg": [10, 60, 120, 170, 220, 260, 300, 340], "dec_deg": [50, -20, 10, -60, 30, -5, 70, -40]}

KINDS = {
    "smoke": [
        "n_frames=300",
        "output.shard_size=150",
        "camera.width_px=256",
        "camera.height_px=256",
        "camera.fov_deg=20",
        "output.image_size_px=64",
        "attitude.mode=list",
        f"attitude.ra_deg={SMOKE_DIRECTIONS['ra_deg']}",
        f"attitude.dec_deg={SMOKE_DIRECTIONS['dec_deg']}",
        "attitude.roll_range_deg=[0, 20]",
        "output.split_fractions=[0.6, 0.2, 0.2]",
    ],
    "uniform": [
        "n_frames=120",
        "output.shard_size=60",
        "camera.width_px=512",
        "camera.height_px=512",
        "camera.fov_deg=20",
        "output.image_size_px=128",
        "output.split_fractions=[0.5, 0.25, 0.25]",
    ],
}

_CACHE: dict[str, Path] = {}
_ROOT: list[Path] = []


def _root() -> Path:
    if not _ROOT:
        root = Path(tempfile.mkdtemp(prefix="fusion-test-data-"))
        atexit.register(shutil.rmtree, root, True)
        _ROOT.append(root)
    return _ROOT[0]


def render_small(out: str | Path, overrides: list[str]) -> Path:
    """Render a dataset from skygen's defaults plus ``overrides`` into ``out`` (one process, no bar)."""
    from skygen.config import load_config
    from skygen.datasets.build import render_dataset

    render_dataset(load_config(overrides=overrides), out, workers=1, progress=False)
    return Path(out)


def small_dataset(kind: str = "smoke") -> Path:
    """Path of the cached dataset ``kind`` (see the module docstring), rendered on first use."""
    if kind not in _CACHE:
        _CACHE[kind] = render_small(_root() / kind, KINDS[kind])
    return _CACHE[kind]


class Killed(Exception):
    """Raised by :func:`killing_log` to interrupt a training run at a chosen point."""


def killing_log(prefix: str):
    """A ``log`` callback for :func:`fusion.train.train` that raises :class:`Killed` at the
    first message starting with ``prefix`` (e.g. ``"epoch 2/3"``: killed after epoch 2)."""

    def log(msg, *a, **k):
        if msg.startswith(prefix):
            raise Killed(msg)

    return log


def assert_same_run(a, b) -> None:
    """Two run folders ended with identical weights and metric history (times aside)."""
    import torch

    from .model.checkpoint import load_checkpoint

    ca, cb = load_checkpoint(Path(a) / "last.pt"), load_checkpoint(Path(b) / "last.pt")
    for name, tensor in ca.model.items():
        assert torch.equal(tensor, cb.model[name]), name
    strip = lambda rows: [{k: v for k, v in r.items() if k != "epoch_time_s"} for r in rows]  # noqa: E731
    assert strip(ca.history) == strip(cb.history)


def benchmark_script(name: str):
    """``benchmarks/<name>.py`` of this checkout as a module (the benchmark scripts are not a package)."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
