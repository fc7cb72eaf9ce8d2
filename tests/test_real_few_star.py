"""benchmarks/real_few_star.py on two real Blackfly frames: truth from the all-detection solve, N = 8 cell."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

pytest.importorskip("tetra3rs")

ROOT = Path(__file__).resolve().parents[1]
FRAMES = sorted((ROOT / "real-frames" / "tetra3-blackfly").glob("*.tiff"))[:2]
CAMERA = ROOT / "configs" / "cameras" / "blackfly-s-imx265-35mm.yaml"


def _script(name: str = "real_few_star"):
    """A benchmark script as a module (sim_vs_real imports its sibling real_few_star, so benchmarks/ is on the path)."""
    import sys

    if str(ROOT / "benchmarks") not in sys.path:
        sys.path.insert(0, str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
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
        # per frame: how many of the brightest 8 are saturated, and how far each unmatched one lies from a brighter one
        assert 0 <= f["saturated_in_brightest"]["8"] <= 8
        gaps = f["non_catalogue_nearest_brighter_px"]["8"]
        assert len(gaps) == f["non_catalogue_in_brightest"]["8"] and all(g is None or g > 0 for g in gaps)
    (cell,) = res["cells"]
    assert cell["n"] == 8 and cell["frames"] == 2
    t = cell["solvers"]["tetra3rs"]
    assert (t["n_correct"], t["n_wrong"], t["n_refused"]) == (2, 0, 0)
    assert t["median_ms"] is not None and 0 <= cell["share_non_catalogue_in_brightest"] <= 1
    md = mod.markdown(res)
    assert "| 8 | 2 | **100 %** / 0 % / 0 %" in md


def test_tracking_cells_on_two_real_frames():
    """--track-hint-deg: the whole-sky solver tracks three of each real Blackfly frame's stars from a hint 2 deg off
    its truth (the zero point from the other frame); tetra3rs tracks with its own hint mode, side by side."""
    mod = _script()
    frames = mod.load_frames([str(f) for f in FRAMES])
    res = mod.run(frames, CAMERA, n_values=(8,), solvers=("tetra3rs", "whole-sky"), background_box=64,
                  track_hint_deg=(2.0,), track_n=(3,), log=lambda s: None)  # fmt: skip
    (row,) = res["tracking_cells"]
    assert (row["hint_deg"], row["n"], row["frames"]) == (2.0, 3, 2) and set(row["solvers"]) == {
        "tetra3rs",
        "whole-sky",
    }
    w = row["solvers"]["whole-sky"]
    assert w["n_wrong"] == 0 and w["n_correct"] == 2 and row["solvers"]["tetra3rs"]["n_wrong"] == 0
    # each solver tracks with its own zero point: the fine stage's cells are the same without tetra3rs listed
    alone = mod.run(frames, CAMERA, n_values=(8,), solvers=("whole-sky",), background_box=64,
                    track_hint_deg=(2.0,), track_n=(3,), log=lambda s: None)  # fmt: skip
    timing = ("median_ms", "p95_ms", "p99_ms")
    got = alone["tracking_cells"][0]["solvers"]["whole-sky"]
    assert {k: v for k, v in got.items() if k not in timing} == {k: v for k, v in w.items() if k not in timing}
    assert "| 2° | 3 | 2 |" in mod.markdown(res) and "Tracking:" in mod.markdown(res)


def test_only_prior_free_solvers_are_accepted():
    mod = _script()
    assert {"tetra3rs", "whole-sky", "tetra3rs>whole-sky"} <= set(mod.prior_free_solvers())
    assert "learned+fine" not in mod.prior_free_solvers() and "oracle-prior" not in mod.prior_free_solvers()
    with pytest.raises(SystemExit, match="prior-free"):
        mod.run([], CAMERA, solvers=("learned+fine",), log=lambda s: None)


def test_sim_vs_real_intervals_and_verdicts():
    """benchmarks/sim_vs_real.py's scoring: Wilson intervals, points off, within 5 points or intervals overlap."""
    mod = _script("sim_vs_real")
    lo, hi = mod.wilson(8, 8)
    assert lo == pytest.approx(0.676, abs=0.002) and hi == 1.0  # 8 of 8 says little: 68-100 %
    lo, hi = mod.wilson(49, 60)
    assert lo < 49 / 60 < hi and hi - lo < 0.22

    def run(k, n):
        return {"cells": [{"n": 4, "frames": n, "solvers": {"whole-sky": {"n_correct": k, "n_wrong": 0}}}]}

    rows = mod.compare(run(8, 8), run(40, 40), run(49, 60), ["whole-sky"], [4])
    at, rnd = rows[0]["at_truth"], rows[0]["random_sky"]
    assert at["points_off"] == 0 and at["within_target"]
    assert rnd["points_off"] == pytest.approx(-18.33, abs=0.01) and not rnd["within_target"]
    assert rnd["intervals_overlap"]  # 70-89 % against 68-100 %
    far = mod.compare(run(8, 8), run(4, 40), None, ["whole-sky"], [4])[0]["at_truth"]
    assert not far["within_target"] and not far["intervals_overlap"]
    md = mod.markdown({"camera": "c.yaml", "real": {"frames_kept": 8, "frames_given": 8}, "per_attitude": 5,
                       "renders": 60, "seed": 0, "rows": rows})  # fmt: skip
    assert "| 4 | whole-sky | **100 %** (8/8, 68–100) | **100 %** (40/40, 91–100), +0 pts ✓ |" in md


