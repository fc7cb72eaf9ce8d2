"""A `fusion train` process killed with SIGKILL mid-run resumes to the same metrics as an uninterrupted run."""

import csv
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from fusion.testing import small_dataset

ARGS = ["--config", "configs/smoke.yaml", "train.epochs=6", "train.workers=0"]


def metrics(run) -> list[dict]:
    with open(run / "metrics.csv") as f:
        return [{k: v for k, v in row.items() if k != "epoch_time_s"} for row in csv.DictReader(f)]


def train_cmd(data, out, *extra):
    return [sys.executable, "-m", "fusion.cli", "train", "--data", str(data), "--out", str(out), *ARGS, *extra]


@pytest.mark.parametrize("delay_s", [0.05])
def test_sigkill_mid_run_then_resume_matches(tmp_path, delay_s):
    data = small_dataset("smoke")
    ref = tmp_path / "ref"
    assert subprocess.run(train_cmd(data, ref), capture_output=True).returncode == 0
    run = tmp_path / "killed"
    proc = subprocess.Popen(train_cmd(data, run), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and not (run / "last.pt").exists():  # first epoch done, second under way
        time.sleep(0.01)
    time.sleep(delay_s)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (run / "summary.json").exists(), "the run finished before it could be killed"
    from fusion.model.checkpoint import load_checkpoint

    for ckpt in run.glob("*.pt"):  # whatever looks whole is whole (temp names aside)
        load_checkpoint(ckpt)
    assert subprocess.run(train_cmd(data, run, "--resume"), capture_output=True).returncode == 0
    assert metrics(run) == metrics(ref)
    assert np.allclose(np.load(run / "centroids.npy"), np.load(ref / "centroids.npy"))


def test_sigterm_prints_the_resume_command_and_that_command_finishes_the_run(tmp_path):
    import shlex

    run = tmp_path / "run dir"  # a space: the printed command must quote it
    cmd = [
        sys.executable,
        "-m",
        "fusion.cli",
        "train",
        "--data",
        str(small_dataset("smoke")),
        "--out",
        str(run),
        "--config",
        "configs/smoke.yaml",
        "train.epochs=3",
        "train.workers=0",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and not (run / "last.pt").exists():
        time.sleep(0.01)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate()
    assert not (run / "summary.json").exists(), "the run finished before it could be stopped"
    assert proc.returncode == 143  # 128 + SIGTERM, as skygen render
    last = err.strip().splitlines()[-1]
    assert last.startswith("fusion train: terminated (SIGTERM); continue it with: fusion train --out ")
    assert not list(run.glob(".skygen*.lock"))  # the lock went with the process
    resume = shlex.split(last.split("with: ", 1)[1])
    assert resume[:2] == ["fusion", "train"] and resume[3] == str(run)
    assert subprocess.run([sys.executable, "-m", "fusion.cli", *resume[1:]], capture_output=True).returncode == 0
    assert (run / "summary.json").exists()


def test_a_second_training_into_a_busy_run_folder_is_refused(tmp_path, capsys):
    from fusion.cli import main
    from skygen.lock import FolderLock

    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.csv").write_text("the other run's\n")
    with FolderLock(run, what="fusion train"):
        assert (
            main(
                [
                    "train",
                    "--data",
                    str(small_dataset("smoke")),
                    "--out",
                    str(run),
                    "--config",
                    "configs/smoke.yaml",
                    "--force",
                ]
            )
            == 2
        )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is in use by fusion train (PID" in err[0]
    assert sorted(p.name for p in run.iterdir()) == ["metrics.csv"]  # --force deleted nothing; no lock left
