"""skygen.render.binned: the stored-resolution renderer is equal in distribution to render-then-downsample.

Both paths rasterise the *same scenes* (``Renderer.scene(i)`` of the frames stream, default
camera: 1024² sensor stored at 256², factor 4) with independent noise. Every statistic below is
a two-sample comparison with a stated tolerance; ``test_a_wrong_read_noise_is_caught`` runs the
same background statistics on a binned renderer with 10 % too much read noise and requires
them to fail, so the tolerances are not too loose to catch a physics error.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from scipy import stats

from skygen.config import load_config
from skygen.render.binned import (
    BinnedRenderer,
    aliasing_bound,
    area_rounding,
    round_block_sums,
    unsupported_reason,
)
from skygen.render.frame import Renderer
from skygen.stream.samples import SampleStream

N_SCENES = 100  # scenes rendered by both paths (two noise draws each)
F = 4  # default camera: 1024 -> 256


@pytest.fixture(scope="module")
def renderer():
    return Renderer(load_config(), rng_tag="@stream-frames")


@pytest.fixture(scope="module")
def pair(renderer):
    """Stored images of the same scenes by both paths, two independent noise draws each."""
    r = renderer
    b = BinnedRenderer(r)
    scenes = [r.scene(i) for i in range(N_SCENES)]
    binned, full = [], []
    for i, sc in enumerate(scenes):
        binned.append([b.image(sc, seed=7000 + 2 * i + k) for k in range(2)])
        full.append([r.downsample(r.rasterise(dataclasses.replace(sc, rng_key=(i, 500 + k)))[0]) for k in range(2)])
    return scenes, np.array(binned, np.float64), np.array(full, np.float64), b


def _background_mask(r, scenes) -> np.ndarray:
    """Per scene, the stored pixels no light source, cosmic ray, hot or dead pixel touches
    (scenes, H/4, W/4)."""
    hb, wb = r.cfg.camera.height_px // F, r.cfg.camera.width_px // F
    static = ((r.maps.hot_map > 0) | r.maps.dead_mask).reshape(hb, F, wb, F).any((1, 3))
    reach = 12  # px: beyond every Gaussian stamp of the default PSF
    masks = []
    for sc in scenes:
        busy = static.copy()
        for x, y in zip(sc.stars["x_px"], sc.stars["y_px"]):
            busy[
                max(int(y - reach) // F, 0) : max(int(y + reach) // F + 1, 0),
                max(int(x - reach) // F, 0) : max(int(x + reach) // F + 1, 0),
            ] = True
        for y0, y1, x0, x1 in sc.cosmic_boxes:
            busy[y0 // F : (y1 - 1) // F + 1, x0 // F : (x1 - 1) // F + 1] = True
        masks.append(~busy)
    return np.array(masks)


def _chi2_two_sample(a: np.ndarray, b: np.ndarray, min_count: int = 20) -> float:
    """p-value of the chi-square test that integer samples a and b share one distribution
    (values with fewer than ``min_count`` occurrences pooled into the tails)."""
    lo, hi = int(min(a.min(), b.min())), int(max(a.max(), b.max()))
    ca = np.bincount((a - lo).astype(np.int64), minlength=hi - lo + 1)
    cb = np.bincount((b - lo).astype(np.int64), minlength=hi - lo + 1)
    tot = ca + cb
    groups, cur = [], np.zeros(2)
    for x, y, t in zip(ca, cb, tot):
        cur += (x, y)
        if cur.sum() >= min_count:
            groups.append(cur.copy())
            cur[:] = 0
    if cur.sum():
        groups[-1] += cur
    table = np.array(groups).T
    return float(stats.chi2_contingency(table)[1])


def _background_stats(binned: np.ndarray, full: np.ndarray, mask: np.ndarray) -> dict:
    """The per-pixel background statistics both tests below use (first noise draw); ``mask``
    (scenes, H, W) marks each scene's background pixels."""
    xb, xf = binned[:, 0], full[:, 0]  # (scenes, H, W)
    n = mask.sum(0)
    use = n >= 20  # pixels background in >= 20 scenes

    def mean(x):
        return np.where(mask, x, 0).sum(0)[use] / n[use]

    def var(x, m):
        return (np.where(mask, x, 0) ** 2).sum(0)[use] / n[use] - m**2

    mb, mf = mean(xb), mean(xf)
    vb, vf = var(xb, mb) * n[use] / (n[use] - 1), var(xf, mf) * n[use] / (n[use] - 1)
    z = (mb - mf) / np.sqrt((vb + vf) / n[use])
    lb = np.array([x[m].mean() for x, m in zip(xb, mask)])
    lf = np.array([x[m].mean() for x, m in zip(xf, mask)])
    return {
        "pixels": int(mask.sum()),
        "per_pixel": int(use.sum()),
        "p_hist": _chi2_two_sample(xb[mask], xf[mask]),
        "var_ratio": float(vb.mean() / vf.mean()),
        "z_mean": float(z.mean()),
        "z_sd": float(z.std()),
        "p_level": float(stats.ks_2samp(lb, lf).pvalue),
        "level": (float(lb.mean()), float(lf.mean())),
    }


