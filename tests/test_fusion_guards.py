"""What a newcomer trips on (issue 36): data of other frame settings, damaged checkpoints, blank frames,
learned solvers without a model, outputs that cannot be written, and reports that name their hardware."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from fusion.cli import main
from fusion.errors import CheckpointError, ConfigError
from fusion.model.checkpoint import frame_config_differences, load_checkpoint, verify_weights, weights_sha256
from fusion.testing import KINDS, render_small, small_dataset

ROOT = Path(__file__).resolve().parents[1]


def quiet(*a, **k) -> None:
    """A log or warn callback that drops everything."""


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A one-epoch smoke run (its best.pt carries the training data's render config and a weights sha256)."""
    from fusion.config import load_config
    from fusion.train.run import train

    out = tmp_path_factory.mktemp("guards") / "run"
    train(
        load_config(ROOT / "configs" / "smoke.yaml", [f"data.path={small_dataset('smoke')}", "train.epochs=1"]),
        out,
        log=quiet,
    )
    return out


@pytest.fixture(scope="module")
def short_exposure(tmp_path_factory) -> Path:
    """Frames of the smoke camera at half the exposure (the issue's `--set sensor.exposure_s=0.05`), other seed."""
    smoke = [o for o in KINDS["smoke"] if not o.startswith("n_frames")]
    return render_small(
        tmp_path_factory.mktemp("exp") / "short", smoke + ["n_frames=20", "seed=9", "sensor.exposure_s=0.05"]
    )


# ------------------------------------------------------------------ render settings that change frames
def test_only_settings_that_change_frames_count_as_differences():
    from skygen.config import build_config, config_dict

    base = config_dict(build_config({}))
    same_frames = {
        **base,
        "seed": 5,
        "n_frames": 7,
        "output": {**base["output"], "image_size_px": 128},
        "attitude": {**base["attitude"], "mode": "region"},
        "render": {**base["render"], "batch_size": 3},
        "detection": {**base["detection"], "match_radius_px": 4.0},
    }
    assert frame_config_differences(base, same_frames) == {}
    assert frame_config_differences(base, {"camera": base["camera"]}) == {}  # omitted defaults are no difference
    other = {
        **base,
        "sensor": {**base["sensor"], "exposure_s": 0.05},
        "corruptions": {**base["corruptions"], "hotpixels": 1e-3},
        "optics": {**base["optics"], "psf_sigma_px": 2.0},
        "detection": {**base["detection"], "threshold_sigma": 4},
    }
    assert frame_config_differences(base, other) == {
        "corruptions.hotpixels": {"training": 5e-05, "data": 1e-3},
        "detection.threshold_sigma": {"training": 5.0, "data": 4.0},
        "optics.psf_sigma_px": {"training": 1.2, "data": 2.0},
        "sensor.exposure_s": {"training": 0.1, "data": 0.05},
    }


def test_evaluate_warns_loudly_about_another_exposure_and_records_it(run, short_exposure, tmp_path, capsys):
    warnings, lines = [], []
    r = evaluate_quietly(run, short_exposure, tmp_path / "a", warnings, lines)
    want = {"sensor.exposure_s": {"training": 0.1, "data": 0.05}}
    assert r["config_differences"] == want
    assert json.loads((tmp_path / "a" / "eval-test.json").read_text())["config_differences"] == want
    assert len(warnings) == 2 and all(w.startswith("WARNING:") and "\n" not in w for w in warnings)
    assert "sensor.exposure_s 0.1 -> 0.05" in warnings[0] and "--set sensor.exposure_s=0.1" in warnings[0]
    (score,) = [line for line in lines if "top-1" in line]
    assert "WARNING" in score and "sensor.exposure_s" in score  # beside the score
    assert "**Warning:**" in (tmp_path / "a" / "eval-test.md").read_text()
    # the data the model was trained on: nothing to say
    warnings.clear()
    same = evaluate_quietly(run, small_dataset("smoke"), tmp_path / "b", warnings, [])
    assert same["config_differences"] == {} and warnings == []
    assert "Warning" not in (tmp_path / "b" / "eval-test.md").read_text()
    # through the command line: rc 0 (a robustness study does this on purpose), the warning on stderr
    assert (
        main(["evaluate", "--checkpoint", str(run), "--data", str(short_exposure), "--out", str(tmp_path / "c")]) == 0
    )
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("WARNING:")]
    assert err and all("sensor.exposure_s" in line for line in err)


