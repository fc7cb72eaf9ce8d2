"""catalog.source=gaia: Gaia DR3 to G = 10 merged with Hipparcos-2 (skygen.sky.catalog.load_deep), rendered,
labelled and licensed as such; Hipparcos renders unchanged."""

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from skygen.config import load_config
from skygen.errors import ConfigError
from skygen.sky.catalog import (
    GAIA_DR3_EPOCH_YR,
    HIPPARCOS_COMPLETE_HP,
    OFFSET_G_RANGE,
    load_catalog,
    load_deep,
    load_gaia,
    propagate,
)


@pytest.fixture(scope="module")
def cats():
    return load_deep(), load_catalog(), load_gaia()


def _xmatch(a, b, arcsec=0.05):
    """Rows of ``b`` within ``arcsec`` of each row of ``a`` (both at J2016.0), -1 where none."""
    d, i = cKDTree(propagate(b, GAIA_DR3_EPOCH_YR)).query(propagate(a, GAIA_DR3_EPOCH_YR))
    return np.where(np.degrees(d) * 3600 < arcsec, i, -1)


def test_the_merge_keeps_every_star_of_both_with_hipparcos_photometry_where_it_has_the_star(cats):
    deep, hip, gaia = cats
    assert deep.band == "Hp" and deep.epoch_yr == GAIA_DR3_EPOCH_YR
    # ids: unique, never negative (negative = false star in shards), HIP numbers far below Gaia source ids
    assert len(np.unique(deep.hip)) == len(deep) and deep.hip.min() > 0
    assert not np.any((deep.hip > 200_000) & (deep.hip < 10**12))
    # every Gaia star, then the Hipparcos stars Gaia's file lacks (most fainter than G = 10)
    assert len(gaia) < len(deep) < len(gaia) + len(hip)
    np.testing.assert_array_equal(deep.ra_rad[: len(gaia)], gaia.ra_rad)
    added = deep.select(np.arange(len(deep)) >= len(gaia))
    assert np.median(added.mag) > 9.5  # the stars a G <= 10 cut misses: faint ones (and a few Gaia lacks)
    # every Hipparcos star with a position is in the merge, at its own propagated place
    ok = np.isfinite(hip.ra_rad) & np.isfinite(hip.mag)
    hit = _xmatch(hip.select(ok), deep, arcsec=2.5)
    assert np.mean(hit >= 0) > 0.999
    # photometry: the matched stars render exactly as with Hipparcos; HIP 91262 (Vega) keeps its Hp and B-V
    vega = int(np.flatnonzero(hip.hip == 91262)[0])
    j = int(_xmatch(hip.select(np.arange(len(hip)) == vega), deep, arcsec=2.5)[0])
    assert deep.mag[j] == hip.mag[vega] and deep.bv[j] == hip.bv[vega]
    # Gaia-only stars: G plus one offset, Hipparcos's median Hp - G at G 9-10 (0.24-0.25 mag), no colour
    only = np.flatnonzero(np.isnan(deep.bv[: len(gaia)]) & (gaia.mag > OFFSET_G_RANGE[0]))
    offset = deep.mag[only] - gaia.mag[only]
    assert np.ptp(offset) < 1e-5 and 0.2 < offset[0] < 0.3
    assert f"{offset[0]:+.3f}" in deep.source


def test_added_hipparcos_stars_sit_where_their_own_proper_motion_puts_them(cats):
    deep, hip, gaia = cats
    added = np.arange(len(gaia), len(deep))
    rows = {h: i for i, h in enumerate(hip.hip)}
    src = np.array([rows[h] for h in deep.hip[added]])
    # at J2016.0 exactly; ten years on, within what linear propagation itself leaves over 35 years for the
    # fastest stars (the two start from different epochs)
    for epoch, tol_mas in ((GAIA_DR3_EPOCH_YR, 0.1), (2026.0, 25.0)):
        a = propagate(deep.select(added), epoch)
        b = propagate(hip.select(src), epoch)
        sep = np.degrees(np.linalg.norm(a - b, axis=1)) * 3600e3
        assert np.max(sep) < tol_mas and np.median(sep) < 0.1


def test_hipparcos_completeness_constant_is_where_its_counts_fall_behind(cats):
    """HIPPARCOS_COMPLETE_HP: at least 82 % of the merged catalogue's stars in each half magnitude up to it,
    under 75 % in the next (the depth warning of skygen render rests on it)."""
    deep, hip, _ = cats

    def share(lo, hi):
        return np.sum((hip.mag > lo) & (hip.mag <= hi)) / np.sum((deep.mag > lo) & (deep.mag <= hi))

    edges = np.arange(5.0, HIPPARCOS_COMPLETE_HP + 0.01, 0.5)
    assert min(share(lo, lo + 0.5) for lo in edges[:-1]) > 0.82
    assert share(HIPPARCOS_COMPLETE_HP, HIPPARCOS_COMPLETE_HP + 0.5) < 0.75
    assert 0.5 < share(8.0, 8.5) < 0.65 and 0.3 < share(8.5, 9.0) < 0.45  # the figures the warning quotes


