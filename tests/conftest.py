"""Shared fixtures: a small camera that renders fast, and one small dataset per session."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

# A 256 x 256 sensor with the default optics scaled so that the FOV stays 20 deg:
# frames render in ~1 ms, so physics and format tests stay fast.
SMALL = [
    "camera.width_px=256",
    "camera.height_px=256",
    "camera.pixel_pitch_um=22.0",
    "output.image_size_px=64",
    "output.shard_size=20",
]


@pytest.fixture(scope="session")
def small_overrides() -> list[str]:
    return list(SMALL)


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory) -> Path:
    from skygen.config import load_config
    from skygen.datasets.build import render_dataset

    out = tmp_path_factory.mktemp("data") / "small"
    render_dataset(load_config(overrides=SMALL + ["n_frames=50"]), out, workers=1, progress=False)
    return out


# the default camera's renderer and a tetra3rs solver with its own database: the solver tests
# (test_solvers.py, test_solver_certificate.py) share one per session
@pytest.fixture(scope="session")
def renderer():
    from skygen.config import load_config
    from skygen.render.frame import Renderer

    return Renderer(load_config(overrides=["n_frames=20"]))


@pytest.fixture(scope="session")
def tetra(renderer, tmp_path_factory):
    pytest.importorskip("tetra3rs")
    from fusion.solve.tetra import Tetra3Solver

    return Tetra3Solver(renderer.camera, db_folder=tmp_path_factory.mktemp("db"))


def pytest_configure(config):
    # verified shard checksums are remembered under $XDG_CACHE_HOME/skygen: keep the tests' own
    import tempfile

    os.environ["XDG_CACHE_HOME"] = tempfile.mkdtemp(prefix="skygen-test-cache-")


def pytest_collection_modifyitems(config, items):
    if os.environ.get("RUN_SLOW"):
        return
    skip = pytest.mark.skip(reason="slow: set RUN_SLOW=1 to run")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