# Tolerances (stated once; see the module docstring)
P_MIN = 1e-4  # two-sample tests: p-value floor (false alarm 1 in 10^4 per test)
VAR_RATIO_TOL = 0.01  # per-pixel background variance, binned / full, mean over ~50 k pixels (SE ~0.1 %)
Z_MEAN_TOL = 0.03  # per-pixel mean difference in standard errors, averaged over ~50 k pixels (SE ~0.005)
Z_SD_RANGE = (0.95, 1.07)  # ... its spread (1 when every pixel's mean agrees, FPN included)


def test_background_pixels_equal_in_distribution(renderer, pair):
    scenes, binned, full, _ = pair
    s = _background_stats(binned, full, _background_mask(renderer, scenes))
    assert s["pixels"] > 1_000_000 and s["per_pixel"] > 20_000, s
    assert s["p_hist"] > P_MIN, s  # histogram of stored values (chi-square)
    assert abs(s["var_ratio"] - 1) < VAR_RATIO_TOL, s  # per-pixel variance
    assert abs(s["z_mean"]) < Z_MEAN_TOL, s  # per-pixel mean
    assert Z_SD_RANGE[0] < s["z_sd"] < Z_SD_RANGE[1], s
    assert s["p_level"] > 1e-3, s  # per-frame background level (KS)
    assert abs(s["level"][0] - s["level"][1]) < 0.01, s


def test_a_wrong_read_noise_is_caught(renderer, pair):
    """The same statistics reject a binned renderer whose read noise is 10 % too high."""
    scenes, _, full, _ = pair
    sigma = renderer.cfg.sensor.read_noise_e
    extra = float(np.sqrt((1.1 * sigma) ** 2 - sigma**2))
    with renderer.with_levels({"read_noise": extra}):
        b = BinnedRenderer(renderer)
        wrong = np.array([[b.image(sc, seed=8000 + i)] for i, sc in enumerate(scenes)], np.float64)
    s = _background_stats(wrong, full, _background_mask(renderer, scenes))
    assert s["p_hist"] < P_MIN and abs(s["var_ratio"] - 1) > VAR_RATIO_TOL, s


def _star_photometry(img: np.ndarray, x: np.ndarray, y: np.ndarray, bg: float):
    """Peak (3 x 3 stored pixels) and flux (5 x 5) above ``bg`` at full-resolution positions."""
    u = np.rint((x + 0.5) / F - 0.5).astype(int)
    v = np.rint((y + 0.5) / F - 0.5).astype(int)
    peaks, fluxes = [], []
    for a, c in zip(u, v):
        peaks.append(img[c - 1 : c + 2, a - 1 : a + 2].max() - bg)
        fluxes.append(img[c - 2 : c + 3, a - 2 : a + 3].sum() - 25 * bg)
    return np.array(peaks), np.array(fluxes)


def _bright_isolated(r, sc, min_e: float = 1000.0):
    st = sc.stars
    x, y, e = st["x_px"], st["y_px"], st["electrons"]
    h, w = r.cfg.camera.height_px, r.cfg.camera.width_px
    ok = (e > min_e) & (x > 24) & (x < w - 25) & (y > 24) & (y < h - 25)
    d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :]) + np.eye(len(x)) * 1e9
    ok &= (d < 24).sum(1) == 0
    return np.flatnonzero(ok)


