"""Calibrating the detector emulator (:mod:`skygen.stream.emulator`) against the real detector.

:func:`calibrate_from_renders` renders frames with the real renderer and detector
(:func:`calibration_config`: the camera's own settings, no corruptions), and :func:`fit`
turns their sources and detections into a :class:`skygen.stream.emulator.DetectorModel`:
completeness and the rows of isolated detections per bin of ``u``, the blending curve
(catalog pairs plus the designed pairs of :func:`painted_pairs`) and the spurious
detections. :func:`calibrate_from_dataset` fits the same from a rendered dataset's stored
stars and detections. ``skygen calibrate`` runs them and saves the result.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from skygen.errors import ConfigError, DatasetError
from skygen.stream.emulator import (
    BANK_ROWS_PER_BIN,
    BLEND_MAX_PX,
    GAP_EDGES,
    ISOLATION_PX,
    STREAM_CORRUPTIONS,
    U_EDGES,
    DetectorModel,
    calibration_key,
    gap_px,
    threshold_electrons,
)


def _logistic_fit(gap: np.ndarray, resolved: np.ndarray) -> np.ndarray:
    """P(resolved | gap) as a logistic curve fitted by maximum likelihood (pairs near the
    transition are few, so a two-parameter curve beats a binned rate), tabulated at the
    centres of GAP_EDGES."""
    from scipy.optimize import minimize

    y = resolved.astype(np.float64)

    def nll(p):
        z = (gap - p[0]) / np.exp(p[1])
        return float(np.sum(np.logaddexp(0, -z) * y + np.logaddexp(0, z) * (1 - y)))

    start = [float(np.median(gap)), 0.0]
    if 0 < y.sum() < len(y):
        res = minimize(nll, start, method="Nelder-Mead")
        g0, w = res.x[0], np.exp(res.x[1])
    else:  # all resolved or all merged: a step at the edge of the data
        g0, w = (gap.min() - 0.5, 0.1) if y.all() else (gap.max() + 0.5, 0.1)
    centres = 0.5 * (GAP_EDGES[1:] + GAP_EDGES[:-1])
    return 1.0 / (1.0 + np.exp(-(centres - g0) / max(w, 1e-3)))


def _binned_rate(values: np.ndarray, hits: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    b = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, len(edges) - 2)
    ok = values >= edges[0]
    tot = np.bincount(b[ok], minlength=len(edges) - 1).astype(np.float64)
    hit = np.bincount(b[ok], weights=hits[ok].astype(np.float64), minlength=len(edges) - 1)
    return hit, tot


@dataclass
class _Tallies:
    """What the calibration frames add up to, frame by frame (:func:`_tally_frame`)."""

    u: list = field(default_factory=list)  # log10(electrons / threshold) of isolated sources
    hit: list = field(default_factory=list)  # ... and whether the detector found them
    rows: list = field(default_factory=list)  # residual rows of matched isolated detections
    rows_bin: list = field(default_factory=list)  # ... and their brightness bin
    pair_d: list = field(default_factory=list)  # gap of close pairs of bright stars
    pair_res: list = field(default_factory=list)  # ... and whether both were detected (resolved)
    spur_counts: list = field(default_factory=list)  # spurious detections per frame
    spur_rows: list = field(default_factory=list)  # ... their flux, peak and area
    frames: int = 0


def fit(
    frames,
    threshold_e: float,
    key: dict,
    gain_e_per_adu: float,
    psf_sigma_px: float,
    info: dict | None = None,
    rng: np.random.Generator | None = None,
    extra_pairs: tuple | None = None,
) -> DetectorModel:
    """Fit a :class:`DetectorModel` from ``(true_stars, detections)`` pairs of rendered frames.

    ``true_stars`` has ``x_px``, ``y_px``, ``electrons``; ``detections`` has the detector's
    table with ``star_index`` (row of the matched true star or -1). The frames must carry
    no detection-level corruptions (dropout, centroid or magnitude noise): the stream
    applies those itself.
    """
    rng = rng or np.random.default_rng(0)
    t = _Tallies()
    for stars, det in frames:
        _tally_frame(t, stars, det, threshold_e, psf_sigma_px)
    if t.frames == 0:
        raise DatasetError("no frames to calibrate on")
    u_all, hit_all = np.concatenate(t.u), np.concatenate(t.hit)
    hit, tot = _binned_rate(u_all, hit_all, U_EDGES)
    rows = np.concatenate(t.rows) if t.rows else np.zeros((0, 5))
    if len(rows) == 0:
        raise DatasetError(
            "the calibration frames hold no matched detections of isolated stars; render brighter or more frames"
        )
    rows_bin = np.concatenate(t.rows_bin) if t.rows_bin else np.zeros(0, np.int64)
    start, bank = _residual_bank(rows, rows_bin, rng)
    if extra_pairs is not None:
        t.pair_d.append(extra_pairs[0])
        t.pair_res.append(extra_pairs[1])
    p_res = (
        _logistic_fit(np.concatenate(t.pair_d), np.concatenate(t.pair_res)) if t.pair_d else np.ones(len(GAP_EDGES) - 1)
    )
    counts = np.asarray(t.spur_counts)
    pmf, sp = _spurious_model(counts, t.spur_rows, rng)
    info = dict(info or {})
    info.update(
        {
            "frames": t.frames,
            "isolated_sources": int(len(u_all)),
            "matched_rows": int(len(rows)),
            "spurious_per_frame": float(counts.mean()),
            "pairs_for_blending": int(sum(len(p) for p in t.pair_d)),
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
    )
    return DetectorModel(
        key=key,
        threshold_e=float(threshold_e),
        psf_sigma_px=float(psf_sigma_px),
        completeness=_monotone(hit, tot),
        bank_start=start,
        bank=bank,
        p_resolved=p_res,
        spurious_pmf=pmf,
        spurious={"flux_adu": sp[:, 0], "peak_adu": sp[:, 1], "area_px": sp[:, 2]},
        gain_e_per_adu=float(gain_e_per_adu),
        info=info,
    )


def _tally_frame(t: _Tallies, stars: dict, det: dict, threshold_e: float, psf_sigma_px: float) -> None:
    """Add one frame's isolated sources, matched residuals, close pairs and spurious detections to ``t``."""
    t.frames += 1
    e = np.asarray(stars["electrons"], np.float64)
    sx, sy = np.asarray(stars["x_px"], np.float64), np.asarray(stars["y_px"], np.float64)
    u = np.log10(np.maximum(e, 1e-12) / threshold_e)
    sidx = np.asarray(det["star_index"], np.int64)
    matched = np.zeros(len(e), bool)
    matched[sidx[sidx >= 0]] = True
    # isolation: no other source above u = -0.7 (a fifth of the threshold) within ISOLATION_PX
    strong = u > -0.7
    isolated = np.ones(len(e), bool)
    if len(e) > 1 and strong.any():
        tree = cKDTree(np.column_stack([sx[strong], sy[strong]]))
        cnt = np.array([len(c) for c in tree.query_ball_point(np.column_stack([sx, sy]), ISOLATION_PX)])
        isolated = cnt - strong.astype(int) == 0
        pts = np.column_stack([sx, sy])
        good = np.flatnonzero(u > 0.3)
        if len(good) > 1:
            pr = cKDTree(pts[good]).query_pairs(BLEND_MAX_PX, output_type="ndarray")
            if len(pr):
                a, b = good[pr[:, 0]], good[pr[:, 1]]
                # only pairs with no third source nearby: the pair alone decides
                third = np.array([len(c) for c in tree.query_ball_point(pts[a], ISOLATION_PX)]) + np.array(
                    [len(c) for c in tree.query_ball_point(pts[b], ISOLATION_PX)]
                )
                clean = third <= 4
                d = np.hypot(sx[a] - sx[b], sy[a] - sy[b])
                t.pair_d.append(gap_px(e[a], e[b], d, threshold_e, psf_sigma_px)[clean])
                t.pair_res.append((matched[a] & matched[b])[clean])
    t.u.append(u[isolated])
    t.hit.append(matched[isolated])
    m = np.flatnonzero(sidx >= 0)
    s = sidx[m]
    keep = isolated[s]
    m, s = m[keep], s[keep]

    def col(name: str, rows: np.ndarray) -> np.ndarray:
        return np.asarray(det[name], np.float64)[rows]

    if len(m):
        t.rows.append(
            np.column_stack(
                [
                    col("x_px", m) - sx[s],
                    col("y_px", m) - sy[s],
                    np.log10(np.maximum(col("flux_adu", m), 1e-3) / e[s]),
                    np.log10(np.maximum(col("peak_adu", m), 1e-3) / e[s]),
                    col("area_px", m),
                ]
            )
        )
        t.rows_bin.append(np.clip(np.searchsorted(U_EDGES, u[s], side="right") - 1, 0, len(U_EDGES) - 2))
    sp = np.flatnonzero(sidx < 0)
    t.spur_counts.append(len(sp))
    if len(sp):
        t.spur_rows.append(np.column_stack([col("flux_adu", sp), col("peak_adu", sp), col("area_px", sp)]))


