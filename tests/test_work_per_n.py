"""benchmarks/work_per_n.py: the budget's per-detection hypothesis cost against the budget before, side by side."""

from __future__ import annotations

import pytest

from fusion.testing import benchmark_script

pytest.importorskip("tetra3rs")


def _script():
    return benchmark_script("work_per_n")


def test_both_variants_per_n_and_the_shipped_cost_restored(tmp_path, capsys):
    """Four noise sets of 11-12 detections: one row per N and variant, every set refused by both (no truth to
    find), the variant that counts a hypothesis (N - 2) / 4 units trying fewer hypotheses than the one that counts
    it 1; fine.COST_REFERENCE_N as shipped afterwards; bad N bounds refused."""
    import fusion.solve.fine as fine

    out = tmp_path / "w.md"
    assert _script().main(["--cases", "4", "--repeats", "1", "--n-min", "11", "--n-max", "12", "--families", "noise",
                           "--out", str(out)]) == 0  # fmt: skip
    assert fine.COST_REFERENCE_N == 6
    text = out.read_text()
    assert text.strip() in capsys.readouterr().out
    rows = [r.split("|")[1:-1] for r in text.splitlines() if r.startswith("| 1")]
    assert rows and len(rows) % 2 == 0
    for shipped, before in zip(rows[::2], rows[1::2]):
        assert "shipped" in shipped[1] and "before" in before[1] and shipped[0] == before[0]
        assert shipped[3].strip() == before[3].strip() == "0 / 0"  # nothing answered
        h_now, h_before = (float(r[5].replace(",", "")) for r in (shipped, before))
        assert h_now < h_before
    with pytest.raises(SystemExit):
        _script().main(["--n-min", "8", "--n-max", "5"])
