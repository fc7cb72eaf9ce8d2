"""Latency of a model (``fusion timing``): the forward pass alone, and end to end from a raw frame.

Two modes, each after ``warmup`` untimed iterations, then ``iters`` timed ones under
``torch.inference_mode``:

``forward``
    ``model(image, coords, mask)`` on ready-made inputs already on the device — what the
    paper's 18.4 ms (Jetson, FP16, batch 1) measures. On CUDA each iteration is timed with
    CUDA events (``start.record(); model(...); end.record(); end.synchronize()``); on the
    CPU with :func:`time.perf_counter` (monotonic) around the call, which returns only when
    the work is done.
``end2end``
    From the raw full-resolution sensor frame (``uint16`` ADU, rendered once by skygen) to
    class probabilities on the host, each stage timed with :func:`time.perf_counter` and a
    device synchronisation at its end:

    ``detect``               background estimate, threshold, connected components and
                             centroids on the full frame (:func:`skygen.instrument.detect.detect`);
    ``downsample_normalise`` ``cv2.resize(INTER_AREA)`` to the stored size and the log stretch
                             (:meth:`fusion.model.inputs.Preprocessor.image`);
    ``encode_coords``        brightest-first rows, normalised positions, padding and mask
                             (:meth:`fusion.model.inputs.Preprocessor.coords`);
    ``to_device``            stacking the batch and the host-to-device copy;
    ``forward``              the model (the heatmap is rasterised inside it), softmax and the
                             copy of the probabilities back to the host;
    ``heatmap_rasterise``    the heatmap rasterisation alone, timed separately — it is part
                             of ``forward`` and not added to the total.

    ``total`` is timed around the whole chain (not the sum of the stages). A batch of B
    frames is preprocessed frame by frame, as a tracker would.

Precision: ``fp32``, or the model's weights and float inputs cast to ``fp16``/``bf16``
(as a deployed half-precision engine runs; no autocast). Statistics per mode: median,
p90, p99, mean, min, max in milliseconds, and throughput = batch / median latency.

Threads: one torch thread by default (``--threads 1``): the latency of one model on one
core, as a tracker runs it beside its other work on a Jetson-class computer, and a figure
that other jobs on the machine barely move (on a loaded 2-core machine torch's own choice
measured 200 ms per forward against 0.77 ms on one thread). ``--threads N`` uses N,
``--threads 0`` every usable core (torch's own default); the report records the count and how it was
chosen. Where the timed distribution is bimodal (p90 above :data:`BIMODAL_RATIO` times the
median) the machine was busy: a one-line WARNING says so and the report lists it under
``warnings``.

Memory: a ``--batch`` whose input tensors alone would take more than half the memory
available (``MemAvailable`` of ``/proc/meminfo``, or the free memory of the GPU) is refused
before any work, naming the largest batch that fits; running out of memory later is one
line too.

The model comes from a checkpoint (its weights), from a training preset (``--config``:
its architecture with random weights, which time the same), or, with neither, from the
default config: the paper's Star-Fusion with the SwinV2-T image branch. The JSON records
the hardware, library versions and the 1-minute load average before and after the run
(a busy machine inflates every figure).

FLOPs come from :class:`torch.utils.flop_counter.FlopCounterMode` on one image: it counts
matrix multiplications, convolutions and attention (2 FLOPs per multiply-add), not
element-wise work; the JSON gives FLOPs and MACs = FLOPs / 2 side by side, per branch.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from skygen.runtime import hardware, pick_device, usable_cores, write_json

from ..config import FusionConfig, load_config
from ..errors import ConfigError, DatasetError
from ..model.checkpoint import load_checkpoint
from ..model.inputs import Preprocessor, sample_from_table
from ..model.networks import StarFusion, create_model, parameter_counts, resolve_model_config

FORMAT = "fusion-timing"
FORMAT_VERSION = 1
PRECISIONS = {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}
MODES = ("forward", "end2end", "both")
STAGES = ("detect", "downsample_normalise", "encode_coords", "to_device", "forward")
DEFAULT_THREADS = 1
BIMODAL_RATIO = 5.0  # p90 / median above this: the machine was busy, not the model slow
FLOP_NOTE = (
    "FlopCounterMode counts matrix multiplications, convolutions and attention (2 FLOPs per "
    "multiply-add); element-wise work (norms, activations, heatmap exponentials) is not counted. "
    "MACs = FLOPs / 2."
)


# --------------------------------------------------------------------------- the model
@dataclass
class TimedModel:
    model: StarFusion
    cfg: FusionConfig
    source: dict  # where it came from: checkpoint or config
    image_size: int
    max_stars: int
    num_classes: int
    render_config: dict | None  # the skygen config of the training data, when known


def load_timed_model(
    checkpoint: str | Path | None = None,
    config: str | Path | None = None,
    *,
    image_size: int = 256,
    overrides: tuple[str, ...] = (),
) -> TimedModel:
    """The model of a checkpoint (its weights) or of a training config (random weights: timing only).

    With neither, the default config: the paper's Star-Fusion (SwinV2-T image branch).
    """
    if checkpoint is not None and config is not None:
        raise ConfigError(
            "give one of --checkpoint CKPT (a trained model) or --config FILE.yaml "
            "(the architecture of a preset, random weights), not both"
        )
    if checkpoint is not None:
        ckpt = load_checkpoint(checkpoint)
        render = None
        root = (ckpt.dataset or {}).get("root")
        if root and Path(root).is_dir():
            render = _dataset_config(root)
        source = {"checkpoint": str(checkpoint), "checkpoint_mtime": Path(checkpoint).stat().st_mtime}
        return TimedModel(
            ckpt.build_model(), ckpt.fusion_config, source, ckpt.image_size, ckpt.max_stars, ckpt.num_classes, render
        )
    cfg = load_config(config, overrides)
    cfg = replace(cfg, model=resolve_model_config(cfg.model))
    model = create_model(
        cfg.model.name,
        cfg.labels.k,
        cfg.model,
        image_size=image_size,
        fine_classes=cfg.labels.fine_k,
        max_stars=cfg.data.max_stars,
        load_pretrained=False,
    )
    return TimedModel(
        model.eval(),
        cfg,
        {
            "config": str(config) if config else "defaults (the paper's recipe)",
            "overrides": list(overrides),
            "weights": "random (architecture only)",
        },
        image_size,
        cfg.data.max_stars,
        cfg.labels.k,
        None,
    )


def _dataset_config(path: str | Path) -> dict | None:
    from skygen.datasets.shards import open_dataset

    try:
        with open_dataset(path) as ds:
            return dict(ds.config)
    except DatasetError:
        return None


# --------------------------------------------------------------------------- inputs
def random_inputs(
    batch: int, image_size: int, max_stars: int, device: torch.device, dtype: torch.dtype, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inputs of the right shapes and ranges (image in [0, 1), positions in [-1, 1], 4 stars of max_stars)."""
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(batch, 1, image_size, image_size, generator=g)
    coords = torch.rand(batch, max_stars, 3, generator=g) * 2 - 1
    mask = torch.zeros(batch, max_stars, dtype=torch.bool)
    mask[:, : min(4, max_stars)] = True
    return image.to(device, dtype), coords.to(device, dtype), mask.to(device)


