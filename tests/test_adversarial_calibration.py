"""benchmarks/adversarial_calibration.py on a tiny sample: pure noise is never correct, the reliability table adds
up, and an interrupted run is never mistaken for a complete one."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("tetra3rs")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cal():
    spec = importlib.util.spec_from_file_location(
        "adversarial_calibration", ROOT / "benchmarks" / "adversarial_calibration.py"
    )
    mod = importlib.util.module_from_spec(spec)
    sys.modules["adversarial_calibration"] = mod
    spec.loader.exec_module(mod)
    return mod


def settings(cal, out, **kw) -> dict:
    st = {"seed": 3, "attempts": 12, "families": ["noise", "clean", "false_stars"], "chunk": 6,
          "solvers": ["tetra3rs", "whole-sky", "tetra3rs>whole-sky"], "n_min": 3, "n_max": 5, "correct_deg": 0.1,
          "correct_roll_deg": 1.0, "focal_tol": 0.02, "config": None, "checkpoint": None, "jobs": 1,
          "out": str(out), "keep_chunks": False, "version": cal.VERSION}  # fmt: skip
    return {**st, **kw}


def test_noise_is_never_correct_and_the_tables_add_up(cal, tmp_path):
    r = cal.run(settings(cal, tmp_path), log=lambda *a: None)
    assert cal.load_report(tmp_path)["complete"] and r["cases"] == 12 and r["solve_attempts"] == 36
    assert cal.rebuild(tmp_path, log=lambda *a: None)["table"] == r["table"]  # the same report from the CSV
    rows = cal.as_dicts(_rows(cal, tmp_path))
    assert len(rows) == 36 and {(x["case"], x["solver"]) for x in rows} == {
        (i, s) for i in range(12) for s in ("tetra3rs", "whole-sky", "tetra3rs>whole-sky")
    }
    noise = [x for x in rows if x["family"] == "noise"]
    assert len(noise) == 12 and not any(x["correct"] for x in noise)  # no truth: never correct
    assert all(x["correct"] is False for x in noise if x["returned"])  # ... and every answer wrong
    # a chain composed from its parts: the first's answer where it gave one, else the second's
    by = {(x["case"], x["solver"]): x for x in rows}
    for i in range(12):
        first, chain = by[(i, "tetra3rs")], by[(i, "tetra3rs>whole-sky")]
        src = first if first["returned"] else by[(i, "whole-sky")]
        assert (chain["status"], chain["p"], chain["correct"]) == (src["status"], src["p"], src["correct"])
    assert any(x["returned"] and x["correct"] for x in rows)  # clean cases are solved: the scoring sees truth
    for s in r["overall"]:
        mine = [x for x in rows if x["solver"] == s]
        t = r["overall"][s]
        rel = r["reliability"][s]
        returned = [x for x in mine if x["returned"]]
        assert t["attempts"] == len(mine) and t["returned"] == len(returned)
        assert t["correct"] + t["wrong"] == t["returned"]
        assert sum(b["count"] for b in rel) == t["returned"] - t["no_probability"]
        assert sum(b["wrong"] for b in rel) == t["wrong"]
        assert math.isclose(sum(b["p_sum"] for b in rel), t["p_sum"], rel_tol=1e-9, abs_tol=1e-300)
        fam = [u for u in r["table"] if u["solver"] == s and u["family"] != "all"]
        for k in ("attempts", "returned", "wrong", "wrong_below_1e-6"):
            assert sum(u[k] for u in fam) == t[k]
        assert t["wrong_below_1e-6"] == sum(1 for x in returned if not x["correct"] and x["p"] < cal.LOW_P)
    # the per-family bins count every solver's answers of that family, each once
    for fam, bins in r["reliability_by_family"].items():
        answers = [x for x in rows if x["family"] == fam and x["returned"] and x["p"] is not None]
        assert sum(b["count"] for b in bins) == len(answers)
        assert sum(b["wrong"] for b in bins) == sum(1 for x in answers if not x["correct"])
    assert "Reliability by family" in (tmp_path / "calibration.md").read_text()
    # latency by detection count: every attempt of a solver in exactly one N, its median at most its p99
    for s, by_n in r["latency_by_n"].items():
        assert sum(v["attempts"] for v in by_n.values()) == r["overall"][s]["attempts"]
        assert all(v["median_ms"] <= v["p99_ms"] for v in by_n.values())
        assert {int(n) for n in by_n} == {x["n"] for x in rows if x["solver"] == s}
    assert "Latency by detection count N" in (tmp_path / "calibration.md").read_text()
    assert (tmp_path / "reliability.png").stat().st_size > 1000 and not (tmp_path / "chunks").exists()


def _rows(cal, out):
    import csv
    import gzip

    with gzip.open(out / "attempts.csv.gz", "rt") as f:
        rd = csv.reader(f)
        cols = tuple(next(rd))
        return [[cal._cell_value(k, v) for k, v in zip(cols, line)] for line in rd]


def test_reliability_bins_and_verdicts(cal):
    rows = [{"returned": True, "correct": c, "p": p} for c, p in
            [(True, 1e-12), (False, 1e-12), (True, 5e-8), (True, 2e-4), (False, 0.5), (True, 0.005)]]  # fmt: skip
    rel = cal.reliability(rows + [{"returned": False, "correct": None, "p": None}])
    assert [b["count"] for b in rel] == [2, 1, 1, 1, 0, 1] and [b["wrong"] for b in rel] == [1, 0, 0, 0, 0, 1]
    assert rel[1]["rate_upper95"] == 1.0 and rel[0]["rate_upper95"] is None
    assert cal.verdict(10, 10.0) == "within x3"
    assert cal.verdict(1, 1e-9) == "UNDER-estimates risk"  # one wrong answer where p promised 1e-9
    assert cal.verdict(0, 0.01) == "consistent (few expected)"
    assert cal.verdict(0, 50.0) == "over-conservative"


def test_score_without_truth_is_wrong(cal):
    from fusion.solve.base import solution_from_matrix

    sol = solution_from_matrix(np.eye(3), matched=np.zeros((4, 2), np.int64), residual_arcsec=1.0, confidence=1.0,
                               solver="x", false_match_probability=1e-12)  # fmt: skip
    s = cal.score(sol, None, 0.1, 1.0)
    assert s["returned"] and s["correct"] is False and s["p"] == 1e-12
    assert cal.score(sol, (np.eye(3), sol.roll_deg), 0.1, 1.0)["correct"] is True


def test_an_interrupted_run_is_not_mistaken_for_complete_and_resumes(cal, tmp_path):
    st = settings(cal, tmp_path, solvers=["tetra3rs"], families=["noise", "clean"], attempts=9, chunk=3)
    # the report of an earlier run: removed as soon as a new run starts
    (tmp_path / "calibration.json").write_text(json.dumps({"format": cal.FORMAT, "complete": True}))
    with pytest.raises(cal.Incomplete):
        cal.run(st, log=lambda *a: None, stop_after_chunks=1)
    assert not (tmp_path / "calibration.json").exists()
    assert json.loads((tmp_path / "progress.json").read_text())["complete"] is False
    with pytest.raises(cal.Incomplete, match="1 chunks done"):
        cal.load_report(tmp_path)
    lines = []
    r = cal.run(st, log=lines.append)
    assert any("resuming: 1 of 3 chunks" in m for m in lines)
    assert cal.load_report(tmp_path)["cases"] == 9 == r["cases"] and r["solve_attempts"] == 9
    assert not (tmp_path / "progress.json").exists()
    # other settings do not reuse the chunks of this run; a report marked incomplete is refused
    assert cal.settings_digest({**st, "seed": 4}) != cal.settings_digest(st)
    rep = json.loads((tmp_path / "calibration.json").read_text())
    (tmp_path / "calibration.json").write_text(json.dumps({**rep, "complete": False}))
    with pytest.raises(cal.Incomplete):
        cal.load_report(tmp_path)


def test_answer_bar_relaxes_every_fine_stage_of_a_chain(cal):
    """``--answer-bar P``: a chain's fine stage answers up to p = P (its bars 1 - P); tetra3rs is left alone."""
    from types import SimpleNamespace

    fine = SimpleNamespace(min_confidence=0.99, unverified_confidence=1 - 1e-6, tracking_unverified_confidence=0.999)
    tetra = SimpleNamespace(match_threshold=1e-5)
    cal.relax(SimpleNamespace(first=tetra, second=fine), 0.5)
    assert fine.min_confidence == fine.unverified_confidence == fine.tracking_unverified_confidence == 0.5
    assert tetra.match_threshold == 1e-5 and not hasattr(tetra, "min_confidence")
    with pytest.raises(SystemExit, match="answer-bar"):
        cal.main(["--out", "/nonexistent", "--answer-bar", "1.5"])
