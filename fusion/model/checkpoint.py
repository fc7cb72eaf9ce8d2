"""Checkpoints: one typed schema (:class:`Checkpoint`), loaded once, saved atomically, versioned.

A checkpoint file (``best.pt``, ``last.pt``) is a ``torch.save`` dict that loads with
``torch.load(weights_only=True)`` (tensors and plain Python values only). Its keys are the
fields of :class:`Checkpoint` plus ``format`` = ``"fusion-checkpoint"`` and
``format_version`` = :data:`FORMAT_VERSION`:

``model``
    the model's state dict (unwrapped from DDP).
``config``
    the resolved training config (dict); ``model_name``, ``branches``, ``num_classes`` (K),
    ``image_size`` (stored image columns), ``max_stars``.
``centroids``, ``fine_centroids``
    (K, 3) and (F, 3) or None float64 tensors: the regions (:class:`fusion.model.regions.Regions`).
``render_config``
    the training dataset's resolved skygen config (camera, sensor, detector, stored image
    size): everything applying the model to a new frame needs.
``dataset``, ``train_frame_ids``
    the training dataset (root as an absolute path, dataset_id, schema_version, camera) and
    the uint64 frame identities of its training frames as int64 (empty for a stream-trained
    model), so that evaluation can refuse frames the model has seen.
``versions``
    the library versions that wrote it.
``weights_sha256``
    the sha256 of the weights (:func:`weights_sha256`: every tensor of ``model``, then
    ``centroids`` and ``fine_centroids``, names, dtypes, shapes and bytes in sorted name
    order), computed by :meth:`Checkpoint.save`; :func:`load_checkpoint` recomputes it and
    refuses a file whose weights changed after it was written (a flipped bit scores
    without a word otherwise). Files written before it existed load, with a one-line note.
``content_sha256``
    the sha256 of everything else (:func:`content_sha256`: the configs, the camera's render settings,
    the training state), checked on load like the weights'; files without it are checked for their
    weights only.
``epoch``, ``history``, ``best``, ``finished``, ``optimizer``, ``scheduler``, ``scaler``, ``rng``
    training state: completed epochs (training resumes at this epoch index), metric rows, the
    best-epoch record, whether the run ended, optimiser/schedule/scaler states and generator
    states.

Older files of format version 1 lack some keys (``fine_centroids``, ``render_config``,
``train_frame_ids``, ``dataset``, ``weights_sha256``); :func:`migrate` fills them with None, and the users of
those fields say what to do when they need one. A file of another format version is
refused with one line.
"""

from __future__ import annotations

import hashlib
import io
import platform
import sys
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch

from skygen.runtime import atomic_write_bytes

from ..errors import CheckpointError, ConfigError
from .regions import Regions

FORMAT = "fusion-checkpoint"
FORMAT_VERSION = 1


def versions() -> dict:
    import timm

    from skygen import __version__ as skygen_version

    from .. import __version__

    return {
        "fusion": __version__,
        "skygen": skygen_version,
        "torch": str(torch.__version__),
        "timm": str(timm.__version__),
        "numpy": str(np.__version__),
        "python": platform.python_version(),
    }


#: config keys that no trained weight depends on, so that ``fusion evaluate --set`` may change them on a
#: trained model: the tied views' weighing and the image view's defect cut (the tied image view has no
#: parameters, and the model trains on detections only)
INFERENCE_KEYS = (
    "model.peaks.image_weight",
    "model.peaks.image_weight_stars",
    "model.peaks.image_weight_by",
    "model.peaks.image_weight_unexplained",
    "model.peaks.max_peak_share",
)


