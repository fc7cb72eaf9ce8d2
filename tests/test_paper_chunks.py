"""scripts/paper_chunks.py: which command each chunk runs, and one real chunk on the CPU."""

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
    code = chunks.main(["--data", str(small_dataset("smoke")), "--out", str(out), "--config",
                        str(ROOT / "configs" / "smoke.yaml"), "--max-chunks", "1", "--chunk-minutes", "8",
                        "--launcher", f"{sys.executable} -m fusion.cli", "train.epochs=2", "train.progress=false"])
    assert code == 0 and (out / "summary.json").exists() and chunks.epochs_done(out) == 2