def raw_frames(render_config: dict | None, image_size: int, n: int) -> tuple[list[np.ndarray], dict, str]:
    """``n`` full-resolution frames (uint16 ADU) rendered by skygen, with the render config used."""
    from skygen.config import build_config, config_dict
    from skygen.config import load_config as load_render_config
    from skygen.render.frame import Renderer

    if render_config is not None:
        data, source = dict(render_config), "the checkpoint's training dataset (or --data)"
    else:
        data, source = config_dict(load_render_config()), "skygen's default camera"
        width = int(data["camera"]["width_px"])
        if width % image_size:
            raise ConfigError(
                f"end-to-end timing: the default {width} px sensor cannot be downsampled to the "
                f"model's {image_size} px input by an integer factor; pass --data DIR with a "
                "dataset rendered for this model"
            )
        data["output"] = {**data["output"], "image_size_px": image_size}
    data["output"] = {**data["output"], "full_res": True}
    cfg = build_config(data)
    if cfg.output.image_size_px != image_size:
        raise ConfigError(
            f"end-to-end timing: the dataset stores {cfg.output.image_size_px} px images but the model "
            f"takes {image_size} px; pass --data DIR with a dataset rendered for this model"
        )
    renderer = Renderer(cfg)
    frames = [renderer.render(i % cfg.n_frames).image_full for i in range(n)]
    return frames, config_dict(cfg), source


