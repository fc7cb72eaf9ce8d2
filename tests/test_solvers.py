"""The solver interface and the tetra3rs baseline: conventions checked on rendered frames."""

from __future__ import annotations

import numpy as np
import pytest

from skygen.attitude import attitude_matrix
from skygen.config import load_config
from skygen.render import Renderer

from fusion.solvers.base import (Detections, Refusal, Solution, Solver, boresight_error_deg, radec_roll_from_matrix,
                                 roll_error_deg, rotation_angle_deg)

tetra3rs = pytest.importorskip("tetra3rs")


@pytest.fixture(scope="module")
def renderer():
    return Renderer(load_config(overrides=["n_frames=20"]))


@pytest.fixture(scope="module")
def tetra(renderer, tmp_path_factory):
    from fusion.solvers.tetra import Tetra3Solver
    return Tetra3Solver(renderer.camera, db_folder=tmp_path_factory.mktemp("db"))


def test_radec_roll_from_matrix_inverts_attitude_matrix():
    rng = np.random.default_rng(0)
    for _ in range(200):
        ra, dec, roll = rng.uniform(0, 360), rng.uniform(-89, 89), rng.uniform(0, 360)
        r2, d2, o2 = radec_roll_from_matrix(attitude_matrix(ra, dec, roll))
        assert abs((r2 - ra + 180) % 360 - 180) < 1e-9 and abs(d2 - dec) < 1e-9
        assert roll_error_deg(o2, roll) < 1e-8


def test_attitude_errors():
    a, b = attitude_matrix(10, 20, 30), attitude_matrix(10, 20, 31)
    assert rotation_angle_deg(a, b) == pytest.approx(1.0, abs=1e-9)
    assert boresight_error_deg(a, b) == pytest.approx(0.0, abs=1e-6)
    assert roll_error_deg(359.5, 0.5) == pytest.approx(1.0)


def test_tetra3rs_agrees_with_skygen_conventions(renderer, tetra):
    """Rendered frames solved from their detections: quaternion, RA/Dec and roll in skygen's convention."""
    assert isinstance(tetra, Solver)
    n_solved = 0
    for i in range(6):
        f = renderer.render(i)
        res = tetra.solve(Detections.from_table(f.detections), renderer.camera)
        if isinstance(res, Refusal):
            continue
        n_solved += 1
        truth = attitude_matrix(f.ra_deg, f.dec_deg, f.roll_deg)
        assert rotation_angle_deg(truth, res.matrix) < 60 / 3600        # < 1 arcmin, full attitude
        assert abs((res.ra_deg - f.ra_deg + 180) % 360 - 180) * np.cos(np.radians(f.dec_deg)) < 0.01
        assert res.dec_deg == pytest.approx(f.dec_deg, abs=0.01)
        assert roll_error_deg(res.roll_deg, f.roll_deg) < 0.02
        # tetra3rs's own roll is the position angle of +y (image down): skygen's roll + 180
        assert roll_error_deg(res.extra["tetra3rs_roll_deg"] + 180.0, f.roll_deg) < 0.02
        np.testing.assert_allclose(res.quaternion, f.quaternion, atol=1e-3)
        assert res.n_matched >= 4 and res.residual_arcsec < 60 and 0 <= res.confidence <= 1
        assert set(res.matched[:, 0]) <= set(range(len(f.detections["x_px"])))
    assert n_solved >= 5


def test_tetra3rs_principal_point_and_distortion(tmp_path):
    """An off-centre principal point and barrel distortion are removed before tetra3rs sees the centroids."""
    from fusion.solvers.tetra import Tetra3Solver
    r = Renderer(load_config(overrides=["n_frames=4", "camera.principal_x_px=540", "camera.principal_y_px=490",
                                        "camera.k1=-0.05"]))
    solver = Tetra3Solver(r.camera, db_folder=tmp_path)
    f = r.render(1)
    res = solver.solve(Detections.from_table(f.detections), r.camera)
    assert isinstance(res, Solution), res
    assert rotation_angle_deg(attitude_matrix(f.ra_deg, f.dec_deg, f.roll_deg), res.matrix) < 60 / 3600


def test_tetra3rs_refuses_few_or_random_detections(renderer, tetra):
    f = renderer.render(0)
    det = Detections.from_table(f.detections)
    assert isinstance(tetra.solve(det.brightest(2), renderer.camera), Refusal)
    rng = np.random.default_rng(1)
    noise = Detections(rng.uniform(0, 1023, 12), rng.uniform(0, 1023, 12), rng.uniform(1e3, 1e4, 12))
    res = tetra.solve(noise, renderer.camera)
    assert isinstance(res, Refusal) and res.reason in ("no_match", "timeout")
    assert res.to_dict()["status"] == "refused"
