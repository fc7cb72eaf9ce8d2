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
    cells = ["whole-sky:6", "tetra3rs>whole-sky:8", "whole-sky:6:dropout=0.5"]
    assert _script().main(["--data", str(small_dataset), "--frames", "4", "--repeats", "2", "--cells", *cells,
                           "--out", str(out)]) == 0  # fmt: skip
    text = out.read_text()
    assert text.strip() in capsys.readouterr().out
    rows = [r.split("|")[1:-1] for r in text.splitlines() if r.startswith("| whole-sky") or r.startswith("| tetra3rs")]
    got = [(r[0].strip(), int(r[1]), r[2].strip()) for r in rows]
    assert got == [("whole-sky", 6, "clean"), ("tetra3rs>whole-sky", 8, "clean"), ("whole-sky", 6, "dropout=0.5")]
    for r in rows:
        shares = [float(x) for x in r[3].replace("%", "").split("/")]
        assert sum(shares) == pytest.approx(100.0, abs=0.2)
        each = [float(x) for x in r[5].split("/")]
        assert len(each) == 2 and float(r[4].strip(" *")) == pytest.approx(min(each), abs=0.006)
    with pytest.raises(SystemExit):
        _script().main(["--data", str(small_dataset), "--cells", "learned+fine>whole-sky:4"])
    for bad in ("whole-sky", "whole-sky:4:dropout", "whole-sky:4:dropout=0.2:x"):
        with pytest.raises(SystemExit):
            _script().main(["--data", str(small_dataset), "--cells", bad])


def test_chain_latency_adds_each_corruption_at_the_corrupted_n(small_dataset, tmp_path):
    """--corrupted-n 5: every detection-level corruption of the benchmark's sweep at N = 5 for the solver named
    there, one row each, labelled as the benchmark labels them."""
    from fusion.solve.benchmark import DETECTION_CORRUPTIONS, grid

    out = tmp_path / "latency.md"
    assert _script().main(["--data", str(small_dataset), "--frames", "4", "--repeats", "1", "--cells", "whole-sky:5",
                           "--corrupted-n", "5", "--out", str(out)]) == 0  # fmt: skip
    rows = [r.split("|")[1:-1] for r in out.read_text().splitlines() if r.startswith("| whole-sky")]
    sweep = grid((), (5,), DETECTION_CORRUPTIONS)
    assert len(rows) == 1 + len(sweep)
    assert {r[2].strip() for r in rows} == {"clean"} | {f"{g['corruption']}={g['severity']:g}" for g in sweep}


def test_chain_latency_prior_first_measures_the_chain_in_both_orders(tmp_path):
    """--prior-first: the learned chain as shipped (the whole sky first at four detections) and as it was (the
    prior's regions first), one row each per cell, side by side; the module's order is restored afterwards."""
    import fusion.solve.fine as fine
    from fusion.config import load_config
    from fusion.testing import small_dataset
    from fusion.train.run import train

    data = small_dataset("smoke")
    run_dir = tmp_path / "run"
    train(load_config("configs/smoke.yaml", [f"data.path={data}", "train.epochs=1"]), run_dir, log=lambda *a, **k: None)
    out = tmp_path / "latency.md"
    chain = "learned+fine>whole-sky"
    ck = str(run_dir / "best.pt")
    assert _script().main(["--data", str(data), "--frames", "4", "--repeats", "1", "--cells", f"{chain}:4",
                           "--checkpoint", ck, "--prior-first", "--out", str(out)]) == 0  # fmt: skip
    rows = [r.split("|")[1:-1] for r in out.read_text().splitlines() if r.startswith("| learned")]
    assert [r[0].strip() for r in rows] == [chain, f"{chain} (prior first)"]
    assert fine.SKY_FIRST_FROM == 4