class EndToEnd:
    """The stages between a raw frame and the model's inputs, exactly as the training data was made:
    skygen's detector with the dataset's detection settings, then the model's :class:`Preprocessor`."""

    def __init__(self, render_config: dict, cfg: FusionConfig, max_stars: int):
        from skygen.config import build_config

        self.det = build_config(render_config).detection
        self.pre = Preprocessor.from_configs(render_config, cfg.data, max_stars)
        self.geo = self.pre.geo

    def detect(self, full: np.ndarray) -> dict:
        from skygen.instrument.detect import detect

        return detect(full, self.det.threshold_sigma, self.det.min_area_px, self.det.max_detections)[0]

    def downsample_normalise(self, full: np.ndarray) -> np.ndarray:
        return self.pre.image(self.pre.downsample(full))

    def encode(self, det: dict) -> tuple[np.ndarray, np.ndarray]:
        return self.pre.coords(sample_from_table(det))


# --------------------------------------------------------------------------- timing loops
def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def stats_ms(samples_ms: list[float], batch: int) -> dict:
    a = np.asarray(samples_ms, np.float64)
    med = float(np.median(a))
    return {
        "median_ms": med,
        "p90_ms": float(np.percentile(a, 90)),
        "p99_ms": float(np.percentile(a, 99)),
        "mean_ms": float(a.mean()),
        "min_ms": float(a.min()),
        "max_ms": float(a.max()),
        "std_ms": float(a.std()),
        "n": int(len(a)),
        "throughput_per_s": batch * 1000.0 / med,
        "p90_over_median": float(np.percentile(a, 90)) / med if med > 0 else None,
    }


def time_forward(model: StarFusion, inputs: tuple, device: torch.device, iters: int, warmup: int) -> dict:
    """Latency of ``model(*inputs)``; CUDA events on GPU, perf_counter on CPU."""
    batch = inputs[0].shape[0]
    samples = []
    with torch.inference_mode():
        for _ in range(warmup):
            model(*inputs)
        _sync(device)
        if device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            for _ in range(iters):
                start.record()
                model(*inputs)
                end.record()
                end.synchronize()
                samples.append(start.elapsed_time(end))
            timer = "CUDA events, synchronised after every iteration"
        else:
            for _ in range(iters):
                t0 = time.perf_counter()
                model(*inputs)
                samples.append((time.perf_counter() - t0) * 1000.0)
            timer = "time.perf_counter around each call (CPU work is synchronous)"
    return {**stats_ms(samples, batch), "timer": timer}


def end_to_end_once(
    frames: list[np.ndarray], pre: EndToEnd, model: StarFusion, device: torch.device, dtype: torch.dtype
) -> tuple[dict, np.ndarray]:
    """One pass raw frames -> probabilities; returns per-stage milliseconds and the probabilities."""
    t = [time.perf_counter()]
    dets = [pre.detect(f) for f in frames]
    t.append(time.perf_counter())
    images = [pre.downsample_normalise(f) for f in frames]
    t.append(time.perf_counter())
    rows = [pre.encode(d) for d in dets]
    t.append(time.perf_counter())
    image = torch.from_numpy(np.stack(images)[:, None]).to(device, dtype)
    coords = torch.from_numpy(np.stack([r[0] for r in rows])).to(device, dtype)
    mask = torch.from_numpy(np.stack([r[1] for r in rows])).to(device)
    _sync(device)
    t.append(time.perf_counter())
    probs = torch.softmax(model(image, coords, mask).float(), dim=1).cpu().numpy()
    t.append(time.perf_counter())
    ms = {name: (t[i + 1] - t[i]) * 1000.0 for i, name in enumerate(STAGES)}
    ms["total"] = (t[-1] - t[0]) * 1000.0
    if model.heatmap is not None:
        t0 = time.perf_counter()
        model.heatmap.rasterise(coords, mask)
        _sync(device)
        ms["heatmap_rasterise"] = (time.perf_counter() - t0) * 1000.0
    return ms, probs


