"""The fine stage's pair index and compiled scoring: against brute force, cached safely, refusing early."""

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fusion.solve import pairs as pairs_mod
from fusion.solve.fine import NO_CODES
from fusion.solve.match import anchor_hypotheses, partner_table, triad
from fusion.solve.pairs import build_index, load_or_build


def random_catalogue(n=400, seed=0):
    v = np.random.default_rng(seed).standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_pair_index_holds_every_close_pair_once_sorted():
    vec, max_sep = random_catalogue(), 0.35
    idx = build_index(vec, max_sep)
    sep = np.arccos(np.clip(vec @ vec.T, -1, 1))
    iu = np.triu_indices(len(vec), 1)
    want = {(a, b) for a, b, d in zip(*iu, sep[iu]) if d < max_sep}
    got = list(zip(idx.first.tolist(), idx.second.tolist()))
    assert len(got) == len(set(got)) == len(want) and set(got) == want
    assert np.all(np.diff(idx.sep) >= 0) and np.all(idx.first < idx.second)
    np.testing.assert_allclose(idx.sep, sep[idx.first, idx.second], atol=1e-12)
    lo, hi = idx.range(0.1, 0.12)  # a range is exactly the pairs in it
    assert set(got[lo:hi]) == {(a, b) for a, b in want if 0.1 <= sep[a, b] <= 0.12}


def test_pair_index_cache_is_reused_never_confused_and_rebuilt_when_damaged(tmp_path, monkeypatch):
    vec = random_catalogue(200)
    first = load_or_build(vec, 0.3, tmp_path)
    files = list(tmp_path.glob("pairs-*.npz"))
    assert len(files) == 1
    real_build = pairs_mod.build_index
    monkeypatch.setattr(pairs_mod, "build_index", lambda *a: pytest.fail("rebuilt although cached"))
    again = load_or_build(vec, 0.3, tmp_path)
    np.testing.assert_array_equal(again.sep, first.sep)
    monkeypatch.setattr(pairs_mod, "build_index", real_build)
    other = load_or_build(random_catalogue(200, seed=1), 0.3, tmp_path)  # another catalogue cut
    assert other.key != first.key and len(list(tmp_path.glob("pairs-*.npz"))) == 2
    files[0].write_bytes(b"not a zip")  # damaged
    lines = []
    fixed = load_or_build(vec, 0.3, tmp_path, log=lines.append)
    np.testing.assert_array_equal(fixed.sep, first.sep)
    assert len(lines) == 2 and "unreadable" in lines[0] and "rebuilding" in lines[0]


def brute_force_scores(t, i, j, a, b, kf, vec, tol_n):
    """Score of hypothesis (i is a, j is b) by projecting every detection and searching the nearest star."""
    u = np.column_stack([t / kf, np.ones(len(t))])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = triad(u[i], u[j], vec[a], vec[b])
    sky = u @ r.T
    dist, idx = cKDTree(vec).query(sky)
    ang = 2 * np.arcsin(np.clip(dist / 2, 0, 1))
    score = 1 + int(np.arccos(np.clip(sky[j] @ vec[b], -1, 1)) <= tol_n[j])
    others = [k for k in range(len(t)) if k not in (i, j)]
    return score + int(sum(ang[k] <= tol_n[k] for k in others)), r


def _anchor_case(s):
    """One anchor pair's search: a true attitude's field (6 stars + 2 false detections) of a random catalogue,
    the pair index and every partner table; (args of anchor_hypotheses up to min_score, t, i, j, vec, tol_n,
    the true stars' rows, lo, hi)."""
    rng = np.random.default_rng(3)
    vec = random_catalogue(3000, seed=2)
    tol = 2.0 / 2900.0  # 2 px at a 2,900 px focal length
    # a true attitude, the catalogue stars in its 20 deg field as detections (+ 2 false ones), at focal factor 1.01
    boresight = vec[7]
    cam_z = boresight
    cam_x = np.cross([0, 0, 1.0], cam_z)
    cam_x /= np.linalg.norm(cam_x)
    cam_y = np.cross(cam_z, cam_x)
    rot = np.column_stack([cam_x, cam_y, cam_z])  # camera -> sky
    cam = vec @ rot
    inside = np.flatnonzero(
        (cam[:, 2] > 0) & (np.abs(cam[:, 0] / cam[:, 2]) < 0.17) & (np.abs(cam[:, 1] / cam[:, 2]) < 0.17)
    )[:6]
    t = cam[inside, :2] / cam[inside, 2:3] * (1.01 if s else 1.0) + rng.normal(0, 0.05 * tol, (len(inside), 2))
    t = np.vstack([t, rng.uniform(-0.17, 0.17, (2, 2))])
    n = len(t)
    idx = build_index(vec, 0.7)
    i, j = 0, 1
    u = np.column_stack([t, np.ones(n)])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    d = math.acos(u[i] @ u[j])
    lo, hi = idx.range(d / (1 + s) - 2 * tol, d / (1 - s) + 2 * tol)
    tol_n = (tol + min(s, 2 * tol / d) * np.hypot(*(t - t[i]).T)) if s else np.full(n, tol)
    offs = np.zeros((len(vec) + 1, n), np.int64)
    parts, seps, base = [], [], 0
    for k in range(n):
        if k in (i, j):
            continue
        o, p, q = partner_table(0, len(idx), idx.first, idx.second, idx.sep, len(vec))  # every pair: a superset
        offs[:, k] = o + base
        parts.append(p)
        seps.append(q)
        base += len(p)
    args = (
        i,
        j,
        t,
        lo,
        hi,
        idx.first,
        idx.second,
        idx.sep,
        vec,
        np.ones(len(vec), bool),
        s,
        tol_n,
        offs,
        np.concatenate(parts),
        np.concatenate(seps),
        np.array([0, 0, 1.0]),
        -1.0,
        0,
    )
    return args, t, i, j, vec, tol_n, inside, lo, hi


