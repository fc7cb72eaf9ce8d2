"""`fusion experiment`: sections run end to end on the smoke preset, and re-runs skip finished work."""

from fusion.measure.experiment import load_preset, plan, run_experiment


def test_plan_shares_identical_runs():
    p = load_preset("cpu")
    runs = plan(p)
    assert len(runs["table1"]) == len(p.table1) * len(p.seeds) and len(runs["ablation"]) == 7 * len(p.seeds)
    assert len(runs["recipe"]) == len(p.recipe) * len(p.seeds) >= 2 * len(p.seeds)
    keys = {r.key for v in runs.values() for r in v}
    assert len(keys) < sum(len(v) for v in runs.values())  # the full model is trained once per seed
    k15 = {r.key for r in runs["k_sweep"] if r.name == "K=15"}
    assert k15 == {r.key for r in runs["labels"] if "fine regions" in r.name}  # the preset's own K is not retrained
    assert all(r.overrides == p.sweep_base for r in runs["k_sweep"] if r.name == "K=15")
    # the CPU preset sweeps a shorter geometry run than table 1's (sweep_overrides), and table 1 shares its
    # three-branch and few-star geometry runs with the ablation
    assert p.sweep_overrides == [] and p.sweep_base != tuple(p.table1[p.sweep_model])
    t1 = {r.name: r.key for r in runs["table1"] if r.seed == p.seeds[0]}
    ab = {r.name: r.key for r in runs["ablation"] if r.seed == p.seeds[0]}
    assert t1["star_fusion"] == ab["image+heatmap+coords"] and t1["image_only"] == ab["image"]
    assert t1["geometry_only, few-star recipe"] == ab["coords"]


def test_smoke_experiment_writes_report_and_resumes(tmp_path):
    kw = dict(
        sections=("table1", "few_star", "coords", "latency"),
        workers=1,
        data_dir=tmp_path / "data",
        runs_dir=tmp_path / "runs",
        log=lambda *a, **k: None,
    )
    report = run_experiment("smoke", tmp_path / "out", jobs=2, **kw)  # two trainings at a time
    text = report.read_text()
    for heading in (
        "## 1. Table 1",
        "## 1b. Few-star frames",
        "| N = 2 |",
        "## 5. Coordinate encoders",
        "## 8. Latency",
        "## Provenance",
        "paper top-1/3/5",
        "training (min)",
    ):
        assert heading in text
    # the provenance line repeats the command that reproduces this report, every non-default option included
    assert (
        f"- command: `fusion experiment --preset smoke --sections table1,few_star,coords,latency "
        f"--data-dir {tmp_path / 'data'} --runs-dir {tmp_path / 'runs'} --jobs 2 --out {tmp_path / 'out'}`"
    ) in text
    # the two-stage row: warm-started from the geometry_only run of its seed, both stages' time in its row
    import json

    two = sorted((tmp_path / "runs").glob("star_fusion_two_stages-*/summary.json"))
    assert len(two) == 2
    for f in two:
        init = json.loads(f.read_text())["init"]
        assert init.startswith("warm start from ") and "/geometry_only-" in init and init.endswith("best.pt")
    row = next(line for line in text.splitlines() if line.startswith("| star_fusion, two stages |"))
    assert " + " in row.split("|")[7]  # training (min): "total (first + second)"
    best = sorted((tmp_path / "runs").glob("*/best.pt"))
    stamps = [p.stat().st_mtime_ns for p in best]
    run_experiment("smoke", tmp_path / "out", **kw)
    assert [p.stat().st_mtime_ns for p in best] == stamps  # nothing retrained
    # results carried to another machine without checkpoints: a second stage still to train gets its
    # first stage trained again (said in the log); finished runs are only read
    from fusion.measure.experiment import first_stage, run_folder, stage_row

    p = load_preset("smoke")
    two = next(r for r in plan(p)["table1"] if stage_row(r.overrides) and r.seed == 0)
    first = run_folder(tmp_path / "runs", first_stage(p, two))
    (first / "best.pt").unlink()
    (run_folder(tmp_path / "runs", two) / "summary.json").unlink()
    said = []
    run_experiment("smoke", tmp_path / "out", **{**kw, "sections": ("table1",), "log": said.append})
    assert any("checkpoint is gone" in line for line in said)
    assert (first / "best.pt").exists() and (run_folder(tmp_path / "runs", two) / "summary.json").exists()


