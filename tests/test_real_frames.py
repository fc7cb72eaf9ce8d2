"""The real frames shipped in real-frames/ are whole, and their table names every frame; colour frames
become one plane and a raw Bayer mosaic stored as mono is flagged."""

from __future__ import annotations

import csv
import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from skygen.errors import ConfigError
from skygen.real.frames import LUMINANCE_RGB, FrameError, read_frame

ROOT = Path(__file__).resolve().parents[1]
FOLDER = ROOT / "real-frames" / "tetra3-blackfly"


def test_shipped_real_frames_match_their_checksums_and_table():
    sums = dict(reversed(line.split()) for line in (FOLDER / "SHA256SUMS").read_text().splitlines())
    assert len(sums) == 8
    for name, digest in sums.items():
        assert hashlib.sha256((FOLDER / name).read_bytes()).hexdigest() == digest, name
    with open(FOLDER / "solutions.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert sorted(r["file"] for r in rows) == sorted(sums)
    for r in rows:
        assert 11.4 < float(r["fov_deg"]) < 11.44 and -90 <= float(r["dec_deg"]) <= 90
    assert "Apache License" in (FOLDER / "LICENSE-Apache-2.0.txt").read_text()


@pytest.mark.parametrize(
    "folder", ["tetra3-blackfly", "openstartracker-science-cam", "startrackerpy-dmk41bu02", "creusot-16mm"]
)
def test_every_shipped_camera_folder_matches_its_checksums_and_carries_its_licence(folder):
    here = ROOT / "real-frames" / folder
    sums = dict(reversed(line.split(None, 1)) for line in (here / "SHA256SUMS").read_text().splitlines())
    frames = [n for n in sums if not n.startswith("LICENSE")]
    assert len(frames) >= 5 and list(here.glob("LICENSE*"))
    for name, digest in sums.items():
        assert hashlib.sha256((here / name).read_bytes()).hexdigest() == digest, name
    assert folder in (ROOT / "real-frames" / "README.md").read_text()


def test_a_jpeg_frame_is_read_with_one_line_saying_it_is_lossy(tmp_path):
    rng = np.random.default_rng(3)
    img = np.clip(rng.normal(20, 3, (48, 64)), 0, 255).astype(np.uint8)
    img[20:23, 30:33] = 200
    path = tmp_path / "frame.jpg"
    cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, 100])
    said = []
    out = read_frame(path, log=said.append)
    assert out.shape == img.shape and out.dtype == np.float32
    assert np.abs(out - img).max() <= 3  # quality 100: nearly lossless
    assert len(said) == 1 and "JPEG" in said[0] and "lossy" in said[0] and "quality 100" in said[0]


def test_a_bmp_frame_is_read_as_stored_grey_or_colour(tmp_path):
    """BMP (lossless 8 bit, what cedar-detect's own test frames are): grey as stored, colour as one plane."""
    rng = np.random.default_rng(4)
    img = np.clip(rng.normal(20, 3, (48, 64)), 0, 255).astype(np.uint8)
    img[20:23, 30:33] = 200
    cv2.imwrite(str(tmp_path / "grey.bmp"), img)
    said = []
    np.testing.assert_array_equal(read_frame(tmp_path / "grey.bmp", log=said.append), img.astype(np.float32))
    assert said == []
    rgb = _rgb()
    cv2.imwrite(str(tmp_path / "colour.bmp"), np.ascontiguousarray(rgb[:, :, ::-1]))
    np.testing.assert_array_equal(read_frame(tmp_path / "colour.bmp", "g", log=said.append), rgb[:, :, 1])
    assert len(said) == 1 and "colour frame (RGB, 8 bit) read as one plane: the G plane" in said[0]
    (tmp_path / "cut.bmp").write_bytes((tmp_path / "grey.bmp").read_bytes()[:40])
    with pytest.raises(FrameError, match="not a readable BMP image"):
        read_frame(tmp_path / "cut.bmp")