def test_stars_peak_and_flux_equal_in_distribution(renderer, pair):
    scenes, binned, full, _ = pair
    P, Fl, D = {"b": [], "f": []}, {"b": [], "f": []}, {"b": [], "f": []}
    for i, sc in enumerate(scenes):
        k = _bright_isolated(renderer, sc)
        x, y = sc.stars["x_px"][k], sc.stars["y_px"][k]
        for key, imgs in (("b", binned[i]), ("f", full[i])):
            ph = [_star_photometry(im, x, y, float(np.median(im))) for im in imgs]
            P[key].append(ph[0][0])
            Fl[key].append(ph[0][1])
            D[key].append(ph[0][1] - ph[1][1])  # two noise draws of the same stars
    P = {k: np.concatenate(v) for k, v in P.items()}
    Fl = {k: np.concatenate(v) for k, v in Fl.items()}
    D = {k: np.concatenate(v) for k, v in D.items()}
    n = len(P["b"])
    assert n > 300
    # the same stars: paired differences centre on 0 (flux within 4 standard errors)
    dflux = Fl["b"] - Fl["f"]
    assert abs(dflux.mean()) < 4 * dflux.std() / np.sqrt(n), (dflux.mean(), dflux.std())
    # distributions over the stars (two-sample KS)
    assert stats.ks_2samp(P["b"], P["f"]).pvalue > P_MIN
    assert stats.ks_2samp(Fl["b"], Fl["f"]).pvalue > P_MIN
    # flux noise (difference of two draws of the same stars): variance ratio within 15 %
    # (F-distribution with ~n, n degrees of freedom: SE ~ sqrt(4/n) ~ 8 % at n = 600; 15 % ~ 2 SE at
    # the smallest n allowed, more at the n this test has)
    ratio = (D["b"] ** 2).mean() / (D["f"] ** 2).mean()
    assert abs(ratio - 1) < 0.15, (ratio, n)
    # peak histogram, log-spaced bins (chi-square)
    edges = np.quantile(np.concatenate([P["b"], P["f"]]), np.linspace(0, 1, 11))
    cb, _ = np.histogram(P["b"], edges)
    cf, _ = np.histogram(P["f"], edges)
    assert stats.chi2_contingency(np.array([cb, cf]))[1] > P_MIN


def test_same_index_same_stars_at_same_stored_positions(renderer, pair):
    """Light-weighted centroids of bright isolated stars agree between the paths to < 0.1 stored
    pixel (median) and sit where skygen.conventions puts them: u = (x + 0.5) / 4 - 0.5."""
    scenes, binned, full, _ = pair
    err_b, err_f, diff = [], [], []
    for i, sc in enumerate(scenes):
        k = _bright_isolated(renderer, sc, 5000.0)
        for x, y in zip(sc.stars["x_px"][k], sc.stars["y_px"][k]):
            u, v = (x + 0.5) / F - 0.5, (y + 0.5) / F - 0.5
            c = []
            for im in (binned[i, 0], full[i, 0]):
                a, b = round(u), round(v)
                cut = im[b - 2 : b + 3, a - 2 : a + 3] - np.median(im)
                cut = np.clip(cut, 0, None)
                yy, xx = np.mgrid[b - 2 : b + 3, a - 2 : a + 3]
                c.append(((cut * xx).sum() / cut.sum(), (cut * yy).sum() / cut.sum()))
            err_b.append(np.hypot(c[0][0] - u, c[0][1] - v))
            err_f.append(np.hypot(c[1][0] - u, c[1][1] - v))
            diff.append(np.hypot(c[0][0] - c[1][0], c[0][1] - c[1][1]))
    assert len(diff) > 50
    assert np.median(diff) < 0.1 and np.max(diff) < 0.5, (np.median(diff), np.max(diff))
    assert np.median(err_b) < 0.15 and np.median(err_f) < 0.15


def test_saturated_blocks_match_the_full_renderer(renderer):
    """Blocks where a pixel may fill the full well (bright stars, strong hot pixels) are drawn per
    sensor pixel: their stored values agree with render-then-downsample in mean per block."""
    r = renderer
    b = BinnedRenderer(r)
    sc = r.scene(0)
    bright = dict(sc.stars)
    bright["electrons"] = np.where(np.arange(len(sc.stars["electrons"])) < 3, 5e6, sc.stars["electrons"])
    sc = dataclasses.replace(sc, stars=bright)
    xb = np.array([b.image(sc, seed=k) for k in range(8)], np.float64)
    xf = np.array(
        [r.downsample(r.rasterise(dataclasses.replace(sc, rng_key=(0, 900 + k)))[0]) for k in range(8)], np.float64
    )
    hot = xf.mean(0) > 400  # saturated cores and bloom trails
    assert hot.sum() > 20
    se = np.sqrt((xb.var(0, ddof=1) + xf.var(0, ddof=1)) / len(xb))[hot]
    assert (np.abs(xb.mean(0)[hot] - xf.mean(0)[hot]) < 5 * se + 1.0).all()  # per block, 5 standard errors
    assert abs(xb.mean(0)[hot].sum() - xf.mean(0)[hot].sum()) < 0.01 * xf.mean(0)[hot].sum()


