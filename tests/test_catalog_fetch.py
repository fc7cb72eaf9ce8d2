"""`skygen catalog fetch` conversion, tested offline with a table in VizieR's layout."""

from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table

from skygen.cli import main
from skygen.config import load_config
from skygen.errors import CatalogError
from skygen.render.frame import Renderer
from skygen.sky import vizier
from skygen.sky.catalog import load_catalog

TABLE = Path(__file__).parent / "data" / "vizier_I_239_hip_main.ecsv"


def test_table_to_stars_converts_units_and_masks():
    t = Table.read(TABLE)
    stars = vizier.table_to_stars(vizier.SOURCES["hipparcos-v"], t)
    assert len(stars) == len(t) - 1  # masked V dropped
    assert stars.band == "V" and stars.epoch_yr == 1991.25
    np.testing.assert_allclose(np.degrees(stars.ra_rad), np.asarray(t["RAICRS"])[:-1])
    assert np.isnan(stars.bv[-1])  # masked B-V kept as NaN


def test_fetch_writes_a_catalog_the_renderer_uses(tmp_path, monkeypatch):
    monkeypatch.setattr(vizier, "query_vizier", lambda source, mag: Table.read(TABLE))
    out = tmp_path / "hipv.npz"
    assert main(["catalog", "fetch", "--catalog", "hipparcos-v", "--out", str(out)]) == 0
    stars = load_catalog(out)
    assert len(stars) == 39 and stars.band == "V"
    r = Renderer(load_config(overrides=[f"catalog.path={out}"]))
    assert len(r.sky) == 39


def test_tycho_conversion():
    t = Table(
        {
            "TYC1": [1, 2],
            "TYC2": [5, 6],
            "TYC3": [1, 1],
            "RAmdeg": [10.0, 20.0],
            "DEmdeg": [-5.0, 5.0],
            "pmRA": [1.0, 2.0],
            "pmDE": [0.0, 0.0],
            "BTmag": [9.0, 8.5],
            "VTmag": [8.0, 8.5],
        }
    )
    s = vizier.table_to_stars(vizier.SOURCES["tycho2"], t)
    assert s.mag[0] == pytest.approx(8.0 - 0.09) and s.bv[0] == pytest.approx(0.85)
    assert s.epoch_yr == 2000.0


def test_unknown_catalog_and_network_failure(monkeypatch):
    with pytest.raises(CatalogError, match="choose one of"):
        vizier.fetch("gaia", "x.npz")

    class Boom:
        def __init__(self, *a, **k):
            pass

        def query_constraints(self, **k):
            raise ConnectionError("no route to host")

    import astroquery.vizier

    monkeypatch.setattr(astroquery.vizier, "Vizier", Boom)
    with pytest.raises(CatalogError, match="VizieR query .* failed"):
        vizier.query_vizier(vizier.SOURCES["tycho2"], 9.0)
