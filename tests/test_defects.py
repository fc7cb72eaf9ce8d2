"""A sensor's defect map (fusion.solve.defects): learned from unexplained detections that stay on one pixel while
the sky moves, applied before solving (fusion predict --defects, fusion benchmark --known-defects)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fusion.errors import ConfigError
from fusion.solve.base import Detections
from fusion.solve.defects import DefectMap, learn, learn_command, leave_one_out


def _frames(hot=((100.2, 200.7),), lit_in=5, frames=8, seed=0):
    """Detection tables of ``frames`` frames: 20 stars at random pixels (explained) and each hot pixel (with
    0.2 px of centroid scatter) unexplained in the first ``lit_in`` frames, plus one random unexplained
    detection per frame (a cosmic ray)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(frames):
        x, y = list(rng.uniform(0, 1024, 20)), list(rng.uniform(0, 1024, 20))
        e = [True] * 20
        for hx, hy in hot if k < lit_in else ():
            x.append(hx + rng.normal(0, 0.2))
            y.append(hy + rng.normal(0, 0.2))
            e.append(False)
        x.append(rng.uniform(0, 1024))
        y.append(rng.uniform(0, 1024))
        e.append(False)
        out.append((np.array(x), np.array(y), np.array(e)))
    return out


def test_a_pixel_unexplained_in_three_frames_is_a_defect_and_nothing_else_is():
    tables = _frames(hot=((100.2, 200.7), (700.0, 33.0)), lit_in=3)
    dmap = learn(tables)
    assert len(dmap) == 2
    assert np.allclose(sorted(map(tuple, dmap.xy)), [(100, 201), (700, 33)], atol=1)
    assert len(learn(_frames(lit_in=2))) == 0  # two frames: not enough
    # a star that recurs (explained) is no defect
    stars = [(np.array([50.0]), np.array([60.0]), np.array([True]))] * 6
    assert len(learn(stars)) == 0


def test_remove_drops_the_flagged_detections_and_keeps_the_order():
    dmap = DefectMap(np.array([[100.0, 200.0]]), 1.0)
    det = Detections(
        np.array([10.0, 100.4, 300.0, 101.5]), np.array([10.0, 199.8, 5.0, 200.0]), np.array([9, 8, 7, 6.0])
    )
    kept, n = dmap.remove(det)
    assert n == 1 and kept.x_px.tolist() == [10.0, 300.0, 101.5] and kept.flux_adu.tolist() == [9, 7, 6]
    same, none = DefectMap(np.zeros((0, 2))).remove(det)
    assert none == 0 and same is det


def test_leave_one_out_never_lets_a_frame_flag_itself():
    tables = _frames(lit_in=3)
    maps = leave_one_out(tables)
    # frames 0-2 hold the hot pixel: each sees it in only two others, so not a defect for them
    assert [len(m) for m in maps[:3]] == [0, 0, 0]
    assert all(len(m) == 1 for m in maps[3:])  # the others see it in three
    tables4 = _frames(lit_in=4)
    assert all(len(m) == 1 for m in leave_one_out(tables4))


def test_a_staring_camera_does_not_make_its_faint_stars_defects():
    """An uncatalogued star stays on one pixel while the camera stares: frames at one pointing count once."""
    tables = _frames(lit_in=8)
    still = np.tile([0.0, 0.0, 1.0], (8, 1))
    assert len(learn(tables, boresights=still)) == 0
    moving = np.array([[np.sin(np.radians(k)), 0.0, np.cos(np.radians(k))] for k in range(8)])
    assert len(learn(tables, boresights=moving)) == 1


