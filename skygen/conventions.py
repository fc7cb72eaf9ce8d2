"""Conventions used everywhere in skygen, written down once.

These strings are stored in every shard (root attribute ``conventions``) so that a
reader who never installed skygen knows how to interpret the numbers.

Angles
    Degrees in every stored dataset and config key, unless the name ends in ``_rad``.
    Right ascension in [0, 360), declination in [-90, 90].

Celestial frame
    ICRS. Star positions are propagated with their proper motion from the catalog epoch
    (Hipparcos: J1991.25) to the observation epoch ``epoch_yr`` (Julian years, TCB/TT
    differences neglected). Parallax and aberration are not applied.

Camera frame
    Right-handed. +z is the boresight (from the camera towards the sky), +x points
    along increasing image column (to the right in the stored array), +y along
    increasing image row (down in the stored array). A direction (X, Y, Z) in the camera
    frame lands on the pixel ``x = cx + f * X / Z``, ``y = cy + f * Y / Z`` (pinhole,
    before distortion); ``f`` is the focal length in pixels.

Roll
    The position angle of image "up" (the -y direction, towards row 0) measured from
    celestial north through east, in degrees. At roll 0 north is up and east is to the
    *left* (the sky seen from inside the sphere, like a photograph of the sky); at roll
    90 east is up.

Attitude quaternion
    ``[w, x, y, z]`` (scalar first), unit norm, ``w >= 0``. It rotates camera-frame
    vectors into ICRS: ``v_icrs = q * v_cam * conj(q)``. Its rotation matrix has the
    camera axes x, y, z (in ICRS) as columns.

Pixels and arrays
    Images are stored as ``[row, col]`` = ``[y, x]``. The *centre* of the top-left pixel
    is (x, y) = (0, 0); that pixel covers [-0.5, 0.5) x [-0.5, 0.5). Positions of
    stars and detections are always in full-resolution sensor pixels, even when the
    stored image is downsampled. For a stored image downsampled by an integer factor
    ``s``, stored pixel (u, v) covers full-resolution x in [s*u - 0.5, s*(u+1) - 0.5):
    ``u = (x + 0.5) / s - 0.5``.

Other tools (checked on rendered frames in ``tests/test_solvers.py``)
    tetra3rs: centroids relative to the image centre, ``x_t3 = x - (W - 1)/2`` (same axes);
    its quaternion and ``rotation_matrix_icrs_to_camera`` rotate ICRS into the camera frame
    (the conjugate / transpose of ours); its ``roll_deg`` is the position angle of +y, i.e.
    ``roll_tetra3rs = roll - 180`` (mod 360).

Photometry
    Electrons (e-) for charge, ADU for digital numbers, gain in e-/ADU. Magnitudes are
    Hipparcos Hp unless named otherwise.
"""

CONVENTIONS = {
    "angles": "degrees unless the name ends in _rad",
    "celestial_frame": "ICRS; positions propagated with proper motion to epoch_yr",
    "camera_frame": "+z boresight towards the sky, +x along increasing column, +y along increasing row",
    "roll": "position angle of image up (-y, towards row 0) from celestial north through east, degrees; "
    "roll 0: north up, east left",
    "quaternion": "[w, x, y, z] scalar first, unit, w >= 0, rotates camera-frame vectors into ICRS",
    "array_order": "images stored [y, x] = [row, col]",
    "pixel_centre": "centre of the top-left pixel is (x, y) = (0, 0); positions in full-resolution pixels",
    "downsample": "stored pixel u covers full-resolution x in [s*u - 0.5, s*(u+1) - 0.5)",
    "charge": "electrons (e-); digital numbers in ADU; gain in e-/ADU",
    "magnitude": "Hipparcos Hp unless named otherwise",
}


def full_to_stored(xy_full, factor: int):
    """Convert full-resolution pixel coordinates to stored (downsampled) coordinates."""
    return (xy_full + 0.5) / factor - 0.5
