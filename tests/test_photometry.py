"""Magnitude to electrons: zero point, colour, sky, detection limit."""

import numpy as np
import pytest

from skygen.config import load_config
from skygen.instrument.photometry import Photometry, bv_to_temperature, effective_bandwidth_a
from skygen.render.frame import Renderer


def test_zero_point_by_hand():
    cfg = load_config(overrides=["photometry.colour=false", "photometry.hp_minus_v=0"])
    p = Photometry.from_config(cfg.optics, cfg.photometry, cfg.sensor)
    area_cm2 = np.pi * (cfg.optics.aperture_mm / 20) ** 2
    by_hand = 1004.5 * area_cm2 * cfg.optics.transmission * cfg.sensor.qe_peak * float(effective_bandwidth_a(None))
    assert p.electrons_per_s(np.array([0.0]))[0] == pytest.approx(by_hand)
    assert p.electrons_per_s(np.array([5.0]))[0] == pytest.approx(by_hand / 100)


def test_colour_response():
    assert bv_to_temperature(np.array([0.65]))[0] == pytest.approx(5800, rel=0.03)  # the Sun
    assert bv_to_temperature(np.array([0.0]))[0] > 9000
    cfg = load_config()
    p = Photometry.from_config(cfg.optics, cfg.photometry, cfg.sensor)
    e = p.electrons_per_s(np.array([5.0, 5.0]), np.array([0.0, 1.6]))
    assert e[1] > e[0]  # at equal V, a red star gives more electrons in a red-sensitive CMOS


def test_detection_limit_is_derived_from_the_sensor():
    dark_sky = ["photometry.sky_mag_arcsec2=30"]  # else the sky grows with the aperture too
    base = Renderer(load_config(overrides=dark_sky))
    bigger = Renderer(load_config(overrides=dark_sky + ["optics.aperture_mm=14"]))
    noisier = Renderer(load_config(overrides=dark_sky + ["sensor.read_noise_e=20"]))
    assert bigger.detection_limit_mag == pytest.approx(base.detection_limit_mag + 5 * np.log10(2), abs=1e-3)
    assert noisier.detection_limit_mag < base.detection_limit_mag - 0.5
    assert base.mag_limit == pytest.approx(base.detection_limit_mag + 1.0)
