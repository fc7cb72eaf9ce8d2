"""``fusion`` command line: thin wrappers over the library functions.

    fusion train --data DIR --out RUNDIR [--config FILE.yaml] [--stream detections|frames] [--resume]
                 [--force] [--pretrained PATH_OR_HUB] [--set key=value ...] [key=value ...]
    fusion evaluate --checkpoint RUNDIR[/best.pt] --data DIR [--split test] [--out DIR] [--allow-overlap]

    fusion robustness --corruption hotpixels --checkpoint CKPT [CKPT ...] --data DIR --out DIR
    fusion timing --checkpoint CKPT --mode both --out FILE.json
    fusion export --checkpoint CKPT --onnx FILE.onnx [--opset 17]
    fusion experiment --preset cpu|gpu|smoke [--out results/PRESET]
    fusion predict FRAME... --checkpoint CKPT [--solve] [--overlay DIR]   (or --camera PRESET.yaml)
    fusion benchmark --data DIR --out DIR [--checkpoint CKPT] [--grid small|full]

Each subcommand is registered in :data:`SUBCOMMANDS` (name -> (help, add_arguments, run)). Errors the project raises
on purpose (:class:`skygen.errors.SkygenError` and subclasses) print one line and return 2, also when raised
inside a DataLoader worker (torch re-raises them with the worker's traceback in the message; only its last
line is printed).

Multi-GPU: ``torchrun --nproc_per_node N -m fusion.cli train ...``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable

from skygen.errors import SkygenError

from . import __version__


# --------------------------------------------------------------------------- train
def _add_train(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", help="(required unless the config sets data.path) skygen dataset folder (sets data.path)")
    p.add_argument("--out", required=False, help="(required) run folder (created; must not hold a finished run "
                   "unless --force, or --resume with more train.epochs to extend it)")
    p.add_argument("--config", help="YAML preset, e.g. configs/paper.yaml, configs/cpu.yaml")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from last.pt; a finished run "
                   "is extended with --resume --set train.epochs=N (N more than it ran)")
    p.add_argument("--force", action="store_true", help="delete the run files in --out and start over")
    p.add_argument("--pretrained", metavar="PATH_OR_HUB",
                   help="ImageNet weights for the image backbone: a file, 'hf-hub:ORG/REPO' or 'timm' "
                        "(default: train from scratch)")
    p.add_argument("--stream", choices=("none", "detections", "frames"),
                   help="train on samples synthesised on the fly from the render config of --data (sets "
                        "stream.kind); validation and test stay on --data's rendered frames")
    p.add_argument("--help-config", action="store_true", help="list every config key with its range and exit")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="set_overrides",
                   help="override one config key, e.g. --set train.epochs=5 (repeatable; as in skygen)")
    p.add_argument("overrides", nargs="*", metavar="key=value",
                   help="more config overrides without --set, e.g. train.epochs=5 labels.k=15")


def _run_train(args: argparse.Namespace) -> int:
    from skygen.configlib import merge_overrides, read_yaml
    from .config import build_config, config_help
    from .train import train
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
        base = read_yaml(Path(args.out) / "config.yaml")    # resume: the run's own resolved config
    else:
        base = read_yaml(args.config) if args.config else {}
    cfg = build_config(merge_overrides(base, overrides))
    train(cfg, args.out, resume=args.resume and not args.force, force=args.force)
    return 0


# --------------------------------------------------------------------------- evaluate
def _add_evaluate(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", required=True, help="(required) best.pt or last.pt of a run, or the run folder "
                   "(its best.pt)")
    p.add_argument("--data", required=True, help="(required) skygen dataset folder")
    p.add_argument("--split", default="test", choices=("train", "val", "test"), help="split to evaluate (default test)")
    p.add_argument("--out", help="folder for eval-<split>.json/.md and confusion-<split>.png (default: the checkpoint's)")
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--workers", type=int, default=0, help="DataLoader workers (default 0: in-process)")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    p.add_argument("--max-frames", type=int, help="evaluate only the first N frames of the split (N >= 1)")
    p.add_argument("--allow-overlap", action="store_true",
                   help="score frames the checkpoint was trained on (refused by default) with a loud warning")


def _run_evaluate(args: argparse.Namespace) -> int:
    from .evaluate import evaluate_checkpoint
    evaluate_checkpoint(args.checkpoint, args.data, args.split, args.out, batch_size=args.batch_size,
                        workers=args.workers, device=args.device, max_frames=args.max_frames,
                        allow_overlap=args.allow_overlap)
    return 0


def _module(name: str) -> tuple[Callable, Callable]:
    """(add_arguments, run) of ``fusion.<name>``, imported only when that subcommand is used."""
    import importlib

    def add(p: argparse.ArgumentParser) -> None:
        importlib.import_module(f"fusion.{name}").add_arguments(p)

    def run(args: argparse.Namespace) -> int:
        return importlib.import_module(f"fusion.{name}").run(args)
    return add, run


SUBCOMMANDS: dict[str, tuple[str, Callable, Callable]] = {
    "train": ("train a model on skygen shards into a run folder", _add_train, _run_train),
    "evaluate": ("evaluate a checkpoint on a split: top-k, angular error, confusion matrix", _add_evaluate,
                 _run_evaluate),
    "robustness": ("accuracy against corruption severity (skygen's registry), one line per checkpoint",
                   *_module("robustness")),
    "timing": ("latency (forward and end-to-end from a raw frame), parameters and FLOPs", *_module("timing")),
    "export": ("export a checkpoint to ONNX and verify it against onnxruntime", *_module("export")),
    "experiment": ("run the paper's tables and the missing experiments; writes REPORT.md",
                   *_module("experiment")),
    "predict": ("detections, the model's top-k regions and (--solve) a full attitude for PNG/TIFF/FITS/.npy frames",
                *_module("predict")),
    "benchmark": ("score attitude solvers (tetra3rs lost-in-space, learned prior + fine stage, ...) on the same "
                  "detections: correct/wrong/refused vs N and corruptions", *_module("benchmark")),
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
        prog="fusion", description="Star-Fusion: coarse lost-in-space boresight classification on skygen shards.",
        epilog="Example: fusion train --data data/sky --out runs/cpu --config configs/cpu.yaml; "
               "fusion evaluate --checkpoint runs/cpu/best.pt --data data/sky --split test")
    parser.add_argument("--version", action="version", version=f"fusion {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (help_text, add, _) in SUBCOMMANDS.items():
        add(sub.add_parser(name, help=help_text, description=help_text))
    return parser


def main(argv: list[str] | None = None) -> int:
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


if __name__ == "__main__":
    sys.exit(main())
