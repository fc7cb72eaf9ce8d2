"""benchmarks/prior_photometry.py: the inputs that tell which stars are kept from the fluxes read."""

from __future__ import annotations

import numpy as np

from fusion.solve.base import Detections
from fusion.testing import benchmark_script


def _script():
    return benchmark_script("prior_photometry")


def test_variants_separate_the_kept_set_from_the_flux_values():
    mod = _script()
    x = np.arange(8, dtype=float) * 10
    table = {"x_px": x, "y_px": x + 1, "flux_adu": np.array([800.0, 700, 600, 500, 400, 300, 200, 100])}
    # noise that swaps star 2 (600) below star 4 (400 -> 650) and star 0 below star 1
    noisy_flux = np.array([650.0, 700, 350, 500, 660, 300, 200, 100])
    noisy = Detections.from_table({"x_px": x, "y_px": x + 1, "flux_adu": noisy_flux})
    v = mod.variants(table, noisy, 3, zero_flux_adu=999.0)
    assert v["clean"].x_px.tolist() == [0, 10, 20] and v["clean"].flux_adu.tolist() == [800, 700, 600]
    assert v["benchmark"].x_px.tolist() == [10, 40, 0] and v["benchmark"].flux_adu.tolist() == [700, 660, 650]
    # the true three, their noisy fluxes, brightest (noisy) first
    assert v["true set, noisy flux"].x_px.tolist() == [10, 0, 20]
    assert v["true set, noisy flux"].flux_adu.tolist() == [700, 650, 350]
    # the noisy three, their true fluxes
    assert v["noisy set, true flux"].x_px.tolist() == [0, 10, 40]
    assert v["noisy set, true flux"].flux_adu.tolist() == [800, 700, 400]
    # the noisy three in noisy order, no flux
    assert v["noisy set, no flux"].x_px.tolist() == [10, 40, 0] and set(v["noisy set, no flux"].flux_adu) == {999.0}
