"""Whole frames: determinism, truth, corruption registry."""

import numpy as np
import pytest

from skygen.config import config_dict, load_config
from skygen.instrument import corruptions as corr
from skygen.render.frame import Renderer

CLEAN = [f"corruptions.{name}=0" for name in corr.REGISTRY]


@pytest.fixture(scope="module")
def renderer(small_overrides):
    return Renderer(load_config(overrides=small_overrides))


def frames_equal(a, b) -> bool:
    same = np.array_equal(a.image, b.image) and (a.ra_deg, a.dec_deg, a.roll_deg) == (b.ra_deg, b.dec_deg, b.roll_deg)
    for k in a.detections:
        same &= np.array_equal(a.detections[k], b.detections[k])
    return bool(same)


def test_frame_is_a_pure_function_of_seed_and_index(renderer, small_overrides):
    a = renderer.render(7)
    renderer.render(3)
    b = renderer.render(7)
    c = Renderer(load_config(overrides=small_overrides)).render(7)
    assert frames_equal(a, b) and frames_equal(a, c)
    assert not np.array_equal(renderer.render(8).image, a.image)


def test_true_stars_are_where_the_detector_finds_them():
    r = Renderer(load_config())
    errs = []
    for i in range(10):
        f = r.render(i)
        ok = f.detections["star_index"] >= 0
        s = f.detections["star_index"][ok]
        bright = f.stars["mag"][s] < r.detection_limit_mag - 1.5  # isolated bright stars
        dx = f.detections["x_px"][ok][bright] - f.stars["x_px"][s][bright]
        dy = f.detections["y_px"][ok][bright] - f.stars["y_px"][s][bright]
        errs.append(np.hypot(dx, dy))
    e = np.concatenate(errs)
    assert len(e) > 30 and np.median(e) < 0.1


def _matched_offsets(plain: Renderer, other: Renderer, n: int):
    """Frames 0..n-1 of ``other``, checked to have ``plain``'s labels: (frame, matched star rows, and each matched
    detection's x and y offset from its star's label)."""
    for i in range(n):
        a, f = plain.render(i), other.render(i)
        np.testing.assert_array_equal(a.stars["x_px"], f.stars["x_px"])
        ok = f.detections["star_index"] >= 0
        s = f.detections["star_index"][ok]
        yield f, s, f.detections["x_px"][ok] - f.stars["x_px"][s], f.detections["y_px"][ok] - f.stars["y_px"][s]


def test_star_jitter_moves_each_star_image_but_not_its_label():
    """optics.star_jitter_px: the detector finds each bright star about that far (per axis) from its label, the
    labels are those of the same frame without jitter, and the draw is a pure function of seed and frame."""
    from skygen.config import ConfigError, build_config

    plain, jit = Renderer(load_config()), Renderer(load_config(overrides=["optics.star_jitter_px=0.8"]))
    d = []
    for f, s, dx, dy in _matched_offsets(plain, jit, 8):
        bright = f.stars["mag"][s] < jit.detection_limit_mag - 1.5
        d += [dx[bright], dy[bright]]
    d = np.concatenate(d)
    assert len(d) > 60 and 0.65 < np.sqrt(np.mean(d**2)) < 0.95  # 0.8 px drawn, the detector's own ~0.05
    np.testing.assert_array_equal(jit.render(3).image, Renderer(jit.cfg).render(3).image)
    assert jit.render(2).log["star_jitter"]["rms_px"] > 0
    with pytest.raises(ConfigError, match="star_jitter_px needs render.backend=numpy"):
        build_config({"optics": {"star_jitter_px": 1.0}, "render": {"backend": "torch"}})


def test_bright_shift_moves_bright_stars_outward_and_leaves_faint_ones_and_labels():
    """camera.bright_shift_px: a star's image is drawn outward from the principal point by the camera's shift for
    its brightness (its electrons over the background noise), growing with the distance from the principal point;
    stars fainter than camera.bright_shift_from are not moved, labels never; the torch backend refuses it."""
    from skygen.config import ConfigError, build_config

    shift = ["camera.bright_shift_px=4.0", "camera.bright_shift_from=1.8"]
    plain, moved = Renderer(load_config(overrides=CLEAN)), Renderer(load_config(overrides=CLEAN + shift))
    cam = moved.camera
    rows = []
    for f, s, dx, dy in _matched_offsets(plain, moved, 12):
        ux, uy = f.stars["x_px"][s] - cam.cx_px, f.stars["y_px"][s] - cam.cy_px
        r = np.hypot(ux, uy)
        radial = (dx * ux + dy * uy) / np.maximum(r, 1e-9)
        q = np.log10(f.stars["electrons"][s] / moved.noise_e())
        want = 4.0 * np.maximum(q - 1.8, 0) * r / cam.far_corner_px
        rows.append(np.column_stack([q, r, radial, want]))
    g = np.concatenate(rows)
    bright = (g[:, 0] > 2.2) & (g[:, 1] > 250)
    faint = g[:, 0] < 1.75
    assert bright.sum() >= 20 and faint.sum() >= 15
    assert np.median(np.abs(g[bright, 2] - g[bright, 3])) < 0.15  # drawn where the camera's shift says
    assert np.median(g[bright, 2]) > 0.5  # outward
    assert abs(np.median(g[faint, 2])) < 0.1
    assert moved.render(1).log["bright_shift"]["max_px"] > 0
    with pytest.raises(ConfigError, match="bright_shift_px needs render.backend=numpy"):
        build_config({"camera": {"bright_shift_px": 1.0}, "render": {"backend": "torch"}})