def test_a_gaia_render_adds_faint_stars_and_leaves_the_bright_ones_where_they_were():
    from skygen.render.frame import Renderer

    over = ["camera.fov_deg=15", "sensor.exposure_s=2.0", "output.image_size_px=256"]
    hip_r = Renderer(load_config(overrides=over))
    gaia_r = Renderer(load_config(overrides=over + ["catalog.source=gaia"]))
    assert hip_r.mag_limit == gaia_r.mag_limit > 9  # the same camera, the same limit
    assert len(gaia_r.sky) > 1.8 * len(hip_r.sky)
    n_h = n_g = 0
    for i in range(4):
        a, b = hip_r.scene(i).stars, gaia_r.scene(i).stars
        n_h, n_g = n_h + len(a["x_px"]), n_g + len(b["x_px"])
        bright = a["mag"] < 7
        d, j = cKDTree(np.c_[b["x_px"], b["y_px"]]).query(np.c_[a["x_px"], a["y_px"]][bright])
        assert np.all(d < 0.5) and np.median(d) < 0.05  # the same attitude; positions to Gaia's precision
        np.testing.assert_allclose(b["mag"][j], a["mag"][bright])  # Hipparcos photometry kept
        assert (b["hip_id"] > 0).all()
    assert n_g > 1.5 * n_h


def test_source_is_checked_and_hipparcos_renders_keep_their_ids():
    from skygen.identity import content_id

    with pytest.raises(ConfigError, match="hipparcos, gaia|'hipparcos', 'gaia'"):
        load_config(overrides=["catalog.source=tycho2"])
    from skygen.config import config_dict

    d = config_dict(load_config())
    old = json.loads(json.dumps(d))
    old["catalog"].pop("source")  # a config written before the key existed
    assert content_id(d) == content_id(old)
    d["catalog"]["source"] = "gaia"
    assert content_id(d) != content_id(old)


def test_render_warns_when_the_camera_sees_fainter_than_hipparcos_holds():
    from skygen.render.frame import Renderer

    deep_cam = ["camera.fov_deg=15", "sensor.exposure_s=2.0", "output.image_size_px=256"]
    assert Renderer(load_config()).depth_warning() is None  # the default camera: Hp ~5.9
    msg = Renderer(load_config(overrides=deep_cam)).depth_warning()
    assert msg and "catalog.source=gaia" in msg and "Hp ~7.5" in msg
    assert Renderer(load_config(overrides=deep_cam + ["catalog.source=gaia"])).depth_warning() is None
    # a fitted camera's false stars stand in for the stars the catalogue lacks
    assert Renderer(load_config(overrides=deep_cam + ["corruptions.false_stars=5"])).depth_warning() is None


def test_the_card_of_a_gaia_render_says_share_alike_and_cites_gaia(small_dataset):
    from skygen.datasets.card import SHARE_ALIKE_LICENCE, card_markdown, croissant

    man = json.loads((small_dataset / "manifest.json").read_text())
    assert "Hipparcos-2 (van Leeuwen" in card_markdown(man) and "CC BY 4.0" in card_markdown(man)
    man["config"]["catalog"]["source"] = "gaia"
    text, meta = card_markdown(man), croissant(man)
    assert "CC BY-SA 3.0 IGO" in text and "CC BY-SA 4.0" in text and "Gaia DR3" in text
    assert meta["license"] == SHARE_ALIKE_LICENCE and "Gaia DR3" in meta["citeAs"]


def test_a_render_made_before_catalog_source_existed_resumes(tmp_path):
    """A manifest written before the key (no catalog.source, its dataset_id computed without it) is the same
    dataset: the same command resumes it instead of refusing it as "a different dataset"."""
    from skygen.datasets.build import render_dataset
    from skygen.datasets.shards import config_id

    small = ["camera.width_px=256", "camera.height_px=256", "camera.pixel_pitch_um=22.0", "output.image_size_px=64"]
    cfg = load_config(overrides=small + ["n_frames=4", "output.shard_size=2"])
    out = tmp_path / "old"
    render_dataset(cfg, out, workers=1, progress=False)
    man_path = out / "manifest.json"
    man = json.loads(man_path.read_text())
    man["config"]["catalog"].pop("source")
    man["dataset_id"] = config_id(man["config"])
    man["shards"] = man["shards"][:1]  # as if interrupted after its first shard
    man["complete"] = False
    man_path.write_text(json.dumps(man))
    (out / "shard-00001.h5").unlink()
    render_dataset(cfg, out, workers=1, progress=False)
    assert json.loads(man_path.read_text())["complete"] and (out / "shard-00001.h5").exists()
    man = json.loads(man_path.read_text())
    man["config"]["catalog"]["source"] = "gaia"  # a real difference is still refused
    man["dataset_id"] = config_id(man["config"])
    man_path.write_text(json.dumps(man))
    with pytest.raises(Exception, match="catalog.source"):
        render_dataset(cfg, out, workers=1, progress=False)
