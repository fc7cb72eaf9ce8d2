"""Boresight attitudes: sampling, rotation matrices and quaternions.

See :mod:`skygen.conventions` for the definition of roll and of the quaternion. The
attitude matrix ``R`` has the camera axes (x, y, z) expressed in ICRS as its columns,
so ``v_icrs = R @ v_cam`` and ``v_cam = R.T @ v_icrs``.
"""

from __future__ import annotations

import numpy as np

from skygen.sky.catalog import radec_to_vec


def attitude_matrix(ra_deg: float, dec_deg: float, roll_deg: float) -> np.ndarray:
    """Camera-to-ICRS rotation matrix (3, 3) for a boresight and a roll.

    With b the boresight, n and e the local north and east unit vectors and
    up = cos(roll) n + sin(roll) e: z_cam = b, y_cam = -up (rows grow downwards),
    x_cam = y_cam x z_cam = -cos(roll) e + sin(roll) n.
    """
    a, d, r = np.radians([ra_deg, dec_deg, roll_deg])
    b = radec_to_vec(a, d)
    east = np.array([-np.sin(a), np.cos(a), 0.0])
    north = np.array([-np.sin(d) * np.cos(a), -np.sin(d) * np.sin(a), np.cos(d)])
    up = np.cos(r) * north + np.sin(r) * east
    y = -up
    x = np.cross(y, b)
    return np.column_stack([x, y, b])


def matrix_to_radec_roll(m: np.ndarray) -> tuple[float, float, float]:
    """(ra_deg, dec_deg, roll_deg) of a camera -> ICRS matrix: the inverse of :func:`attitude_matrix`.

    ra in [0, 360), dec in [-90, 90], roll (the position angle of image up, -y, from north through
    east) in [0, 360). The one inverse: fusion's solvers and ``skygen fit-camera`` both use it.
    """
    m = np.asarray(m, np.float64)
    b, up = m[:, 2], -m[:, 1]
    ra = np.arctan2(b[1], b[0])
    dec = np.arcsin(np.clip(b[2], -1.0, 1.0))
    east = np.array([-np.sin(ra), np.cos(ra), 0.0])
    north = np.array([-np.sin(dec) * np.cos(ra), -np.sin(dec) * np.sin(ra), np.cos(dec)])
    roll = np.arctan2(up @ east, up @ north)
    return float(np.degrees(ra) % 360.0), float(np.degrees(dec)), float(np.degrees(roll) % 360.0)


def matrix_to_quaternion(m: np.ndarray) -> np.ndarray:
    """Unit quaternion [w, x, y, z] (w >= 0) of a rotation matrix (Shepperd's method)."""
    m = np.asarray(m, dtype=np.float64)
    tr = np.trace(m)
    cands = np.array([tr, m[0, 0], m[1, 1], m[2, 2]])
    k = int(np.argmax(cands))
    if k == 0:
        w = np.sqrt(1.0 + tr) / 2
        q = [w, (m[2, 1] - m[1, 2]) / (4 * w), (m[0, 2] - m[2, 0]) / (4 * w), (m[1, 0] - m[0, 1]) / (4 * w)]
    elif k == 1:
        x = np.sqrt(1.0 + 2 * m[0, 0] - tr) / 2
        q = [(m[2, 1] - m[1, 2]) / (4 * x), x, (m[0, 1] + m[1, 0]) / (4 * x), (m[0, 2] + m[2, 0]) / (4 * x)]
    elif k == 2:
        y = np.sqrt(1.0 + 2 * m[1, 1] - tr) / 2
        q = [(m[0, 2] - m[2, 0]) / (4 * y), (m[0, 1] + m[1, 0]) / (4 * y), y, (m[1, 2] + m[2, 1]) / (4 * y)]
    else:
        z = np.sqrt(1.0 + 2 * m[2, 2] - tr) / 2
        q = [(m[1, 0] - m[0, 1]) / (4 * z), (m[0, 2] + m[2, 0]) / (4 * z), (m[1, 2] + m[2, 1]) / (4 * z), z]
    quat = np.array(q)
    quat /= np.linalg.norm(quat)
    return -quat if quat[0] < 0 else quat


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion [w, x, y, z]."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation matrix for a right-handed rotation by ``angle_rad`` about ``axis`` (Rodrigues)."""
    axis = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(axis)
    if n == 0 or angle_rad == 0:
        return np.eye(3)
    k = axis / n
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * kx + (1 - np.cos(angle_rad)) * kx @ kx


def sample_boresight(cfg, frame_index: int, rng: np.random.Generator) -> tuple[float, float, float]:
    """(ra_deg, dec_deg, roll_deg) for one frame from an :class:`AttitudeConfig`.

    ``uniform``: isotropic on the sphere. ``region``: isotropic within a cap of
    ``region_radius_deg`` around the region centre. ``list``: the frame_index-th entry
    of the lists (cycled). Roll is uniform in ``roll_range_deg`` unless listed.
    """
    lo, hi = cfg.roll_range_deg
    if cfg.mode == "list":
        k = frame_index % len(cfg.ra_deg)
        roll = cfg.roll_deg[k] if cfg.roll_deg else rng.uniform(lo, hi)
        return float(cfg.ra_deg[k]) % 360.0, float(cfg.dec_deg[k]), float(roll) % 360.0
    u1, u2, u3 = rng.random(3)
    if cfg.mode == "uniform":
        ra = 360.0 * u1
        dec = np.degrees(np.arcsin(2.0 * u2 - 1.0))
    else:  # region: uniform in a spherical cap, then rotated onto the centre
        cos_r = np.cos(np.radians(cfg.region_radius_deg))
        cos_t = 1.0 - u2 * (1.0 - cos_r)
        sin_t = np.sqrt(max(0.0, 1.0 - cos_t * cos_t))
        phi = 2 * np.pi * u1
        local = np.array([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])
        m = attitude_matrix(cfg.region_ra_deg, cfg.region_dec_deg, 0.0)
        v = m @ local
        ra = np.degrees(np.arctan2(v[1], v[0])) % 360.0
        dec = np.degrees(np.arcsin(np.clip(v[2], -1, 1)))
    roll = lo + (hi - lo) * u3
    return float(ra % 360.0), float(dec), float(roll % 360.0)