def test_sim_vs_real_per_frame_pairs_each_real_frame_with_its_own_renders():
    """per_frame: render j belongs to real frame j // per_attitude; outcomes and non-catalogue counts per N."""
    mod = _script("sim_vs_real")
    real = {"frames": [
        {"frame": "a.png", "outcomes": {"whole-sky": {"4": "correct"}}, "non_catalogue_in_brightest": {"4": 0}},
        {"frame": "b.png", "outcomes": {"whole-sky": {"4": "weak_evidence"}}, "non_catalogue_in_brightest": {"4": 2}},
    ]}  # fmt: skip
    outcomes = ["weak_evidence", "weak_evidence", "correct", "correct", "correct", "weak_evidence"]
    at = {
        "frames": [{"frame": f"/r/at-truth#{j}", "outcomes": {"whole-sky": {"4": o}}} for j, o in enumerate(outcomes)]
    }
    rows = mod.per_frame(real, at, 3, "whole-sky", [4])
    assert [r["frame"] for r in rows] == ["a.png", "b.png"]
    a, b = rows[0]["cells"]["4"], rows[1]["cells"]["4"]
    assert (a["real"], a["renders_correct"], a["renders"]) == ("correct", 1, 3)
    assert (b["real"], b["renders_correct"], b["non_catalogue_in_brightest"]) == ("weak_evidence", 2, 2)
    res = {"camera": "c.yaml", "real": {"frames_kept": 2, "frames_given": 2}, "per_attitude": 3, "renders": 0}
    md = mod.markdown({**res, "seed": 0, "rows": [], "per_frame": rows, "per_frame_solver": "whole-sky"})
    assert "| a.png | ✓ · 1/3 |" in md and "| b.png | weak_evidence · 2/3 (2) |" in md
    assert mod.agreement(rows) == (0, 2) and "in 0 of 2 (frame, N) cells" in md  # a: 1 of 3 solved; b: 2 of 3


def test_sim_vs_real_renders_each_frame_at_its_own_exposure_from_the_fit_report(tmp_path):
    """--fit-report: fit.json's exposure_scale per frame (by file name; 1 where the fit has none), frames within
    0.02 mag rendered as one group, and per_frame pairs each real frame with its renders in their group's folder."""
    import json

    mod = _script("sim_vs_real")
    scale = {"a": 1.0, "b": 2.0, "c": 2.01, "d": float("nan")}
    solved = [{"frame": f"{n}.png", "exposure_scale": v} for n, v in scale.items()]
    (tmp_path / "fit.json").write_text(json.dumps({"solved": solved}))
    frames = [{"frame": f"/data/{n}.png"} for n in "abcde"]
    scales = mod.exposure_scales(tmp_path, frames)
    assert scales == [1.0, 2.0, 2.01, 1.0, 1.0]  # d: no finite scale, e: not in the fit
    groups = mod.group_by_exposure(scales)
    assert sorted(groups.values()) == [[0, 3, 4], [1, 2]]
    assert min(groups) == 1.0 and max(groups) == pytest.approx(2.0, rel=0.01)
    with pytest.raises(SystemExit, match="no fit.json"):
        mod.exposure_scales(tmp_path / "nowhere", frames)
    real = {"frames": [{"frame": f"{n}.png", "outcomes": {"whole-sky": {"4": "correct"}}} for n in "ab"]}
    origin = {"/r/exposure-00": [1, 1], "/r/exposure-01": [0, 0]}  # folder -> the real frame of each render
    at = {"frames": [{"frame": f"{d}#{j}", "outcomes": {"whole-sky": {"4": o}}}
                     for d, outs in (("/r/exposure-00", ["correct", "correct"]), ("/r/exposure-01", ["x", "correct"]))
                     for j, o in enumerate(outs)]}  # fmt: skip
    rows = mod.per_frame(real, at, 2, "whole-sky", [4], origin)
    assert [(r["cells"]["4"]["renders_correct"], r["cells"]["4"]["renders"]) for r in rows] == [(1, 2), (2, 2)]