def test_rounding_and_model_bound():
    """INTER_AREA's rounding is reproduced exactly at every factor we use (fresh data, ties
    included); the model's bound is tiny for the default sensor and large where per-pixel
    quantisation shows."""
    import cv2

    rng = np.random.default_rng(1)
    for f in (2, 3, 4, 8):
        rule = area_rounding(f)
        a = rng.integers(0, 4096, (32 * f, 32 * f)).astype(np.uint16)
        out = cv2.resize(a, (32, 32), interpolation=cv2.INTER_AREA)
        total = a.reshape(32, f, 32, f).sum((1, 3)).astype(np.int64)
        np.testing.assert_array_equal(round_block_sums(total, f * f, rule), out)
    assert aliasing_bound(5.0, 3.3, 16) < 1e-15
    assert aliasing_bound(0.5, 3.3, 16) > 1e-12


def test_block_sum_model_matches_background_table(renderer):
    """The two samplers of skygen.render.binned agree where both apply: background-only blocks drawn by
    the block-sum model (Poisson of the sum, summed read noise, n - 1 uniforms) and by the exact
    n-fold convolution of the per-pixel distribution."""
    b = BinnedRenderer(renderer)
    s = renderer.cfg.sensor
    smin, pmf = b.block_sum_pmf(float(renderer.background_e), s.read_noise_e)
    rng = np.random.default_rng(3)
    m = 400000
    t = rng.poisson(16 * renderer.background_e, m) + s.read_noise_e * 4 * rng.standard_normal(m)
    S = np.floor(t / s.gain_e_per_adu - rng.random((m, 15)).sum(1)).astype(np.int64)
    expect = pmf * m
    ok = expect > 20
    counts = np.bincount(S - smin, minlength=len(pmf))[: len(pmf)]
    chi2 = (((counts - expect) ** 2 / expect)[ok]).sum()
    assert stats.chi2.sf(chi2, ok.sum() - 1) > P_MIN


def test_unsupported_configs_fall_back_once_with_a_warning(recwarn):
    """A config the binned renderer cannot reproduce exactly renders full frames, says why once."""
    cfg = load_config(overrides=["sensor.read_noise_e=0.5"])
    r = Renderer(cfg, rng_tag="@stream-frames")
    assert "read noise" in unsupported_reason(r)
    with pytest.raises(Exception, match="cannot reproduce"):
        BinnedRenderer(r)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        a = SampleStream(cfg, "frames")
        SampleStream(cfg, "frames")
    said = [w for w in caught if "binned renderer" in str(w.message)]
    assert len(said) == 1 and "read noise" in str(said[0].message)
    assert a.frames_renderer == "full" and a.frame(0).image.shape == (256, 256)


def test_frames_stream_uses_binned_renderer_with_emulated_detections():
    cfg = load_config()
    s = SampleStream(cfg, "frames", level_ranges={"dropout": (0, 0.3), "false_stars": (0, 2)})
    assert s.frames_renderer == "binned"
    frames, images = s.frames_batch([5, 6, 7])
    assert images is None
    one = s.frame(6)  # alone or in a batch: the same sample
    assert np.array_equal(one.image, frames[1].image)
    assert all(np.array_equal(one.detections[k], frames[1].detections[k]) for k in one.detections)
    assert one.image.shape == (256, 256) and one.image.dtype == np.uint16
    # the same scene as the full renderer's sample 6
    full = SampleStream(
        cfg, "frames", frames_renderer="full", level_ranges={"dropout": (0, 0.3), "false_stars": (0, 2)}
    ).frame(6)
    assert (full.ra_deg, full.dec_deg, full.roll_deg) == (one.ra_deg, one.dec_deg, one.roll_deg)
    np.testing.assert_array_equal(full.stars["x_px"], one.stars["x_px"])
    # detections: emulated, matched to catalog stars of the scene
    d = one.detections
    ok = d["star_index"] >= 0
    assert ok.sum() >= 3
    np.testing.assert_array_equal(d["hip_id"][ok], one.stars["hip_id"][d["star_index"][ok]])
    assert (
        np.median(
            np.hypot(
                d["x_px"][ok] - one.stars["x_px"][d["star_index"][ok]],
                d["y_px"][ok] - one.stars["y_px"][d["star_index"][ok]],
            )
        )
        < 0.5
    )
    with pytest.raises(Exception, match="frames renderer"):
        SampleStream(cfg, "frames", frames_renderer="fast")


