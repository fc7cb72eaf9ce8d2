"""Projection, attitude and convention checks against independent references."""

import numpy as np
import pytest
from astropy.wcs import WCS

from skygen.config import load_config
from skygen.instrument.camera import Camera
from skygen.sky.attitude import attitude_matrix, matrix_to_quaternion, quaternion_to_matrix, sample_boresight
from skygen.sky.catalog import radec_to_vec


def make_wcs(cam: Camera, ra, dec, roll) -> WCS:
    """A FITS TAN WCS built from the conventions, not from skygen's projection code."""
    r = np.radians(roll)
    scale = np.degrees(1.0 / cam.f_px)
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [ra, dec]
    w.wcs.crpix = [cam.cx_px + 1, cam.cy_px + 1]  # FITS pixels are 1-based
    # image x = -cos(roll) east + sin(roll) north ; image y = -sin(roll) east - cos(roll) north
    w.wcs.cd = scale * np.array([[-np.cos(r), -np.sin(r)], [np.sin(r), -np.cos(r)]])
    return w


@pytest.mark.parametrize("seed", range(6))
def test_projection_matches_astropy_wcs(seed):
    rng = np.random.default_rng(seed)
    cam = Camera.from_config(load_config().camera)
    ra, dec, roll = rng.uniform(0, 360), np.degrees(np.arcsin(rng.uniform(-1, 1))), rng.uniform(0, 360)
    if seed == 0:
        dec = 89.9  # near the pole
    R = attitude_matrix(ra, dec, roll)
    x = rng.uniform(-0.5, cam.width_px - 0.5, 200)
    y = rng.uniform(-0.5, cam.height_px - 0.5, 200)
    sky = make_wcs(cam, ra, dec, roll).pixel_to_world_values(x, y)
    v = radec_to_vec(np.radians(sky[0]), np.radians(sky[1]))
    px, py, front = cam.project(v @ R)
    assert front.all()
    assert np.max(np.hypot(px - x, py - y)) < 0.01


def test_roll_convention_north_up_east_left():
    cam = Camera.from_config(load_config().camera)
    R = attitude_matrix(100.0, 20.0, 0.0)
    north = radec_to_vec(np.radians(100.0), np.radians(21.0))
    east = radec_to_vec(np.radians(101.0), np.radians(20.0))
    xn, yn, _ = cam.project(north @ R)
    xe, ye, _ = cam.project(east @ R)
    assert yn[0] < cam.cy_px - 10 and abs(xn[0] - cam.cx_px) < 1  # north is up
    assert xe[0] < cam.cx_px - 10 and abs(ye[0] - cam.cy_px) < 1  # east is left
    R90 = attitude_matrix(100.0, 20.0, 90.0)
    xe, ye, _ = cam.project(east @ R90)
    assert ye[0] < cam.cy_px - 10  # roll 90: east is up


def test_quaternion_round_trip_and_direction():
    rng = np.random.default_rng(1)
    for _ in range(50):
        R = attitude_matrix(rng.uniform(0, 360), rng.uniform(-90, 90), rng.uniform(0, 360))
        q = matrix_to_quaternion(R)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(quaternion_to_matrix(q), R, atol=1e-12)
        # rotating the camera boresight (0, 0, 1) with q gives the ICRS boresight
        w, x, y, z = q
        v = np.array([0, 0, 1.0])
        u = np.array([x, y, z])
        rotated = v + 2 * w * np.cross(u, v) + 2 * np.cross(u, np.cross(u, v))
        np.testing.assert_allclose(rotated, R[:, 2], atol=1e-12)


def test_distortion_round_trip_and_unproject():
    cfg = load_config(overrides=["camera.k1=-0.05", "camera.k2=0.01", "camera.p1=0.001", "camera.p2=-0.0005"])
    cam = Camera.from_config(cfg.camera)
    rng = np.random.default_rng(2)
    x = rng.uniform(0, 1023, 500)
    y = rng.uniform(0, 1023, 500)
    v = cam.unproject(x, y)
    px, py, _ = cam.project(v)
    assert np.max(np.hypot(px - x, py - y)) < 1e-6
    assert cam.has_distortion


def test_fov_from_config():
    cam = Camera.from_config(load_config(overrides=["camera.fov_deg=15"]).camera)
    assert abs(cam.fov_deg[0] - 15.0) < 1e-9
    assert abs(Camera.from_config(load_config().camera).fov_deg[0] - 20.0) < 0.01


def test_uniform_boresights_are_isotropic():
    cfg = load_config().attitude
    pts = np.array([sample_boresight(cfg, i, np.random.default_rng(i)) for i in range(4000)])
    z = np.sin(np.radians(pts[:, 1]))
    assert abs(z.mean()) < 0.05 and abs(np.mean(z**2) - 1 / 3) < 0.03  # uniform in sin(dec)
    assert pts[:, 0].min() >= 0 and pts[:, 0].max() < 360 and pts[:, 2].max() < 360


def test_region_and_list_modes():
    cfg = load_config(
        overrides=[
            "attitude.mode=region",
            "attitude.region_ra_deg=80",
            "attitude.region_dec_deg=-30",
            "attitude.region_radius_deg=5",
        ]
    ).attitude
    c = radec_to_vec(np.radians(80), np.radians(-30))
    for i in range(200):
        ra, dec, _ = sample_boresight(cfg, i, np.random.default_rng(i))
        assert np.degrees(np.arccos(radec_to_vec(np.radians(ra), np.radians(dec)) @ c)) <= 5 + 1e-9
    cfg = load_config(
        overrides=["attitude.mode=list", "attitude.ra_deg=[1,2]", "attitude.dec_deg=[3,4]", "attitude.roll_deg=[5,6]"]
    ).attitude
    assert sample_boresight(cfg, 3, np.random.default_rng(0)) == (2.0, 4.0, 6.0)