def _residual_bank(rows: np.ndarray, rows_bin: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """At most BANK_ROWS_PER_BIN residual rows per brightness bin (a random subset, kept in order):
    the bank's start offsets per bin and its columns."""
    chosen = []
    for b in range(len(U_EDGES) - 1):
        r = np.flatnonzero(rows_bin == b)
        if len(r) > BANK_ROWS_PER_BIN:
            r = np.sort(rng.choice(r, BANK_ROWS_PER_BIN, replace=False))
        chosen.append(r)
    start = np.concatenate([[0], np.cumsum([len(c) for c in chosen])]).astype(np.int64)
    sel = rows[np.concatenate(chosen)]
    return start, {
        "dx": sel[:, 0],
        "dy": sel[:, 1],
        "log_flux_ratio": sel[:, 2],
        "log_peak_ratio": sel[:, 3],
        "area": sel[:, 4],
    }


def _spurious_model(counts: np.ndarray, spur_rows: list, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The distribution of spurious detections per frame and a bank of their (flux, peak, area) rows."""
    pmf = np.bincount(counts).astype(np.float64) / len(counts)
    sp = np.concatenate(spur_rows) if spur_rows else np.zeros((0, 3))
    if len(sp) > 4 * BANK_ROWS_PER_BIN:
        sp = sp[np.sort(rng.choice(len(sp), 4 * BANK_ROWS_PER_BIN, replace=False))]
    if len(sp) == 0:
        pmf = np.array([1.0])
        sp = np.zeros((1, 3))
    return pmf, sp


def _monotone(hit: np.ndarray, tot: np.ndarray) -> np.ndarray:
    """Completeness per bin, made non-decreasing in brightness (pool-adjacent-violators, weighted).

    Empty bins take the value of their neighbours: 0 below the faintest observed bin, 1
    above the brightest.
    """
    n = len(tot)
    have = np.flatnonzero(tot > 0)
    out = np.zeros(n)
    if len(have) == 0:
        return out
    vals = list(hit[have] / tot[have])
    wts = list(tot[have])
    blocks = [[v, w, 1] for v, w in zip(vals, wts)]
    merged: list = []
    for blk in blocks:
        merged.append(blk)
        while len(merged) > 1 and merged[-2][0] > merged[-1][0]:
            v2, w2, c2 = merged.pop()
            v1, w1, c1 = merged.pop()
            merged.append([(v1 * w1 + v2 * w2) / (w1 + w2), w1 + w2, c1 + c2])
    fitted = np.concatenate([[v] * c for v, _, c in merged])
    out[have] = fitted
    # fill gaps: interpolate inside, hold the ends
    out = np.interp(np.arange(n), have, fitted, left=0.0, right=fitted[-1])
    return out


# ---------------------------------------------------------------------------------- calibrate


def painted_pairs(
    renderer, n_frames: int, rng: np.random.Generator, per_side: int = 6
) -> tuple[np.ndarray, np.ndarray]:
    """A designed blending experiment on the real sensor model and detector.

    Catalog pairs near the merging separation are rare (a few known doubles), so blending
    is measured directly: ``per_side**2`` pairs per frame, each in its own cell of the
    sensor, brightness log-uniform between 2x and 1000x the threshold, separation uniform in
    1-12 px, painted with the configured PSF, read out with the configured sensor (noise,
    PRNU, hot pixels, ADC) and detected by :func:`skygen.instrument.detect.detect`. Returns the
    pairs' footprint gaps and whether both stars were detected separately.
    """
    from skygen.instrument.detect import detect, match
    from skygen.instrument.psf import add_patch, stamp
    from skygen.instrument.sensor import Exposure, read_out

    cfg = renderer.cfg
    h, w = cfg.camera.height_px, cfg.camera.width_px
    o, d = cfg.optics, cfg.detection
    thr = threshold_electrons(renderer)
    gaps, res = [], []
    for _ in range(n_frames):
        img = np.zeros((h, w), np.float32)
        cy, cx = (np.arange(per_side) + 0.5) * h / per_side, (np.arange(per_side) + 0.5) * w / per_side
        yy, xx = np.meshgrid(cy, cx, indexing="ij")
        n = yy.size
        e = thr * 10 ** rng.uniform(np.log10(2), 3, size=(n, 2))
        sep, ang = rng.uniform(1, 12, n), rng.uniform(0, np.pi, n)
        xa, ya = xx.ravel() + rng.uniform(-0.5, 0.5, n), yy.ravel() + rng.uniform(-0.5, 0.5, n)
        xb, yb = xa + sep * np.cos(ang), ya + sep * np.sin(ang)
        xs, ys, es = np.concatenate([xa, xb]), np.concatenate([ya, yb]), np.concatenate([e[:, 0], e[:, 1]])
        boxes = [
            add_patch(
                img, *stamp(float(x), float(y), float(f), o.psf, o.psf_sigma_px, o.moffat_beta, renderer.camera.aspect)
            )
            for x, y, f in zip(xs, ys, es)
        ]
        full, _ = read_out(
            Exposure(img, None, [b for b in boxes if b], renderer.background_e, None),
            cfg.sensor,
            renderer.maps,
            rng,
            renderer.levels["read_noise"],
        )
        det, _, _ = detect(full, d.threshold_sigma, d.min_area_px, 4 * n + 64, d.background_box_px)
        sidx = match(det["x_px"], det["y_px"], xs, ys, es, d.match_radius_px)
        found = np.zeros(2 * n, bool)
        found[sidx[sidx >= 0]] = True
        gaps.append(gap_px(e[:, 0], e[:, 1], sep, thr, o.psf_sigma_px))
        res.append(found[:n] & found[n:])
    return np.concatenate(gaps), np.concatenate(res)


def calibration_config(cfg):
    """``cfg`` with the stream-applied corruptions off (the calibration must not contain them)."""
    from skygen.config import build_config, config_dict

    data = config_dict(cfg)
    for name in STREAM_CORRUPTIONS:
        data["corruptions"][name] = 0.0
    data["sensor"]["fixed_sources"] = []  # the stream places them itself (STREAM_SOURCES), as it does false stars
    return build_config(data)


def calibrate_from_renders(cfg, n_frames: int = 2000, tag: str = "@calibration", progress=None) -> DetectorModel:
    """Render ``n_frames`` calibration frames (their own random streams) and fit the emulator."""
    from skygen.config import config_dict
    from skygen.render.frame import Renderer

    cfg = calibration_config(cfg)
    r = Renderer(cfg, rng_tag=tag)

    def frames():
        for i in range(n_frames):
            fr = r.render(i)
            if progress:
                progress(i + 1, n_frames)
            yield fr.stars, fr.detections

    d = config_dict(cfg)
    n_pair_frames = max(10, n_frames // 20)
    pairs = painted_pairs(r, n_pair_frames, np.random.default_rng([cfg.seed, 7]))
    return fit(
        frames(),
        threshold_electrons(r),
        calibration_key(d),
        cfg.sensor.gain_e_per_adu,
        cfg.optics.psf_sigma_px,
        {
            "source": f"{n_frames} frames rendered with rng tag {tag!r}, seed {cfg.seed}; blending also from "
            f"{len(pairs[0])} painted pairs in {n_pair_frames} frames",
            "skygen_detector": "skygen.instrument.detect.detect",
        },
        extra_pairs=pairs,
    )


def calibrate_from_dataset(path: str | Path, max_frames: int | None = None) -> DetectorModel:
    """Fit the emulator on the frames of a rendered dataset (all splits)."""
    from skygen.config import build_config
    from skygen.datasets.shards import open_dataset
    from skygen.render.frame import Renderer

    with open_dataset(path) as ds:
        config = ds.config
        bad = [n for n in STREAM_CORRUPTIONS[1:] if float(config["corruptions"][n]) != 0.0]
        if bad:
            raise ConfigError(
                f"{path}: rendered with detection-level corruptions {bad}; calibrate on a dataset "
                "without them (the stream applies them itself), or let `skygen calibrate` render "
                "its own frames"
            )
        if config.get("sensor", {}).get("fixed_sources"):
            raise ConfigError(
                f"{path}: rendered with sensor.fixed_sources, which the stream places itself; calibrate on a "
                "dataset without them, or let `skygen calibrate` render its own frames"
            )
        cfg = build_config(config)
        r = Renderer(cfg)
        n = len(ds) if max_frames is None else min(max_frames, len(ds))
        frames = ((ds.true_stars(i), ds.detections(i)) for i in range(n))
        pairs = painted_pairs(r, max(10, n // 20), np.random.default_rng([cfg.seed, 7]))
        return fit(
            frames,
            threshold_electrons(r),
            calibration_key(config),
            cfg.sensor.gain_e_per_adu,
            cfg.optics.psf_sigma_px,
            {
                "source": f"dataset {Path(path).name} ({ds.manifest.get('dataset_id')}), first {n} frames; "
                f"blending also from {len(pairs[0])} painted pairs",
                "skygen_detector": "skygen.instrument.detect.detect",
            },
            extra_pairs=pairs,
        )