@dataclass
class Checkpoint:
    """A fusion checkpoint (see the module docstring for each field). ``source`` (not saved) names
    where it was read from, for messages."""

    model: dict
    config: dict
    centroids: np.ndarray
    num_classes: int
    image_size: int
    max_stars: int
    model_name: str
    branches: dict
    fine_centroids: np.ndarray | None = None
    render_config: dict | None = None
    dataset: dict | None = None
    train_frame_ids: np.ndarray | None = None
    versions: dict = field(default_factory=dict)
    epoch: int = 0
    history: list = field(default_factory=list)
    best: dict = field(default_factory=dict)
    finished: bool = False
    optimizer: dict | None = None
    scheduler: dict | None = None
    scaler: dict | None = None
    rng: dict | None = None
    weights_sha256: str | None = None
    content_sha256: str | None = None
    source: str = field(default="checkpoint", compare=False)

    # ---------------------------------------------------------------- file
    def to_dict(self) -> dict:
        """The dict that is saved (tensors and plain values)."""
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "source"}
        d["centroids"] = torch.from_numpy(np.asarray(self.centroids, np.float64))
        if self.fine_centroids is not None:
            d["fine_centroids"] = torch.from_numpy(np.asarray(self.fine_centroids, np.float64))
        if self.train_frame_ids is not None:
            d["train_frame_ids"] = torch.from_numpy(np.asarray(self.train_frame_ids).view(np.int64))
        d["weights_sha256"] = weights_sha256(d)  # of what is written, whatever the field held
        d["content_sha256"] = content_sha256(d)
        return {"format": FORMAT, "format_version": FORMAT_VERSION, **d}

    @classmethod
    def from_dict(cls, d: dict, source: str = "checkpoint") -> "Checkpoint":
        d = migrate(dict(d), source)

        def arr(t):
            return None if t is None else (t.numpy() if isinstance(t, torch.Tensor) else np.asarray(t))

        try:
            kw = {f.name: d[f.name] for f in fields(cls) if f.name in d and f.name != "source"}
            kw["centroids"] = np.asarray(arr(d["centroids"]), np.float64)
            kw["fine_centroids"] = (
                None if d.get("fine_centroids") is None else np.asarray(arr(d["fine_centroids"]), np.float64)
            )
            kw["train_frame_ids"] = arr(d.get("train_frame_ids"))
            for key in ("num_classes", "image_size", "max_stars", "epoch"):
                kw[key] = int(d.get(key, 0))
            return cls(source=str(source), **kw)
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(
                f"{source}: a fusion checkpoint without a usable {exc} entry; it is damaged or was written by hand"
            ) from None

    def save(self, path: str | Path) -> None:
        """``torch.save`` atomically (a hidden temporary file renamed into place)."""
        buf = io.BytesIO()
        torch.save(self.to_dict(), buf)
        atomic_write_bytes(path, buf.getvalue())

    # ---------------------------------------------------------------- what it holds
    @property
    def regions(self) -> Regions:
        """The regions; fine ones only when the model was trained on them."""
        fine_k = (self.config.get("labels") or {}).get("fine_k")
        return Regions(self.centroids, self.fine_centroids if fine_k else None)

    @property
    def fusion_config(self):
        """The resolved training config as a :class:`fusion.config.FusionConfig`."""
        from ..config import build_config

        try:
            return build_config(self.config)
        except ConfigError as exc:
            raise CheckpointError(f"{self.source}: its config is not valid for this fusion version ({exc})") from None

    def config_differences(self, config: dict) -> dict:
        """Keys that change what a frame looks like whose values differ between this model's training
        data and a dataset rendered with ``config`` (:func:`frame_config_differences`); ``{}`` when they
        agree or when the checkpoint records nothing to compare (only ``camera.*`` for checkpoints
        without ``render_config``)."""
        trained = self.render_config
        if not isinstance(trained, dict):
            camera = (self.dataset or {}).get("camera")
            if camera is None:
                return {}
            trained, config = {"camera": camera}, {"camera": (config or {}).get("camera", {})}
        return frame_config_differences(trained, config)

    def require_render_config(self) -> dict:
        """The skygen render config the model was trained for; a one-line CheckpointError when it lacks one."""
        rc = self.render_config
        if not isinstance(rc, dict) or "camera" not in rc:
            raise CheckpointError(
                f"{self.source}: this checkpoint predates camera data in checkpoints (no "
                "'render_config'); re-train it with this fusion, or pass --dataset DIR (its "
                "training dataset) to take the camera and detector from there"
            )
        return rc

    def with_inference_overrides(self, overrides: list[str] | tuple[str, ...]) -> "Checkpoint":
        """A copy whose config has ``key=value`` ``overrides`` applied, for keys no trained weight depends on
        (:data:`INFERENCE_KEYS`, e.g. how the tied views are weighed); any other key is refused, since the
        weights were trained for its old value."""
        from skygen.configlib import merge_overrides, parse_override

        from ..config import build_config

        for text in overrides:
            key = ".".join(parse_override(text)[0])
            if key not in INFERENCE_KEYS:
                raise ConfigError(
                    f"--set {text}: {key} cannot change on a trained model (its weights were trained with the old "
                    f"value); only {', '.join(INFERENCE_KEYS)} may. Train with it instead: fusion train --set {text}"
                )
        config = merge_overrides(self.config, list(overrides))
        build_config(config)  # the new values checked (range, type, consistency) before any work
        return replace(self, config=config)

    def build_model(self):
        """The model, rebuilt from this checkpoint's own config, with its weights, on the CPU, in eval mode."""
        from .inputs import Preprocessor
        from .networks import create_model

        cfg = self.fusion_config
        rc = self.render_config  # only the pixel-flux view needs the training data's stretch
        pre = None
        if rc is not None and cfg.model.peaks.pixel_flux:
            pre = Preprocessor.from_configs(rc, cfg.data, self.max_stars)
        model = create_model(
            cfg.model.name,
            self.num_classes,
            cfg.model,
            image_size=self.image_size,
            fine_classes=cfg.labels.fine_k,
            max_stars=self.max_stars,
            load_pretrained=False,
            pre=pre,
        )
        load_model_state(model, self)
        return model.eval()