def test_cached_latency_is_retimed_for_another_cpu_or_a_retrained_checkpoint(tmp_path):
    """A timing JSON is reused only for this CPU and this very checkpoint file (same path, same mtime): a run
    folder of an older plan with the same key holds another model, and another machine other numbers."""
    import os

    from fusion.measure.experiment import _stale_timing
    from skygen.runtime import hardware

    ckpt = tmp_path / "best.pt"
    ckpt.write_bytes(b"x")
    cpu = hardware()["cpu_model"]
    rec = {"hardware": {"cpu_model": cpu}, "model": {"checkpoint": str(ckpt), "checkpoint_mtime": ckpt.stat().st_mtime}}
    assert not _stale_timing(rec, ckpt)
    assert _stale_timing({**rec, "hardware": {"cpu_model": "another CPU"}}, ckpt)
    assert _stale_timing({**rec, "model": {"checkpoint": str(ckpt)}}, ckpt)  # written before mtimes were kept
    os.utime(ckpt, (1e9, 1e9))  # retrained since
    assert _stale_timing(rec, ckpt)
    assert not _stale_timing({"hardware": {"cpu_model": cpu}}, None)  # the paper-size model: CPU only


def test_two_stage_rows_must_name_a_one_stage_table1_row(tmp_path):
    import pytest
    import yaml

    from fusion.errors import ConfigError
    from fusion.measure.experiment import PRESET_DIR, first_stage, stage_row

    raw = yaml.safe_load((PRESET_DIR / "smoke.yaml").read_text())
    raw["train_config"] = str(PRESET_DIR.parents[1] / raw["train_config"])
    p = load_preset(PRESET_DIR / "smoke.yaml")
    two = next(r for r in plan(p)["table1"] if stage_row(r.overrides))
    assert first_stage(p, two).name == "geometry_only" and first_stage(p, two).seed == two.seed
    for bad in ("no_such_row", "star_fusion, two stages"):  # unknown, or itself two-stage
        raw["sections"]["table1"]["star_fusion, two stages"] = [f"model.init_from=row:{bad}"]
        f = tmp_path / "bad.yaml"
        f.write_text(yaml.safe_dump(raw))
        with pytest.raises(ConfigError, match="one-stage row of sections.table1"):
            load_preset(f)


def test_cpu30_rows_train_from_their_own_presets_and_sections_are_the_presets_own(tmp_path):
    import pytest

    from fusion.errors import ConfigError
    from fusion.measure.experiment import first_stage, load_run_config, stage_row

    p = load_preset("cpu30")
    assert p.sections == ("table1", "few_star") and p.few_star == [3, 4, 5, 6, 10]
    runs = plan(p)
    assert len(runs["table1"]) == 7 * 3 and runs["few_star"] == runs["table1"] and not runs["ablation"]
    by_name = {r.name: r for r in runs["table1"] if r.seed == 0}
    assert load_run_config(p, by_name["image_only"].overrides).model.image_backbone == "peak_set"
    assert load_run_config(p, by_name["geometry_only"].overrides).train.epochs == 53
    tied = load_run_config(p, by_name["star_fusion, tied views"].overrides)
    assert (tied.model.image_backbone, tied.stream.kind) == ("peak_rows", "detections")
    flux = load_run_config(p, by_name["star_fusion, tied views, pixel flux"].overrides)
    assert flux.model.peaks.pixel_flux and not tied.model.peaks.pixel_flux and flux.model.flux_dropout == 0
    two = by_name["star_fusion, two stages"]
    assert first_stage(p, two).overrides == by_name["geometry_only, 42 epochs (the first stage)"].overrides
    assert (
        stage_row(two.overrides)
        and load_run_config(p, [o for o in two.overrides if "row:" not in o]).model.detections_dropout > 0
    )
    with pytest.raises(ConfigError, match="defines no section ablation"):
        run_experiment("cpu30", tmp_path / "out", sections=("ablation",), data_dir=tmp_path / "d", log=lambda *a: None)
