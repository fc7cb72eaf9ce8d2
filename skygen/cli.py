"""``skygen`` command line: render, inspect, preview, validate, merge, calibrate, fit-camera, stream, catalog, config.

Each subcommand is a thin wrapper over a library function; ``main(argv) -> int``.
Exit codes: 0 success, 1 validation found problems, 2 bad input (message on stderr),
130 interrupted (Ctrl-C), 143 terminated (SIGTERM). Output cut short by a closed pipe
(``skygen inspect DIR | head``) ends quietly with 0.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Callable

import numpy as np

from skygen.errors import SkygenError
from skygen.runtime import StopRequested as Terminated  # SIGTERM -> cleanup -> the resume hint

EPILOG = """examples:
  skygen render --n 2000 --workers 2            # into data/sky-n2000-s0
  skygen render --n 50000 --set sensor.exposure_s=0.05 --set corruptions.false_stars=1
  skygen render --n 50000 --slice 3/10 --out /scratch/big   # one slice of a job array
  skygen inspect data/sky-n2000-s0
  skygen preview data/sky-n2000-s0 --out grid.png
  skygen validate data/sky-n2000-s0
  skygen merge /scratch/part-a /scratch/part-b --out /scratch/all
  skygen config --keys                          # every config key, default, range and unit
  skygen stream --kind detections --n 100000     # training samples on the fly: throughput + statistics
  skygen calibrate --out detector.json           # fit the detector emulator for a config
  skygen fit-camera real-frames/tetra3-blackfly/*.tiff --camera configs/cameras/blackfly-s-imx265-35mm.yaml \
      --out my-camera.yaml --report my-camera-report   # a camera file fitted to your own frames
"""


def _default_out(n: int, seed: int) -> Path:
    return Path("data") / f"sky-n{n}-s{seed}"


def _parse_slice(text: str | None) -> tuple[int, int]:
    if not text:
        return 0, 1
    try:
        i, k = (int(v) for v in text.split("/"))
    except ValueError:
        raise SkygenError(f"--slice {text!r} must look like I/K, e.g. 3/10 (slice 3 of 10, counting from 0)") from None
    if k < 1 or not 0 <= i < k:
        raise SkygenError(f"--slice {text}: need 0 <= I < K")
    return i, k


def _load(args):
    from skygen.config import load_config

    sets = list(args.set or [])
    if getattr(args, "n", None) is not None:
        sets.append(f"n_frames={args.n}")
    if getattr(args, "seed", None) is not None:
        sets.append(f"seed={args.seed}")
    if getattr(args, "full_res", False):
        sets.append("output.full_res=true")
    return load_config(args.config, sets)


def add_channel_argument(p: argparse.ArgumentParser) -> None:
    """--channel: how colour frames become one plane (skygen fit-camera, fusion predict; skygen.real.frames)."""
    p.add_argument(
        "--channel",
        choices=("luminance", "r", "g", "b", "sum"),
        default="luminance",
        help="colour (RGB/RGBA) frames become one plane: luminance (Rec. 709 weights; default), "
        "one of the r, g, b planes, or their sum",
    )


def _config_args(p: argparse.ArgumentParser, with_n: bool = True) -> None:
    """--config, --set, --seed (and --n): the one config system's options, shared by several commands."""
    p.add_argument("--config", metavar="FILE.yaml", help="YAML config (keys as in `skygen config`)")
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override one config key, e.g. --set sensor.exposure_s=0.05 (repeatable)",
    )
    if with_n:
        p.add_argument("--n", type=int, help="number of frames (config n_frames; default 1000)")
    p.add_argument("--seed", type=int, help="dataset seed (config seed; default 0)")


# --------------------------------------------------------------------------- render
def _add_render(p: argparse.ArgumentParser) -> None:
    _config_args(p)
    p.add_argument(
        "--out",
        help="output folder (default data/sky-n{N}-s{SEED}); locked while rendering: a "
        "second render into it is refused, naming the first",
    )
    p.add_argument("--workers", type=int, default=0, help="worker processes, >= 1 (default 0: all cores)")
    p.add_argument("--full-res", action="store_true", help="also store full-resolution frames")
    p.add_argument(
        "--slice",
        metavar="I/K",
        help="render only slice I of K (job arrays, counting from 0). "
        "Slices are whole shards (output.shard_size frames, default 1000): shard k belongs to slice "
        "k mod K, so K may not exceed the number of shards. Slices may render into one folder at "
        "once; the last slice to finish writes manifest.json",
    )
    p.add_argument("--force", action="store_true", help="replace a different dataset found in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _run_render(args: argparse.Namespace) -> int:
    from skygen.datasets.build import render_dataset
    from skygen.runtime import stop_on_sigterm

    cfg = _load(args)
    out = Path(args.out) if args.out else _default_out(cfg.n_frames, cfg.seed)
    i, k = _parse_slice(args.slice)
    if args.workers < 0:
        raise SkygenError(f"--workers {args.workers}: give a number of worker processes >= 1 (0 = all cores)")
    workers = args.workers or os.cpu_count() or 1
    with stop_on_sigterm():
        man = render_dataset(
            cfg, out, workers=workers, slice_index=i, num_slices=k, force=args.force, progress=not args.quiet
        )
    print(
        f"{man['n_frames']} frames in {len(man['shards'])} shard(s) at {out}  "
        f"(train {man['splits']['train']}, val {man['splits']['val']}, test {man['splits']['test']})"
    )
    print(f"look at it:  skygen inspect {out}   |   skygen preview {out} --out {out}/preview.png")
    return 0


# --------------------------------------------------------------------------- inspect
def _add_inspect(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="dataset folder (or one shard file)")
    p.add_argument("--json", action="store_true", help="machine-readable output")


def _run_inspect(args: argparse.Namespace) -> int:
    from skygen.datasets.summary import inspect_dataset

    print(inspect_dataset(args.path, as_json=args.json))
    return 0


# --------------------------------------------------------------------------- preview
def _add_preview(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="dataset folder (or one shard file)")
    p.add_argument("--out", default="preview.png", help="PNG file to write (its folder must exist)")
    p.add_argument("--n", type=int, default=12, help="frames to show (>= 1)")
    p.add_argument("--start", type=int, default=0, help="first frame, a position within the split (>= 0)")
    p.add_argument("--split", choices=("train", "val", "test"), default=None)


def _run_preview(args: argparse.Namespace) -> int:
    from skygen.datasets.preview import preview

    out = preview(args.path, args.out, n=args.n, split=args.split, start=args.start)
    print(f"wrote {out}")
    return 0


# --------------------------------------------------------------------------- validate
def _add_validate(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="dataset folder (or one shard file); a missing path exits 2")
    p.add_argument("--no-checksums", action="store_true", help="skip sha256 verification (faster)")


def _run_validate(args: argparse.Namespace) -> int:
    from skygen.datasets.validate import validate
    from skygen.errors import DatasetError

    if not Path(args.path).exists():
        raise DatasetError(f"{args.path}: no such dataset folder or shard file")
    report = validate(args.path, checksums=not args.no_checksums)
    print(report.text())
    return 0 if report.ok else 1


# --------------------------------------------------------------------------- merge
def _add_merge(p: argparse.ArgumentParser) -> None:
    p.add_argument("inputs", nargs="+", help="dataset folders")
    p.add_argument("--out", required=True, help="new folder for the merged manifest (locked while merging)")


def _run_merge(args: argparse.Namespace) -> int:
    from skygen.datasets.merge import merge_datasets

    man = merge_datasets(args.inputs, args.out)
    print(
        f"merged {len(args.inputs)} folders into {args.out}/manifest.json: {man['n_frames']} frames in "
        f"{man['n_shards']} shards (no frame data copied; shards are referenced by relative path)"
    )
    return 0


# --------------------------------------------------------------------------- catalog
def _add_catalog(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=("info", "fetch"))
    p.add_argument("--catalog", default="hipparcos-v", help="fetch: hipparcos-v (I/239) or tycho2 (I/259)")
    p.add_argument("--mag-limit", type=float, default=9.0, help="fetch: faintest V magnitude")
    p.add_argument("--out", help="fetch: output .npz (default catalogs/NAME.npz)")
    p.add_argument(
        "--source",
        choices=("hipparcos", "gaia"),
        default="hipparcos",
        help="info: hipparcos (Hipparcos-2) or gaia (Gaia DR3 to G = 10 merged with it), as catalog.source",
    )
    p.add_argument("--path", help="info: catalog file (default: the source's bundled one)")


def _run_catalog(args: argparse.Namespace) -> int:
    from skygen.sky.catalog import open_catalog

    if args.action == "fetch":
        from skygen.sky.vizier import fetch

        out = Path(args.out or f"catalogs/{args.catalog}.npz")
        out.parent.mkdir(parents=True, exist_ok=True)
        stars = fetch(args.catalog, out, args.mag_limit)
        print(f"saved {len(stars)} stars to {out}; use it with --set catalog.path={out}")
        return 0
    table = open_catalog(args.source, args.path)
    import numpy as np

    print(f"source: {table.source}\nstars: {len(table)}\nepoch: J{table.epoch_yr}\nband: {table.band}")
    for m in (3, 4, 5, 6, 7, 8, 9, 10):
        print(f"  {table.band} <= {m}: {int(np.sum(table.mag <= m))}")
    return 0


# --------------------------------------------------------------------------- calibrate
def _add_calibrate(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", nargs="?", help="rendered dataset folder to fit on (optional; default: render frames)")
    _config_args(p, with_n=False)
    p.add_argument("--frames", type=int, default=3000, help="frames to render when no DIR is given (default 3000)")
    p.add_argument("--max-frames", type=int, default=None, help="with DIR: use at most this many frames")
    p.add_argument("--out", required=True, help="calibration JSON to write")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _run_calibrate(args: argparse.Namespace) -> int:
    from skygen.stream import calibration as cal
    from skygen.stream import emulator as emu

    if args.path:
        if args.config or args.set:
            raise SkygenError(
                "calibrate: give either a dataset DIR (its own config is used) or --config/--set "
                "(frames are rendered), not both"
            )
        model = cal.calibrate_from_dataset(args.path, args.max_frames)
    else:
        cfg = _load(args)
        bar = None
        if not args.quiet:
            from tqdm import tqdm

            bar = tqdm(total=args.frames, desc="calibration frames", unit="frame")
        model = cal.calibrate_from_renders(cfg, args.frames, progress=(lambda k, n: bar.update(1)) if bar else None)
        if bar:
            bar.close()
    emu.save(model, args.out)
    c = model.completeness
    u50 = float(emu.U_EDGES[np.argmax(c >= 0.5)]) if (c >= 0.5).any() else float("nan")
    print(
        f"wrote {args.out}: {model.info['frames']} frames, {model.info['matched_rows']} matched isolated "
        f"detections, threshold {model.threshold_e:.0f} e-, 50 % completeness at {10**u50:.2f} x threshold, "
        f"pairs of stars at 10 x threshold merged below {model.blend_radius_px(10 * model.threshold_e):.1f} px, "
        f"{model.info['spurious_per_frame']:.2f} spurious "
        "detections per frame"
    )
    return 0


# --------------------------------------------------------------------------- fit-camera
def _add_fit_camera(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "frames",
        nargs="+",
        metavar="FRAME",
        help="frame files (PNG, TIFF 8/16 bit, BMP, FITS, .npy, JPEG (lossy: said); one "
        "full-resolution read-out each, all of one size: monochrome, or RGB/RGBA PNG/TIFF/BMP/JPEG read as one plane, "
        "see --channel) or folders of them",
    )
    add_channel_argument(p)
    p.add_argument("--out", required=True, metavar="CAMERA.yaml", help="camera file to write")
    p.add_argument(
        "--camera",
        metavar="START.yaml",
        help="camera file to start from (size must match the frames; a camera section with width_px, height_px, "
        "pixel_pitch_um and fov_deg or focal_length_mm is enough)",
    )
    p.add_argument(
        "--fov",
        type=float,
        metavar="DEG",
        help="instead of --camera or --fov-range: the horizontal field of view, degrees, where it is known (a "
        "lens's focal length over the sensor width, a plate scale times the width); the start camera is the "
        "frames' size with this field, and its solver database is built for it. The way for fields too narrow "
        "for a --fov-range search (under ~2.1 deg)",
    )
    p.add_argument(
        "--fov-range",
        nargs=2,
        type=float,
        metavar=("LO", "HI"),
        help="instead of --camera: the horizontal field of view is searched between LO and HI degrees "
        "(default without --camera: 5 30; the first search of a range builds a cached database, ~35 s for 5-30; "
        "a range whose database would pass 350 MB is refused, naming a narrower one)",
    )
    p.add_argument(
        "--pixel-pitch",
        type=float,
        metavar="UM",
        help="without --camera: pixel width, micrometres (default 5.5; only the written focal_length_mm depends on it)",
    )
    p.add_argument(
        "--pixel-aspect",
        type=float,
        metavar="A",
        help="start value of pixel height / width "
        "(default: the camera file's, or 1); e.g. 2 for interlaced frames stored at half height. Not given: "
        "when fewer than half the frames solve, 2 and 0.5 are tried too and the best kept, with a line",
    )
    p.add_argument(
        "--epoch",
        type=float,
        metavar="YEAR",
        help="when the frames were taken, Julian year (catalogue proper motions; default: the frames' own date, EXIF "
        "DateTimeOriginal or FITS DATE-OBS, where they carry one, else the camera file's epoch_yr); written to the "
        "fitted camera",
    )
    p.add_argument(
        "--catalog",
        choices=("hipparcos", "gaia"),
        help="the catalogue renders of this camera will use (written as catalog.source; default: the camera "
        "file's, or hipparcos): the false stars fitted are the detections it does not explain. gaia: Gaia DR3 to "
        "G = 10 merged with Hipparcos, for cameras that see fainter than Hipparcos is complete (Hp ~ 8-9)",
    )
    p.add_argument(
        "--black-level",
        type=int,
        metavar="ADU",
        help="the level the camera's processor subtracts before clipping at 0 (sensor.black_level_adu), given "
        "instead of fitted; 0: none. In the fitted camera's terms: ADU of the frames as read (after the scale they "
        "carry) above the fitted bias, which is 0 where the darks are crushed, so a datasheet's raw black level "
        "does not carry over. Default: fitted where the frames' background sits at 0 ADU and they lose faint "
        "stars their renders keep (processed frames, e.g. JPEGs of a Raspberry Pi camera)",
    )
    p.add_argument(
        "--processor-blur",
        choices=("auto", "on", "off"),
        default="auto",
        help="whether the camera renders the blur a processor (demosaicing, JPEG, a denoiser) put on the frames "
        "(sensor.processor_blur_px, from their background noise's neighbour correlation; the read-out's noise and PSF "
        "then fitted as before it). auto (default): where a blur is measured, the camera is fitted with and without "
        "it and the one whose renders miss the frames by less is kept (twice the fitting time on processed frames; "
        "results/real-frames/processor-blur); on; off: reported only",
    )
    p.add_argument(
        "--report",
        metavar="DIR",
        help="write the report here: DIR/REPORT.md, DIR/fit.json, DIR/fit.png (default: beside --out, OUT-report/)",
    )


def _run_fit_camera(args: argparse.Namespace) -> int:
    import shlex

    from skygen.real.fit_camera import fit_camera

    command = "skygen fit-camera " + " ".join(shlex.quote(a) for a in (args.argv or []))
    report = args.report or str(Path(args.out).with_suffix("")) + "-report"
    rec = fit_camera(
        args.frames,
        args.out,
        camera=args.camera,
        fov_range=args.fov_range,
        fov_deg=args.fov,
        pixel_pitch_um=args.pixel_pitch,
        pixel_aspect=args.pixel_aspect,
        epoch_yr=args.epoch,
        channel=args.channel,
        catalog=args.catalog,
        black_level=args.black_level,
        processor_blur=args.processor_blur,
        report_dir=report,
        command=command,
        log=lambda m: print(m, file=sys.stderr),
    )
    g, c = rec["geometry"], rec["compare"]
    print(
        f"wrote {args.out}: {len(rec['solved'])} of {len(rec['frames'])} frames solved"
        + (f" ({len(rec['dropped'])} dropped: see above)" if rec["dropped"] else "")
        + f"; field {g['fov_deg']:.4f} deg, aspect {g['aspect']:.4f}, {g['n_matched']} stars at {g['rms_px']:.3f} px "
        f"rms; "
        f"fitted {', '.join(g['fitted'])}"
        + (f", fixed {', '.join(g['fixed'])}" if g["fixed"] else "")
        + f"; in {rec['timing_s']['total_s']:.1f} s"
    )
    print(
        f"renders vs real (medians): background {c['background_adu']['fitted']:.1f} / "
        f"{c['background_adu']['real']:.1f} "
        f"ADU, noise {c['noise_adu']['fitted']:.2f} / {c['noise_adu']['real']:.2f} ADU, detections "
        f"{c['detections']['fitted']:.0f} / {c['detections']['real']:.0f}, star width "
        f"{c['star_sigma_px']['fitted']:.2f} / {c['star_sigma_px']['real']:.2f} px, zero point "
        f"{c['zero_point_mag']['fitted']:.2f} / {c['zero_point_mag']['real']:.2f} mag"
    )
    print(f"report: {report}/REPORT.md")
    print(f"use it:  skygen render --config {args.out} ...   |   fusion predict FRAME... --camera {args.out} --solve")
    return 0


# --------------------------------------------------------------------------- stream
def _add_stream(p: argparse.ArgumentParser) -> None:
    _config_args(p, with_n=False)
    p.add_argument("--kind", choices=("detections", "frames"), default="detections", help="sample kind")
    p.add_argument("--n", type=int, default=10000, help="samples to make (default 10000)")
    p.add_argument("--start", type=int, default=0, help="first sample index (default 0)")
    p.add_argument("--batch", type=int, default=1024, help="detections: samples per vectorised batch")
    p.add_argument("--calibration", help="detector calibration JSON (default: the shipped one for the default camera)")
    p.add_argument(
        "--range",
        action="append",
        metavar="NAME=LO:HI",
        help="per-sample severity range of a corruption (false_stars, dropout, centroid_noise, "
        "magnitude_noise), e.g. --range dropout=0:0.3 (repeatable)",
    )
    p.add_argument("--out", help="also write the detection sets to this HDF5 file (shard table layout)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def _run_stream(args: argparse.Namespace) -> int:
    import json
    import time

    from skygen.config import config_dict
    from skygen.datasets.detection_sets import write_detection_sets
    from skygen.stream.samples import SampleStream, stream_summary

    if args.n < 1:
        raise SkygenError(f"--n {args.n}: need at least 1 sample")
    if args.start < 0:
        raise SkygenError(f"--start {args.start}: the stream index must be >= 0")
    cfg = _load(args)
    ranges = {}
    for text in args.range or []:
        try:
            name, lohi = text.split("=")
            lo, hi = (float(v) for v in lohi.split(":"))
        except ValueError:
            raise SkygenError(f"--range {text!r} must look like NAME=LO:HI, e.g. dropout=0:0.3") from None
        ranges[name] = (lo, hi)
    stream = SampleStream(cfg, args.kind, calibration=args.calibration, level_ranges=ranges)
    t0, c0 = time.perf_counter(), time.process_time()
    if args.kind == "detections":
        batches = [
            stream.batch(range(a, min(a + args.batch, args.start + args.n)))
            for a in range(args.start, args.start + args.n, args.batch)
        ]
    else:
        from skygen.stream.samples import frames_as_batch

        batches = [frames_as_batch([stream.frame(i) for i in range(args.start, args.start + args.n)])]
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    summary = stream_summary(batches)
    summary.update(
        {
            "kind": args.kind,
            "start": args.start,
            "wall_s": wall,
            "samples_per_s": args.n / wall,
            "samples_per_cpu_s": args.n / max(cpu, 1e-9),
        }
    )
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        d, m = summary["detections_per_sample"], summary["detected_mag"]
        print(
            f"{args.n} {args.kind} samples from index {args.start} in {wall:.2f} s: {summary['samples_per_s']:.0f} "
            f"samples/s ({summary['samples_per_cpu_s']:.0f} per CPU-second)"
        )
        print(
            f"detections per sample: mean {d['mean']:.1f}, median {d['median']:.0f}, p10-p90 {d['p10']:.0f}-"
            f"{d['p90']:.0f}, min {d['min']}, max {d['max']}; fewer than 3: {100 * summary['fewer_than_3']:.1f} %"
        )
        print(
            f"detected catalog stars Hp: p10 {m['p10']:.2f}, median {m['median']:.2f}, p90 {m['p90']:.2f}; "
            f"spurious detections {100 * summary['spurious_share']:.2f} %"
        )
    if args.out:
        write_detection_sets(batches, args.out, config_dict(cfg))
        print(f"wrote {args.out}")
    return 0


# --------------------------------------------------------------------------- config
def _add_config(p: argparse.ArgumentParser) -> None:
    _config_args(p)
    p.add_argument("--keys", action="store_true", help="list keys, defaults, allowed ranges and units")
    p.add_argument("--summary", action="store_true", help="also print FOV, detection limit, noise")


def _run_config(args: argparse.Namespace) -> int:
    import yaml

    from skygen.config import config_dict, config_help

    if args.keys:
        print(config_help())
        return 0
    cfg = _load(args)
    print(yaml.safe_dump(config_dict(cfg), sort_keys=False), end="")
    if args.summary:
        from skygen.render.frame import Renderer

        r = Renderer(cfg)
        fx, fy = r.camera.fov_deg
        print(
            f"# FOV {fx:.2f} x {fy:.2f} deg, {r.camera.pixel_scale_arcsec:.1f} arcsec/px, "
            f"detection limit Hp {r.detection_limit_mag:.2f}, rendering to Hp {r.mag_limit:.2f} "
            f"({len(r.sky)} stars), background {r.background_e:.2f} e-/px, noise {r.noise_e():.2f} e-/px"
        )
    return 0


SUBCOMMANDS: dict[str, tuple[dict, Callable, Callable]] = {
    "render": (
        dict(
            help="render a dataset (resumes an interrupted one)",
            description="Render frames into HDF5 shards plus manifest.json. Re-running the same "
            "command resumes; Ctrl-C never leaves a broken shard.",
        ),
        _add_render,
        _run_render,
    ),
    "inspect": (dict(help="counts, splits, star and detection histograms, config summary"), _add_inspect, _run_inspect),
    "preview": (dict(help="PNG grid of frames with detections and true stars"), _add_preview, _run_preview),
    "validate": (dict(help="check schema, shapes, value ranges and checksums"), _add_validate, _run_validate),
    "merge": (
        dict(
            help="combine slices or compatible datasets into one (no data copied)",
            description="Write OUT/manifest.json listing the shards of several dataset folders: "
            "slices of one job-array render, or datasets whose configs differ only in seed, "
            "n_frames or storage options. Incompatible inputs are refused with the differing keys.",
        ),
        _add_merge,
        _run_merge,
    ),
    "catalog": (dict(help="show the catalog, or fetch another one from VizieR (online)"), _add_catalog, _run_catalog),
    "calibrate": (
        dict(
            help="fit the detector emulator of the detections stream",
            description="Fit the detector emulator (skygen.stream.emulator) to the real detector: from a "
            "rendered dataset DIR (its frames and config), or, without DIR, from --frames frames "
            "rendered for --config/--set in their own random streams. The calibration is valid for "
            "that camera, optics, photometry, sensor and detector only; streams refuse it for "
            "any other.",
        ),
        _add_calibrate,
        _run_calibrate,
    ),
    "fit-camera": (
        dict(
            help="fit a camera file to a real sensor from its own star frames",
            description="Solve real star frames (tetra3rs lost-in-space), then fit the camera to all of "
            "them at once: focal length, pixel aspect, principal point and radial distortion (terms the "
            "frames cannot constrain are fixed and named), and from the pixels: bias, gain and read "
            "noise (background mean-variance), sky level, gradient and vignetting, PSF (Gaussian or "
            "Moffat), hot pixels, light fixed on the sensor (a glow: sensor.fixed_sources), a processor's black "
            "level (sensor.black_level_adu, where the frames' darks are crushed to 0), the photometric "
            "zero point (as exposure x throughput), the detector settings and the centroid error solvers "
            "should assume (camera.centroid_sigma_px; its part beyond the renders' own is drawn: "
            "optics.star_jitter_px), a bright-star centroid shift where bright stars are detected farther out "
            "than faint ones or one way across the sensor (camera.bright_shift_px, bright_shift_x_px, "
            "bright_shift_y_px: rendered, and taken off by fusion predict --camera) and the "
            "few-star solvers' match window (camera.match_tol_px) and the centroid error a frame's brightest stars "
            "share (camera.shared_sigma_px, added to the attitude covariance). Writes a camera YAML that "
            "`skygen render --config` and `fusion predict --camera` take. Not `skygen calibrate`, which fits the "
            "detector emulator to a camera already described.",
        ),
        _add_fit_camera,
        _run_fit_camera,
    ),
    "stream": (
        dict(
            help="synthesise training samples on the fly; print throughput and statistics",
            description="Make --n samples of an endless stream (sample i is a pure function of "
            "config, seed, kind and i) and print what a model would see. 'detections' uses the "
            "calibrated detector emulator (no pixels, ~0.1 ms/sample); 'frames' adds the stored-size "
            "image, drawn directly at that size (skygen.render.binned, equal in distribution to `skygen "
            "render`'s), with emulated detections; a config it cannot reproduce renders and detects "
            "like `skygen render` (with a warning).",
        ),
        _add_stream,
        _run_stream,
    ),
    "config": (dict(help="print the resolved config, or every key with --keys"), _add_config, _run_config),
}


def build_parser() -> argparse.ArgumentParser:
    """The parser of every command (imports no torch: ``skygen --help`` stays light)."""
    from skygen import __version__
    from skygen.datasets.shards import SCHEMA_VERSION

    p = argparse.ArgumentParser(
        prog="skygen",
        description="Physically-based star-tracker frame generator writing shareable HDF5 shards.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--version", action="version", version=f"skygen {__version__} (writes schema {SCHEMA_VERSION})")
    sub = p.add_subparsers(dest="command", required=True)
    for name, (texts, add, run) in SUBCOMMANDS.items():
        sp = sub.add_parser(name, **texts)
        add(sp)
        sp.set_defaults(func=run)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[2:] if argv is None else argv[1:])
    try:
        return args.func(args)
    except SkygenError as exc:
        print(f"skygen {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except Terminated:  # before KeyboardInterrupt, of which it is a kind
        print(
            f"\nskygen {args.command}: terminated (SIGTERM); finished shards are kept — run the same command "
            "again to resume.",
            file=sys.stderr,
        )
        return 143
    except KeyboardInterrupt:
        print(
            f"\nskygen {args.command}: interrupted; finished shards are kept — run the same command again to resume.",
            file=sys.stderr,
        )
        return 130
    except BrokenPipeError:  # `skygen inspect DIR | head`: the reader has gone; stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except OSError as exc:  # an unwritable --out, a full disk: one line, not a traceback
        from skygen.runtime import describe_os_error

        print(f"skygen {args.command}: error: {describe_os_error(exc)}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