def test_a_uniform_bright_shift_moves_bright_stars_one_way_everywhere():
    """camera.bright_shift_x_px / _y_px alone (no radial part): bright stars' images drawn the same way across the
    sensor, by the camera's shift for their brightness; faint ones not; the torch backend refuses it."""
    from skygen.config import ConfigError, build_config

    shift = ["camera.bright_shift_x_px=-0.8", "camera.bright_shift_y_px=0.5", "camera.bright_shift_from=1.8"]
    plain, moved = Renderer(load_config(overrides=CLEAN)), Renderer(load_config(overrides=CLEAN + shift))
    rows = []
    for f, s, dx, dy in _matched_offsets(plain, moved, 6):
        h = np.maximum(np.log10(f.stars["electrons"][s] / moved.noise_e()) - 1.8, 0)
        rows.append(np.column_stack([h, dx, dy]))
    g = np.concatenate(rows)
    bright, faint = g[:, 0] > 0.4, g[:, 0] == 0
    assert bright.sum() >= 15 and faint.sum() >= 15
    np.testing.assert_allclose(np.median(g[bright, 1] / g[bright, 0]), -0.8, atol=0.1)
    np.testing.assert_allclose(np.median(g[bright, 2] / g[bright, 0]), 0.5, atol=0.1)
    assert np.all(np.abs(np.median(g[faint, 1:], axis=0)) < 0.1)  # faint stars: not moved (the detector's own bias)
    with pytest.raises(ConfigError, match="bright_shift_y_px needs render.backend=numpy"):
        build_config({"camera": {"bright_shift_y_px": 1.0}, "render": {"backend": "torch"}})


def test_motion_blur_conserves_flux_and_keeps_truth_at_mid_exposure():
    cfg = load_config(overrides=CLEAN + ["corruptions.motion_blur=1.0"])
    r = Renderer(cfg)
    omega, n, taus = r.motion_path(np.random.default_rng(0))
    assert n > 10 and abs(np.degrees(np.linalg.norm(omega)) - 1.0) < 1e-12
    from skygen.sky.attitude import attitude_matrix

    stars = r.visible_stars(attitude_matrix(10, 20, 30), omega, taus)
    star_e = np.zeros((1024, 1024), np.float32)
    r.deposit(stars, star_e)
    inside = r.camera.inside(stars["paths"][0].min(1), stars["paths"][1].min(1), -12) & r.camera.inside(
        stars["paths"][0].max(1), stars["paths"][1].max(1), -12
    )
    assert inside.sum() > 10
    # the mid-exposure position is the mean of the sub-exposure positions (to 2nd order)
    mid_x = stars["paths"][0].mean(1)
    assert np.max(np.abs(mid_x - stars["x_px"])[inside]) < 0.05
    total = star_e.sum(dtype=np.float64)
    assert total <= stars["electrons"].sum() + 1e-3
    assert total >= stars["electrons"][inside].sum() * (1 - 1e-6)


def test_registry_matches_config_and_rejects_unknown_names():
    shape = {"false_star_slope", "false_star_span_mag"}  # the false stars' brightness, not corruptions
    assert set(corr.REGISTRY) == set(config_dict(load_config())["corruptions"]) - shape
    assert set(corr.levels_of(load_config())) == set(corr.REGISTRY)
    with pytest.raises(Exception, match="valid names: hotpixels"):
        corr.get("hot_pixels")
    for c in corr.REGISTRY.values():
        assert c.sweep[0] == 0 and list(c.sweep) == sorted(c.sweep) and c.unit and c.description
        corr.with_level(load_config(), c.name, c.sweep[-1])  # every sweep level is a valid config


@pytest.mark.parametrize("name", list(corr.REGISTRY))
def test_severity_zero_is_the_identity(name, small_overrides):
    clean = Renderer(load_config(overrides=small_overrides + CLEAN))
    zero = Renderer(corr.with_level(load_config(overrides=small_overrides + CLEAN), name, 0.0))
    for i in range(3):
        assert frames_equal(clean.render(i), zero.render(i))


