"""tetra3rs databases (skygen.real.platesolve): where they are cached, their size known before they are built."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from skygen.errors import ConfigError
from skygen.real import platesolve as P


def test_the_cache_is_skygens_and_the_old_variable_still_works(monkeypatch, tmp_path):
    monkeypatch.delenv("SKYGEN_CACHE", raising=False)
    monkeypatch.delenv("FUSION_CACHE", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert P.cache_dir() == tmp_path / ".cache" / "skygen"
    monkeypatch.setenv("FUSION_CACHE", str(tmp_path / "legacy"))
    assert P.cache_dir() == tmp_path / "legacy"
    monkeypatch.setenv("SKYGEN_CACHE", str(tmp_path / "new"))
    assert P.cache_dir() == tmp_path / "new"


def test_a_field_range_with_a_huge_database_is_refused_naming_one_that_fits():
    with pytest.raises(ConfigError) as exc:
        P.check_database_size(1.0, 119.0)
    msg = str(exc.value)
    assert msg.startswith("field range 1-119 deg: its tetra3rs database would hold about ")
    assert "over the 350 MB limit; search a narrower range, e.g. --fov-range 3.1 119" in msg and "\n" not in msg
    assert P.estimate_database(3.1, 119.0)["mb"] <= P.MAX_DATABASE_MB < P.estimate_database(3.0, 119.0)["mb"]
    assert P.check_database_size(3.0, 10.0)["seconds"] > 120  # a narrow camera's range: allowed, announced
    with pytest.raises(
        ConfigError, match="too narrow for a lost-in-space search over a range: give the field, --fov DEG"
    ):
        P.check_database_size(1.0, 2.0)
    assert P.check_database_size(5.0, 30.0)["mb"] < 200  # the default fit-camera range: allowed
    assert P.check_database_size(1.0, None)["mb"] > 700  # one field (a known camera) is never refused


def test_the_estimate_follows_the_measured_narrow_fields():
    """Under 2.5 deg the pattern count grows more slowly than 1/field^2, and one field's build time with its
    size: the databases built here (tetra3rs 0.14) were 2.64 deg 240 MB in 41 s and 1.12 deg 737 MB in 152 s,
    where the earlier model announced 1.4 GB and 35 minutes for the latter; 1-119 deg was 1.7 GB."""
    one = P.estimate_database(1.12)
    assert one["mb"] == pytest.approx(737, rel=0.1) and one["seconds"] < 300
    assert P.estimate_database(2.64)["mb"] == pytest.approx(240, rel=0.1)
    assert P.estimate_database(1.0, 119.0)["mb"] == pytest.approx(1700, rel=0.2)
    assert P.estimate_database(3.0, 10.0)["seconds"] > 120  # ranges: the superlinear model (342 MB took ~3 min)
    assert 2.0 < P._smallest_field(P.MAX_DATABASE_MB) < 2.5
    assert P.estimate_database(P._smallest_field(P.MAX_DATABASE_MB))["mb"] == pytest.approx(P.MAX_DATABASE_MB)


def test_the_refusal_comes_before_any_build(tmp_path):
    pytest.importorskip("tetra3rs")
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match="narrower range"):
        P.load_database(1.0, tmp_path, fov_max_deg=119.0)
    assert time.perf_counter() - t0 < 5 and not any(tmp_path.iterdir())


def test_the_size_estimate_matches_a_built_database_and_is_announced(tmp_path, monkeypatch):
    """Two small builds (about 1.5 s): the model's pattern count and file size within 15 %."""
    pytest.importorskip("tetra3rs")
    monkeypatch.setattr(P, "ANNOUNCE_S", 0.0)
    for lo, hi in ((30.0, None), (20.0, 45.0)):
        said = []
        db = P.load_database(lo, tmp_path, said.append, fov_max_deg=hi)
        est = P.estimate_database(lo, hi)
        assert db.num_patterns == pytest.approx(est["patterns"], rel=0.15)
        path = P.database_path(lo, tmp_path, hi)
        assert os.path.getsize(path) / 1e6 == pytest.approx(est["mb"], rel=0.15)
        assert said[0].startswith(f"tetra3rs: building the database for a {lo:.2f}")
        assert f"{est['mb']:.0f} MB" in said[0]
        assert said[1].startswith("tetra3rs: built database") and len(said) == 2
    assert Path(P.database_path(30.0, tmp_path)).parent == tmp_path


def test_a_field_within_half_a_percent_reuses_the_cached_database(tmp_path):
    """A fitted camera's field (1.1205 deg from --fov 1.12) loads the database cached for the field it started from
    instead of building another one; a field 2 % away builds its own."""
    pytest.importorskip("tetra3rs")
    said = []
    built = P.load_database(30.0, tmp_path, said.append)
    n_files = len(list(tmp_path.iterdir()))
    P._DB_MEMO.clear()
    again = P.load_database(30.12, tmp_path, said.append)  # 0.4 % wider
    assert len(list(tmp_path.iterdir())) == n_files and again.num_patterns == built.num_patterns
    assert said[-1].startswith("tetra3rs: the 30.120 deg field uses the database cached for 30.000 deg")
    assert P._nearby_database(30.6, tmp_path) is None  # 2 % away: not reused