def time_end_to_end(
    frames: list[np.ndarray],
    pre: EndToEnd,
    model: StarFusion,
    device: torch.device,
    dtype: torch.dtype,
    iters: int,
    warmup: int,
) -> dict:
    batch = len(frames)
    samples: dict[str, list[float]] = {}
    with torch.inference_mode():
        for _ in range(warmup):
            end_to_end_once(frames, pre, model, device, dtype)
        for _ in range(iters):
            ms, probs = end_to_end_once(frames, pre, model, device, dtype)
            for k, v in ms.items():
                samples.setdefault(k, []).append(v)
    n_det = [len(pre.detect(f)["x_px"]) for f in frames]
    stages = {k: stats_ms(v, batch) for k, v in samples.items() if k != "total"}
    return {
        "total": stats_ms(samples["total"], batch),
        "stages": stages,
        "stage_order": list(STAGES) + (["heatmap_rasterise"] if "heatmap_rasterise" in stages else []),
        "timer": "time.perf_counter per stage, device synchronised at the end of each stage",
        "notes": {
            "detect": "background + threshold + connected components + centroids, full-resolution frame (CPU)",
            "downsample_normalise": "cv2.resize INTER_AREA to the stored size + log stretch (CPU)",
            "encode_coords": "brightest-first rows, normalised positions, padding and mask (CPU)",
            "to_device": "stack the batch, host-to-device copy",
            "forward": "model incl. heatmap rasterisation, softmax, probabilities copied to host",
            "heatmap_rasterise": "timed separately; already inside forward, not added to total",
        },
        "frame": {
            "sensor_px": list(frames[0].shape),
            "dtype": str(frames[0].dtype),
            "detections_per_frame": n_det,
            "probabilities_shape": list(probs.shape),
        },
    }