def test_scene_builder_draws_scenes_like_the_renderer(renderer):
    """The stream's vectorised scenes (skygen.render.scenes) against Renderer.scene: same distribution of
    stars per scene, their electrons, declination, false stars and cosmic-ray hits (two-sample KS,
    p > 1e-3); the same stars, projected and sized alike, for a given attitude."""
    from skygen import hashrng
    from skygen.render.scenes import SceneBuilder

    cfg = load_config(overrides=["corruptions.false_stars=1.5", "corruptions.cosmic_rays=200"])
    r = Renderer(cfg, rng_tag="@stream-frames")
    built = SceneBuilder(r, hashrng.stream_key(cfg.seed, "@stream-frames")).scenes(np.arange(400), {})
    ref = [r.scene(i) for i in range(400)]
    for stat in (
        lambda sc: (sc.stars["hip_id"] >= 0).sum(),
        lambda sc: sc.stars["electrons"].sum(),
        lambda sc: sc.dec_deg,
        lambda sc: (sc.stars["hip_id"] < 0).sum(),
        lambda sc: len(sc.cosmic_rays),
    ):
        a, b = [stat(sc) for sc in built], [stat(sc) for sc in ref]
        assert stats.ks_2samp(a, b).pvalue > 1e-3, (np.mean(a), np.mean(b))
    # same attitude -> the renderer's own star selection and projection
    sc = built[7]
    with r.with_levels({}):
        stars = r.visible_stars(sc.rotation, np.zeros(3), np.zeros(1))
    cat = sc.stars["hip_id"] >= 0
    np.testing.assert_array_equal(np.sort(stars["hip_id"]), np.sort(sc.stars["hip_id"][cat]))
    np.testing.assert_allclose(np.sort(stars["electrons"]), np.sort(sc.stars["electrons"][cat]), rtol=1e-6)


@pytest.mark.parametrize(
    "overrides",
    [
        ["corruptions.stray_light=3000", "optics.vignetting=0.3"],
        ["corruptions.motion_blur=1.5", "optics.psf=moffat"],
        ["sensor.sampler=exact", "corruptions.hotpixels=1e-3"],
    ],
    ids=["stray-light+vignetting", "motion-blur+moffat", "exact-sampler+hot-pixels"],
)
def test_other_features_equal_in_distribution(overrides):
    """A non-uniform background (every block by the block-sum model), streaked Moffat stars (the
    generic stamp path), and the exact sampler (every pixel drawn exactly: blooming hot pixels spill
    onto all neighbours): per-pixel means agree (within 5 standard errors on 16 x 16 averages
    of the stored pixels) and the per-pixel variance within 3 % (pixels of variance < 50 ADU²)."""
    r = Renderer(load_config(overrides=overrides), rng_tag="@stream-frames")
    assert unsupported_reason(r) is None
    b = BinnedRenderer(r)
    scenes = [r.scene(i) for i in range(24)]
    xb = np.array([b.image(sc, seed=i) for i, sc in enumerate(scenes)], np.float64)
    xf = np.array([r.downsample(r.rasterise(sc)[0]) for sc in scenes], np.float64)
    d = (xb - xf).reshape(len(scenes), 16, 16, 16, 16).mean((2, 4))  # per scene, 16 x 16 super-blocks
    z = d.mean(0) / (d.std(0, ddof=1) / np.sqrt(len(scenes)))
    assert np.abs(z).max() < 5, np.abs(z).max()
    assert abs(z.mean()) < 0.5
    vb, vf = xb.var(0, ddof=1), xf.var(0, ddof=1)
    calm = (vb + vf) / 2 < 50  # leave out bright cores and bloom trails (heavy-tailed estimates)
    ratio = vb[calm].mean() / vf[calm].mean()
    assert abs(ratio - 1) < 0.03, ratio