def migrate(d: dict, source: str = "checkpoint") -> dict:
    """A loaded checkpoint dict brought to the current schema of format version 1 (missing keys -> None)."""
    for key in (
        "fine_centroids",
        "render_config",
        "dataset",
        "train_frame_ids",
        "optimizer",
        "scheduler",
        "scaler",
        "rng",
    ):
        d.setdefault(key, None)
    d.setdefault("versions", {})
    d.setdefault("weights_sha256", None)
    d.setdefault("content_sha256", None)
    return d


# ------------------------------------------------------------------------- integrity
def weights_sha256(d: dict) -> str:
    """sha256 of the weights of a checkpoint dict: every tensor of ``d["model"]`` (the state dict), then
    ``d["centroids"]`` and ``d["fine_centroids"]`` when present, each as its name, dtype, shape and bytes, in
    sorted name order (the same digest whatever order the dict was built in, on any machine)."""
    h = hashlib.sha256()
    items = [(f"model.{k}", v) for k, v in sorted((d.get("model") or {}).items())]
    items += [(k, d[k]) for k in ("centroids", "fine_centroids") if d.get(k) is not None]
    for name, value in items:
        t = value.detach().cpu().contiguous() if isinstance(value, torch.Tensor) else torch.as_tensor(np.asarray(value))
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        if t.numel():
            h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def content_sha256(d: dict) -> str:
    """sha256 of everything else a checkpoint dict holds (the configs it rebuilds the model and the camera
    from, the training state a resume continues: optimiser, schedule, scaler, generators, history): every
    key but the two digests, walked in sorted key order, tensors and arrays as dtype, shape and bytes, plain
    values by type and repr. A damaged stored focal length or optimiser moment is caught as a weight is."""
    h = hashlib.sha256()

    def walk(v) -> None:
        if isinstance(v, torch.Tensor):
            t = v.detach().cpu().contiguous()
            h.update(f"T{t.dtype}{tuple(t.shape)}|".encode())
            if t.numel():
                h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
        elif isinstance(v, np.ndarray):
            h.update(f"A{v.dtype}{v.shape}|".encode() + np.ascontiguousarray(v).tobytes())
        elif isinstance(v, dict):
            h.update(b"{")
            for k in sorted(v, key=str):
                h.update(f"{k!r}:".encode())
                walk(v[k])
            h.update(b"}")
        elif isinstance(v, (list, tuple)):
            h.update(b"[")
            for x in v:
                walk(x)
            h.update(b"]")
        else:
            x = v.item() if isinstance(v, np.generic) else v
            h.update(f"{type(x).__name__}:{x!r};".encode())

    walk({k: v for k, v in d.items() if k not in ("weights_sha256", "content_sha256", "format", "format_version")})
    return h.hexdigest()


