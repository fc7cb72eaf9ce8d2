"""`fusion experiment`: sections run end to end on the smoke preset, and re-runs skip finished work."""

from fusion.measure.experiment import load_preset, plan, run_experiment


def test_plan_shares_identical_runs():
    p = load_preset("cpu")
    runs = plan(p)
    assert len(runs["table1"]) == len(p.table1) * len(p.seeds) and len(runs["ablation"]) == 7 * len(p.seeds)
    assert len(runs["recipe"]) == len(p.recipe) * len(p.seeds) >= 2 * len(p.seeds)
    keys = {r.key for v in runs.values() for r in v}
    assert len(keys) < sum(len(v) for v in runs.values())      # the full model is trained once per seed
    k15 = {r.key for r in runs["k_sweep"] if r.name == "K=15"}
    assert k15 == {r.key for r in runs["labels"] if "fine regions" in r.name}   # the preset's own K is not retrained
    assert all(r.overrides == p.sweep_base for r in runs["k_sweep"] if r.name == "K=15")
    # the CPU preset sweeps a shorter geometry run than table 1's (sweep_overrides), and table 1 shares its
    # three-branch and few-star geometry runs with the ablation
    assert p.sweep_overrides == [] and p.sweep_base != tuple(p.table1[p.sweep_model])
    t1 = {r.name: r.key for r in runs["table1"] if r.seed == p.seeds[0]}
    ab = {r.name: r.key for r in runs["ablation"] if r.seed == p.seeds[0]}
    assert t1["star_fusion"] == ab["image+heatmap+coords"] and t1["image_only"] == ab["image"]
    assert t1["geometry_only, few-star recipe"] == ab["coords"]


def test_smoke_experiment_writes_report_and_resumes(tmp_path):
    kw = dict(sections=("table1", "coords", "latency"), workers=1, data_dir=tmp_path / "data",
              runs_dir=tmp_path / "runs", log=lambda *a, **k: None)
    report = run_experiment("smoke", tmp_path / "out", jobs=2, **kw)      # two trainings at a time
    text = report.read_text()
    for heading in ("## 1. Table 1", "## 5. Coordinate encoders", "## 8. Latency", "## Provenance", "paper top-1/3/5",
                    "training (min)"):
        assert heading in text
    best = sorted((tmp_path / "runs").glob("*/best.pt"))
    stamps = [p.stat().st_mtime_ns for p in best]
    run_experiment("smoke", tmp_path / "out", **kw)
    assert [p.stat().st_mtime_ns for p in best] == stamps          # nothing retrained


def test_cached_latency_is_retimed_for_another_cpu_or_a_retrained_checkpoint(tmp_path):
    """A timing JSON is reused only for this CPU and this very checkpoint file (same path, same mtime): a run
    folder of an older plan with the same key holds another model, and another machine other numbers."""
    import os
    from skygen.runtime import hardware
    from fusion.measure.experiment import _stale_timing
    ckpt = tmp_path / "best.pt"
    ckpt.write_bytes(b"x")
    cpu = hardware()["cpu_model"]
    rec = {"hardware": {"cpu_model": cpu}, "model": {"checkpoint": str(ckpt), "checkpoint_mtime": ckpt.stat().st_mtime}}
    assert not _stale_timing(rec, ckpt)
    assert _stale_timing({**rec, "hardware": {"cpu_model": "another CPU"}}, ckpt)
    assert _stale_timing({**rec, "model": {"checkpoint": str(ckpt)}}, ckpt)          # written before mtimes were kept
    os.utime(ckpt, (1e9, 1e9))                                                     # retrained since
    assert _stale_timing(rec, ckpt)
    assert not _stale_timing({"hardware": {"cpu_model": cpu}}, None)              # the paper-size model: CPU only
