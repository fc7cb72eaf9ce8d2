"""ONNX export (``fusion export``), verified against onnxruntime before the file appears.

The graph takes the model's own inputs, with a dynamic batch axis ``batch``:

``image``   float32 (batch, 1, S, S) — the stored-size frame after the log stretch of
            :func:`fusion.data.normalise_image` (only when the image branch is on);
``coords``  float32 (batch, max_stars, 3) — ``[x, y, log_flux]`` rows of
            :func:`fusion.data.encode_detections`;
``mask``    bool (batch, max_stars) — True for real detections, False for padding
            (``coords`` and ``mask`` only when the heatmap or coordinate branch is on;
            ``--mask-dtype float32`` takes 0/1 floats instead, for runtimes that reject
            boolean inputs);

and returns ``logits`` float32 (batch, K); apply a softmax for class probabilities. The
heatmap is rasterised inside the graph, so preprocessing stops at the coordinate rows.

Exporters: ``legacy`` (TorchScript-based ``torch.onnx.export(dynamo=False)``, default) at
opset 17 suits the TensorRT of JetPack 5 / 6.0; ``dynamo`` (``torch.export``-based) is the
newer path (opset 18 and up). Both were checked on SwinV2-T and on the geometry-only model of
``configs/cpu.yaml`` (transformer set encoder, roll canonicalisation, 1000 fine regions;
``tests/test_fusion_export.py``). A model with fine regions sums them per region with
``ScatterElements(reduction="add")``, which the legacy exporter has from opset 16 on.

Verification: onnxruntime (CPU) runs the file on random inputs at batch 1 and 3 (the
dynamic axis) and on real-looking inputs — a dark frame with Gaussian stars at the
positions of the coordinate rows, brightest first, or real frames of ``--data`` — and the
largest absolute difference of the logits from PyTorch's is reported. Above the tolerance
(1e-4 by default) the export fails with :class:`ExportError` and no file is left behind:
the graph is written to a hidden temporary name in the same folder and renamed only after
it passed.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from skygen.runtime import atomic_path, hardware, write_json

from ..errors import ConfigError, FusionError
from ..model.checkpoint import load_checkpoint
from ..model.networks import StarFusion

DEFAULT_TOLERANCE = 1e-4
EXPORTERS = ("legacy", "dynamo")
MASK_DTYPES = ("bool", "float32")


class ExportError(FusionError):
    """The exported graph could not be built or does not reproduce the PyTorch model."""


class ExportWrapper(nn.Module):
    """The model with exactly the inputs its branches use, in the order ``image, coords, mask``.

    ``mask_dtype="float32"`` takes the mask as 0/1 floats (True where > 0.5) for runtimes
    that reject boolean graph inputs.
    """

    def __init__(self, model: StarFusion, mask_dtype: str = "bool"):
        super().__init__()
        if mask_dtype not in MASK_DTYPES:
            raise ConfigError(f"--mask-dtype: {mask_dtype!r}; expected one of {', '.join(MASK_DTYPES)}")
        self.model, self.mask_dtype = model, mask_dtype
        b = model.branches
        self.uses_image, self.uses_geometry = b["image"], b["heatmap"] or b["coords"]

    @property
    def input_names(self) -> list[str]:
        return (["image"] if self.uses_image else []) + (["coords", "mask"] if self.uses_geometry else [])

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        named = dict(zip(self.input_names, inputs))
        mask = named.get("mask")
        if mask is not None and mask.dtype != torch.bool:
            mask = mask > 0.5
        return self.model(named.get("image"), named.get("coords"), mask)

    def feeds(self, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``inputs`` (bool mask) in this graph's input types."""
        out = {k: np.ascontiguousarray(inputs[k]) for k in self.input_names}
        if "mask" in out and self.mask_dtype == "float32":
            out["mask"] = out["mask"].astype(np.float32)
        return out


