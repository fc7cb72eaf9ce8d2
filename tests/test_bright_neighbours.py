"""benchmarks/bright_neighbours.py: which of the brightest detections are non-stars, and where they sit."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _script():
    if str(ROOT / "benchmarks") not in sys.path:
        sys.path.insert(0, str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location("bright_neighbours", ROOT / "benchmarks" / "bright_neighbours.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _blob(img, x, y, flux, sigma=1.2):
    yy, xx = np.mgrid[: img.shape[0], : img.shape[1]]
    img += flux / (2 * np.pi * sigma**2) * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma**2))


def test_a_displaced_star_and_a_false_star_are_told_apart_by_their_distances():
    """Catalogue: a bright star (Hp 1) at (100, 100) and a fainter one (Hp 4) at (300, 200). On the image: the bright
    one where it should be, the fainter one 4 px off its catalogue place, and a source at (250, 50) with no star.
    Non-stars within 2 px: the displaced star (its catalogue star 4 px away, 206 px from the bright star) and the false
    one (no catalogue star within 6 px); the bright star is a star."""
    mod = _script()
    rng = np.random.default_rng(1)
    img = rng.normal(10.0, 1.0, (300, 400))
    _blob(img, 100, 100, 5000)
    _blob(img, 304, 200, 2000)
    _blob(img, 250, 50, 1500)
    det_cfg = SimpleNamespace(threshold_sigma=5.0, min_area_px=3, background_box_px=0)
    x, y, mags = np.array([100.0, 300.0]), np.array([100.0, 200.0]), np.array([1.0, 4.0])
    got = mod.nonstars(img, det_cfg, 65535.0, x, y, mags, 3.0, 10, 2.0)
    got = got[np.argsort(got[:, 0])]
    assert got.shape == (2, len(mod.COLUMNS))
    assert got[0, 0] == pytest.approx(np.hypot(150, 50), abs=0.5) and got[0, 1] > 6  # the false star
    assert got[1, 0] == pytest.approx(np.hypot(204, 100), abs=0.5) and got[1, 1] == pytest.approx(4.0, abs=0.3)
    # the displaced star: detected at (304, 200), its catalogue star (Hp 4) 4 px to the left of it
    x_px, y_px, dx, dy, mag, area = got[1, 2:]
    assert (x_px, y_px) == pytest.approx((304, 200), abs=0.3) and (dx, dy) == pytest.approx((-4, 0), abs=0.3)
    assert mag == 4.0 and area >= 3
    # with a 5 px radius the displaced star is a star again; with no bright star on the sensor, inf
    assert len(mod.nonstars(img, det_cfg, 65535.0, x, y, mags, 3.0, 10, 5.0)) == 1
    assert np.isinf(mod.nonstars(img, det_cfg, 65535.0, x, y, mags, 0.5, 10, 2.0)[:, 0]).all()


def test_centroid_shift_splits_each_offset_along_the_line_from_the_principal_point():
    """benchmarks/centroid_shift.py: a star detected 2 px farther out than the camera puts it has a radial offset of
    -2 px, one 1 px sideways 0, and a star with no detection within the match radius is left out."""
    if str(ROOT / "benchmarks") not in sys.path:
        sys.path.insert(0, str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location("centroid_shift", ROOT / "benchmarks" / "centroid_shift.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    x, y, mags = np.array([200.0, 100.0, 400.0]), np.array([100.0, 300.0, 400.0]), np.array([3.0, 6.0, 5.0])
    det = {"x_px": np.array([202.0, 101.0]), "y_px": np.array([100.0, 300.0])}  # centre (100, 100)
    got = mod.radial_offsets(det, x, y, mags, 100.0, 100.0, 8.0)
    assert got.shape == (2, 5)  # ... and each pair's detection and star rows
    assert got[0] == pytest.approx([3.0, 100.0, -2.0, 0, 0]) and got[1] == pytest.approx([6.0, 200.0, 0.0, 1, 1])
    # the second table's rows: rank by flux (the second detection is the brighter), dx, dy as detected and with a
    # camera's uniform shift taken off (here +1 px along x per decade beyond 10^1, flux 1000 over sigma 10: 1 decade)
    from skygen.instrument.camera import Camera

    cam = Camera(500, 500, 1000.0, 100.0, 100.0, bright_shift_from=1.0, bright_shift_x_px=1.0)
    xy = mod.xy_offsets({**det, "flux_adu": np.array([10.0, 1000.0])}, x, y, got, cam, 10.0)
    assert xy[:, 0].tolist() == [1, 0]
    assert xy[0, 1:] == pytest.approx([2.0, 0.0, 2.0, 0.0]) and xy[1, 1:] == pytest.approx([1.0, 0.0, 0.0, 0.0])
