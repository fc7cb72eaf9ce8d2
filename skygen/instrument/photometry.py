"""Photometry: catalog magnitude to photo-electrons, sky background, dark current.

Zero point
    A V = 0 star delivers a photon flux density of 1004.5 photons s^-1 cm^-2 A^-1 at
    550 nm: f_lambda = 3.631e-9 erg s^-1 cm^-2 A^-1 (Bessell, Castelli & Plez 1998,
    A&A 333, 231, Table A2) divided by the photon energy hc/lambda at 550 nm.

Spectrum
    With ``colour`` on, a star's photon spectrum is a blackbody whose temperature comes
    from B-V through Ballesteros (2012, EPL 97, 34008):
    T = 4600 K [1/(0.92 (B-V) + 1.7) + 1/(0.92 (B-V) + 0.62)]. The spectrum is scaled
    so that its mean photon flux density through the Johnson V passband (Bessell 1990,
    PASP 102, 1181) equals the zero point times 10^(-0.4 V), then integrated against the
    sensor's quantum-efficiency curve. With ``colour`` off the spectrum is flat in photon
    flux density. V comes from the catalog's Hp as V = Hp - hp_minus_v.

Electrons collected in the exposure::

    N_e = t * A * T_opt * F0 * 10^(-0.4 V) * W(T)
    W(T) = integral(s_T(l) QE(l) dl) / <s_T>_V      [Angstrom]

with A the entrance-pupil area (cm^2), T_opt the optical transmission and W the
effective bandwidth of the sensor for that spectrum.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ZERO_POINT_NOTE = "Bessell, Castelli & Plez (1998): V=0 -> 3.631e-9 erg/s/cm^2/A at 550 nm"

# Relative QE of a generic front-illuminated CMOS star-tracker sensor (peak = 1).
_QE_NM = np.array([350, 400, 450, 500, 550, 600, 650, 700, 750, 800, 850, 900, 950, 1000, 1050.0])
_QE_REL = np.array([0.15, 0.45, 0.75, 0.92, 1.0, 0.97, 0.88, 0.75, 0.62, 0.48, 0.35, 0.22, 0.12, 0.05, 0.0])
# Johnson V passband, Bessell (1990), photon-counting response.
_V_NM = np.arange(470, 710, 10.0)
_V_REL = np.array(
    [
        0.0,
        0.03,
        0.163,
        0.458,
        0.78,
        0.967,
        1.0,
        0.973,
        0.898,
        0.792,
        0.684,
        0.574,
        0.461,
        0.359,
        0.27,
        0.197,
        0.135,
        0.081,
        0.045,
        0.025,
        0.017,
        0.013,
        0.009,
        0.0,
    ]
)
_GRID_NM = np.arange(300.0, 1100.0, 2.0)
_H, _C, _K = 6.62607015e-34, 2.99792458e8, 1.380649e-23


def bv_to_temperature(bv: np.ndarray) -> np.ndarray:
    """Blackbody temperature (K) from B-V colour (Ballesteros 2012), clipped to a sane range."""
    bv = np.clip(np.asarray(bv, dtype=np.float64), -0.4, 2.5)
    return 4600.0 * (1.0 / (0.92 * bv + 1.7) + 1.0 / (0.92 * bv + 0.62))


def _photon_spectrum(temp_k: np.ndarray) -> np.ndarray:
    """Blackbody photon flux density shape s_T(lambda) on _GRID_NM, arbitrary scale. (T, L)."""
    lam = _GRID_NM[None, :] * 1e-9
    x = _H * _C / (lam * _K * np.asarray(temp_k, dtype=np.float64)[:, None])
    return lam**-4 / np.expm1(np.minimum(x, 700.0))


def effective_bandwidth_a(temp_k: np.ndarray | None) -> np.ndarray:
    """W(T) in Angstrom for unit peak QE; ``None`` gives the flat-spectrum value."""
    qe = np.interp(_GRID_NM, _QE_NM, _QE_REL)
    sv = np.interp(_GRID_NM, _V_NM, _V_REL, left=0, right=0)
    dl_a = 20.0  # grid step, Angstrom
    if temp_k is None:
        return np.array(qe.sum() * dl_a)
    s = _photon_spectrum(np.atleast_1d(temp_k))
    mean_v = (s * sv).sum(1) / sv.sum()
    return (s * qe).sum(1) * dl_a / mean_v


@dataclass(frozen=True)
class Photometry:
    """Magnitude-to-electron conversion for one optical/sensor configuration."""

    e_per_s_at_v0_flat: float  # e-/s for a V=0 flat-spectrum star
    qe_peak: float
    hp_minus_v: float
    colour: bool
    default_bv: float
    aperture_cm2: float
    transmission: float
    zero_point: float

    @classmethod
    def from_config(cls, optics, phot, sensor) -> "Photometry":
        area = np.pi * (optics.aperture_mm / 20.0) ** 2  # cm^2
        e0 = (
            area
            * optics.transmission
            * phot.zero_point_ph_s_cm2_a
            * sensor.qe_peak
            * float(effective_bandwidth_a(None))
        )
        return cls(
            e0,
            sensor.qe_peak,
            phot.hp_minus_v,
            phot.colour,
            phot.default_bv,
            area,
            optics.transmission,
            phot.zero_point_ph_s_cm2_a,
        )

    def electrons_per_s(self, mag_hp: np.ndarray, bv: np.ndarray | None = None) -> np.ndarray:
        """Photo-electrons per second for catalog magnitudes (Hp) and B-V colours."""
        v = np.asarray(mag_hp, dtype=np.float64) - self.hp_minus_v
        if not self.colour:
            return self.e_per_s_at_v0_flat * 10 ** (-0.4 * v)
        bv = np.full(v.shape, self.default_bv) if bv is None else np.where(np.isfinite(bv), bv, self.default_bv)
        w = _bandwidth_of_bv(np.asarray(bv, dtype=np.float64))
        return self.aperture_cm2 * self.transmission * self.zero_point * self.qe_peak * w * 10 ** (-0.4 * v)

    def magnitude_for_electrons_per_s(self, e_per_s: float, bv: float | None = None) -> float:
        """Inverse of :meth:`electrons_per_s` for one star (Hp magnitude)."""
        ref = float(self.electrons_per_s(np.array([0.0]), None if bv is None else np.array([bv]))[0])
        return float(-2.5 * np.log10(e_per_s / ref))

    def sky_electrons_per_px_s(self, sky_mag_arcsec2: float, pixel_scale_arcsec: float) -> float:
        """Diffuse sky (zodiacal) background in e-/pixel/s, solar-like spectrum (B-V = 0.65)."""
        mag_px = sky_mag_arcsec2 - 2.5 * np.log10(pixel_scale_arcsec**2)
        return float(self.electrons_per_s(np.array([mag_px + self.hp_minus_v]), np.array([0.65]))[0])


_BV_GRID = np.linspace(-0.4, 2.5, 300)
_W_GRID = effective_bandwidth_a(bv_to_temperature(_BV_GRID))


def _bandwidth_of_bv(bv: np.ndarray) -> np.ndarray:
    return np.interp(bv, _BV_GRID, _W_GRID)


def star_gains(ids: np.ndarray, scatter_mag: float, sensor_seed: int) -> np.ndarray:
    """Each star's fixed brightness factor on this sensor, 10 ** (-0.4 dm) with dm ~ N(0, ``scatter_mag``) drawn
    from the star's catalogue id and the sensor's seed (``photometry.star_scatter_mag``): what the catalogue's
    magnitude and colour do not predict of a real sensor's flux (its band, catalogue errors, variable stars). The
    same star has the same offset in every frame, on every renderer; ones where ``scatter_mag`` is 0."""
    ids = np.asarray(ids, np.int64)
    if scatter_mag <= 0:
        return np.ones(ids.shape)
    from skygen import hashrng

    dm = scatter_mag * hashrng.normal(hashrng.stream_key(int(sensor_seed), "star_scatter"), ids, 0)
    return 10 ** (-0.4 * dm)


def dark_current_e_s(sensor) -> float:
    """Mean dark current (e-/s/pixel) at the sensor temperature: doubles every dark_doubling_c."""
    return sensor.dark_current_e_s * 2.0 ** ((sensor.temperature_c - sensor.dark_reference_c) / sensor.dark_doubling_c)