def test_a_jpeg_s_quality_is_read_from_its_luminance_table(tmp_path):
    """jpeg_luma_quality: the IJG quality a JPEG was written with, from its quantisation table (OpenCV's libjpeg at
    30, 75 and 100), said in the line the reader prints; None for a file that is not a JPEG or is cut short."""
    from skygen.real.frames import jpeg_luma_quality

    img = (np.random.default_rng(0).random((32, 32)) * 255).astype(np.uint8)
    for q in (30, 75, 100):
        path = tmp_path / f"q{q}.jpg"
        cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, q])
        assert jpeg_luma_quality(path) == pytest.approx(q, abs=1)
    said = []
    read_frame(tmp_path / "q75.jpg", log=said.append)
    assert "quality about 75" in said[0]
    (tmp_path / "cut.jpg").write_bytes((tmp_path / "q75.jpg").read_bytes()[:10])
    np.save(tmp_path / "x.npy", img)
    assert jpeg_luma_quality(tmp_path / "cut.jpg") is None and jpeg_luma_quality(tmp_path / "x.npy") is None


# ------------------------------------------------------------------------------ colour and Bayer frames


def _rgb(h=40, w=60, dtype=np.uint8, seed=0):
    """Distinct R, G, B planes ([y, x, (R, G, B)]) of integer type ``dtype``."""
    rng = np.random.default_rng(seed)
    top = np.iinfo(dtype).max
    return np.stack(
        [
            rng.integers(0, top // 3, (h, w)),
            rng.integers(top // 3, 2 * top // 3, (h, w)),
            rng.integers(2 * top // 3, top, (h, w)),
        ],
        axis=2,
    ).astype(dtype)


@pytest.mark.parametrize("dtype, alpha", [(np.uint8, False), (np.uint16, True)])
def test_colour_frames_become_one_plane_saying_so(tmp_path, dtype, alpha):
    rgb = _rgb(dtype=dtype)
    bgr = rgb[:, :, ::-1]  # OpenCV writes B, G, R (, A)
    if alpha:
        a = np.random.default_rng(1).integers(0, np.iinfo(dtype).max, rgb.shape[:2]).astype(dtype)
        bgr = np.dstack([bgr, a])
    path = tmp_path / "colour.png"
    cv2.imwrite(str(path), np.ascontiguousarray(bgr))
    said = []
    img = read_frame(path, log=said.append)
    r, g, b = (rgb[:, :, k].astype(np.float64) for k in range(3))
    np.testing.assert_allclose(img, LUMINANCE_RGB[0] * r + LUMINANCE_RGB[1] * g + LUMINANCE_RGB[2] * b, rtol=1e-6)
    assert img.shape == rgb.shape[:2] and img.dtype == np.float32
    kind = f"RGBA, {8 * np.dtype(dtype).itemsize} bit; alpha dropped" if alpha else "RGB, 8 bit"
    assert said == [
        (
            f"{path}: colour frame ({kind}) read as one plane: luminance 0.2126 R + 0.7152 G + 0.0722 B "
            "(Rec. 709; --channel r, g, b or sum for another)"
        )
    ]
    # one plane by name, in R, G, B order whatever OpenCV's order, or their sum
    for k, name in enumerate("rgb"):
        np.testing.assert_array_equal(read_frame(path, name, log=lambda m: None), rgb[:, :, k].astype(np.float32))
    np.testing.assert_array_equal(read_frame(path, "sum", log=lambda m: None), rgb.astype(np.float32).sum(axis=2))
    with pytest.raises(ConfigError, match="channel 'red': give one of luminance, r, g, b, sum"):
        read_frame(path, "red")


def test_grey_stored_as_rgb_is_read_without_a_note_and_the_default_note_goes_to_stderr(tmp_path, capsys):
    grey = _rgb()[:, :, 1]
    cv2.imwrite(str(tmp_path / "grey.png"), np.dstack([grey] * 3))
    np.testing.assert_array_equal(read_frame(tmp_path / "grey.png"), grey.astype(np.float32))
    cv2.imwrite(str(tmp_path / "colour.tiff"), _rgb(dtype=np.uint16))
    read_frame(tmp_path / "colour.tiff")
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "colour.tiff: colour frame (RGB, 16 bit) read as one plane" in err[0]
    np.save(tmp_path / "cube.npy", np.zeros((3, 8, 8)))  # planes of a cube: order unknown, refused
    with pytest.raises(FrameError, match="colour or multi-plane image"):
        read_frame(tmp_path / "cube.npy")


def _star_field(h=128, w=160, levels=(100, 100, 100, 100), seed=2):
    """A 16-bit frame: Poisson background of the four 2 x 2 sub-lattice ``levels`` ((0,0), (0,1), (1,0),
    (1,1)) plus a few bright stars."""
    rng = np.random.default_rng(seed)
    bg = np.empty((h, w))
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        bg[dy::2, dx::2] = levels[k]
    img = rng.poisson(bg).astype(np.float64)
    yy, xx = np.mgrid[0:h, 0:w]
    for y, x in rng.uniform(8, min(h, w) - 8, (12, 2)):
        img += 3000 * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * 1.5**2))
    return np.clip(img, 0, 65535).astype(np.uint16)


def test_a_raw_bayer_mosaic_stored_as_mono_is_flagged_in_one_line(tmp_path):
    cases = {
        "bayer.png": (40, 90, 90, 30),  # R G / G B behind the night sky's colour: flagged
        "mono.png": (100, 100, 100, 100),  # one filter: nothing
        "columns.png": (30, 45, 30, 45),  # even/odd column offsets of a mono sensor: not a mosaic
        "faint.png": (100, 104, 104, 98),
    }  # a bias under a weakly coloured sky: under 1.3 x, not flagged
    said = {}
    for name, levels in cases.items():
        cv2.imwrite(str(tmp_path / name), _star_field(levels=levels))
        lines = []
        img = read_frame(tmp_path / name, log=lines.append)
        assert img.shape == (128, 160)  # read as it is either way
        said[name] = lines
    assert len(said["bayer.png"]) == 1 and "looks like a raw Bayer mosaic" in said["bayer.png"][0]
    assert said["bayer.png"][0].endswith("debayer it or give one colour plane")
    assert said["mono.png"] == said["columns.png"] == said["faint.png"] == []


def test_a_colour_file_whose_planes_hold_a_mosaic_gets_only_the_colour_line(tmp_path):
    """A colour file was converted to one plane on purpose; a 2 x 2 pattern left in its planes (a camera
    that stores its raw mosaic in every channel) gets no 'debayer it' warning the user cannot act on."""
    mosaic = _star_field(levels=(40, 90, 90, 30))
    cv2.imwrite(str(tmp_path / "rgb.png"), np.dstack([mosaic, mosaic // 2, mosaic]))
    lines = []
    img = read_frame(tmp_path / "rgb.png", log=lines.append)
    assert img.shape == (128, 160)
    assert len(lines) == 1 and "colour frame" in lines[0] and "Bayer" not in lines[0]


def test_a_frames_date_sets_the_epoch_exif_and_fits(tmp_path):
    """frame_epoch: a JPEG's EXIF DateTimeOriginal and a FITS DATE-OBS as Julian years; a PNG has none.
    frames_epoch: their median and one line naming the fields, and the span where it passes a year."""
    from astropy.io import fits
    from PIL import Image

    from skygen.real.fit_camera import frames_epoch
    from skygen.real.frames import frame_epoch

    jpg = tmp_path / "a.jpg"
    exif = Image.Exif()
    exif.get_ifd(0x8769)[36867] = "2014:12:02 22:30:44"
    Image.new("L", (16, 16)).save(jpg, exif=exif)
    year, field = frame_epoch(jpg)
    assert year == pytest.approx(2014.92, abs=0.005) and field == "EXIF DateTimeOriginal"
    fit = tmp_path / "b.fits"
    fits.PrimaryHDU(np.zeros((4, 4)), header=fits.Header([("DATE-OBS", "2019-07-29T20:47:26")])).writeto(fit)
    assert frame_epoch(fit) == (pytest.approx(2019.574, abs=0.002), "FITS DATE-OBS")
    png = tmp_path / "c.png"
    Image.new("L", (16, 16)).save(png)
    assert frame_epoch(png) is None and frame_epoch(tmp_path / "missing.jpg") is None
    epoch, line = frames_epoch([str(jpg), str(fit), str(png)])
    assert epoch == pytest.approx((2014.92 + 2019.574) / 2, abs=0.01)
    assert "from 2 of 3 frames' EXIF DateTimeOriginal / FITS DATE-OBS, which span 4.7 years" in line
    assert frames_epoch([str(png)]) == (None, "")