FREE = (np.array([1.0, 0, 0]), -2.0)  # no roll bound


def _grid(s, vec, tol_n):
    """The focal pass's sky grid for these tolerances (s > 0), else none (the partner tables)."""
    from fusion.solve.fine import NO_GRID, _focal_grid

    return _focal_grid(vec, float(np.max(tol_n))) if s else NO_GRID


@pytest.mark.parametrize("s", [0.0, 0.02])
def test_compiled_scores_equal_brute_force(s):
    """Every hypothesis of an anchor pair scores as projecting all detections would (j through B)."""
    args, t, i, j, vec, tol_n, inside, lo, hi = _anchor_case(s)
    n, free = len(t), FREE
    every = (0, np.full(n + 1, np.inf))  # no early rejection: every score is enough at every H
    from fusion.solve.fine import NO_GRID

    tried, A, B, K, S, R, best, stopped = anchor_hypotheses(*args, 1 << 62, *free, *every, *NO_GRID, *NO_CODES)
    assert best == S.max() and not stopped
    # the work budget: exactly that many hypotheses, the first ones in order (a count, not a clock)
    cut = anchor_hypotheses(*args, 7, *free, *every, *NO_GRID, *NO_CODES)
    assert cut[0] == 7 and cut[1].tolist() == A[:7].tolist() and cut[4].tolist() == S[:7].tolist()
    assert tried == 2 * (hi - lo) == len(A) > 0
    for a, b, kf, score, r in zip(A, B, K, S, R):
        want, r_want = brute_force_scores(t, i, j, a, b, kf, vec, tol_n)
        assert score == want, (a, b)
        np.testing.assert_allclose(r, r_want, atol=1e-12)
    truth = np.flatnonzero((A == inside[0]) & (B == inside[1]))
    assert len(truth) == 1 and S[truth[0]] == len(inside)  # the true hypothesis matches every real star


def test_the_focal_pass_sky_grid_scores_as_the_partner_tables():
    """The focal pass's sky grid (each detection put on the sky, the stars filed near it tested) finds exactly
    the matches the partner tables find: the same hypotheses, scores and rotations; every star is filed on each
    cube face whose extended square holds it, and a query wider than the grid's margin is an error."""
    from fusion.solve.fine import NO_GRID
    from fusion.solve.match import sky_grid

    args, t, i, j, vec, tol_n, inside, lo, hi = _anchor_case(0.02)
    n = len(t)
    every = (0, np.full(n + 1, np.inf))
    tables = anchor_hypotheses(*args, 1 << 62, *FREE, *every, *NO_GRID, *NO_CODES)
    grid = _grid(0.02, vec, tol_n)
    assert grid[0][-1] >= len(vec) and set(grid[2].tolist()) == set(range(len(vec)))
    by_grid = anchor_hypotheses(*args, 1 << 62, *FREE, *every, *grid, *NO_CODES)
    assert by_grid[0] == tables[0] and by_grid[6] == tables[6] == len(inside)
    for a, b in zip(by_grid[1:6], tables[1:6]):
        np.testing.assert_array_equal(a, b)
    narrow = sky_grid(vec, 1e-4, 1e-4 * 3.1)  # a margin too narrow for these tolerances
    with pytest.raises(ValueError, match="margin"):
        anchor_hypotheses(*args, 1 << 62, *FREE, *every, *narrow, *NO_CODES)