def evaluate_quietly(run, data, out, warnings, lines) -> dict:
    from fusion.measure.evaluate import evaluate_checkpoint

    return evaluate_checkpoint(run, data, "test", out, log=lines.append, warn=warnings.append)


def test_predict_and_robustness_record_other_frame_settings(run, short_exposure, tmp_path, capsys):
    from fusion.measure.robustness import run_sweep

    out = tmp_path / "p.jsonl"
    assert main(["predict", str(short_exposure), "--checkpoint", str(run), "--max-frames", "2", "--out", str(out)]) == 0
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    assert all(r["config_differences"] == {"sensor.exposure_s": {"training": 0.1, "data": 0.05}} for r in recs)
    err = [line for line in capsys.readouterr().err.splitlines() if "sensor.exposure_s 0.1 -> 0.05" in line]
    assert len(err) == 1 and err[0].startswith("WARNING:")
    assert (
        main(["predict", str(small_dataset("smoke")), "--checkpoint", str(run), "--max-frames", "2", "--out", str(out)])
        == 0
    )
    assert not any("config_differences" in json.loads(line) for line in out.read_text().splitlines())
    warnings = []
    report = run_sweep([run], short_exposure, "dropout", levels="0", progress=False, warn=warnings.append)
    assert report["checkpoints"][0]["config_differences"] == {"sensor.exposure_s": {"training": 0.1, "data": 0.05}}
    assert len(warnings) == 1 and "sensor.exposure_s" in warnings[0]
    assert report["hardware"]["logical_cores"] >= 1


# ------------------------------------------------------------------ checkpoint integrity
def _storage_of(path: Path, key: str) -> tuple[str, int]:
    """(zip member, byte offset in the file) of the data of state-dict tensor ``key`` of a torch.save zip."""
    raw = torch.load(path, weights_only=True)
    tensor = raw["model"][key]
    with zipfile.ZipFile(path) as z:
        names = [n for n in z.namelist() if "/data/" in n]
        for name in names:
            with z.open(name) as f:
                if f.read() == tensor.contiguous().view(torch.uint8).numpy().tobytes():
                    info = z.getinfo(name)
                    with open(path, "rb") as fh:
                        fh.seek(info.header_offset)
                        header = fh.read(30)
                    n_name, n_extra = int.from_bytes(header[26:28], "little"), int.from_bytes(header[28:30], "little")
                    return name, info.header_offset + 30 + n_name + n_extra
    raise AssertionError(f"no storage holds {key}")


