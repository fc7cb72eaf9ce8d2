"""benchmarks/pass_cost.py: where the fine stage's work goes, by pass and place (the evidence of its work budget)."""

from __future__ import annotations

import pytest

from fusion.testing import benchmark_script

pytest.importorskip("tetra3rs")


def _script():
    return benchmark_script("pass_cost")


def test_pass_cost_counts_every_hypothesis_by_pass_and_restores_the_loop(small_dataset, tmp_path, capsys):
    """Clean cells of a small dataset through the whole-sky search: the table rows are the strict and focal
    passes over the sky, every count positive; the answers are at most the solves; the shares are fractions; the
    timed wrapper is removed afterwards (the fine stage calls the compiled loop itself again)."""
    import fusion.solve.fine as fine

    original = fine.anchor_hypotheses
    out = tmp_path / "cost.md"
    assert _script().main(["--data", str(small_dataset), "--frames", "4", "--n", "4", "6", "--corruption-n",
                           "--out", str(out)]) == 0  # fmt: skip
    assert fine.anchor_hypotheses is original
    text = out.read_text()
    assert text == capsys.readouterr().out
    rows = [r.split("|")[1:-1] for r in text.splitlines() if r.startswith("| strict") or r.startswith("| focal")]
    assert rows and {r[1].strip() for r in rows} == {"sky"} and {r[0].strip() for r in rows} <= {"strict", "focal"}
    assert all(int(r[3].replace(",", "")) > 0 for r in rows if r[0].strip() == "strict")
    answers = text.split("| correct answers")[1].splitlines()[2].split("|")[1:-1]
    n_answers, from_focal = (int(x.replace(",", "")) for x in answers[:2])
    assert 0 <= from_focal <= n_answers <= 4 * 2
    shares = text.split("| refusals")[1].splitlines()[2].split("|")[1:-1]
    assert all(0.0 <= float(x) <= 1.0 for x in shares[1:])
