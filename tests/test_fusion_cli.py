"""The fusion command line: main([...]) == 0, and one clear line with status 2 on bad input."""

import json
from pathlib import Path

import pytest
import torch

from fusion.cli import main
from fusion.testing import small_dataset

ROOT = Path(__file__).resolve().parents[1]
SMOKE = str(ROOT / "configs" / "smoke.yaml")


def test_train_then_evaluate(tmp_path, capsys):
    data = str(small_dataset("smoke"))
    run = tmp_path / "run"
    assert main(["train", "--data", data, "--out", str(run), "--config", SMOKE, "train.epochs=2"]) == 0
    assert (run / "best.pt").is_file()
    assert main(["evaluate", "--checkpoint", str(run / "best.pt"), "--data", data, "--split", "val"]) == 0
    report = json.loads((run / "eval-val.json").read_text())
    assert report["dataset"]["split"] == "val"
    out = capsys.readouterr().out
    assert "top-1" in out and "K=4" in out
    # a finished run is refused, one line, status 2
    assert main(["train", "--data", data, "--out", str(run), "--config", SMOKE]) == 2
    err = capsys.readouterr().err
    assert "finished run" in err and "--force" in err and "Traceback" not in err


def test_resume_from_the_run_folder_config(tmp_path):
    data = str(small_dataset("smoke"))
    run = tmp_path / "run"
    assert main(["train", "--data", data, "--out", str(run), "--config", SMOKE, "train.epochs=1"]) == 0
    (run / "summary.json").unlink()  # pretend it was killed after its last checkpoint
    assert main(["train", "--data", data, "--out", str(run), "--resume"]) == 0


@pytest.mark.parametrize(
    "args,needle",
    [
        (["train.nonsense=1"], "unknown config key 'train.nonsense'"),
        (["train.epochs=abc"], "train.epochs: expected an integer"),
        (["labels.k=1"], "labels.k: 1 is out of range"),
        (["model.name=vgg"], "unknown model 'vgg'"),
    ],
)
def test_bad_config_is_one_line_and_status_2(tmp_path, capsys, args, needle):
    rc = main(["train", "--data", str(small_dataset("smoke")), "--out", str(tmp_path / "r"), "--config", SMOKE, *args])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1


def test_missing_dataset_and_checkpoint_are_clear(tmp_path, capsys):
    assert main(["train", "--data", str(tmp_path / "nope"), "--out", str(tmp_path / "r"), "--config", SMOKE]) == 2
    assert "no such dataset folder" in capsys.readouterr().err
    assert main(["evaluate", "--checkpoint", str(tmp_path / "x.pt"), "--data", str(small_dataset("smoke"))]) == 2
    assert "checkpoint file not found" in capsys.readouterr().err


def test_help_config_and_no_command(capsys):
    assert main(["train", "--help-config"]) == 0
    out = capsys.readouterr().out
    assert "labels.k" in out and "aug.rotation_max_deg" in out
    assert main([]) == 2


def test_set_overrides_like_skygen_and_extending_a_finished_run(tmp_path, capsys):
    data = str(small_dataset("smoke"))
    run = tmp_path / "run"
    assert main(["train", "--data", data, "--out", str(run), "--config", SMOKE, "--set", "train.epochs=1"]) == 0
    assert json.loads((run / "summary.json").read_text())["epochs_run"] == 1
    # not more epochs than it ran: refused with the way to do it
    assert main(["train", "--out", str(run), "--resume"]) == 2
    assert "--resume --set train.epochs=N with N > 1" in capsys.readouterr().err
    assert main(["train", "--out", str(run), "--resume", "--set", "train.epochs=2"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["epochs_run"] == 2 and summary["last"]["epoch"] == 2


@pytest.mark.parametrize(
    "args,needle",
    [
        (["--batch-size", "0"], "--batch-size 0: must be at least 1"),
        (["--max-frames", "0"], "--max-frames 0: must be at least 1"),
        (["--max-frames", "-1"], "--max-frames -1: must be at least 1"),
        (["--workers", "-1"], "--workers -1: must be at least 0"),
    ],
)
def test_evaluate_refuses_nonsense_numbers(tmp_path, capsys, args, needle):
    assert main(["evaluate", "--checkpoint", str(tmp_path), "--data", str(tmp_path), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1


def test_version_help_and_run_folder_without_best(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith("fusion ")
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--out OUT (required) run folder" in text and "--set KEY=VALUE" in text and "key=value" in text
    assert main(["evaluate", "--checkpoint", str(tmp_path), "--data", str(tmp_path)]) == 2
    assert "is a folder without best.pt" in capsys.readouterr().err


def test_cli_choices_match_the_library():
    """The command line lists choices without importing torch; they must be the library's own."""
    from fusion import cli
    from fusion.measure import experiment, export, timing

    assert cli.PRECISIONS == tuple(timing.PRECISIONS) and cli.TIMING_MODES == timing.MODES
    assert cli.EXPORTERS == export.EXPORTERS and cli.MASK_DTYPES == export.MASK_DTYPES
    assert cli.EXPERIMENT_SECTIONS == experiment.SECTIONS


def test_a_run_too_large_for_a_cpu_says_so_with_its_size_and_pace():
    from fusion.train.run import loader_workers, pace_line

    big = torch.nn.Linear(5000, 4000)  # 20 M parameters
    line = pace_line(2.0, 1000, 10, 64, big, torch.device("cpu"))
    assert "2.00 s per step of 64 samples" in line and "~33.3 min per epoch" in line and "~5.6 h" in line
    assert "20.0 M-parameter model is a GPU recipe" in line and "configs/cpu.yaml" in line
    assert "GPU recipe" not in pace_line(0.01, 100, 10, 64, big, torch.device("cpu"))
    said = []
    assert loader_workers(10_000, said.append) < 10_000 and "core(s)" in said[0]
    assert loader_workers(0, said.append) == 0 and len(said) == 1


def test_after_an_interrupt_only_the_dataloader_worker_report_is_dropped(monkeypatch):
    import sys as _sys
    from types import SimpleNamespace

    from fusion.cli import _quiet_worker_teardown

    seen = []
    monkeypatch.setattr(_sys, "unraisablehook", lambda u: seen.append(u.exc_value))
    _quiet_worker_teardown()
    _sys.unraisablehook(
        SimpleNamespace(exc_value=RuntimeError("DataLoader worker (pid 7) is killed by signal: Terminated. "))
    )
    other = RuntimeError("something else")
    _sys.unraisablehook(SimpleNamespace(exc_value=other))
    assert seen == [other]
