"""benchmarks/real_few_star.py on two real Blackfly frames: truth from the all-detection solve, N = 8 cell."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

pytest.importorskip("tetra3rs")

ROOT = Path(__file__).resolve().parents[1]
FRAMES = sorted((ROOT / "real-frames" / "tetra3-blackfly").glob("*.tiff"))[:2]
CAMERA = ROOT / "configs" / "cameras" / "blackfly-s-imx265-35mm.yaml"


def _script():
    spec = importlib.util.spec_from_file_location("real_few_star", ROOT / "benchmarks" / "real_few_star.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_tetra3rs_solves_two_real_blackfly_frames_from_their_brightest_eight_detections():
    mod = _script()
    assert len(FRAMES) == 2
    frames = mod.load_frames([str(f) for f in FRAMES])
    # the documented detector setting for these ground frames (fusion predict --background-box 64)
    res = mod.run(frames, CAMERA, n_values=(8,), solvers=("tetra3rs",), background_box=64, log=lambda s: None)
    assert res["frames_kept"] == 2, res["dropped"]
    for f in res["frames"]:
        assert f["truth_matched"] >= 10 and f["truth_fpp"] <= 1e-20
    (cell,) = res["cells"]
    assert cell["n"] == 8 and cell["frames"] == 2
    t = cell["solvers"]["tetra3rs"]
    assert (t["n_correct"], t["n_wrong"], t["n_refused"]) == (2, 0, 0)
    assert t["median_ms"] is not None and 0 <= cell["share_non_catalogue_in_brightest"] <= 1
    md = mod.markdown(res)
    assert "| 8 | 2 | **100 %** / 0 % / 0 %" in md


def test_only_prior_free_solvers_are_accepted():
    mod = _script()
    assert {"tetra3rs", "whole-sky", "tetra3rs>whole-sky"} <= set(mod.prior_free_solvers())
    assert "learned+fine" not in mod.prior_free_solvers() and "oracle-prior" not in mod.prior_free_solvers()
    with pytest.raises(SystemExit, match="prior-free"):
        mod.run([], CAMERA, solvers=("learned+fine",), log=lambda s: None)
