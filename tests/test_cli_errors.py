"""Bad input from a new user's session (issue 21's re-probe): one line each, never a traceback."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from fusion.testing import small_dataset
from skygen.real.frames import FrameError, read_frame

ROOT = Path(__file__).resolve().parents[1]
CAMERA = str(ROOT / "configs" / "cameras" / "default-20deg.yaml")


def _one_error_line(err: str, *words: str) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], lines[0]


@pytest.fixture()
def blank_frame(tmp_path):
    path = tmp_path / "blank.npy"
    np.save(path, np.full((1024, 1024), 100.0, np.float32))
    return path


def test_an_unwritable_output_is_one_line_not_a_traceback(blank_frame, tmp_path, capsys):
    from fusion.cli import main as fusion
    from skygen.cli import main as skygen

    missing = tmp_path / "no-such-folder" / "p.jsonl"
    assert fusion(["predict", str(blank_frame), "--camera", CAMERA, "--out", str(missing)]) == 1
    _one_error_line(
        capsys.readouterr().err, "fusion predict: error:", "No such file or directory", str(missing), "check the path"
    )
    assert not missing.parent.exists()
    (tmp_path / "a-file").write_text("x")
    assert skygen(["preview", str(small_dataset("smoke")), "--out", str(tmp_path / "a-file" / "grid.png")]) == 2
    _one_error_line(capsys.readouterr().err, "skygen preview: error:", "a-file")
    if Path("/proc/self").is_dir():  # a folder that exists but takes no new files (Linux)
        assert skygen(["preview", str(small_dataset("smoke")), "--out", "/proc/grid.png"]) == 1
        _one_error_line(capsys.readouterr().err, "skygen preview: error:", "/proc/grid.png")


def test_a_camera_file_without_a_camera_is_refused(blank_frame, tmp_path, capsys):
    from fusion.cli import main as fusion

    for text in ("", "optics:\n  psf_sigma_px: 1.2\n"):
        cam = tmp_path / "cam.yaml"
        cam.write_text(text)
        assert fusion(["predict", str(blank_frame), "--camera", str(cam)]) == 2
        _one_error_line(capsys.readouterr().err, "no camera section", "width_px")


def test_frames_that_are_not_one_real_valued_image_are_refused(tmp_path):
    page = (np.arange(64 * 64).reshape(64, 64) % 60000).astype(np.uint16)
    cv2.imwritemulti(str(tmp_path / "pages.tiff"), [page, page, page])
    with pytest.raises(FrameError, match="multi-page TIFF \\(3 pages\\)"):
        read_frame(tmp_path / "pages.tiff")
    cv2.imwrite(str(tmp_path / "one.tiff"), page)
    np.testing.assert_array_equal(read_frame(tmp_path / "one.tiff"), page.astype(np.float32))
    np.save(tmp_path / "c.npy", np.zeros((8, 8), complex))
    with pytest.raises(FrameError, match="complex128 is not a real number"):
        read_frame(tmp_path / "c.npy")
    np.save(tmp_path / "v.npy", np.ones(8))
    with pytest.raises(FrameError, match="not an image"):
        read_frame(tmp_path / "v.npy")


def test_a_swallowed_sigterm_still_stops_the_next_unit_of_work(monkeypatch):
    from skygen import runtime

    monkeypatch.setitem(runtime._STOP, "requested", False)
    runtime.check_stop()  # nothing asked: carries on
    try:
        runtime.request_stop()
    except runtime.StopRequested:
        pass  # Python may swallow this one (a weakref callback) ...
    with pytest.raises(runtime.StopRequested):
        runtime.check_stop()  # ... the next check raises it again


def test_stop_on_sigterm_raises_within_the_block_and_restores_the_handler():
    """The one SIGTERM handling of both command lines: a kind of KeyboardInterrupt (no `except Exception`
    swallows it), raised inside the block only; the handler that was there before comes back."""
    import os
    import signal

    from skygen import runtime

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(runtime.StopRequested):
        with runtime.stop_on_sigterm():
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):  # the handler runs between bytecodes
                pass
    assert signal.getsignal(signal.SIGTERM) is before
    assert issubclass(runtime.StopRequested, KeyboardInterrupt) and not issubclass(runtime.StopRequested, Exception)
    runtime._STOP["requested"] = False
