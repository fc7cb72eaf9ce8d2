"""Pinhole star-tracker camera with optional Brown-Conrady distortion.

Units: focal length in mm and pixel pitch in micrometres in the config; internally the
focal length in pixels ``f_px = focal_length_mm * 1000 / pixel_pitch_um``. Pixel
coordinates follow :mod:`skygen.conventions` (centre of the top-left pixel at (0, 0)).

Non-square pixels: ``aspect`` = pixel height / pixel width (1: square; 2: each pixel twice
as tall as wide, e.g. an interlaced read-out stored as half-height frames). ``f_px`` and
``pixel_pitch_um`` are along x (columns); along y (rows) the focal length in pixels is
``f_px / aspect``::

    x_px = cx + f_px * x_d            y_px = cy + (f_px / aspect) * y_d

Distortion (Brown-Conrady) acts on normalised image coordinates (X/Z, Y/Z) with
r^2 = x^2 + y^2::

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Camera:
    width_px: int
    height_px: int
    f_px: float
    cx_px: float
    cy_px: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    aspect: float = 1.0  # pixel height / width
    # per-axis centroid error of a matched star measured on real frames (camera.centroid_sigma_px), px; None: unknown.
    # The attitude covariance's floor (fusion.solve.base.attitude_covariance); nothing here depends on it
    centroid_sigma_px: float | None = None
    # a detection's outward centroid shift per decade of flux/noise beyond bright_shift_from, px at the farthest
    # corner (camera.bright_shift_px; see :meth:`bright_shift`)
    bright_shift_px: float = 0.0
    bright_shift_from: float = 1.5
    # the few-star solver's match tolerance on this camera (camera.match_tol_px), px; None: its default
    match_tol_px: float | None = None
    # a detection's shift along +x / +y per decade of flux/noise beyond bright_shift_from, px, the same everywhere on
    # the sensor (camera.bright_shift_x_px / _y_px; see :meth:`bright_shift`)
    bright_shift_x_px: float = 0.0
    bright_shift_y_px: float = 0.0
    # per-axis centroid error a real frame's brightest stars share (camera.shared_sigma_px), px; None: none. Added
    # across the boresight by the attitude covariance (fusion.solve.base.attitude_covariance); renders nothing
    shared_sigma_px: float | None = None

    @classmethod
    def from_config(cls, cfg) -> "Camera":
        if cfg.fov_deg is not None:
            f_px = (cfg.width_px / 2.0) / np.tan(np.radians(cfg.fov_deg) / 2.0)
        else:
            f_px = cfg.focal_length_mm * 1000.0 / cfg.pixel_pitch_um
        cx = (cfg.width_px - 1) / 2.0 if cfg.principal_x_px is None else cfg.principal_x_px
        cy = (cfg.height_px - 1) / 2.0 if cfg.principal_y_px is None else cfg.principal_y_px
        return cls(
            cfg.width_px,
            cfg.height_px,
            float(f_px),
            float(cx),
            float(cy),
            cfg.k1,
            cfg.k2,
            cfg.k3,
            cfg.p1,
            cfg.p2,
            float(getattr(cfg, "pixel_aspect", 1.0)),
            getattr(cfg, "centroid_sigma_px", None),
            float(getattr(cfg, "bright_shift_px", 0.0)),
            float(getattr(cfg, "bright_shift_from", 1.5)),
            getattr(cfg, "match_tol_px", None),
            float(getattr(cfg, "bright_shift_x_px", 0.0)),
            float(getattr(cfg, "bright_shift_y_px", 0.0)),
            getattr(cfg, "shared_sigma_px", None),
        )

    @property
    def has_bright_shift(self) -> bool:
        """Whether bright stars are detected away from where the camera puts them (:meth:`bright_shift`)."""
        return any((self.bright_shift_px, self.bright_shift_x_px, self.bright_shift_y_px))

    @property
    def has_distortion(self) -> bool:
        return any((self.k1, self.k2, self.k3, self.p1, self.p2))

    @property
    def pixel_scale_arcsec(self) -> float:
        """Angular width (along x) of one pixel at the centre, arcseconds; its height is ``aspect`` times that."""
        return float(np.degrees(1.0 / self.f_px) * 3600.0)

    @property
    def fy_px(self) -> float:
        """Focal length in rows (pixels along y): ``f_px / aspect``."""
        return self.f_px / self.aspect

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Full field of view (horizontal, vertical) of the pinhole, degrees."""
        return (
            float(np.degrees(2 * np.arctan(self.width_px / 2 / self.f_px))),
            float(np.degrees(2 * np.arctan(self.height_px / 2 / self.fy_px))),
        )

    def corner_radius_rad(self) -> float:
        """Largest angle between the boresight and a sensor corner (distortion included)."""
        xs = np.array([-0.5, self.width_px - 0.5, -0.5, self.width_px - 0.5])
        ys = np.array([-0.5, -0.5, self.height_px - 0.5, self.height_px - 0.5])
        v = self.unproject(xs, ys)
        return float(np.max(np.arccos(np.clip(v[:, 2], -1, 1))))

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not self.has_distortion:
            return x, y
        r2 = x * x + y * y
        radial = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        return xd, yd

    def undistort(self, xd: np.ndarray, yd: np.ndarray, iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
        """Invert :meth:`distort` by fixed-point iteration (converges for mild distortion)."""
        if not self.has_distortion:
            return xd, yd
        x, y = np.array(xd, dtype=np.float64), np.array(yd, dtype=np.float64)
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
            dx = 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
            dy = self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
            x = (xd - dx) / radial
            y = (yd - dy) / radial
        return x, y

    def project(self, v_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel (x, y) of camera-frame directions (N, 3); third value: in front (Z > 0)."""
        v_cam = np.atleast_2d(v_cam)
        z = v_cam[:, 2]
        front = z > 1e-9
        zs = np.where(front, z, 1.0)
        xd, yd = self.distort(v_cam[:, 0] / zs, v_cam[:, 1] / zs)
        return self.cx_px + self.f_px * xd, self.cy_px + self.fy_px * yd, front

    def unproject(self, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
        """Camera-frame unit vectors (N, 3) seen at pixel positions."""
        xd = (np.asarray(x_px, dtype=np.float64) - self.cx_px) / self.f_px
        yd = (np.asarray(y_px, dtype=np.float64) - self.cy_px) / self.fy_px
        x, y = self.undistort(xd, yd)
        v = np.stack([x, y, np.ones_like(x)], axis=-1)
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    def corner_r2(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Squared distance of (x, y) from the principal point over the half-diagonal's: 0 there, 1 at a corner of
        a centred sensor (the radius ``optics.vignetting`` is defined on)."""
        dx, dy = np.asarray(x, dtype=np.float64) - self.cx_px, np.asarray(y, dtype=np.float64) - self.cy_px
        return (dx * dx + dy * dy) / ((self.width_px / 2) ** 2 + (self.height_px / 2) ** 2)

    @property
    def far_corner_px(self) -> float:
        """Distance from the principal point to the farthest sensor corner, px (along x and y as stored)."""
        return float(
            np.hypot(
                max(self.cx_px + 0.5, self.width_px - 0.5 - self.cx_px),
                max(self.cy_px + 0.5, self.height_px - 0.5 - self.cy_px),
            )
        )

    def bright_shift(
        self, x: np.ndarray, y: np.ndarray, log_flux_over_sigma: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(dx, dy) px by which a source of this brightness at (x, y) is detected away from where the camera puts
        it, growing with ``h = max(q - bright_shift_from, 0)``, ``q`` the log10 of its detected flux over the
        background's noise sigma (ADU): outward from the principal point by ``bright_shift_px * rho * h`` (``rho`` the
        distance from the principal point over :attr:`far_corner_px`: an image whose tail points away from the centre,
        coma or lateral colour), plus ``(bright_shift_x_px, bright_shift_y_px) * h`` the same everywhere (a tail of
        one direction across the sensor: a tilted or decentred lens, a processor's asymmetric filtering). Zero
        where the camera has neither (:attr:`has_bright_shift`)."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if not self.has_bright_shift:
            return np.zeros_like(x), np.zeros_like(y)
        h = self._excess(log_flux_over_sigma)
        k = self.bright_shift_px * h / self.far_corner_px
        return k * (x - self.cx_px) + self.bright_shift_x_px * h, k * (y - self.cy_px) + self.bright_shift_y_px * h

    def _excess(self, log_flux_over_sigma) -> np.ndarray:
        """``max(q - bright_shift_from, 0)``: the decades of brightness the shift grows with."""
        return np.maximum(np.asarray(log_flux_over_sigma, np.float64) - self.bright_shift_from, 0.0)

    def unshift(self, x: np.ndarray, y: np.ndarray, flux_adu: np.ndarray, sigma_adu: float) -> tuple:
        """Detections at (x, y) of these fluxes on a frame of background noise ``sigma_adu`` (ADU), moved back by
        :meth:`bright_shift` to where the camera puts their stars (exactly: the radial part is ``k`` times the offset
        from the principal point and the uniform part ``h`` times a fixed vector, ``k`` and ``h`` set by the brightness
        alone). Unchanged where the camera has no shift."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if not self.has_bright_shift or not x.size:
            return x, y
        h = self._excess(np.log10(np.maximum(np.asarray(flux_adu, np.float64), 1e-12) / max(float(sigma_adu), 1e-12)))
        k = self.bright_shift_px * h / self.far_corner_px
        x0, y0 = x - self.bright_shift_x_px * h, y - self.bright_shift_y_px * h
        return self.cx_px + (x0 - self.cx_px) / (1.0 + k), self.cy_px + (y0 - self.cy_px) / (1.0 + k)

    def inside(self, x: np.ndarray, y: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        return (
            (x >= -0.5 - margin_px)
            & (x < self.width_px - 0.5 + margin_px)
            & (y >= -0.5 - margin_px)
            & (y < self.height_px - 0.5 + margin_px)
        )
