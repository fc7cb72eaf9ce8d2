"""fusion predict: frame readers, bad input, the checkpoint's camera, regions and --solve."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from fusion.cli import main
from fusion.solve.frames import FrameError, read_frame
from fusion.testing import small_dataset
from skygen.errors import SkygenError

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "real-frames" / "tetra3-blackfly"  # shipped with the project (real-frames/README.md)


def _write_all(folder: Path, img16: np.ndarray) -> dict[str, Path]:
    from astropy.io import fits

    paths = {k: folder / f"frame.{k}" for k in ("npy", "tiff", "fits", "png")}
    np.save(paths["npy"], img16)
    cv2.imwrite(str(paths["tiff"]), img16)
    fits.PrimaryHDU(img16.astype(np.int32)).writeto(paths["fits"])
    cv2.imwrite(str(paths["png"]), img16)
    return paths


def test_readers_agree_and_bad_files_say_why(tmp_path):
    img = np.arange(12 * 20, dtype=np.uint16).reshape(12, 20) * 200
    for name, p in _write_all(tmp_path, img).items():
        np.testing.assert_array_equal(read_frame(p), img.astype(np.float32)), name
    cv2.imwrite(str(tmp_path / "eight.png"), (img // 256).astype(np.uint8))
    assert read_frame(tmp_path / "eight.png").max() == img.max() // 256
    rgb = np.zeros((12, 20, 3), np.uint8)
    rgb[..., 0] = 50
    cv2.imwrite(str(tmp_path / "colour.png"), rgb)
    grey_rgb = np.repeat((img // 256).astype(np.uint8)[..., None], 3, axis=2)
    cv2.imwrite(str(tmp_path / "grey3.png"), grey_rgb)
    assert read_frame(tmp_path / "grey3.png").shape == (12, 20)  # grey saved as RGB: accepted
    (tmp_path / "empty.tiff").write_bytes(b"")
    (tmp_path / "junk.png").write_bytes(b"not a png at all")
    np.save(tmp_path / "cube.npy", np.zeros((2, 3, 4)))
    assert read_frame(tmp_path / "colour.png", log=lambda m: None).shape == (12, 20)  # colour: one plane
    for name, words in [
        ("empty.tiff", "empty"),
        ("junk.png", "not a readable"),
        ("cube.npy", "colour or multi-plane"),
        ("missing.fits", "no such file"),
        ("eight.jpg2", "unsupported"),
    ]:
        if name == "eight.jpg2":
            (tmp_path / name).write_bytes(b"x")
        with pytest.raises(FrameError, match=words):
            read_frame(tmp_path / name)


@pytest.fixture(scope="module")
def frame_and_truth(tmp_path_factory):
    """A full-resolution frame of the smoke dataset's camera, in every format, with its true attitude."""
    from skygen.config import build_config
    from skygen.datasets.shards import open_dataset
    from skygen.render.frame import Renderer

    with open_dataset(small_dataset("smoke")) as ds:
        cfg = dict(ds.config)
    cfg["output"] = {**cfg["output"], "full_res": True}
    f = Renderer(build_config(cfg)).render(3)
    folder = tmp_path_factory.mktemp("frames")
    return _write_all(folder, f.image_full.astype(np.uint16)), f


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    from fusion.config import load_config
    from fusion.train.run import train

    out = tmp_path_factory.mktemp("run") / "run"
    cfg = load_config(ROOT / "configs" / "smoke.yaml", [f"data.path={small_dataset('smoke')}", "train.epochs=2"])
    train(cfg, out, log=lambda *a, **k: None)
    return out / "best.pt"