# --------------------------------------------------------------------------- inputs
def random_inputs(batch: int, image_size: int, max_stars: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Uniform image in [0, 1), positions in [-1, 1], a random number of real rows per sample."""
    n = rng.integers(0, max_stars + 1, size=batch)
    mask = np.arange(max_stars)[None, :] < n[:, None]
    coords = rng.uniform(-1, 1, size=(batch, max_stars, 3)).astype(np.float32) * mask[..., None]
    return {
        "image": rng.random((batch, 1, image_size, image_size), dtype=np.float32),
        "coords": coords.astype(np.float32),
        "mask": mask,
    }


def star_like_inputs(batch: int, image_size: int, max_stars: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A dark, slightly noisy frame with Gaussian stars at the rows' positions, brightest first (2..max rows)."""
    image = np.abs(rng.normal(0.02, 0.01, size=(batch, 1, image_size, image_size))).astype(np.float32)
    coords = np.zeros((batch, max_stars, 3), np.float32)
    mask = np.zeros((batch, max_stars), bool)
    yy, xx = np.mgrid[0:image_size, 0:image_size]
    for b in range(batch):
        n = int(rng.integers(min(2, max_stars), max_stars + 1))
        xy = rng.uniform(-0.95, 0.95, size=(n, 2))
        log_flux = np.sort(rng.uniform(-0.5, 2.0, size=n))[::-1]
        coords[b, :n, :2], coords[b, :n, 2], mask[b, :n] = xy, log_flux, True
        for (x, y), f in zip(xy, log_flux):
            u, v = (x + 1) * image_size / 2 - 0.5, (y + 1) * image_size / 2 - 0.5
            amp = min(1.0, 0.2 + 0.3 * f)
            image[b, 0] += (amp * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 1.2**2))).astype(np.float32)
    return {"image": np.clip(image, 0, 1), "coords": coords, "mask": mask}


def dataset_inputs(data: str | Path, cfg, n: int = 4) -> dict[str, np.ndarray]:
    """The first ``n`` test frames of a skygen dataset, preprocessed as in training."""
    from skygen.datasets.shards import open_dataset

    from ..model.shards import FrameDataset, split_positions

    with open_dataset(data) as ds:
        pos = split_positions(ds, "test")[:n]
        d = cfg.data
        fd = FrameDataset(
            ds,
            pos,
            np.zeros(len(pos), np.int64),
            max_stars=d.max_stars,
            norm_scale_adu=d.norm_scale_adu,
            log_flux_offset=d.log_flux_offset,
        )
        items = [fd[j] for j in range(len(pos))]
    return {k: torch.stack([it[k] for it in items]).numpy() for k in ("image", "coords", "mask")}


# --------------------------------------------------------------------------- export and verify
def _torch_logits(wrapper: ExportWrapper, feeds: dict[str, np.ndarray]) -> np.ndarray:
    with torch.inference_mode():
        return wrapper(*[torch.from_numpy(feeds[k]) for k in wrapper.input_names]).numpy()