_NOTED_UNHASHED: set[str] = set()


def verify_weights(d: dict, path: str | Path, note=None) -> None:
    """Refuse (CheckpointError) a checkpoint dict whose weights differ from the sha256 stored at save; a file
    written before checkpoints carried one gets a one-line note (once per file and process) on ``note``
    (default: stderr)."""
    stored = d.get("weights_sha256")
    if stored is None:
        if str(path) not in _NOTED_UNHASHED:
            _NOTED_UNHASHED.add(str(path))
            (note or (lambda m: print(m, file=sys.stderr)))(
                f"note: {path} predates checkpoint checksums (no weights_sha256); its weights cannot be checked "
                "for damage. Training further (--resume) or re-training writes checkpoints that carry one"
            )
        return
    if weights_sha256(d) != stored:
        raise CheckpointError(
            f"{path}: its weights do not match the sha256 stored when it was written (the file "
            "was damaged or edited since); use an intact copy (best.pt or last.pt of the run, a "
            "backup) or train again"
        )
    content = d.get("content_sha256")
    if content is not None and content_sha256(d) != content:
        raise CheckpointError(
            f"{path}: its configs or training state do not match the sha256 stored when it was written (the "
            "file was damaged or edited since: a stored camera or optimiser state would mislead every use); use "
            "an intact copy (best.pt or last.pt of the run, a backup) or train again"
        )


# ------------------------------------------------------------------------- render settings
# the render settings that change what a frame (pixels or detections) looks like; the rest (seed, n_frames,
# attitude.*, output.*, render.*: which frames, how they are stored and on which backend) does not
FRAME_SECTIONS = ("catalog", "camera", "optics", "photometry", "sensor", "corruptions", "detection")
FRAME_KEYS = ("epoch_yr",)
NOT_FRAME_KEYS = (
    "detection.match_radius_px",  # matching detections to true stars (labels), not detection
    "sensor.sampler",
)  # two samplers of the same noise distribution


def changes_frames(key: str) -> bool:
    """Whether the dotted render-config ``key`` changes what a frame looks like (pixels or detections)."""
    return (key in FRAME_KEYS or key.split(".", 1)[0] in FRAME_SECTIONS) and key not in NOT_FRAME_KEYS


def frame_config_differences(trained: dict, other: dict) -> dict:
    """``{dotted key: {"training": value, "data": value}}`` for the render settings that change what a frame
    looks like (:data:`FRAME_SECTIONS`, :data:`FRAME_KEYS`) and differ between two skygen configs. Both are
    first resolved by skygen (a key a config predates takes skygen's default), so a config that merely
    omits a default is not a difference."""
    from skygen.configlib import flatten

    fa, fb = flatten(_resolved(trained)), flatten(_resolved(other))
    missing = "<missing>"
    out = {}
    for k in sorted(k for k in set(fa) | set(fb) if changes_frames(k)):
        a, b = _plain(fa.get(k, missing)), _plain(fb.get(k, missing))
        if a != b:
            out[k] = {"training": None if a == missing else a, "data": None if b == missing else b}
    return out


def _resolved(config: dict) -> dict:
    from skygen.config import build_config, config_dict
    from skygen.errors import SkygenError

    try:
        return config_dict(build_config(config))
    except (SkygenError, TypeError, ValueError):  # a config of another skygen version: compared as written
        return dict(config or {})