def _lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_predict_with_a_checkpoint_from_another_folder(checkpoint, frame_and_truth, tmp_path, monkeypatch):
    paths, f = frame_and_truth
    monkeypatch.chdir(tmp_path)  # the checkpoint carries camera and detector: any folder works
    out = tmp_path / "p.jsonl"
    assert (
        main(
            [
                "predict",
                *map(str, paths.values()),
                "--checkpoint",
                str(checkpoint),
                "--top-k",
                "2",
                "--solve",
                "--overlay",
                str(tmp_path / "ov"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    recs = _lines(out)
    assert len(recs) == 4
    first = recs[0]
    for r in recs[1:]:  # every format gives the same detections
        assert r["detections"] == first["detections"]
    assert first["n_detections"] >= 5 and len(first["regions"]) == 2
    assert first["regions"][0]["probability"] >= first["regions"][1]["probability"]
    sol = first["solution"]
    if sol["status"] == "solved":  # solved: right; else an explicit refusal
        v = np.array(f.unit_vector)
        a, d = np.radians(sol["ra_deg"]), np.radians(sol["dec_deg"])
        got = np.array([np.cos(d) * np.cos(a), np.cos(d) * np.sin(a), np.sin(d)])
        assert np.degrees(np.arccos(np.clip(v @ got, -1, 1))) < 0.1
    else:
        assert sol["reason"]
    assert (tmp_path / "ov" / "frame.png").stat().st_size > 500


def test_predict_camera_preset_solves_with_tetra3rs(frame_and_truth, tmp_path):
    import yaml

    from skygen.datasets.shards import open_dataset

    paths, f = frame_and_truth
    with open_dataset(small_dataset("smoke")) as ds:
        (tmp_path / "cam.yaml").write_text(yaml.safe_dump({k: ds.config[k] for k in ("camera", "detection", "output")}))
    out = tmp_path / "p.jsonl"
    assert (
        main(["predict", str(paths["tiff"]), "--camera", str(tmp_path / "cam.yaml"), "--solve", "--out", str(out)]) == 0
    )
    sol = _lines(out)[0]["solution"]
    assert sol["status"] == "solved" and sol["solver"] == "tetra3rs-lis"
    assert abs((sol["roll_deg"] - f.roll_deg + 180) % 360 - 180) < 0.1
    assert abs(sol["dec_deg"] - f.dec_deg) < 0.05


def test_bad_frames_one_line_each_and_the_batch_continues(checkpoint, frame_and_truth, tmp_path, capsys):
    paths, _ = frame_and_truth
    (tmp_path / "empty.png").write_bytes(b"")
    np.save(tmp_path / "small.npy", np.zeros((10, 12), np.uint16))
    out = tmp_path / "p.jsonl"
    rc = main(
        [
            "predict",
            str(tmp_path / "empty.png"),
            str(paths["npy"]),
            str(tmp_path / "small.npy"),
            "--checkpoint",
            str(checkpoint),
            "--out",
            str(out),
        ]
    )
    assert rc == 1
    recs = _lines(out)
    assert "empty" in recs[0]["error"] and "regions" in recs[1] and "12 x 10 px" in recs[2]["error"]
    err = capsys.readouterr().err.strip().splitlines()
    assert len([e for e in err if e.startswith("fusion predict:")]) == 2


def test_old_checkpoint_gets_one_clear_line(checkpoint, frame_and_truth, tmp_path, capsys):
    paths, _ = frame_and_truth
    ck = torch.load(checkpoint, weights_only=True)
    del ck["render_config"]
    del ck["content_sha256"]  # as old files: written before configs were hashed
    old = tmp_path / "old.pt"
    torch.save(ck, old)
    assert main(["predict", str(paths["npy"]), "--checkpoint", str(old)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "predates camera data" in err and "--dataset" in err
    assert (
        main(
            [
                "predict",
                str(paths["npy"]),
                "--checkpoint",
                str(old),
                "--dataset",
                str(small_dataset("smoke")),
                "--out",
                str(tmp_path / "o.jsonl"),
            ]
        )
        == 0
    )


def test_real_blackfly_frame_solves_to_the_listed_attitude(tmp_path):
    """One real frame (ESA tetra3 test data): tetra3rs via the camera preset agrees with the listed plate solution."""
    out = tmp_path / "r.jsonl"
    frame = REAL / "2019-07-29T204726_Alt60_Azi135_Try1.tiff"
    assert (
        main(
            [
                "predict",
                str(frame),
                "--camera",
                str(ROOT / "configs/cameras/blackfly-s-imx265-35mm.yaml"),
                "--solve",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    r = _lines(out)[0]
    assert r["shape"] == [768, 1024]
    sol = r["solution"]
    assert sol["status"] == "solved"
    assert abs(sol["ra_deg"] - 286.4356) * np.cos(np.radians(28.94)) < 0.01 and abs(sol["dec_deg"] - 28.9442) < 0.01
    assert abs((sol["roll_deg"] - (151.367 + 180.0) + 180) % 360 - 180) < 0.05  # listed roll is tetra3rs's (+y)


def test_real_frame_with_few_skygen_detections_solves_with_the_tetra3rs_extractor(tmp_path):
    frame = REAL / "2019-07-29T204726_Alt40_Azi-45_Try1.tiff"  # sky gradient: skygen's detector finds 4 stars
    cam = str(ROOT / "configs/cameras/blackfly-s-imx265-35mm.yaml")
    out = tmp_path / "r.jsonl"
    assert main(["predict", str(frame), "--camera", cam, "--solve", "--detector", "tetra3rs", "--out", str(out)]) == 0
    sol = _lines(out)[0]["solution"]
    assert sol["status"] == "solved"
    assert abs(sol["ra_deg"] - 172.3667) * np.cos(np.radians(57.65)) < 0.01 and abs(sol["dec_deg"] - 57.6494) < 0.01
    # skygen's own detector with a background per 64 px box follows the gradient: many more stars, solved
    out2 = tmp_path / "r2.jsonl"
    assert main(["predict", str(frame), "--camera", cam, "--solve", "--background-box", "64", "--out", str(out2)]) == 0
    r = _lines(out2)[0]
    assert r["n_detections"] >= 15 and r["solution"]["status"] == "solved"
    sol = r["solution"]
    assert abs(sol["ra_deg"] - 172.3667) * np.cos(np.radians(57.65)) < 0.01 and abs(sol["dec_deg"] - 57.6494) < 0.01


def test_predict_on_a_dataset_folder(checkpoint, tmp_path):
    out = tmp_path / "d.jsonl"
    assert (
        main(
            [
                "predict",
                str(small_dataset("smoke")),
                "--checkpoint",
                str(checkpoint),
                "--max-frames",
                "3",
                "--solve",
                "--top-k",
                "4",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    recs = _lines(out)
    assert len(recs) == 3 and all(r["detections_from"] == "dataset" for r in recs)
    assert all(abs(sum(x["probability"] for x in r["regions"]) - 1) < 1e-5 for r in recs)  # K = 4, all listed
    assert all(r["solution"]["status"] in ("solved", "refused") for r in recs)


def test_checkpoint_and_camera_are_exclusive(checkpoint, frame_and_truth, capsys):
    paths, _ = frame_and_truth
    cam = str(ROOT / "configs/cameras/default-20deg.yaml")
    assert main(["predict", str(paths["npy"]), "--checkpoint", str(checkpoint), "--camera", cam]) == 2
    assert main(["predict", str(paths["npy"])]) == 2
    assert "exactly one" in capsys.readouterr().err


def test_search_options_are_checked(checkpoint, frame_and_truth, capsys):
    paths, _ = frame_and_truth
    assert main(["predict", str(paths["npy"]), "--checkpoint", str(checkpoint), "--solve", "--focal-tol", "0.5"]) == 2
    assert "--focal-tol 0.5" in capsys.readouterr().err
    assert main(["predict", str(paths["npy"]), "--checkpoint", str(checkpoint), "--solve", "--search-k", "0"]) == 2
    assert "--search-k 0" in capsys.readouterr().err


def test_predict_without_a_model_chains_lost_in_space_and_the_whole_sky_fine_stage(tmp_path):
    """--solve without a checkpoint: tetra3rs, then the whole-sky fine stage; --solver picks any registered one."""
    import yaml

    from fusion.errors import ConfigError
    from fusion.solve.predict import Predictor
    from skygen.datasets import open_dataset

    with open_dataset(small_dataset("smoke")) as ds:
        (tmp_path / "cam.yaml").write_text(yaml.safe_dump({k: ds.config[k] for k in ("camera", "detection", "output")}))
    cam = str(tmp_path / "cam.yaml")
    chain = Predictor(camera=cam, solve=True).solver
    assert [chain.first.name, chain.second.name] == ["tetra3rs-lis", "whole-sky"]
    assert Predictor(camera=cam, solve=True, solver="whole-sky").solver.name == "whole-sky"
    with pytest.raises(ConfigError, match="needs a learned prior"):
        Predictor(camera=cam, solve=True, solver="learned+fine")
    with pytest.raises(SystemExit):  # a benchmark reference is not offered
        main(["predict", "x.npy", "--camera", cam, "--solve", "--solver", "oracle-prior"])


def _strict(line: str) -> dict:
    def refuse(token):
        raise ValueError(f"non-strict JSON token {token}")

    return json.loads(line, parse_constant=refuse)


def test_non_finite_pixels_are_bad_pixels_and_the_frame_still_solves(frame_and_truth, tmp_path, recwarn):
    import yaml

    from skygen.datasets.shards import open_dataset

    paths, f = frame_and_truth
    with open_dataset(small_dataset("smoke")) as ds:
        (tmp_path / "cam.yaml").write_text(yaml.safe_dump({k: ds.config[k] for k in ("camera", "detection", "output")}))
    img = np.load(paths["npy"]).astype(np.float32)
    img[5, 7], img[100, 3], img[200, 250] = np.nan, np.inf, -np.inf
    np.save(tmp_path / "nan.npy", img)
    out = tmp_path / "p.jsonl"
    assert (
        main(
            [
                "predict",
                str(paths["npy"]),
                str(tmp_path / "nan.npy"),
                "--camera",
                str(tmp_path / "cam.yaml"),
                "--solve",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    clean, bad = (_strict(line) for line in out.read_text().splitlines())
    assert (clean["bad_pixels"], bad["bad_pixels"]) == (0, 3)
    assert bad["n_detections"] == clean["n_detections"] >= 5
    assert bad["solution"]["status"] == "solved"
    assert abs(bad["solution"]["dec_deg"] - f.dec_deg) < 0.05
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]
    np.save(tmp_path / "all-nan.npy", np.full(img.shape, np.nan, np.float32))
    assert (
        main(["predict", str(tmp_path / "all-nan.npy"), "--camera", str(tmp_path / "cam.yaml"), "--out", str(out)]) == 1
    )
    assert "no finite pixel" in _strict(out.read_text())["error"]


def test_a_folder_of_frames_is_read_in_name_order(checkpoint, frame_and_truth, tmp_path, capsys):
    paths, _ = frame_and_truth
    folder = tmp_path / "frames"
    folder.mkdir()
    for name in ("b.tiff", "a.npy", "c.fits"):
        (folder / name).write_bytes(paths[name.split(".")[1]].read_bytes())
    (folder / "notes.txt").write_text("not a frame")
    out = tmp_path / "p.jsonl"
    assert main(["predict", str(folder), "--checkpoint", str(checkpoint), "--out", str(out)]) == 0
    recs = _lines(out)
    assert [Path(r["frame"]).name for r in recs] == ["a.npy", "b.tiff", "c.fits"]
    assert recs[0]["detections"] == recs[1]["detections"] == recs[2]["detections"]
    assert main(["predict", str(folder), "--checkpoint", str(checkpoint), "--max-frames", "1", "--out", str(out)]) == 0
    assert len(_lines(out)) == 1
    (tmp_path / "empty").mkdir()
    capsys.readouterr()
    assert main(["predict", str(tmp_path / "empty"), "--checkpoint", str(checkpoint), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds no frame files" in err[0] and "no such file" not in err[0]


@pytest.mark.parametrize("option,value", [("--top-k", "0"), ("--top-k", "-1"), ("--max-frames", "0")])
def test_nonsense_counts_are_refused_in_one_line(checkpoint, frame_and_truth, option, value, capsys):
    from fusion.solve.predict import predict

    paths, _ = frame_and_truth
    assert main(["predict", str(paths["npy"]), "--checkpoint", str(checkpoint), option, value]) == 2
    err = capsys.readouterr()
    assert err.out == "" and len(err.err.strip().splitlines()) == 1 and f"{option} {value}" in err.err
    kw = {"top_k": int(value)} if option == "--top-k" else {"max_frames": int(value)}
    with pytest.raises(SkygenError, match=f"{option} {value}"):
        predict([str(paths["npy"])], str(checkpoint), **kw)


def test_a_truncated_tiff_is_one_line(capfd, tmp_path):
    """OpenCV's libtiff warnings (written by C code to stderr) are silenced; our line remains."""
    img = (np.arange(300 * 400, dtype=np.uint32).reshape(300, 400) % 65536).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "full.tiff"), img)
    data = (tmp_path / "full.tiff").read_bytes()
    (tmp_path / "cut.tiff").write_bytes(data[: len(data) // 3])
    capfd.readouterr()
    with pytest.raises(FrameError, match="not a readable TIFF"):
        read_frame(tmp_path / "cut.tiff")
    assert capfd.readouterr().err == ""


def test_a_truncated_fits_is_one_line_of_ours(capfd, tmp_path):
    """astropy's own WARNING line about the truncation is not printed; ours names the file and says so."""
    from astropy.io import fits

    fits.writeto(tmp_path / "full.fits", np.random.default_rng(0).random((128, 128), np.float32))
    data = (tmp_path / "full.fits").read_bytes()
    (tmp_path / "cut.fits").write_bytes(data[: len(data) // 2])
    capfd.readouterr()
    with pytest.raises(FrameError, match="cut.fits: truncated FITS file"):
        read_frame(tmp_path / "cut.fits")
    captured = capfd.readouterr()
    assert captured.err == "" and captured.out == ""
    assert read_frame(tmp_path / "full.fits").shape == (128, 128)


def test_real_16_bit_frames_read_as_the_decoder_gives_them():
    for path in sorted(REAL.glob("*.tiff")):
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16
        np.testing.assert_array_equal(read_frame(path), raw.astype(np.float32))


def test_top_k_above_the_models_regions_says_it_reports_all(checkpoint, frame_and_truth, tmp_path, capsys):
    paths, _ = frame_and_truth
    out = tmp_path / "p.jsonl"
    assert (
        main(["predict", str(paths["npy"]), "--checkpoint", str(checkpoint), "--top-k", "50", "--out", str(out)]) == 0
    )
    assert "--top-k 50: the model has 4 regions; reporting all 4" in capsys.readouterr().err
    assert len(_lines(out)[0]["regions"]) == 4