def boresights_from_uniforms(acfg, idx: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ra, dec, roll) in degrees for frames ``idx`` from three uniforms per frame ``u`` (B, 3),
    distributed as :func:`sample_boresight` draws them (the vectorised form the streams use)."""
    lo, hi = acfg.roll_range_deg
    roll = (lo + (hi - lo) * u[:, 2]) % 360.0
    if acfg.mode == "list":
        k = idx % len(acfg.ra_deg)
        ra = np.asarray(acfg.ra_deg, np.float64)[k] % 360.0
        dec = np.asarray(acfg.dec_deg, np.float64)[k]
        if acfg.roll_deg:
            roll = np.asarray(acfg.roll_deg, np.float64)[k] % 360.0
        return ra, dec, roll
    if acfg.mode == "uniform":
        return (360.0 * u[:, 0]) % 360.0, np.degrees(np.arcsin(2.0 * u[:, 1] - 1.0)), roll
    cos_r = np.cos(np.radians(acfg.region_radius_deg))
    cos_t = 1.0 - u[:, 1] * (1.0 - cos_r)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t**2))
    phi = 2 * np.pi * u[:, 0]
    local = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)
    v = local @ attitude_matrix(acfg.region_ra_deg, acfg.region_dec_deg, 0.0).T
    return (np.degrees(np.arctan2(v[:, 1], v[:, 0])) % 360.0, np.degrees(np.arcsin(np.clip(v[:, 2], -1, 1))), roll)


def boresight_sample(acfg, n: int, seed: int) -> np.ndarray:
    """(n, 3) ICRS unit boresight vectors drawn from an :class:`AttitudeConfig`'s distribution
    (uniform on the sphere, a cap, or the listed pointings cycled), seeded by ``seed`` alone: what
    regions of the sky are fitted on when they must not depend on a dataset's size."""
    u = np.random.default_rng([int(seed), 0x5B7]).random((int(n), 3))
    ra, dec, _ = boresights_from_uniforms(acfg, np.arange(int(n)), u)
    ra, dec = np.radians(ra), np.radians(dec)
    return np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=1)


def attitude_matrices(ra_deg, dec_deg, roll_deg) -> np.ndarray:
    """:func:`attitude_matrix` for arrays: (B, 3, 3)."""
    a, d, r = (np.radians(np.asarray(v, np.float64)) for v in (ra_deg, dec_deg, roll_deg))
    b = radec_to_vec(a, d)
    z = np.zeros_like(a)
    east = np.stack([-np.sin(a), np.cos(a), z], -1)
    north = np.stack([-np.sin(d) * np.cos(a), -np.sin(d) * np.sin(a), np.cos(d)], -1)
    y = -(np.cos(r)[:, None] * north + np.sin(r)[:, None] * east)
    x = np.cross(y, b)
    return np.stack([x, y, b], axis=-1)


def matrices_to_quaternions(R: np.ndarray) -> np.ndarray:
    """:func:`matrix_to_quaternion` for (B, 3, 3): (B, 4), w >= 0 (same method)."""
    R = np.asarray(R, np.float64).reshape(-1, 3, 3)
    tr = np.trace(R, axis1=1, axis2=2)
    k = np.argmax(np.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], -1), axis=-1)
    q = np.empty((len(R), 4))
    for case in range(4):
        m = R[k == case]
        t = tr[k == case]
        if case == 0:
            w = np.sqrt(1.0 + t) / 2
            c = [
                w,
                (m[:, 2, 1] - m[:, 1, 2]) / (4 * w),
                (m[:, 0, 2] - m[:, 2, 0]) / (4 * w),
                (m[:, 1, 0] - m[:, 0, 1]) / (4 * w),
            ]
        elif case == 1:
            x = np.sqrt(1.0 + 2 * m[:, 0, 0] - t) / 2
            c = [
                (m[:, 2, 1] - m[:, 1, 2]) / (4 * x),
                x,
                (m[:, 0, 1] + m[:, 1, 0]) / (4 * x),
                (m[:, 0, 2] + m[:, 2, 0]) / (4 * x),
            ]
        elif case == 2:
            y = np.sqrt(1.0 + 2 * m[:, 1, 1] - t) / 2
            c = [
                (m[:, 0, 2] - m[:, 2, 0]) / (4 * y),
                (m[:, 0, 1] + m[:, 1, 0]) / (4 * y),
                y,
                (m[:, 1, 2] + m[:, 2, 1]) / (4 * y),
            ]
        else:
            z = np.sqrt(1.0 + 2 * m[:, 2, 2] - t) / 2
            c = [
                (m[:, 1, 0] - m[:, 0, 1]) / (4 * z),
                (m[:, 0, 2] + m[:, 2, 0]) / (4 * z),
                (m[:, 1, 2] + m[:, 2, 1]) / (4 * z),
                z,
            ]
        q[k == case] = np.stack(c, -1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, :1] < 0, -q, q)