def onnxruntime_logits(path: str | Path, feeds: dict[str, np.ndarray]) -> np.ndarray:
    """Run the ONNX file on CPU with onnxruntime; ``feeds`` may hold unused inputs."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    names = [i.name for i in sess.get_inputs()]
    return sess.run(None, {k: feeds[k] for k in names})[0]


def verify(
    path: str | Path,
    wrapper: ExportWrapper,
    checks: dict[str, dict[str, np.ndarray]],
    tolerance: float = DEFAULT_TOLERANCE,
) -> dict:
    """Max |onnxruntime - PyTorch| of the logits for each named input set; ExportError above ``tolerance``."""
    diffs = {}
    for name, inputs in checks.items():
        feeds = wrapper.feeds(inputs)
        ref = _torch_logits(wrapper, feeds)
        try:
            got = onnxruntime_logits(path, feeds)
        except Exception as exc:  # onnxruntime raises its own types (bad shapes, missing kernels)
            raise ExportError(
                f"onnxruntime cannot run the exported graph on the '{name}' inputs "
                f"(batch {len(ref)}): {_first_line(exc)}; no file was written"
            ) from None
        if got.shape != ref.shape:
            raise ExportError(f"{name}: onnxruntime returned logits of shape {got.shape}, PyTorch {ref.shape}")
        diffs[name] = float(np.max(np.abs(got.astype(np.float64) - ref))) if ref.size else 0.0
        if not np.isfinite(diffs[name]):
            diffs[name] = float("inf")
    worst = max(diffs, key=diffs.get)
    result = {
        "max_abs_diff": diffs[worst],
        "by_check": diffs,
        "tolerance": tolerance,
        "passed": diffs[worst] <= tolerance,
    }
    if not result["passed"]:
        raise ExportError(
            f"ONNX graph does not match PyTorch: max |difference| of the logits {diffs[worst]:.3g} on "
            f"'{worst}' inputs exceeds the tolerance {tolerance:g} (all checks: "
            + ", ".join(f"{k} {v:.3g}" for k, v in diffs.items())
            + "); try the other --exporter or another --opset; no file was written"
        )
    return result


@contextlib.contextmanager
def _quiet():
    """Silence the exporters' warnings and progress logs (failures still raise)."""
    loggers = [logging.getLogger(n) for n in ("torch.onnx", "onnxscript", "torch.export", "torch._dynamo")]
    levels = [lg.level for lg in loggers]
    try:
        for lg in loggers:
            lg.setLevel(logging.CRITICAL)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        for lg, lvl in zip(loggers, levels):
            lg.setLevel(lvl)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0] if text else ''}"


def _check_writable(path: Path, option: str, example: str) -> None:
    """Refuse an output file that cannot be written before the minutes of export and verification."""
    from skygen.runtime import check_output_file

    check_output_file(path, option, example, error=ExportError)