def test_defect_map_files_round_trip_and_bad_ones_are_refused(tmp_path):
    dmap = DefectMap(np.array([[1.5, 2.0], [30.0, 40.25]]), 1.5)
    path = tmp_path / "d.json"
    dmap.to_json(path)
    back = DefectMap.from_json(path)
    assert np.allclose(back.xy, dmap.xy) and back.radius_px == 1.5
    path.write_text("{not json")
    with pytest.raises(ConfigError, match="not a defect map"):
        DefectMap.from_json(path)
    path.write_text(json.dumps({"radius_px": -1, "pixels_xy": [[1, 2]]}))
    with pytest.raises(ConfigError, match="positive radius"):
        DefectMap.from_json(path)
    with pytest.raises(ConfigError, match="cannot read"):
        DefectMap.from_json(tmp_path / "missing.json")


def _predictions(path, tables, solved=True):
    lines = []
    for k, (x, y, e) in enumerate(tables):
        det = [[float(a), float(b), 100.0] for a, b in zip(x, y)]
        th = np.radians(k)  # a different pointing each frame
        q = [float(np.cos(th / 2)), float(np.sin(th / 2)), 0.0, 0.0]
        sol = {"status": "solved", "quaternion_wxyz": q, "matched": [[int(r), 7] for r in np.flatnonzero(e)]}
        lines.append(
            json.dumps({"frame": f"f{k}", "detections": det, "solution": sol if solved else {"status": "refused"}})
        )
    path.write_text("\n".join(lines) + "\n")


def test_fusion_defects_learns_from_predictions_and_says_what_is_wrong(tmp_path, capsys):
    from fusion.cli import main

    pred = tmp_path / "p.jsonl"
    _predictions(pred, _frames(hot=((512.0, 12.0),), lit_in=4))
    out = tmp_path / "defects.json"
    assert main(["defects", str(pred), "--out", str(out)]) == 0
    assert "1 defect pixel(s) from 8 solved frames" in capsys.readouterr().out
    assert np.allclose(DefectMap.from_json(out).xy, [[512, 12]])
    _predictions(pred, _frames(lit_in=4), solved=False)
    assert main(["defects", str(pred), "--out", str(tmp_path / "none.json")]) == 2
    assert "0 solved frame(s)" in capsys.readouterr().err and not (tmp_path / "none.json").exists()
    pred.write_text("not a record\n")
    assert main(["defects", str(pred), "--out", str(out)]) == 2
    assert "line 1: not a fusion predict record" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="--min-frames"):
        learn_command([pred], out, min_frames=1)


def test_leave_one_out_with_pointings_counts_each_pointing_once():
    tables = _frames(lit_in=5)
    apart = np.array([[np.sin(np.radians(k)), 0.0, np.cos(np.radians(k))] for k in range(8)])
    assert [len(m) for m in leave_one_out(tables, boresights=apart)] == [1] * 8  # 4 other pointings or 5
    # frames 0-3 at one pointing, 4 apart: the hot pixel is lit at two pointings only
    two = np.array(
        [[0.0, 0.0, 1.0]] * 4 + [[np.sin(np.radians(5 + k)), 0.0, np.cos(np.radians(5 + k))] for k in range(4)]
    )
    assert all(len(m) == 0 for m in leave_one_out(tables, boresights=two))