@pytest.mark.parametrize("s", [0.0, 0.02])
@pytest.mark.parametrize("budget", [1 << 62, 20])
def test_region_hypotheses_listed_from_its_stars_equal_the_row_scan(s, budget):
    """A region's hypotheses listed from its stars A (window_codes / region_codes) are the row scan's: the same
    count, hypotheses, scores, rotations and order, with and without early rejection and with a budget that runs
    out part way (the order decides which are tried)."""
    from fusion.solve.match import region_codes, window_codes

    args, t, i, j, vec, tol_n, inside, lo, hi = _anchor_case(s)
    n = len(t)
    centre = vec[7]  # the true field's boresight, and a cap around it
    star_ok = vec @ centre >= math.cos(math.radians(30.0))  # stars A that can lie in the field of a boresight
    region = list(args)  # within 15 deg of it (37 hypotheses of the strict pass, 119 of the focal one)
    region[9], region[15], region[16] = star_ok, centre, math.cos(math.radians(15.0))
    grid = _grid(s, vec, tol_n)
    limit = np.full(n + 1, -1.0)
    limit[3:] = [40, 400, 4000, np.inf, np.inf, np.inf]
    codes = (True, region_codes(*window_codes(lo, hi, args[5], args[6], len(vec)), np.flatnonzero(star_ok)))
    for early in ((0, np.full(n + 1, np.inf)), (0, limit)):
        scan = anchor_hypotheses(*region, budget, *FREE, *early, *grid, *NO_CODES)
        listed = anchor_hypotheses(*region, budget, *FREE, *early, *grid, *codes)
        assert scan[0] == listed[0] and scan[6:] == listed[6:]
        for x, y in zip(scan[1:6], listed[1:6]):
            np.testing.assert_array_equal(x, y)
    assert scan[0] == min(budget, 37 if s == 0 else 119) and len(codes[1]) < 2 * (hi - lo)
    assert len(scan[1]) > 0 or budget < 37  # the true attitude among them when the budget reaches it


@pytest.mark.parametrize("s", [0.0, 0.02])
def test_early_rejection_drops_only_what_could_never_be_accepted(s):
    """With the E_false bar as h_limit (the largest H at which each score can be accepted), the search returns
    exactly the hypotheses of the full search whose score is enough at the H they were tried at, the same
    best score, and scores none once not even every detection matched could be accepted (``stopped``)."""
    args, t, i, j, vec, tol_n, inside, lo, hi = _anchor_case(s)
    n = len(t)
    grid = _grid(s, vec, tol_n)
    full = anchor_hypotheses(*args, 1 << 62, *FREE, 0, np.full(n + 1, np.inf), *grid, *NO_CODES)
    h0 = 100  # hypotheses of earlier anchor pairs
    limit = np.full(n + 1, -1.0)
    limit[3:] = [h0 + 40, h0 + 400, h0 + 4000, np.inf, np.inf, np.inf]  # 3 matches until H = 140, 4 until 500, ...
    tried, A, B, K, S, R, best, stopped = anchor_hypotheses(*args, 1 << 62, *FREE, h0, limit, *grid, *NO_CODES)
    assert tried == full[0] and not stopped and best == full[6] == len(inside)
    # the h-th hypothesis needs the least s with limit[s] >= h0 + h: the full search's, filtered by that
    order = {(a, b): h for h, (a, b) in enumerate(_tried_pairs(args, lo, hi), start=1)}
    need = [int(np.argmax(limit >= h0 + order[(a, b)])) for a, b in zip(full[1], full[2])]
    keep = [k for k, (sc, nd) in enumerate(zip(full[4], need)) if sc >= nd]
    assert 0 < len(keep) < len(full[1])  # the limits do drop some here
    assert A.tolist() == full[1][keep].tolist() and S.tolist() == full[4][keep].tolist()
    np.testing.assert_array_equal(R, full[5][keep])
    # no score can pass beyond H = 150: after 50 of its own hypotheses the rest are counted, none scored
    low = np.where(limit > 0, h0 + 50.0, -1.0)
    tried, A, B, *_, stopped = anchor_hypotheses(*args, 1 << 62, *FREE, h0, low, *grid, *NO_CODES)
    assert stopped and tried == full[0]
    assert all(order[(a, b)] <= 50 for a, b in zip(A, B))


def _tried_pairs(args, lo, hi):
    """(A, B) of every hypothesis in the order the search tries them (whole sky: every row, both orders)."""
    first, second = args[5], args[6]
    return [(a, b) for q in range(lo, hi) for a, b in ((first[q], second[q]), (second[q], first[q]))]