def _plain(v):
    return [_plain(x) for x in v] if isinstance(v, (list, tuple)) else v


def _value_text(v) -> str:
    """A config value as it is typed after ``--set key=``: numbers and names plain, lists and null as YAML/JSON."""
    import json

    if isinstance(v, bool) or v is None or isinstance(v, (list, dict)):
        return json.dumps(v)
    return f"{v:g}" if isinstance(v, float) else str(v)


def differences_text(diffs: dict, limit: int = 6) -> str:
    """``sensor.exposure_s 0.1 -> 0.05, ...`` (training -> data) for a message."""
    parts = [f"{k} {_value_text(v['training'])} -> {_value_text(v['data'])}" for k, v in list(diffs.items())[:limit]]
    return ", ".join(parts) + (f" and {len(diffs) - limit} more" if len(diffs) > limit else "")


def differences_warning(what: str, diffs: dict, checkpoint: str) -> str:
    """The one-line warning for data rendered with other frame settings than ``checkpoint``'s training data:
    the keys (training -> data) and the ``--set`` overrides that render data as the model was trained."""
    fix = " ".join(f"--set {k}={_value_text(v['training'])}" for k, v in list(diffs.items())[:6])
    more = " ..." if len(diffs) > 6 else ""
    return (
        f"WARNING: {what} was rendered with other frame settings than the training data of {checkpoint} "
        f"({differences_text(diffs)}; training -> this data): the model may score near chance on it. Render "
        f"it with the training settings (skygen render {fix}{more}) unless the difference is intended, "
        "as in a robustness study"
    )


def resolve_checkpoint(path: str | Path) -> Path:
    """``path`` itself, or ``path/best.pt`` when ``path`` is a run folder."""
    path = Path(path)
    if path.is_dir():
        if (path / "best.pt").is_file():
            return path / "best.pt"
        raise CheckpointError(
            f"{path} is a folder without best.pt; give a run folder written by `fusion train` "
            "or a checkpoint file (best.pt, last.pt)"
        )
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu", note=None) -> Checkpoint:
    """Load and check a fusion checkpoint (a file, or a run folder: its best.pt); CheckpointError otherwise,
    also when its weights no longer match the sha256 stored at save (:func:`verify_weights`; ``note``
    receives the one-line note for a file that predates checksums, default stderr).

    Parameters
    ----------
    path : str or Path
        ``best.pt`` / ``last.pt`` written by ``fusion train``, or its run folder.
    map_location : str or torch.device
        Where the tensors go (``"cpu"`` by default).
    note : callable, optional
        Receives one line for a checkpoint written before weights carried a sha256.

    Returns
    -------
    Checkpoint
        Typed: the training config, the render config of its data, the regions (unit-vector
        centroids, ICRS), the weights; ``build_model()`` gives the network in eval mode.

    Raises
    ------
    fusion.errors.CheckpointError
        Not a file of ``fusion train``, a newer format, truncated, or weights that fail their sha256.
    """
    path = resolve_checkpoint(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found")
    try:
        d = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises many types for damaged or foreign files
        # torch's own text ("re-running with weights_only=False will likely succeed") is advice to run
        # untrusted code: not repeated
        raise CheckpointError(
            f"{path}: not a readable checkpoint ({type(exc).__name__}); it may be truncated, "
            "not a PyTorch file, or from another program"
        ) from None
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        found = d.get("format") if isinstance(d, dict) else type(d).__name__
        raise CheckpointError(
            f"{path}: not a fusion checkpoint (format={found!r}); give a best.pt or last.pt written by `fusion train`"
        )
    if d.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format version {d.get('format_version')} is not supported "
            f"(this fusion reads version {FORMAT_VERSION}); use the fusion version that wrote it"
        )
    verify_weights(d, path, note)
    return Checkpoint.from_dict(d, str(path))