# --------------------------------------------------------------------------- FLOPs, hardware
def count_flops(model: StarFusion, image_size: int, max_stars: int, device: torch.device, dtype: torch.dtype) -> dict:
    """FLOPs and MACs of one image, in total and per branch (see :data:`FLOP_NOTE`)."""
    from torch.utils.flop_counter import FlopCounterMode

    inputs = random_inputs(1, image_size, max_stars, device, dtype)
    counter = FlopCounterMode(display=False)
    with torch.inference_mode(), counter:
        model(*inputs)
    total = int(counter.get_total_flops())
    by_module = {k: sum(v.values()) for k, v in counter.get_flop_counts().items()}
    root = type(model).__name__
    branch = {b: int(by_module.get(f"{root}.{b}", 0)) for b in ("image", "heatmap", "coords")}
    branch["head"] = int(by_module.get(f"{root}.head", 0)) + int(by_module.get(f"{root}.norm", 0))
    return {
        "per_image_flops": total,
        "per_image_macs": total // 2,
        "per_image_gflops": total / 1e9,
        "per_image_gmacs": total / 2e9,
        "by_branch_flops": branch,
        "by_branch_macs": {k: v // 2 for k, v in branch.items()},
        "note": FLOP_NOTE,
    }


# --------------------------------------------------------------------------- the command
def resolve_threads(threads: int | None) -> tuple[int, str]:
    """(torch threads to use, how they were chosen) for ``--threads`` (None: :data:`DEFAULT_THREADS`;
    0: every usable core, torch's own default)."""
    if threads is None:
        return DEFAULT_THREADS, (
            f"default ({DEFAULT_THREADS}: the latency of one model on one core, as a tracker "
            "runs it; --threads N for more)"
        )
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 0:
        raise ConfigError(f"--threads: {threads}; give 1 or more, or 0 for every usable core")
    if threads == 0:
        return usable_cores(), f"--threads 0: every usable core ({usable_cores()})"
    return threads, f"--threads {threads}"


def available_memory_bytes(device: torch.device) -> int | None:
    """Memory free for new tensors: the GPU's free memory, or ``MemAvailable`` of /proc/meminfo (None if unknown)."""
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def check_batch_memory(batch: int, image_size: int, max_stars: int, device: torch.device, dtype: torch.dtype) -> int:
    """Bytes of one batch's input tensors; ConfigError when they alone would take more than half the memory
    available (the model's activations need at least as much again), naming the largest batch that fits."""
    item = torch.tensor([], dtype=dtype).element_size()
    per_frame = item * (image_size * image_size + max_stars * 3) + max_stars  # image, coords, mask (bool)
    if dtype != torch.float32:
        per_frame += 4 * (image_size * image_size + max_stars * 3)  # made in float32, then cast
    need = batch * per_frame
    free = available_memory_bytes(device)
    if free is not None and need > free / 2:
        fits = max(int(free / 2 // per_frame), 1)
        raise ConfigError(
            f"--batch {batch}: its input tensors alone take {need / 1e9:.1f} GB ({batch} x "
            f"{image_size} x {image_size} images and coordinate rows) but {device} has "
            f"{free / 1e9:.1f} GB available; use a smaller --batch (the inputs of {min(fits, batch - 1)} "
            "frames fill half of it, before the model's own working memory)"
        )
    return need


def _out_of_memory(exc: BaseException) -> bool:
    text = str(exc).lower()
    return isinstance(exc, MemoryError) or "out of memory" in text or "can't allocate memory" in text


def spread_warning(name: str, stats: dict, hw: dict) -> str | None:
    """A one-line WARNING when the timed distribution is bimodal (p90 > :data:`BIMODAL_RATIO` x median)."""
    ratio = stats.get("p90_over_median")
    if ratio is None or ratio <= BIMODAL_RATIO:
        return None
    load = hw.get("load_average_1m")
    load_text = "" if load is None else f"; load average {load:.1f} on {hw.get('usable_cores')} usable cores"
    return (
        f"WARNING: {name} latency is bimodal (median {stats['median_ms']:.2f} ms, p90 {stats['p90_ms']:.2f} ms, "
        f"{ratio:.0f}x the median{load_text}): other work on the machine interrupted the run and the figures "
        "measure the machine, not the model; time again on an idle machine (with --threads 1, the default)"
    )


def busy_warning(hw: dict, threads: int) -> str | None:
    """A one-line WARNING when the machine was busy while timing: the 1-minute load average, before or after
    the run, less the run's own ``threads``, is more work than the cores the run leaves idle can take
    (with half a core of slack)."""
    cores = hw.get("usable_cores") or os.cpu_count() or 1
    loads = [x for x in (hw.get("load_average_1m"), hw.get("load_average_1m_after")) if x is not None]
    other = max(loads) - threads if loads else 0.0  # runnable processes besides this run, at most
    if other <= max(cores - threads, 0) + 0.5:  # other work fits on the idle cores (half a core of slack)
        return None
    return (
        f"WARNING: the machine was busy while timing (load average {max(loads):.1f} on {cores} usable cores, this "
        f"run's {threads} thread(s) included): the figures are inflated by other work; time again on an idle "
        "machine"
    )


def run_timing(
    checkpoint: str | Path | None = None,
    config: str | Path | None = None,
    *,
    device: str = "cpu",
    precision: str = "fp32",
    batch: int = 1,
    iters: int = 100,
    warmup: int = 10,
    mode: str = "both",
    data: str | Path | None = None,
    image_size: int = 256,
    threads: int | None = None,
    overrides: tuple[str, ...] = (),
    warn=None,
) -> dict:
    """Measure the latency of a model; returns the report (the JSON ``fusion timing`` writes).

    ``threads``: torch CPU threads (None: :data:`DEFAULT_THREADS`; 0: every usable core); set for the
    run and restored after it. ``warn`` (default: stderr) receives the bimodality warnings."""
    import sys

    warn = warn or (lambda msg: print(msg, file=sys.stderr))
    if precision not in PRECISIONS:
        raise ConfigError(f"--precision: {precision!r}; expected one of {', '.join(PRECISIONS)}")
    if mode not in MODES:
        raise ConfigError(f"--mode: {mode!r}; expected one of {', '.join(MODES)}")
    if batch < 1 or iters < 1 or warmup < 0:
        raise ConfigError(f"--batch ({batch}) and --iters ({iters}) must be >= 1 and --warmup ({warmup}) >= 0")
    n_threads, threads_note = resolve_threads(threads)
    before = torch.get_num_threads()
    torch.set_num_threads(n_threads)
    try:
        report = _run_timing(
            checkpoint,
            config,
            device=device,
            precision=precision,
            batch=batch,
            iters=iters,
            warmup=warmup,
            mode=mode,
            data=data,
            image_size=image_size,
            overrides=overrides,
        )
    finally:
        torch.set_num_threads(before)
    report["settings"]["threads_chosen_by"] = threads_note
    report["warnings"] = []
    timed = {"forward": report.get("forward"), "end-to-end": (report.get("end2end") or {}).get("total")}
    lines = [spread_warning(name, stats, report["hardware"]) if stats else None for name, stats in timed.items()]
    lines.append(busy_warning(report["hardware"], n_threads))
    for line in lines:
        if line:
            report["warnings"].append(line)
            warn(line)
    return report


def _run_timing(
    checkpoint,
    config,
    *,
    device: str,
    precision: str,
    batch: int,
    iters: int,
    warmup: int,
    mode: str,
    data,
    image_size: int,
    overrides: tuple[str, ...],
) -> dict:
    """:func:`run_timing` once its arguments are checked and the thread count is set."""
    dev, dtype = pick_device(device), PRECISIONS[precision]
    tm = load_timed_model(checkpoint, config, image_size=image_size, overrides=overrides)
    render_config = _dataset_config(data) if data is not None else tm.render_config
    if data is not None and render_config is None:
        raise DatasetError(f"--data {data}: not a readable skygen dataset")
    input_bytes = check_batch_memory(batch, tm.image_size, tm.max_stars, dev, dtype)
    model = tm.model.to(dev)
    b = model.branches
    report = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "model": {
            "name": tm.cfg.model.name,
            "image_backbone": tm.cfg.model.image_backbone if b["image"] else None,
            "coord_encoder": tm.cfg.model.coord_encoder if b["coords"] else None,
            "branches": b,
            "num_classes": tm.num_classes,
            "image_size": tm.image_size,
            "max_stars": tm.max_stars,
            **tm.source,
        },
        "parameters": parameter_counts(model),
        "flops": count_flops(model, tm.image_size, tm.max_stars, dev, torch.float32),
        "settings": {
            "device": str(dev),
            "precision": precision,
            "batch": batch,
            "iters": iters,
            "warmup": warmup,
            "mode": mode,
            "torch_threads": torch.get_num_threads(),
            "input_bytes": input_bytes,
            "precision_note": "fp32"
            if precision == "fp32"
            else f"weights and float inputs cast to {dtype} (no autocast)",
        },
        "hardware": hardware(dev),
    }
    model = model.to(dtype)
    try:
        if mode in ("forward", "both"):
            inputs = random_inputs(batch, tm.image_size, tm.max_stars, dev, dtype)
            report["forward"] = time_forward(model, inputs, dev, iters, warmup)
            del inputs
        if mode in ("end2end", "both"):
            frames, used, source = raw_frames(render_config, tm.image_size, min(batch, 8))
            frames = [frames[i % len(frames)] for i in range(batch)]
            pre = EndToEnd(used, tm.cfg, tm.max_stars)
            e2e = time_end_to_end(frames, pre, model, dev, dtype, iters, warmup)
            e2e["frame"]["source"] = source
            e2e["frame"]["downsample_factor"] = pre.geo.factor
            report["end2end"] = e2e
    except (RuntimeError, NotImplementedError, MemoryError) as exc:
        if _out_of_memory(exc):
            raise ConfigError(
                f"--batch {batch}: out of memory on {dev} ({str(exc).strip().splitlines()[0][:160]}); "
                f"use a smaller --batch"
            ) from None
        if "not implemented" in str(exc).lower() and precision != "fp32":
            raise ConfigError(
                f"--precision {precision} is not supported on {dev} for this model "
                f"({str(exc).splitlines()[0]}); try another precision or device"
            ) from None
        raise
    if hasattr(os, "getloadavg"):  # other work on the machine during the run shows here
        report["hardware"]["load_average_1m_after"] = os.getloadavg()[0]
    return report


def summary_text(r: dict) -> str:
    s, p, f = r["settings"], r["parameters"], r["flops"]
    lines = [
        f"{r['model']['name']} ({r['model']['image_backbone'] or 'no image branch'}), "
        f"{p['total'] / 1e6:.2f} M parameters, {f['per_image_gflops']:.3f} GFLOPs = "
        f"{f['per_image_gmacs']:.3f} GMACs per image; {s['device']} ({r['hardware']['device_name']}), "
        f"{s['precision']}, batch {s['batch']}, {s['iters']} iterations, {s['torch_threads']} torch "
        f"thread{'s' if s['torch_threads'] != 1 else ''}"
    ]
    if "forward" in r:
        fw = r["forward"]
        lines.append(
            f"forward: median {fw['median_ms']:.2f} ms, p90 {fw['p90_ms']:.2f}, p99 {fw['p99_ms']:.2f}; "
            f"{fw['throughput_per_s']:.1f} images/s"
        )
    if "end2end" in r:
        e = r["end2end"]
        parts = ", ".join(f"{k} {e['stages'][k]['median_ms']:.2f}" for k in e["stage_order"])
        lines.append(f"end to end: median {e['total']['median_ms']:.2f} ms ({parts} ms)")
    return "\n".join(lines)


def timing(out: str | Path, log=print, **kw) -> dict:
    """:func:`run_timing` and write the report to ``out`` (JSON, atomically)."""
    from skygen.runtime import check_output_file

    out = Path(out)
    check_output_file(out, "--out", "cpu.json")  # before the run, not after it
    report = run_timing(**kw)
    write_json(out, report)
    log(summary_text(report))
    log(f"wrote {out}")
    return report