def test_learned_solvers_run_beside_the_prior_free_ones_with_a_checkpoint(tmp_path):
    """--checkpoint: the camera is the model's own, the learned chain is scored in the same cells as the
    prior-free solvers (here on full-resolution renders of the smoke camera, truth their rendered attitude),
    and a learned solver without a checkpoint, or a camera given as well, is refused. (At five detections this
    one-epoch model of 4 regions, 3 searched, makes the chain refuse frames whole-sky solves: the region
    searches spend the chain's one hypothesis count.)"""
    from fusion.config import load_config
    from fusion.testing import KINDS, render_small, small_dataset
    from fusion.train.run import train

    mod = _script()
    run_dir = tmp_path / "run"
    train(
        load_config("configs/smoke.yaml", [f"data.path={small_dataset('smoke')}", "train.epochs=1"]),
        run_dir,
        log=lambda *a, **k: None,
    )
    data = render_small(
        tmp_path / "frames",
        [*KINDS["smoke"], "n_frames=4", "output.shard_size=4", "output.full_res=true", "seed=9",
         "output.split_fractions=[0.0, 0.0, 1.0]"],
    )  # fmt: skip
    frames = mod.load_frames([str(data)])
    solvers = ("whole-sky", "learned+fine>whole-sky")
    res = mod.run(frames, None, n_values=(5, 8), solvers=solvers, checkpoint=run_dir / "best.pt", log=lambda s: None)
    assert res["checkpoint"].endswith("best.pt") and res["frames_kept"] == 4
    for cell in res["cells"]:
        for s in solvers:
            v = cell["solvers"][s]
            assert v["n_correct"] + v["n_wrong"] + v["n_refused"] == cell["frames"] == 4 and v["n_wrong"] == 0
    # from eight detections both solve (the chain: tetra3rs first, then the whole sky at once)
    assert [v["n_correct"] for v in res["cells"][1]["solvers"].values()] == [4, 4]
    assert "learned+fine>whole-sky" in mod.markdown(res)
    with pytest.raises(SystemExit, match="exactly one"):
        mod.run(frames, CAMERA, solvers=("whole-sky",), checkpoint=run_dir / "best.pt", log=lambda s: None)
    with pytest.raises(SystemExit, match="need --checkpoint"):
        mod.run(frames, CAMERA, solvers=("learned+fine>whole-sky",), log=lambda s: None)


def test_mask_fixed_sources_reaches_the_detector_and_the_record():
    """--mask-fixed-sources: the benchmark's Predictor drops the camera's fixed sources at detection, the result says
    it was on, and a camera without any is refused with the reason."""
    from fusion.errors import ConfigError

    mod = _script()
    glow_cam = ROOT / "results" / "real-frames" / "centroid-scatter" / "creusot-16mm" / "creusot-16mm-fitted.yaml"
    res = mod.run([], glow_cam, n_values=(4,), solvers=("tetra3rs",), mask_fixed_sources=True, log=lambda s: None)
    assert res["mask_fixed_sources"] is True and res["frames_kept"] == 0
    with pytest.raises(ConfigError, match="no sensor.fixed_sources"):
        mod.run([], CAMERA, n_values=(4,), solvers=("tetra3rs",), mask_fixed_sources=True, log=lambda s: None)


