"""Fetch other star catalogs from VizieR (needs network; astroquery).

``skygen catalog fetch --catalog hipparcos-v`` (I/239, Hipparcos with Johnson V) or
``--catalog tycho2`` (I/259, 2.5 million stars to V ~ 11.5) saves a ``.npz`` star table
in ``catalogs/`` that ``catalog.path`` can point at. The conversion from the VizieR
columns is pure and tested offline with a table in VizieR's column layout
(``tests/data/``); only :func:`query_vizier` touches the network.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skygen.errors import CatalogError
from skygen.sky.catalog import HIPPARCOS_EPOCH_YR, StarTable


@dataclass(frozen=True)
class VizierSource:
    name: str
    table: str
    columns: tuple[str, ...]
    mag_column: str
    epoch_yr: float
    description: str


SOURCES = {
    "hipparcos-v": VizierSource(
        "hipparcos-v",
        "I/239/hip_main",
        ("HIP", "RAICRS", "DEICRS", "pmRA", "pmDE", "Vmag", "B-V"),
        "Vmag",
        HIPPARCOS_EPOCH_YR,
        "Hipparcos (ESA 1997) with Johnson V, 118k stars, epoch J1991.25",
    ),
    "tycho2": VizierSource(
        "tycho2",
        "I/259/tyc2",
        ("TYC1", "TYC2", "TYC3", "RAmdeg", "DEmdeg", "pmRA", "pmDE", "BTmag", "VTmag"),
        "VTmag",
        2000.0,
        "Tycho-2 (Hog et al. 2000), 2.5M stars, mean positions at J2000; "
        "V = VT - 0.090 (BT - VT), B-V = 0.850 (BT - VT)",
    ),
}


def query_vizier(source: VizierSource, mag_limit: float):
    """Download the table from VizieR (network). Returns an astropy Table."""
    try:
        from astroquery.vizier import Vizier
    except ImportError:
        raise CatalogError("astroquery is needed to fetch catalogs: pip install astroquery") from None
    viz = Vizier(columns=list(source.columns), row_limit=-1)
    try:
        result = viz.query_constraints(catalog=source.table, **{source.mag_column: f"<{mag_limit}"})
    except Exception as exc:  # network errors come in many types
        raise CatalogError(
            f"VizieR query for {source.table} failed ({type(exc).__name__}: {exc}); "
            "check the network connection, or use the bundled Hipparcos-2 (catalog.path=null)"
        ) from None
    if len(result) == 0:
        raise CatalogError(f"VizieR returned no table for {source.table}")
    return result[0]


def _col(table, name: str) -> np.ndarray:
    if name not in table.colnames:
        raise CatalogError(f"VizieR table lacks column {name!r} (has {', '.join(table.colnames)})")
    col = table[name]
    data = np.ma.filled(np.ma.asarray(col, dtype=np.float64), np.nan)
    return np.asarray(data, dtype=np.float64)


def table_to_stars(source: VizierSource, table) -> StarTable:
    """Convert a VizieR table of ``source`` to a :class:`StarTable` (magnitudes in V)."""
    pmra, pmde = _col(table, "pmRA"), _col(table, "pmDE")
    if source.name == "hipparcos-v":
        ids = _col(table, "HIP").astype(np.int64)
        ra, dec = _col(table, "RAICRS"), _col(table, "DEICRS")
        mag, bv = _col(table, "Vmag"), _col(table, "B-V")
    else:
        ids = (_col(table, "TYC1") * 1e6 + _col(table, "TYC2") * 10 + _col(table, "TYC3")).astype(np.int64)
        ra, dec = _col(table, "RAmdeg"), _col(table, "DEmdeg")
        bt, vt = _col(table, "BTmag"), _col(table, "VTmag")
        colour = bt - vt
        mag = np.where(np.isfinite(colour), vt - 0.090 * colour, vt)
        bv = 0.850 * colour
    ok = np.isfinite(ra) & np.isfinite(dec) & np.isfinite(mag)
    return StarTable(
        ids[ok],
        np.radians(ra[ok]),
        np.radians(dec[ok]),
        np.nan_to_num(pmra[ok]),
        np.nan_to_num(pmde[ok]),
        mag[ok].astype(np.float32),
        bv[ok].astype(np.float32),
        source.epoch_yr,
        f"vizier:{source.table}",
        band="V",
    )


def fetch(name: str, out, mag_limit: float = 9.0) -> StarTable:
    """Fetch catalog ``name`` (a key of SOURCES) and save it as ``out`` (.npz)."""
    from skygen.sky.catalog import write_npz

    try:
        source = SOURCES[name]
    except KeyError:
        raise CatalogError(f"unknown catalog {name!r}; choose one of {', '.join(SOURCES)}") from None
    stars = table_to_stars(source, query_vizier(source, mag_limit))
    write_npz(stars, out)
    return stars