def load_model_state(model: torch.nn.Module, ckpt: Checkpoint) -> None:
    """Load ``ckpt.model`` strictly; a mismatch becomes a CheckpointError naming model and K."""
    try:
        model.load_state_dict(ckpt.model)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        raise CheckpointError(
            f"{ckpt.source} does not fit this model: it holds model {ckpt.model_name!r} "
            f"with K={ckpt.num_classes} and branches {ckpt.branches} "
            f"({first[1].strip() if len(first) > 1 else first[0]})"
        ) from None


def load_matching_state(model: torch.nn.Module, path: str | Path) -> dict:
    """Warm start: copy every parameter/buffer of checkpoint ``path`` whose name and shape match.

    Returns ``{"loaded": [...], "skipped": [...], "head_blocks": [...]}`` (names). Refuses a
    checkpoint that matches nothing (wrong file). When the checkpoint's branches are a subset of
    this model's (a geometry run warm-starting the three-branch model), its fusion LayerNorm and
    head are copied block by block into the columns of those branches and the columns of the new
    branches start at zero (their LayerNorm scale at 1, shift at 0): the warm model starts from the
    geometry model's scores and the new branches enter as they learn, instead of the head starting
    from random. Only the copied branches' head columns stand in ``head_blocks``; with another
    number of (fine) regions the head is simply trained from scratch.
    """
    ckpt = load_checkpoint(path)
    own = model.state_dict()
    take = {k: v for k, v in ckpt.model.items() if k in own and own[k].shape == v.shape}
    if not take:
        raise CheckpointError(
            f"model.init_from={path}: no parameter of that checkpoint fits this model "
            f"(it holds {ckpt.model_name!r} with branches {ckpt.branches})"
        )
    blocks, shared = _head_blocks(model, ckpt, own, take)
    take.update(blocks)
    model.load_state_dict(take, strict=False)
    return {"loaded": sorted(take), "skipped": sorted(k for k in own if k not in take), "head_blocks": shared}


def _branch_slices(model) -> list[tuple[str, slice]]:
    """The fused feature's column range of each branch, in StarFusion.forward_features order."""
    out, at = [], 0
    for name in ("image", "heatmap", "coords"):
        b = getattr(model, name, None)
        if b is not None:
            out.append((name, slice(at, at + b.out_dim)))
            at += b.out_dim
    return out


def _head_blocks(model, ckpt: Checkpoint, own: dict, take: dict) -> tuple[dict, list[str]]:
    """norm.weight/bias and head.weight of ``model`` built from ``ckpt``'s, and the shared branches
    (sorted), where its branches are a strict subset of the model's, each of those branches loaded
    whole; ({}, []) where that does not hold."""
    keys = ("norm.weight", "norm.bias", "head.weight")
    if not all(k in own and k in ckpt.model for k in keys) or any(k in take for k in keys):
        return {}, []
    src_on = [n for n, on in (ckpt.branches or {}).items() if on]
    order = _branch_slices(model)
    slices = dict(order)
    if not src_on or set(src_on) == set(slices) or not set(src_on) <= set(slices):
        return {}, []
    for name in src_on:  # every tensor of a shared branch must have been copied
        if any(k.startswith(name + ".") and k not in take for k in own):
            return {}, []
    src_dim = ckpt.model["norm.weight"].shape[0]
    if sum(slices[n].stop - slices[n].start for n in src_on) != src_dim:
        return {}, []
    hw = ckpt.model["head.weight"]
    if hw.shape[0] != own["head.weight"].shape[0]:
        return {}, []
    nw, nb = torch.ones_like(own["norm.weight"]), torch.zeros_like(own["norm.bias"])
    w = torch.zeros_like(own["head.weight"])
    at = 0
    for name, sl in order:  # the source's columns are its branches in the same order
        if name not in src_on:
            continue
        n = sl.stop - sl.start
        nw[sl] = ckpt.model["norm.weight"][at : at + n]
        nb[sl] = ckpt.model["norm.bias"][at : at + n]
        w[:, sl] = hw[:, at : at + n]
        at += n
    return {"norm.weight": nw, "norm.bias": nb, "head.weight": w}, sorted(src_on)