def written_opset(path: str | Path) -> int:
    """The default-domain opset version recorded in an ONNX file."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    return next(int(o.version) for o in model.opset_import if o.domain in ("", "ai.onnx"))


def _export(wrapper: ExportWrapper, example: dict[str, np.ndarray], path: Path, opset: int, exporter: str) -> None:
    feeds = wrapper.feeds(example)
    args = tuple(torch.from_numpy(feeds[k]) for k in wrapper.input_names)
    names = wrapper.input_names
    with _quiet():
        if exporter == "legacy":
            torch.onnx.export(
                wrapper,
                args,
                str(path),
                dynamo=False,
                opset_version=opset,
                input_names=names,
                output_names=["logits"],
                do_constant_folding=True,
                dynamic_axes={**{k: {0: "batch"} for k in names}, "logits": {0: "batch"}},
            )
        else:
            batch = torch.export.Dim("batch", min=1, max=4096)
            prog = torch.onnx.export(
                wrapper,
                args,
                dynamo=True,
                opset_version=opset,
                input_names=names,
                output_names=["logits"],
                verbose=False,
                dynamic_shapes=(tuple({0: batch} for _ in names),),
            )  # one entry: *inputs
            prog.save(str(path), external_data=False)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def export_onnx(
    checkpoint: str | Path,
    onnx_path: str | Path,
    *,
    opset: int = 17,
    exporter: str = "legacy",
    tolerance: float = DEFAULT_TOLERANCE,
    data: str | Path | None = None,
    seed: int = 0,
    mask_dtype: str = "bool",
    report: str | Path | None = None,
) -> dict:
    """Export ``checkpoint`` to ``onnx_path``, verify it with onnxruntime, then move it into place.

    ``report``: also write the returned record there as strict JSON (it names the hardware the
    verification ran on, :func:`skygen.runtime.hardware`). Both output paths are checked for
    writing before the export starts.
    """
    if exporter not in EXPORTERS:
        raise ConfigError(f"--exporter: {exporter!r}; expected one of {', '.join(EXPORTERS)}")
    if not 7 <= opset <= 23:
        raise ConfigError(f"--opset: {opset} is outside 7..23 (17 suits TensorRT 8.5+ on JetPack 5/6.0)")
    if not tolerance > 0:
        raise ConfigError(f"--tolerance: {tolerance}; give a positive number")
    t0 = time.perf_counter()
    ckpt = load_checkpoint(checkpoint)
    model, cfg = ckpt.build_model(), ckpt.fusion_config
    if model.fine_classes and exporter == "legacy" and opset < 16:
        raise ConfigError(
            f"--opset {opset}: this model sums its {model.fine_classes} fine regions per region "
            "(ScatterElements with reduction=add), which ONNX has from opset 16; use --opset 16 or later"
        )
    if model.image is not None and model.image.rotates_tokens:
        raise ExportError(
            f"{checkpoint}: its image branch reads the image's peaks (model.image_backbone="
            f"{cfg.model.image_backbone}), whose "
            "per-frame median, clipped noise and top-k peak selection have no ONNX export here; "
            "run it in PyTorch (fusion predict, fusion time) or export a model with a CNN image "
            "branch or none. No file was written."
        )
    wrapper = ExportWrapper(model.float(), mask_dtype)
    size, stars = ckpt.image_size, ckpt.max_stars
    rng = np.random.default_rng(seed)
    checks = {
        "random_batch1": random_inputs(1, size, stars, rng),
        "random_batch3": random_inputs(3, size, stars, rng),
        "star_like_batch2": star_like_inputs(2, size, stars, rng),
    }
    if data is not None:
        checks["dataset_frames"] = dataset_inputs(data, cfg)
    out = Path(onnx_path)
    _check_writable(out, "--onnx", "model.onnx")
    if report is not None:
        _check_writable(Path(report), "--report", "export.json")
    with atomic_path(out) as tmp:
        try:
            # traced at batch 3: torch.export specialises a batch of 1 to a constant in places
            # (the transformer's key-padding mask), and the graph then refuses other batch sizes
            _export(wrapper, checks["random_batch3"], tmp, opset, exporter)
            import onnx

            onnx.checker.check_model(str(tmp))
        except Exception as exc:  # exporters raise many types; the user needs the reason, not the trace
            raise ExportError(
                f"ONNX export of {checkpoint} failed with the {exporter} exporter at opset {opset}: {_first_line(exc)}"
            ) from None
        got = written_opset(tmp)
        if got != opset:
            raise ExportError(
                f"the {exporter} exporter wrote opset {got}, not the requested {opset} (it cannot convert "
                f"this graph down); use --exporter legacy for opset {opset}, or --opset {got} if your "
                "runtime supports it"
            )
        result = verify(tmp, wrapper, checks, tolerance)
    import onnxruntime

    r = {
        "onnx": str(out),
        "checkpoint": str(checkpoint),
        "exporter": exporter,
        "opset": opset,
        "inputs": {k: _shape(k, size, stars) for k in wrapper.input_names},
        "input_types": {
            k: ("bool" if k == "mask" and mask_dtype == "bool" else "float32") for k in wrapper.input_names
        },
        "outputs": {"logits": ["batch", model.num_classes]},
        "model": ckpt.model_name,
        "branches": model.branches,
        "verification": result,
        "bytes": out.stat().st_size,
        "sha256": _sha256(out),
        "onnxruntime": onnxruntime.__version__,
        "torch": str(torch.__version__),
        "hardware": hardware(torch.device("cpu")),
        "time_s": time.perf_counter() - t0,
    }
    if report is not None:
        write_json(report, r)
    return r


def _shape(name: str, size: int, stars: int) -> list:
    return {"image": ["batch", 1, size, size], "coords": ["batch", stars, 3], "mask": ["batch", stars]}[name]


def summary_text(r: dict) -> str:
    v = r["verification"]
    ins = ", ".join(f"{k} {tuple(s)}" for k, s in r["inputs"].items())
    return (
        f"wrote {r['onnx']} ({r['bytes'] / 1e6:.1f} MB, {r['exporter']} exporter, opset {r['opset']}); inputs {ins}; "
        f"output logits {tuple(r['outputs']['logits'])}; onnxruntime {r['onnxruntime']} vs PyTorch: max abs "
        f"difference {v['max_abs_diff']:.2e} (tolerance {v['tolerance']:g})"
    )


# --------------------------------------------------------------------------- command line