def test_a_defect_that_wanders_along_a_band_is_a_region_and_stars_are_not():
    """A glow along one edge of the sensor whose detections land on different pixels in every frame (a band 4 px
    wide and 150 px long, 6 detections a frame, 12 frames) seldom makes a one-pixel defect, but its detections
    crowd far beyond the chance density of unexplained detections: the leave-one-out maps flag most of them, while
    the stars (explained, random pixels) and the random unexplained detections are almost never flagged; with
    seven times as many random ones the threshold rises with their density and still flags no star."""
    for n_random, lo_glow in ((3, 0.8), (20, 0.6)):
        rng = np.random.default_rng(n_random)
        tables = []
        for _ in range(12):
            x, y = list(rng.uniform(0, 1024, 30)), list(rng.uniform(0, 768, 30))
            e = [True] * 30
            for _ in range(6):  # the glow: a column band at the left edge
                x.append(rng.uniform(2.0, 6.0))
                y.append(rng.uniform(400.0, 550.0))
                e.append(False)
            for _ in range(n_random):  # random unexplained detections (cosmic rays, uncatalogued stars)
                x.append(rng.uniform(0, 1024))
                y.append(rng.uniform(0, 768))
                e.append(False)
            tables.append((np.array(x), np.array(y), np.array(e)))
        maps = leave_one_out(tables)
        glow = stars = random = 0
        for (x, y, _), dmap in zip(tables, maps):
            f = dmap.flags(Detections(x, y, np.ones(len(x))))
            glow, stars, random = glow + f[30:36].sum(), stars + f[:30].sum(), random + f[36:].sum()
        assert glow >= lo_glow * 72 and stars <= 1 and random <= 1
        if n_random == 20:
            assert maps[0].region_min > 3  # a denser background needs a bigger crowd
    # the map's regions survive a round trip through JSON (fusion defects writes it, fusion predict reads it)
    path = Path(pytest.importorskip("tempfile").mkdtemp()) / "map.json"
    dmap = learn(tables)
    dmap.to_json(path)
    back = DefectMap.from_json(path)
    assert back.region_min == dmap.region_min and len(back.region_xy) == len(dmap.region_xy)
    probe = Detections(np.array([4.0, 500.0]), np.array([470.0, 300.0]), np.ones(2))
    assert back.flags(probe).tolist() == dmap.flags(probe).tolist() == [True, False]


def test_a_camera_files_fixed_sources_are_dropped_at_detection(tmp_path):
    """--mask-fixed-sources: the light a fitted camera knows is fixed on its sensor (sensor.fixed_sources) loses its
    detections in Predictor.detect, before anything takes the brightest N; a camera without any is refused."""
    import yaml

    from fusion.solve.predict import Predictor
    from skygen.config import build_config
    from skygen.render.frame import Renderer

    glow = [300.0, 120.0, 3.0e5, 3.0]  # x, y px, e-/s, sigma px
    cam = {
        "camera": {"width_px": 512, "height_px": 256, "pixel_pitch_um": 5.5, "fov_deg": 12.0},
        "output": {"image_size_px": 128},
    }
    path = tmp_path / "glow.yaml"
    path.write_text(yaml.safe_dump({**cam, "sensor": {"fixed_sources": [glow]}}))
    img = (
        Renderer(
            build_config(
                {**cam, "sensor": {"fixed_sources": [glow]}, "output": {"image_size_px": 128, "full_res": True}}
            )
        )
        .render(0)
        .image_full
    )
    near = lambda det: np.hypot(det.x_px - glow[0], det.y_px - glow[1]) < 5  # noqa: E731
    plain, _, _ = Predictor(camera=path).detect(img)
    masked, _, _ = Predictor(camera=path, mask_fixed_sources=True).detect(img)
    assert near(plain).any() and not near(masked).any()
    assert len(plain) - len(masked) == int(DefectMap.from_fixed_sources([glow]).flags(plain).sum()) >= 1
    # fusion predict: the record says how many it dropped
    from fusion.cli import main

    np.save(tmp_path / "frame.npy", img)
    out = tmp_path / "pred.jsonl"
    argv = ["predict", str(tmp_path / "frame.npy"), "--camera", str(path), "--out", str(out)]
    assert main([*argv, "--mask-fixed-sources"]) == 0
    rec = json.loads(out.read_text().splitlines()[0])
    assert rec["fixed_sources_removed"] == len(plain) - len(masked) and rec["n_detections"] == len(masked)
    assert (
        DefectMap.from_fixed_sources([glow]).radius_px == 9.0
        and DefectMap.from_fixed_sources([[1, 1, 1, 1]]).radius_px == 8.0
    )
    bare = tmp_path / "bare.yaml"
    bare.write_text(yaml.safe_dump(cam))
    with pytest.raises(ConfigError, match="no sensor.fixed_sources"):
        Predictor(camera=bare, mask_fixed_sources=True)
