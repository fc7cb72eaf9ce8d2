"""Real frames: reading a user's frames, plate solving them, fitting a camera to them.

* :mod:`~skygen.real.frames` — the one reader of frame files (PNG, TIFF, BMP, FITS, ``.npy``, JPEG);
* :mod:`~skygen.real.platesolve` — tetra3rs databases (cached) and ideal-pinhole centroids,
  shared with ``fusion.solve.tetra``;
* ``skygen fit-camera``: :mod:`~skygen.real.fit_camera` (the command's steps),
  :mod:`~skygen.real.fit_geometry` (solutions, catalogue matches, the joint geometry fit),
  :mod:`~skygen.real.fit_pixels` (background, noise, fixed pattern, PSF, hot pixels, zero point),
  :mod:`~skygen.real.fit_sensor` (gain, bias, read noise: the mean-variance line where the frames constrain
  it, else a direct fit of the background's level and noise),
  :mod:`~skygen.real.fit_render` (the camera config, renders at the frames' attitudes, the check against
  the frames and one correction),
  :mod:`~skygen.real.fit_report` (camera YAML and report) and
  :mod:`~skygen.real.frame_stats` (the real-versus-rendered statistics and their tolerances).
"""