@pytest.mark.parametrize("rows_from_bottom", [False, True])
def test_wcs_agreement_puts_pixels_on_the_sky_as_a_camera_with_the_same_attitude(tmp_path, rows_from_bottom):
    """skygen.real.wcs (benchmarks/wcs_agreement.py, real_few_star.py --truth-wcs): a TAN WCS written for a pinhole
    camera and attitude puts every pixel where the camera does (to well under a milli-arcsecond), counting rows from
    the top or, with --flip-y, from the bottom; and gives that attitude back."""
    import numpy as np
    from astropy.wcs import WCS

    from skygen.instrument.camera import Camera
    from skygen.real.wcs import angle_arcsec, attitude_from_wcs, read_wcs, wcs_directions
    from skygen.sky.attitude import matrix_to_radec_roll

    cam = Camera(640, 480, 3000.0, 319.5, 239.5)
    rng = np.random.default_rng(1)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    m = q * np.sign(np.linalg.det(q))  # camera -> ICRS, a proper rotation
    ra, dec, _ = matrix_to_radec_roll(m)
    z = m[:, 2]
    north = np.array([0.0, 0.0, 1.0]) - z[2] * z
    north /= np.linalg.norm(north)
    east = np.cross(north, z)
    cd = np.degrees(1.0 / cam.f_px) * np.array([[m[:, 0] @ east, m[:, 1] @ east], [m[:, 0] @ north, m[:, 1] @ north]])
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [ra, dec]
    w.wcs.crpix = [cam.cx_px + 1, cam.cy_px + 1]
    if rows_from_bottom:  # row r from the top is row H - 1 - r from the bottom
        cd[:, 1] *= -1
        w.wcs.crpix = [cam.cx_px + 1, cam.height_px - cam.cy_px]
    w.wcs.cd = cd
    path = tmp_path / "f.wcs"
    path.write_text(w.to_header().tostring())
    x, y = rng.uniform(0, 639, 50), rng.uniform(0, 479, 50)
    theirs = wcs_directions(path, x, y, cam.height_px if rows_from_bottom else None)
    assert angle_arcsec(cam.unproject(x, y) @ m.T, theirs).max() < 1e-3
    got, misfit = attitude_from_wcs(read_wcs(path), cam, rows_from_bottom)
    assert np.abs(got - m).max() < 1e-9 and misfit < 1e-3
    _, flipped = attitude_from_wcs(read_wcs(path), cam, not rows_from_bottom)  # the rows read the wrong way up
    assert flipped > 100.0


def test_a_file_that_is_no_wcs_is_refused_by_name(tmp_path):
    from skygen.real.wcs import WCSError, read_wcs

    bad = tmp_path / "x.wcs"
    bad.write_text("SIMPLE  =                    T" + " " * 50 + "END" + " " * 77)
    with pytest.raises(WCSError, match="x.wcs: its WCS has no celestial axes"):
        read_wcs(bad)


def test_tracking_with_a_hint_that_misses_counts_wrong_answers_beside_their_probabilities():
    """benchmarks/real_tracking_offhint.py: hints 6 sigma off each real frame's truth; every answer's probability is
    summed and every one more than 0.1 deg off counted wrong; a hint inside its own 3-sigma region is refused."""
    mod = _script("real_tracking_offhint")
    frames = _script().load_frames([str(f) for f in FRAMES])
    res = mod.run(
        frames, ROOT / "configs" / "cameras" / "blackfly-fitted.yaml", n_values=(3,), reps=2, log=lambda s: None
    )
    c = res["cells"][3]
    assert res["frames_kept"] == 2 and c["attempts"] == 4 and 0 <= c["wrong"] <= c["answers"] <= 4
    assert c["sum_p"] >= sum(c["wrong_p"]) and len(c["wrong_p"]) == c["wrong"]
    assert "| 3 | 4 |" in mod.markdown(res, "cmd")
    with pytest.raises(SystemExit, match="off-sigmas"):
        mod.main([str(FRAMES[0]), "--camera", str(CAMERA), "--off-sigmas", "2", "--out", "x"])


def test_fine_trace_prints_each_step_of_one_real_solve(capsys):
    """benchmarks/fine_trace.py: the decision, both refinement fits, tetra3rs's confirmation and the answer."""
    mod = _script("fine_trace")
    mod.main(
        ["--frame", str(FRAMES[0]), "--camera", str(ROOT / "configs" / "cameras" / "blackfly-fitted.yaml"), "--n", "6"]
    )
    out = capsys.readouterr().out
    assert "decide" in out and "refine  free scale" in out and "refine  own scale" in out
    assert "confirm tetra3rs" in out and "answer:" in out
    with pytest.raises(SystemExit, match="--frame"):
        mod.main(["--n", "6"])