def damage(r: Renderer, limit: float, frames=range(20)) -> float:
    """Detection damage on a fixed population (catalog stars 0.5 mag above the clean limit):
    mean position error (a missed star counts as the 2 px match radius) + share of
    detections that are not catalog stars + (1 - rank correlation of detected flux with
    true brightness)."""
    from scipy.stats import spearmanr

    err, rank = [], []
    false = ndet = 0
    for i in frames:
        f = r.render(i)
        bright = np.flatnonzero((f.stars["mag"] < limit - 0.5) & (f.stars["hip_id"] >= 0))
        d = f.detections
        false += (d["hip_id"] < 0).sum()
        ndet += len(d["hip_id"])
        for s in bright:
            j = np.flatnonzero(d["star_index"] == s)
            err.append(
                min(np.hypot(d["x_px"][j[0]] - f.stars["x_px"][s], d["y_px"][j[0]] - f.stars["y_px"][s]), 2.0)
                if len(j)
                else 2.0
            )
        sel = np.isin(d["star_index"], bright)
        if sel.sum() > 3:
            rank.append(1 - spearmanr(d["flux_adu"][sel], -f.stars["mag"][d["star_index"][sel]]).statistic)
    return float(np.mean(err)) + false / max(ndet, 1) + float(np.mean(rank or [1.0]))


@pytest.mark.parametrize("name", list(corr.REGISTRY))
def test_severity_increases_damage(name, small_overrides):
    base = load_config(overrides=small_overrides + CLEAN)
    levels = corr.REGISTRY[name].sweep
    limit = Renderer(base).detection_limit_mag
    d = [damage(Renderer(corr.with_level(base, name, lv)), limit) for lv in (levels[0], levels[2], levels[-1])]
    assert d[2] > d[0] and d[1] >= d[0] - 0.02 and d[2] >= d[1] - 0.02, d


def test_extra_severity_stacks_on_the_dataset_and_zero_is_identity():
    cfg = load_config(overrides=["corruptions.dropout=0.2", "corruptions.centroid_noise=3"])
    for name in corr.REGISTRY:
        assert corr.with_extra(cfg, name, 0.0) == cfg
    assert corr.with_extra(cfg, "dropout", 0.5).corruptions.dropout == pytest.approx(0.6)
    assert corr.with_extra(cfg, "centroid_noise", 4.0).corruptions.centroid_noise == pytest.approx(5.0)
    assert corr.with_extra(cfg, "cosmic_rays", 10.0).corruptions.cosmic_rays == pytest.approx(15.0)


def test_corruption_log_records_what_happened(small_overrides):
    cfg = load_config(
        overrides=small_overrides
        + ["corruptions.cosmic_rays=20000", "corruptions.false_stars=3", "corruptions.dropout=0.3"]
    )
    f = Renderer(cfg).render(0)
    assert f.log["cosmic_rays"]["n_hits"] > 0 and "false_stars" in f.log and "dropout" in f.log
    assert f.applied["cosmic_rays"] == 20000 and f.applied["motion_blur"] == 0
    assert (f.stars["hip_id"] == -1).sum() == f.log["false_stars"]["n"]


def test_a_frame_with_detections_but_no_catalog_star(small_overrides):
    """Only false sources (a one-star catalog far from the boresight, cosmic rays): every
    detection is false (hip_id -1), no IndexError."""
    from skygen.sky.catalog import StarTable

    one = StarTable(
        np.array([1]),
        np.array([0.0]),
        np.array([-1.5]),
        np.zeros(1),
        np.zeros(1),
        np.array([3.0], np.float32),
        np.array([0.6], np.float32),
        1991.25,
        "test",
    )
    cfg = load_config(
        overrides=small_overrides
        + ["attitude.mode=list", "attitude.ra_deg=[180]", "attitude.dec_deg=[60]", "corruptions.cosmic_rays=3000"]
    )
    f = Renderer(cfg, catalog=one).render(0)
    assert len(f.stars["hip_id"]) == 0 and len(f.detections["hip_id"]) > 0
    assert np.all(f.detections["hip_id"] == -1) and np.all(f.detections["star_index"] == -1)


def test_a_config_detecting_few_stars_renders_with_one_warning(tmp_path):
    """exposure 0.003 s passes the refusal (0.62 stars per field above the limit, more than 0.5) but most
    frames would hold fewer than 3 detections: skygen render says so once, naming the exposure that gives 3."""
    from skygen.datasets.build import render_dataset

    sparse = Renderer(load_config(None, ["sensor.exposure_s=0.003"]))
    assert 0.5 < sparse.detectable_per_field < 3
    assert Renderer(load_config(None, [])).sparse_warning() is None
    said = []
    cfg = load_config(None, ["sensor.exposure_s=0.003", "n_frames=2", "output.shard_size=2"])
    render_dataset(cfg, tmp_path / "d", workers=1, progress=False, warn=said.append)
    assert len(said) == 1 and said[0].startswith("warning: only 0.62 catalog stars per field")
    assert "sensor.exposure_s >= 0.0114 s" in said[0]
