"""fusion benchmark: the grid, the corruptions on detections, the outputs, the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fusion.solve.benchmark import corrupt, grid

pytest.importorskip("tetra3rs")


def _table(n=10):
    rng = np.random.default_rng(0)
    return {
        "x_px": rng.uniform(0, 255, n),
        "y_px": rng.uniform(0, 255, n),
        "flux_adu": np.sort(rng.uniform(100, 1e4, n))[::-1].astype(np.float32),
        "peak_adu": np.ones(n, np.float32),
        "area_px": np.full(n, 5, np.int32),
    }


def test_corruptions_are_deterministic_and_do_what_they_say():
    t = _table()
    clean = corrupt(t, None, 0, 1, 7, 256, 256)
    np.testing.assert_array_equal(clean.x_px, t["x_px"])
    a = corrupt(t, "false_stars", 4, 1, 7, 256, 256)
    b = corrupt(t, "false_stars", 4, 1, 7, 256, 256)
    np.testing.assert_array_equal(a.x_px, b.x_px)
    assert len(a) >= len(t["x_px"]) and np.all(np.diff(a.flux_adu) <= 0)  # brightest first
    d = corrupt(t, "dropout", 0.5, 1, 7, 256, 256)
    assert len(d) < 10
    c = corrupt(t, "centroid_noise", 1.0, 1, 7, 256, 256)
    assert 0 < np.abs(np.sort(c.x_px) - np.sort(t["x_px"])).max() < 10
    assert corrupt(t, "false_stars", 4, 1, 8, 256, 256).x_px.tolist() != a.x_px.tolist()  # per frame


def test_grid_cells():
    cells = grid((3, 5), (6,), ("dropout",), {"dropout": [0.1, 0.3]})
    assert [(c["corruption"], c["severity"], c["n"]) for c in cells] == [
        (None, 0.0, 3),
        (None, 0.0, 5),
        ("dropout", 0.1, 6),
        ("dropout", 0.3, 6),
    ]
    assert len(grid((4,), (6, 10), ("centroid_noise",))) == 1 + 2 * 4  # registry sweep: 4 nonzero levels


def test_benchmark_cli_writes_tables_and_plots(small_dataset, tmp_path, monkeypatch):
    from fusion.cli import main

    monkeypatch.setenv("FUSION_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "bench"
    assert (
        main(
            [
                "benchmark",
                "--data",
                str(small_dataset),
                "--out",
                str(out),
                "--split",
                "train",
                "--frames",
                "6",
                "--n",
                "4",
                "12",
                "--corruption-n",
                "8",
                "--corruptions",
                "false_stars",
                "--solvers",
                "tetra3rs",
                "oracle-prior",
            ]
        )
        == 0
    )
    r = json.loads((out / "benchmark.json").read_text())
    assert [c["n"] for c in r["cells"]][:2] == [4, 12] and len(r["cells"]) == 2 + 4
    for c in r["cells"]:
        for name in ("tetra3rs", "oracle-prior"):
            s = c["solvers"][name]
            assert s["correct"] + s["wrong"] + s["refused"] == pytest.approx(1.0)
            assert s["wrong"] == 0
            # latency tails beside the median, every call timed (refusals too)
            assert s["ms_per_frame_median"] <= s["ms_per_frame_p95"] <= s["ms_per_frame_p99"] <= s["ms_per_frame_max"]
            assert sum(s["refusals_by_status"].values()) == round(s["refused"] * s["frames"])
            assert s["false_match_probability_sum"] >= 0
    assert r["cells"][1]["solvers"]["tetra3rs"]["correct"] > 0.5  # 12 clean stars: solved
    # the fine stage counts its work per solve; tetra3rs does not
    fine = r["cells"][1]["solvers"]["oracle-prior"]["hypotheses"]["answered"]
    assert fine is not None and 0 < fine["median"] <= fine["p99"] <= fine["max"]
    assert r["cells"][1]["solvers"]["tetra3rs"]["hypotheses"] == {"answered": None, "refused": None}
    assert r["solvers"] == ["tetra3rs", "oracle-prior"] and r["notes"] == []
    solved = r["cells"][1]["solvers"]["tetra3rs"]
    assert solved["coverage"]["frames"] == round(solved["correct"] * solved["frames"])
    assert 0 <= solved["coverage"]["cross_1sigma"] <= solved["coverage"]["cross_2sigma"] <= 1
    md = (out / "benchmark.md").read_text()
    assert "correct" in md and "| clean | 12 |" in md
    assert "p50 / p95 / p99" in md and "Refusals by status" in md and "| clean | 12 | tetra3rs |" in md
    assert (out / "success_vs_n.png").stat().st_size > 1000
    assert (out / "success_vs_false_stars.png").exists()


def test_benchmark_rejects_unknown_names(small_dataset, tmp_path):
    from fusion.cli import main

    assert main(["benchmark", "--data", str(small_dataset), "--out", str(tmp_path), "--solvers", "astrometry"]) == 2
    assert main(["benchmark", "--data", str(small_dataset), "--out", str(tmp_path), "--corruptions", "hotpixels"]) == 2


def test_benchmark_scores_a_checkpoint_as_learned_and_learned_plus_fine(tmp_path, monkeypatch):
    """The learned columns: region top-1/top-3 of the checkpoint and coarse-to-fine with it as the prior."""
    from pathlib import Path

    from fusion.cli import main
    from fusion.config import load_config
    from fusion.testing import small_dataset
    from fusion.train.run import train

    monkeypatch.setenv("FUSION_CACHE", str(tmp_path / "cache"))
    root = Path(__file__).resolve().parents[1]
    data = small_dataset("smoke")
    train(
        load_config(root / "configs" / "smoke.yaml", [f"data.path={data}", "train.epochs=2"]),
        tmp_path / "run",
        log=lambda *a, **k: None,
    )
    out = tmp_path / "bench"
    assert (
        main(
            [
                "benchmark",
                "--data",
                str(data),
                "--out",
                str(out),
                "--checkpoint",
                str(tmp_path / "run/best.pt"),
                "--frames",
                "5",
                "--n",
                "8",
                "--corruptions",
                "--top-k",
                "2",
                "--solvers",
                "tetra3rs",
                "learned",
                "learned+fine",
                "tetra3rs>learned+fine",
            ]
        )
        == 0
    )
    r = json.loads((out / "benchmark.json").read_text())
    cell = r["cells"][0]["solvers"]
    assert 0 <= cell["learned"]["top1"] <= cell["learned"]["top3"] <= 1
    # a checkpoint without fine regions: the search falls back to its K regions, top 2 as asked
    assert r["search"] == {
        "level": "coarse", "regions": 4, "top_k": 2, "chain_top_k": 2, "focal_tol": 0.02, "max_hypotheses": None
    }  # fmt: skip
    lf = cell["learned+fine"]
    assert lf["wrong"] == 0 and lf["correct"] + lf["refused"] == pytest.approx(1.0)
    # lost-in-space first, the learned path where it refuses: composed from the two columns' answers
    both, t3 = cell["tetra3rs>learned+fine"], cell["tetra3rs"]
    assert both["refused"] <= min(t3["refused"], lf["refused"]) + 1e-9  # refused only if both refuse
    assert both["correct"] >= t3["correct"] and (t3["wrong"] > 0 or both["correct"] >= lf["correct"])
    assert both["ms_per_frame"] >= t3["ms_per_frame"]
    assert r["region_count"] == 4 and "learned top-1" in (out / "benchmark.md").read_text()


@pytest.mark.parametrize(
    "args,words",
    [
        (["--frames", "0"], "--frames 0"),
        (["--n", "0"], "--n 0"),
        (["--n", "4", "-2"], "--n -2"),
        (["--corruption-n", "0"], "--corruption-n 0"),
        (["--correct-deg", "-1"], "--correct-deg -1"),
        (["--correct-roll-deg", "0"], "--correct-roll-deg 0"),
        (["--correct-deg", "200"], "(0, 180]"),
        (["--corruptions", "none", "dropout"], "cannot be combined"),
    ],
)
def test_nonsense_grids_are_refused_before_any_work(small_dataset, tmp_path, capsys, args, words):
    from fusion.cli import main
    from fusion.solve.benchmark import run_benchmark
    from skygen.errors import ConfigError

    out = tmp_path / "bench"
    assert main(["benchmark", "--data", str(small_dataset), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0]
    assert not out.exists()
    if args[0] == "--frames":  # Python callers get the same check
        with pytest.raises(ConfigError, match="--frames 0"):
            run_benchmark(small_dataset, out, frames=0)


def test_corruptions_none_scores_the_clean_cells_only(small_dataset, tmp_path, monkeypatch):
    from fusion.cli import main

    monkeypatch.setenv("FUSION_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "bench"
    assert (
        main(
            [
                "benchmark",
                "--data",
                str(small_dataset),
                "--out",
                str(out),
                "--split",
                "train",
                "--frames",
                "2",
                "--grid",
                "small",
                "--corruptions",
                "none",
                "--solvers",
                "tetra3rs",
            ]
        )
        == 0
    )
    r = json.loads((out / "benchmark.json").read_text())
    assert [(c["corruption"], c["n"]) for c in r["cells"]] == [(None, 4), (None, 6), (None, 10)]
    assert r["dataset"]["frames"] == 2


def test_a_second_benchmark_into_a_busy_folder_is_refused(small_dataset, tmp_path, capsys):
    from fusion.cli import main
    from skygen.lock import FolderLock

    out = tmp_path / "bench"
    out.mkdir()
    with FolderLock(out, what="fusion benchmark"):
        assert main(["benchmark", "--data", str(small_dataset), "--out", str(out), "--frames", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "in use by fusion benchmark (PID" in err[0]
    assert list(out.iterdir()) == []
