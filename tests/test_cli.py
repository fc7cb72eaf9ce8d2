"""The command line, as users type it."""

import json

from skygen.cli import main


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
    for bad, words in ((["--set", "sensor.exposure_s=-1"], "sensor.exposure_s"),
                       (["--set", "camera.fov_deg=0"], "camera.fov_deg"),
                       (["--set", "optics.psf=square"], "optics.psf"),
                       (["--set", "corruptions.sunburn=1"], "valid keys"),
                       (["--slice", "4/3"], "--slice")):
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