def test_a_damaged_config_or_training_state_is_refused_too(run, tmp_path):
    """The stored camera and the optimiser's moments are hashed like the weights: a focal length edited by a
    few percent (every frame refused afterwards, silently) and one optimiser tensor changed (a resume that
    trains on garbage) are both refused on load."""
    from fusion.model.checkpoint import content_sha256

    for name in ("best.pt", "last.pt"):
        raw = torch.load(run / name, weights_only=True)
        assert raw["content_sha256"] == content_sha256(raw)
    raw = torch.load(run / "best.pt", weights_only=True)
    raw["render_config"]["camera"]["focal_length_mm"] *= 0.97
    torch.save(raw, tmp_path / "camera.pt")
    with pytest.raises(CheckpointError, match="configs or training state do not match the sha256"):
        load_checkpoint(tmp_path / "camera.pt")
    raw = torch.load(run / "last.pt", weights_only=True)
    moments = [v for st in raw["optimizer"]["state"].values() for v in st.values() if isinstance(v, torch.Tensor)]
    biggest = max(moments, key=lambda t: t.numel())
    biggest.view(-1)[biggest.numel() // 2] += 1.0
    torch.save(raw, tmp_path / "optimizer.pt")
    with pytest.raises(CheckpointError, match="configs or training state do not match the sha256"):
        load_checkpoint(tmp_path / "optimizer.pt")


def test_a_flipped_byte_in_a_weight_tensor_is_refused(run, tmp_path):
    good = run / "best.pt"
    raw = torch.load(good, weights_only=True)
    assert raw["weights_sha256"] == weights_sha256(raw) and len(raw["weights_sha256"]) == 64
    load_checkpoint(good)  # intact: loads
    key = max(raw["model"], key=lambda k: raw["model"][k].numel())  # the largest weight tensor
    # one byte changed in memory and saved again as it was
    bytes_ = raw["model"][key].view(torch.uint8).reshape(-1)
    bytes_[len(bytes_) // 2] ^= 0x10
    torch.save(raw, tmp_path / "edited.pt")
    with pytest.raises(CheckpointError, match="do not match the sha256") as info:
        load_checkpoint(tmp_path / "edited.pt")
    assert "\n" not in str(info.value)
    # one byte flipped in the file itself, inside the tensor's stored data
    flipped = tmp_path / "flipped.pt"
    data = bytearray(good.read_bytes())
    _, offset = _storage_of(good, key)
    data[offset + 5] ^= 0x01
    flipped.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="do not match the sha256"):  # torch itself reads it without a word
        load_checkpoint(flipped)


def test_checkpoints_without_a_checksum_load_with_one_note(run, tmp_path):
    raw = torch.load(run / "best.pt", weights_only=True)
    del raw["weights_sha256"]
    old = tmp_path / "old.pt"
    torch.save(raw, old)
    notes = []
    a = load_checkpoint(old, note=notes.append)
    b = load_checkpoint(old, note=notes.append)
    assert a.num_classes == b.num_classes == 4 and a.weights_sha256 is None
    assert len(notes) == 1 and "predates checkpoint checksums" in notes[0] and "\n" not in notes[0]
    a.save(tmp_path / "resaved.pt")  # saving again adds the checksum
    assert torch.load(tmp_path / "resaved.pt", weights_only=True)["weights_sha256"] == weights_sha256(raw)
    verify_weights(raw | {"weights_sha256": weights_sha256(raw)}, "x")  # the digest is of the weights alone


# ------------------------------------------------------------------ blank frames, learned solvers, outputs
def test_a_blank_frame_gets_no_region_probabilities(run, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("FUSION_CACHE", str(tmp_path / "cache"))
    blank = tmp_path / "blank.npy"
    np.save(blank, np.full((256, 256), 100.0, np.float32))  # the smoke camera, no star
    out = tmp_path / "p.jsonl"
    assert main(["predict", str(blank), "--checkpoint", str(run), "--solve", "--out", str(out)]) == 0
    (rec,) = [json.loads(line) for line in out.read_text().splitlines()]
    assert rec["status"] == "no_detections" and rec["n_detections"] == 0 and "regions" not in rec
    assert "no detections" in rec["reason"] and rec["solution"]["status"] == "refused"
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("fusion predict:")]
    assert len(err) == 1 and str(blank) in err[0] and "no detections" in err[0]


@pytest.mark.parametrize("solvers", [["learned"], ["tetra3rs", "learned+fine"], ["tetra3rs>learned+fine>whole-sky"]])
def test_learned_solvers_without_a_checkpoint_are_refused_before_any_work(solvers, tmp_path, capsys):
    pytest.importorskip("tetra3rs")
    out = tmp_path / "bench"
    assert main(["benchmark", "--data", str(small_dataset("smoke")), "--out", str(out), "--solvers", *solvers]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--checkpoint" in err[0] and solvers[-1] in err[0]
    assert not out.exists()


def test_evaluate_checks_its_output_folder_before_loading_anything(run, tmp_path, monkeypatch):
    from fusion.measure import evaluate as ev
    from fusion.measure.evaluate import evaluate_checkpoint

    loaded = []
    monkeypatch.setattr(ev, "load_checkpoint", lambda p: loaded.append(p))
    (tmp_path / "a-file").write_text("x")
    with pytest.raises(ConfigError, match="--out .*a-file.*cannot write there"):
        evaluate_checkpoint(run, small_dataset("smoke"), "test", tmp_path / "a-file" / "sub", log=quiet)
    with pytest.raises(ConfigError, match="not a folder"):
        evaluate_checkpoint(run, small_dataset("smoke"), "test", tmp_path / "a-file", log=quiet)
    if Path("/proc/self").is_dir():  # exists, takes no new files (Linux)
        with pytest.raises(ConfigError, match="/proc/x"):
            evaluate_checkpoint(run, small_dataset("smoke"), "test", "/proc/x", log=quiet)
    assert loaded == []


def test_reports_name_their_hardware(run, tmp_path):
    from fusion.measure.evaluate import evaluate_checkpoint

    r = evaluate_checkpoint(run, small_dataset("smoke"), "test", tmp_path, log=quiet)
    assert r["hardware"]["logical_cores"] >= 1 and "torch" in r["hardware"]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["hardware"]["cpu_model"] and summary["hardware"]["device"] == "cpu"


# ------------------------------------------------------------------ fusion timing
def test_timing_measures_one_thread_by_default_and_says_so(tmp_path):
    from fusion.measure import timing as tim

    before = torch.get_num_threads()
    kw = {"config": "configs/smoke.yaml", "image_size": 64, "iters": 3, "warmup": 1, "mode": "forward", "warn": quiet}
    r = tim.run_timing(**kw)
    assert r["settings"]["torch_threads"] == 1 and r["settings"]["threads_chosen_by"].startswith("default (1")
    assert r["hardware"]["torch_threads"] == 1
    two = tim.run_timing(threads=2, **kw)
    assert two["settings"]["torch_threads"] == 2 and two["settings"]["threads_chosen_by"] == "--threads 2"
    assert torch.get_num_threads() == before  # the caller's setting is restored
    with pytest.raises(ConfigError, match="--threads"):
        tim.run_timing(threads=-1, **kw)


def test_a_bimodal_timing_is_flagged(monkeypatch):
    from fusion.measure import timing as tim

    quiet_machine = tim.stats_ms([1.0, 1.1, 0.9, 1.0, 1.2, 1.0, 1.1, 1.0, 0.9, 1.0], 1)
    busy = tim.stats_ms([1.0] * 8 + [200.0, 190.0], 1)  # median 1 ms, p90 ~190 ms
    hw = {"load_average_1m": 3.5, "usable_cores": 2}
    assert tim.spread_warning("forward", quiet_machine, hw) is None
    line = tim.spread_warning("forward", busy, hw)
    assert line.startswith("WARNING: forward latency is bimodal") and "load average 3.5" in line and "\n" not in line
    # in a run: the warning goes to warn and into the report
    monkeypatch.setattr(tim, "time_forward", lambda *a, **k: {**busy, "timer": "fake"})
    # this machine's own load must not add the busy-machine line (CI pinned to one core sees load > 1)
    monkeypatch.setattr(tim, "busy_warning", lambda hw, threads: None)
    warnings = []
    r = tim.run_timing(
        config="configs/smoke.yaml", image_size=64, iters=3, warmup=0, mode="forward", warn=warnings.append
    )
    assert r["warnings"] == warnings and len(warnings) == 1 and "bimodal" in warnings[0]


def test_timing_refuses_a_batch_that_cannot_fit_and_an_unwritable_out(tmp_path, capsys, monkeypatch):
    from fusion.measure import timing as tim

    out = tmp_path / "t.json"
    assert main(["timing", "--config", "configs/smoke.yaml", "--batch", "100000000", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--batch 100000000" in err[0] and "GB available" in err[0] and not out.exists()

    # running out of memory later is one line too
    def oom(*a, **k):
        raise RuntimeError(
            "[enforce fail at alloc_cpu.cpp:117] . DefaultCPUAllocator: can't allocate memory: you "
            "tried to allocate 26843545600 bytes. Error code 12 (Cannot allocate memory)"
        )

    monkeypatch.setattr(tim, "time_forward", oom)
    with pytest.raises(ConfigError, match="--batch 2: out of memory"):
        tim.run_timing(config="configs/smoke.yaml", image_size=64, batch=2, iters=1, warmup=0, mode="forward")
    (tmp_path / "a-file").write_text("x")
    called = []
    monkeypatch.setattr(tim, "run_timing", lambda **kw: called.append(kw))
    with pytest.raises(ConfigError, match="cannot write there"):
        tim.timing(tmp_path / "a-file" / "t.json", config="configs/smoke.yaml")
    assert called == []


def test_timing_on_a_busy_machine_says_so():
    """A load average that leaves no idle core beside the run's threads is one WARNING line (the probe timed
    10.6 ms at load 6 on 2 cores, 2.7 ms on a quiet machine, and said nothing)."""
    from fusion.measure.timing import busy_warning

    line = busy_warning({"usable_cores": 2, "load_average_1m": 6.2, "load_average_1m_after": 5.9}, threads=1)
    assert line.startswith("WARNING: the machine was busy while timing (load average 6.2 on 2 usable cores")
    assert busy_warning({"usable_cores": 2, "load_average_1m": 0.1, "load_average_1m_after": 1.1}, threads=1) is None
    assert busy_warning({"usable_cores": 2, "load_average_1m": 0.3, "load_average_1m_after": 2.2}, threads=2) is None
    assert busy_warning({"usable_cores": 2}, threads=1) is None
