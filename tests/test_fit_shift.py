"""camera.bright_shift_px (and _x_px / _y_px): fitted from paired stars where it is there and only there, taken off by
the Predictor."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from skygen.real.fit_shift import FROM_GRID, fit_bright_shift


def _rows(
    shift_px: float, q0: float, n: int = 1500, noise_px: float = 0.6, seed: int = 0, uniform=(0.0, 0.0)
) -> np.ndarray:
    """Paired stars (:func:`skygen.real.fit_shift.shift_rows`' columns) of a camera whose detections lie
    ``shift_px`` per decade beyond ``q0`` farther out and ``uniform`` (px per decade along x, y) away, with a
    distortion residual (what a geometry fit on shifted bright stars leaves) and a per-star scatter per axis."""
    rng = np.random.default_rng(seed)
    rho = np.sqrt(rng.uniform(0, 1, n))  # stars spread evenly over the sensor
    phi = rng.uniform(0, 2 * np.pi, n)
    ex, ey = np.cos(phi), np.sin(phi)
    q = 1.0 + rng.exponential(0.45, n)  # most stars faint, a tail of bright ones
    h = np.maximum(q - q0, 0)
    radial = 0.4 * rho - 0.6 * rho**3 - shift_px * rho * h  # the star's place less the detection's, outward
    dx = ex * radial - uniform[0] * h + rng.normal(0, noise_px, n)
    dy = ey * radial - uniform[1] * h + rng.normal(0, noise_px, n)
    bad = rng.random(n) < 0.02  # a few wrong pairs
    dx[bad], dy[bad] = rng.uniform(-8, 8, bad.sum()), rng.uniform(-8, 8, bad.sum())
    return np.column_stack([rho, q, dx * ex + dy * ey, ex, ey, dx, dy])


def test_a_shift_is_found_where_bright_stars_sit_farther_out():
    fit = fit_bright_shift(_rows(4.0, 2.0))
    assert abs(fit["px"] - 4.0) < 0.6 and abs(fit["from"] - 2.0) <= 0.25
    assert fit["t"] > 10 and "camera.bright_shift_px" in fit["note"]
    assert fit["rms_px"] < fit["rms_px_without"]


def test_no_shift_is_fitted_where_there_is_none():
    for seed in range(4):
        fit = fit_bright_shift(_rows(0.0, 2.0, seed=seed))
        assert fit["px"] == 0.0 and fit["note"].startswith("bright-star shift: none"), fit["note"]


def test_a_uniform_shift_is_found_beside_the_radial_one_or_alone():
    """Bright detections moved one way across the whole sensor (a tilted lens, a processor's filtering): the fit finds
    the vector, with or without a radial shift, and nothing of it where there is none."""
    both = fit_bright_shift(_rows(4.0, 2.0, uniform=(-0.8, 0.5)))
    assert abs(both["px"] - 4.0) < 0.6 and abs(both["from"] - 2.0) <= 0.25
    assert abs(both["x_px"] + 0.8) < 0.25 and abs(both["y_px"] - 0.5) < 0.25, both["uniform"]["note"]
    alone = fit_bright_shift(_rows(0.0, 2.0, uniform=(0.0, -1.0), seed=3))
    assert alone["px"] == 0.0 and abs(alone["y_px"] + 1.0) < 0.4 and abs(alone["x_px"]) < 0.25
    assert abs(alone["from"] - 2.0) <= 0.5 and "bright_shift_y_px" in alone["note"]
    for seed in range(4):
        none = fit_bright_shift(_rows(4.0, 2.0, seed=seed))
        assert none["x_px"] == none["y_px"] == 0.0 and "uniform shift: none" in none["note"], none["note"]


def test_too_few_stars_say_so():
    fit = fit_bright_shift(_rows(4.0, 2.0, n=30))
    assert fit["px"] == 0.0 and "not measured" in fit["note"]
    assert 2.0 in FROM_GRID


def test_unshift_undoes_the_drawn_shift_and_the_predictor_takes_it_off(tmp_path):
    """A star drawn where Camera.bright_shift puts it is moved back exactly; the Predictor of a camera file with the
    shift moves bright detections, not faint ones; a camera without it leaves detections alone."""
    from fusion.solve.base import Detections
    from fusion.solve.predict import Predictor
    from skygen.config import build_config
    from skygen.instrument.camera import Camera

    shifted = {
        "bright_shift_px": 4.0,
        "bright_shift_from": 1.5,
        "bright_shift_x_px": -0.7,
        "bright_shift_y_px": 0.4,
        "focal_length_mm": 16.0,
        "fov_deg": None,
    }
    cam = Camera.from_config(build_config({"camera": shifted}).camera)
    x, y = np.array([30.0, 900.0, 512.0]), np.array([40.0, 1000.0, 300.0])
    q = np.array([3.5, 3.0, 1.2])
    dx, dy = cam.bright_shift(x, y, q)
    assert np.all(np.hypot(dx, dy)[:2] > 2.0) and dx[2] == dy[2] == 0.0
    # outward: away from the principal point
    assert np.all(
        ((x + dx - cam.cx_px) ** 2 + (y + dy - cam.cy_px) ** 2)[:2] > ((x - cam.cx_px) ** 2 + (y - cam.cy_px) ** 2)[:2]
    )
    sigma = 3.0
    flux = sigma * 10**q
    bx, by = cam.unshift(x + dx, y + dy, flux, sigma)
    assert np.max(np.hypot(bx - x, by - y)) < 1e-9
    f = tmp_path / "shifted.yaml"
    base = {"width_px": 1024, "height_px": 1024, "pixel_pitch_um": 5.5, "focal_length_mm": 16.0}
    f.write_text(yaml.safe_dump({"camera": {**base, **{k: v for k, v in shifted.items() if k.startswith("bright")}}}))
    pred = Predictor(camera=f)
    det = pred._unshifted(Detections(x + dx, y + dy, flux), sigma)
    np.testing.assert_allclose(np.column_stack([det.x_px, det.y_px]), np.column_stack([bx, by]))
    plain = tmp_path / "plain.yaml"
    plain.write_text(yaml.safe_dump({"camera": base}))
    same = Predictor(camera=plain)._unshifted(Detections(x, y, flux), sigma)
    np.testing.assert_array_equal(same.x_px, x)


def test_the_match_tolerance_follows_the_bright_stars_scatter_within_1_to_2_px():
    from skygen.real.fit_shift import TOL_FACTOR, match_tolerance

    rng = np.random.default_rng(1)
    tight = match_tolerance(rng.normal(0, 0.15, (200, 2)))
    assert tight["px"] == 1.0 and tight["p95_px"] < 0.5  # a precise camera: the floor
    mid = match_tolerance(rng.normal(0, 0.4, (400, 2)))
    assert 1.0 < mid["px"] < 2.0 and mid["px"] == pytest.approx(TOL_FACTOR * mid["p95_px"])
    loose = match_tolerance(rng.normal(0, 1.0, (200, 2)))
    assert loose["px"] == 2.0  # never wider than the rendered benchmarks' 2 px
    assert match_tolerance(rng.normal(0, 0.1, (10, 2)))["px"] is None


def test_the_fine_stage_takes_the_cameras_match_tolerance():
    """camera.match_tol_px sets the fine stage's window where no tol_px is given; 2 px without one."""
    import dataclasses
    from types import SimpleNamespace

    from fusion.solve import fine
    from skygen.config import build_config
    from skygen.instrument.camera import Camera

    cam = Camera.from_config(build_config({}).camera)
    fitted = dataclasses.replace(cam, match_tol_px=1.2)
    assert fine.tolerance_of(SimpleNamespace(camera=cam), None) == fine.TOL_PX == 2.0
    assert fine.tolerance_of(SimpleNamespace(camera=fitted), None) == 1.2
    assert fine.tolerance_of(SimpleNamespace(camera=fitted), 3.0) == 3.0  # given explicitly: that
    with pytest.raises(ValueError, match="tol_px"):
        fine.tolerance_of(SimpleNamespace(camera=cam), -1.0)
    c = build_config({"camera": {"match_tol_px": 1.3}})
    assert Camera.from_config(c.camera).match_tol_px == 1.3


def test_a_datasets_detections_carry_their_frames_noise_for_the_shift():
    """fusion predict on a dataset: each frame's stored noise comes with its detections, so a camera's bright-star
    shift can be taken off them as off a frame's own (Predictor._unshifted needs the noise)."""
    from pathlib import Path

    from fusion.solve.frames import iter_inputs

    folder = Path(__file__).parent / "data" / "schema1-dataset"
    rows = list(iter_inputs([str(folder)], 2))
    assert len(rows) == 2
    for _, img, table, _, err in rows:
        assert img is None and err is None and table["noise_adu"] > 0 and len(table["x_px"]) == len(table["flux_adu"])


def test_the_error_a_frames_brightest_stars_share_is_told_from_their_own_scatter():
    """shared_error: offsets drawn afresh per star average out in a frame's mean (about 0 shared); an offset every
    star of a frame shares, drawn per frame or the same in every frame (a bias), is what it measures, per axis; stars
    outside the match window and frames with fewer than 3 stars in it do not count."""
    from skygen.real.fit_shift import shared_error

    rng = np.random.default_rng(4)
    own = [rng.normal(0, 0.3, (8, 2)) for _ in range(200)]
    assert shared_error(own, 2.0)["px"] < 0.05  # (each part kept at least 0: a little above 0 by chance)
    common = [o + rng.normal(0, 0.2, 2) for o in own]  # 0.2 px per axis shared within each frame
    got = shared_error(common, 2.0)
    assert got["px"] == pytest.approx(0.2, abs=0.03) and got["frames"] == 200
    biased = [o + np.array([0.25, 0.0]) for o in own]  # the same in every frame: rms over both axes 0.25 / sqrt 2
    got = shared_error(biased, 2.0)
    assert got["bias_px"] == pytest.approx([0.25, 0.0], abs=0.03) and got["px"] == pytest.approx(0.177, abs=0.03)
    assert got["varies_px"] < 0.05 and "lie on average (+0.2" in got["note"]
    # a bias hidden in a wide per-star scatter (0.6 px, 8 stars: 0.21 px in a mean) still shows over 12 frames
    wide = [rng.normal(0, 0.6, (8, 2)) + np.array([0.0, -0.2]) for _ in range(12)]
    assert shared_error(wide, 2.0)["px"] > 0.08
    far = [np.vstack([o, [[4.0, 4.0]]]) for o in own]  # one wrong pair per frame, outside a 2 px window
    assert shared_error(far, 2.0)["px"] < 0.05
    assert shared_error([o[:2] for o in own], 2.0)["px"] is None  # two stars a frame: not measured
