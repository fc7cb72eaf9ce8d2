"""The command line, as users type it."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from skygen.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_render_inspect_preview_validate(tmp_path, small_overrides, capsys):
    out = tmp_path / "d"
    sets = sum((["--set", o] for o in small_overrides), [])
    assert main(["render", "--n", "30", "--seed", "3", "--out", str(out), "--workers", "1", "--quiet"] + sets) == 0
    assert main(["inspect", str(out)]) == 0
    assert "frames       30" in capsys.readouterr().out
    assert main(["inspect", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["seed"] == 3
    assert main(["preview", str(out), "--out", str(tmp_path / "p.png"), "--n", "4"]) == 0
    assert (tmp_path / "p.png").stat().st_size > 10_000
    assert main(["validate", str(out)]) == 0
    (out / "shard-00000.h5").write_bytes(b"broken")
    assert main(["validate", str(out)]) == 1


def test_bad_config_is_rejected_before_rendering(tmp_path, capsys):
    for bad, words in (
        (["--set", "sensor.exposure_s=-1"], "sensor.exposure_s"),
        (["--set", "camera.fov_deg=0"], "camera.fov_deg"),
        (["--set", "optics.psf=square"], "optics.psf"),
        (["--set", "corruptions.sunburn=1"], "valid keys"),
        (["--slice", "4/3"], "--slice"),
    ):
        assert main(["render", "--n", "5", "--out", str(tmp_path / "x")] + bad) == 2
        assert words in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_config_and_catalog_commands(capsys, tmp_path):
    assert main(["config", "--keys"]) == 0
    assert "sensor.read_noise_e" in capsys.readouterr().out
    cfgfile = tmp_path / "c.yaml"
    cfgfile.write_text("sensor:\n  exposure_s: 0.05\n")
    assert main(["config", "--config", str(cfgfile), "--summary"]) == 0
    out = capsys.readouterr().out
    assert "exposure_s: 0.05" in out and "detection limit" in out
    assert main(["catalog", "info"]) == 0
    assert "117955" in capsys.readouterr().out
    cfgfile.write_text("sensor: [1, 2]\n")
    assert main(["config", "--config", str(cfgfile)]) == 2


# ------------------------------------------------------------------ rough edges a new user hit
@pytest.mark.parametrize(
    "args,needle",
    [
        (
            ["--set", "photometry.zero_point_ph_s_cm2_a=.inf"],
            "photometry.zero_point_ph_s_cm2_a: inf is not a finite number",
        ),
        (
            ["--set", "camera.fov_deg=nan"],
            "camera.fov_deg: nan is not a finite number; give a finite number > 0 and < 120",
        ),
        (["--seed", str(2**63)], "seed: 9223372036854775808 is out of range"),
        (["--set", "catalog.mag_limit=-2"], "catalog.mag_limit: -2.0 is out of range; expected >= 0"),
        (
            ["--set", "catalog.mag_limit=2"],
            "catalog.mag_limit=2 leaves 46 catalog stars (the brightest is Hp -1.09), "
            "0.44 per 20.0 x 20.0 deg field on average",
        ),
        (["--workers", "-1"], "--workers -1"),
    ],
)
def test_render_refuses_with_one_line(tmp_path, capsys, args, needle):
    assert main(["render", "--n", "5", "--out", str(tmp_path / "x"), "--quiet", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    "args,needle",
    [
        (["--n", "0"], "--n 0: show at least 1 frame"),
        (["--n", "-3"], "--n -3"),
        (["--start", "500"], "--start 500: the whole dataset holds only 50 frames"),
        (["--start", "-1"], "--start -1"),
        (["--out", "name"], "give a file name ending in .png"),
        (["--out", "nowhere/deeper/p.png"], "does not exist; create it first"),
    ],
)
def test_preview_refuses_nonsense(small_dataset, tmp_path, capsys, monkeypatch, args, needle):
    monkeypatch.chdir(tmp_path)
    assert main(["preview", str(small_dataset), *args]) == 2
    assert needle in capsys.readouterr().err
    assert not list(tmp_path.iterdir())  # nothing written, no folder created


def test_more_slices_than_shards_are_refused(tmp_path, small_overrides, capsys):
    """--n 10 --slice 5/10 gave 0 frames and exit 0: slices are whole shards."""
    sets = sum((["--set", o] for o in small_overrides), [])  # output.shard_size=20
    out = tmp_path / "d"
    assert main(["render", "--n", "10", "--slice", "1/2", "--out", str(out), "--quiet", *sets]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "slices are whole shards of output.shard_size=20 frames" in err
    assert "allows at most 1 slice(s)" in err and "output.shard_size=5 for 2 slices" in err
    assert not out.exists()
    assert (
        main(
            [
                "render",
                "--n",
                "10",
                "--slice",
                "1/2",
                "--out",
                str(out),
                "--quiet",
                *sets,
                "--set",
                "output.shard_size=5",
            ]
        )
        == 0
    )
    assert "5 frames in 1 shard(s)" in capsys.readouterr().out


def test_a_magnitude_limit_giving_a_star_per_field_is_accepted(capsys):
    assert main(["config", "--set", "catalog.mag_limit=3", "--summary"]) == 0
    assert "rendering to Hp 3.00 (165 stars)" in capsys.readouterr().out


def test_preview_of_an_empty_split_and_validate_of_a_missing_path(tmp_path, small_overrides, capsys):
    out = tmp_path / "d"
    sets = sum((["--set", o] for o in small_overrides), [])
    assert (
        main(
            [
                "render",
                "--n",
                "6",
                "--out",
                str(out),
                "--workers",
                "1",
                "--quiet",
                "--set",
                "output.split_fractions=[1, 0, 0]",
                *sets,
            ]
        )
        == 0
    )
    assert main(["preview", str(out), "--split", "val", "--out", str(tmp_path / "p.png")]) == 2
    assert "split 'val' holds no frames" in capsys.readouterr().err
    assert main(["validate", str(tmp_path / "missing")]) == 2
    assert "no such dataset folder" in capsys.readouterr().err


def test_an_exposure_that_saturates_every_pixel_is_warned_about(tmp_path, small_overrides, capsys):
    sets = sum((["--set", o] for o in small_overrides), [])
    assert (
        main(
            [
                "render",
                "--n",
                "2",
                "--out",
                str(tmp_path / "d"),
                "--workers",
                "1",
                "--quiet",
                "--set",
                "sensor.exposure_s=3600",
                *sets,
            ]
        )
        == 0
    )
    assert "warning: every pixel saturates" in capsys.readouterr().err


def test_version_and_documented_positionals(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and "schema 2." in capsys.readouterr().out
    for cmd in ("inspect", "preview", "validate"):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        assert "dataset folder (or one shard file)" in capsys.readouterr().out


def _skygen(*args, **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, "-m", "skygen.cli", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def test_inspect_into_a_closed_pipe_is_quiet(small_dataset):
    p = subprocess.run(
        f"{sys.executable} -m skygen.cli inspect {small_dataset} | head -1",
        shell=True,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert p.stdout.startswith("dataset") and "Traceback" not in p.stderr and "BrokenPipe" not in p.stderr


def _children(pid: int) -> list[int]:
    kids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(d.name))
    return kids


def _alive(pid: int) -> bool:
    try:
        return (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _start_pool_render(tmp_path, small_overrides) -> tuple[subprocess.Popen, list[int]]:
    sets = sum((["--set", o] for o in small_overrides), [])
    p = _skygen(
        "render",
        "--n",
        "4000",
        "--workers",
        "2",
        "--quiet",
        "--out",
        str(tmp_path / "d"),
        *sets,
        "--set",
        "output.shard_size=40",
    )
    deadline = time.time() + 60
    while time.time() < deadline and not list((tmp_path / "d").glob("shard-*.h5")):
        time.sleep(0.2)  # the pool is up and writing
    workers = [k for k in _children(p.pid) if "resource_tracker" not in Path(f"/proc/{k}/cmdline").read_text()]
    assert workers, "no pool workers found"
    return p, workers


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_kill_9_leaves_no_workers_writing(tmp_path, small_overrides):
    """Pool workers would otherwise drain the tasks already queued to them for many seconds."""
    p, workers = _start_pool_render(tmp_path, small_overrides)
    p.kill()
    p.wait()
    at_kill = len(list((tmp_path / "d").glob("shard-*.h5")))
    deadline = time.time() + 3
    while time.time() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.1)
    assert not any(_alive(w) for w in workers)
    time.sleep(1.0)
    assert len(list((tmp_path / "d").glob("shard-*.h5"))) <= at_kill + len(workers)  # at most the shard in hand


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sigterm_says_how_to_resume(tmp_path, small_overrides):
    p, workers = _start_pool_render(tmp_path, small_overrides)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 143
    assert "run the same command again to resume" in err and "leaked semaphore" not in err and "Traceback" not in err
    assert not any(_alive(w) for w in workers)


def test_a_second_render_or_merge_into_a_busy_folder_is_refused_naming_the_first(tmp_path, small_overrides, capsys):
    from skygen.lock import FolderLock, lock_path

    out = tmp_path / "d"
    out.mkdir()
    sets = sum((["--set", o] for o in small_overrides), [])
    with FolderLock(out, what="skygen render"):
        for args in (
            ["render", "--n", "5", "--out", str(out), "--quiet", *sets],
            ["render", "--n", "5", "--out", str(out), "--quiet", "--slice", "0/1", *sets],
            ["merge", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out)],
        ):
            if args[0] == "merge":
                for name in ("a", "b"):
                    assert (
                        main(
                            [
                                "render",
                                "--n",
                                "4",
                                "--seed",
                                str(ord(name)),
                                "--out",
                                str(tmp_path / name),
                                "--quiet",
                                *sets,
                            ]
                        )
                        == 0
                    )
                capsys.readouterr()
            assert main(args) == 2
            err = capsys.readouterr().err.strip()
            assert len(err.splitlines()) == 1 and f"is in use by skygen render (PID {os.getpid()} " in err
        assert not list(out.glob("shard-*")) and not (out / "manifest.json").exists()
    assert not lock_path(out).exists()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_two_renders_into_one_folder_at_once(tmp_path, small_overrides, capsys):
    """Issue 21: both exited 0 and the dataset was invalid in 1 of 4 trials."""
    from skygen.lock import lock_path

    p, _ = _start_pool_render(tmp_path, small_overrides)
    try:
        sets = sum((["--set", o] for o in small_overrides), [])
        assert (
            main(
                [
                    "render",
                    "--n",
                    "4000",
                    "--workers",
                    "1",
                    "--quiet",
                    "--out",
                    str(tmp_path / "d"),
                    *sets,
                    "--set",
                    "output.shard_size=40",
                ]
            )
            == 2
        )
        assert f"is in use by skygen render (PID {p.pid} " in capsys.readouterr().err
    finally:
        p.send_signal(signal.SIGTERM)
        p.communicate(timeout=60)
    assert p.returncode == 143 and not lock_path(tmp_path / "d").exists()  # released on SIGTERM
