"""benchmarks/chain_latency.py: repeated, interleaved medians of the solver chains (issue 37's median targets)."""

from __future__ import annotations

import pytest

from fusion.testing import benchmark_script

pytest.importorskip("tetra3rs")


def _script():
    return benchmark_script("chain_latency")


def test_chain_latency_table_has_every_cell_and_repeat(small_dataset, tmp_path, capsys):
    """Two cells without a model, two repeats: one row per cell, a median per repeat whose least is the bold one,
    shares that sum to 100 %, the table both printed and written; a learned cell without a checkpoint is refused."""
    out = tmp_path / "latency.md"
    cells = ["whole-sky:6", "tetra3rs>whole-sky:8"]
    assert _script().main(["--data", str(small_dataset), "--frames", "4", "--repeats", "2", "--cells", *cells,
                           "--out", str(out)]) == 0  # fmt: skip
    text = out.read_text()
    assert text.strip() in capsys.readouterr().out
    rows = [r.split("|")[1:-1] for r in text.splitlines() if r.startswith("| whole-sky") or r.startswith("| tetra3rs")]
    assert [(r[0].strip(), int(r[1])) for r in rows] == [("whole-sky", 6), ("tetra3rs>whole-sky", 8)]
    for r in rows:
        shares = [float(x) for x in r[2].replace("%", "").split("/")]
        assert sum(shares) == pytest.approx(100.0, abs=0.2)
        each = [float(x) for x in r[4].split("/")]
        assert len(each) == 2 and float(r[3].strip(" *")) == pytest.approx(min(each), abs=0.006)
    with pytest.raises(SystemExit):
        _script().main(["--data", str(small_dataset), "--cells", "learned+fine>whole-sky:4"])
    with pytest.raises(SystemExit):
        _script().main(["--data", str(small_dataset), "--cells", "whole-sky"])
