"""Checkpoints and run folders: atomic writes, self-describing checkpoints, clear refusals.

A checkpoint (``best.pt``, ``last.pt``) is a ``torch.save`` dict that loads with
``torch.load(weights_only=True)`` (tensors and plain Python values only):

``format``/``format_version``
    ``"fusion-checkpoint"``, 1.
``model``, ``optimizer``, ``scheduler``, ``scaler``
    state dicts (the model unwrapped from DDP).
``epoch``
    completed epochs; training resumes at this epoch index.
``config``
    the resolved training config (dict); ``centroids`` (K, 3) float64 tensor; ``num_classes``,
    ``image_size`` (stored image pixels), ``max_stars``, ``model_name``, ``branches``.
``history``, ``best``, ``finished``
    metrics rows so far, the best-epoch record, whether the run ended.
``rng``
    torch / CUDA / NumPy / Python generator states; ``versions`` of the libraries; ``dataset``
    (root as an absolute path, dataset_id, schema_version, camera config) the run was trained on;
    ``train_frame_ids`` (int64 tensor, the uint64 frame identities of the training frames,
    see :mod:`skygen.identity`) so that evaluation can refuse frames the model has seen;
    ``render_config`` the training dataset's resolved skygen config (camera, sensor, detector,
    stored image size): what applying the model to a new frame needs (:func:`render_config_of`).

Every file is written to a hidden temporary name in the same folder and ``os.replace``d,
so a crash never leaves a half-written ``best.pt`` that looks whole.
"""

from __future__ import annotations

import io
import json
import os
import platform
import random
from pathlib import Path

import numpy as np
import torch

from .errors import CheckpointError, RunFolderError

FORMAT = "fusion-checkpoint"
FORMAT_VERSION = 1
RUN_FILES = ("best.pt", "last.pt", "metrics.csv", "config.yaml", "centroids.npy", "summary.json",
             "loss_curves.png", "lr_schedule.png")


def versions() -> dict:
    import timm
    from skygen import __version__ as skygen_version
    from . import __version__
    return {"fusion": __version__, "skygen": skygen_version, "torch": str(torch.__version__),
            "timm": str(timm.__version__), "numpy": str(np.__version__), "python": platform.python_version()}


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def atomic_save_numpy(path: str | Path, array: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, array)
    atomic_write_bytes(path, buf.getvalue())


def save_checkpoint(path: str | Path, state: dict) -> None:
    """``torch.save`` ``state`` (plus format fields) atomically."""
    buf = io.BytesIO()
    torch.save({"format": FORMAT, "format_version": FORMAT_VERSION, **state}, buf)
    atomic_write_bytes(path, buf.getvalue())


def resolve_checkpoint(path: str | Path) -> Path:
    """``path`` itself, or ``path/best.pt`` when ``path`` is a run folder."""
    path = Path(path)
    if path.is_dir():
        if (path / "best.pt").is_file():
            return path / "best.pt"
        raise CheckpointError(f"{path} is a folder without best.pt; give a run folder written by `fusion train` "
                              "or a checkpoint file (best.pt, last.pt)")
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Load and check a fusion checkpoint (a file, or a run folder: its best.pt); CheckpointError otherwise."""
    path = resolve_checkpoint(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises many types for damaged or foreign files
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(exc).__name__}: {exc}); "
                              "it may be truncated or from another program") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        found = ckpt.get("format") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise CheckpointError(f"{path}: not a fusion checkpoint (format={found!r}); give a best.pt or last.pt "
                              "written by `fusion train`")
    if ckpt.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {ckpt.get('format_version')} is not supported "
                              f"(this fusion reads version {FORMAT_VERSION}); use the fusion version that wrote it")
    return ckpt


def load_model_state(model: torch.nn.Module, ckpt: dict, source: str = "checkpoint") -> None:
    """Load ``ckpt['model']`` strictly; a mismatch becomes a CheckpointError naming model and K."""
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        raise CheckpointError(f"{source} does not fit this model: it holds model {ckpt.get('model_name')!r} "
                              f"with K={ckpt.get('num_classes')} and branches {ckpt.get('branches')} "
                              f"({first[1].strip() if len(first) > 1 else first[0]})") from None


def load_matching_state(model: torch.nn.Module, path: str | Path) -> dict:
    """Warm start: copy every parameter/buffer of checkpoint ``path`` whose name and shape match.

    Returns ``{"loaded": [...], "skipped": [...]}`` (names). Refuses a checkpoint that
    matches nothing (wrong file), and one whose class count or centroids would make the
    head meaningless is the caller's business (the head is simply skipped when K differs).
    """
    ckpt = load_checkpoint(path)
    own = model.state_dict()
    take = {k: v for k, v in ckpt["model"].items() if k in own and own[k].shape == v.shape}
    if not take:
        raise CheckpointError(f"model.init_from={path}: no parameter of that checkpoint fits this model "
                              f"(it holds {ckpt.get('model_name')!r} with branches {ckpt.get('branches')})")
    model.load_state_dict(take, strict=False)
    return {"loaded": sorted(take), "skipped": sorted(k for k in own if k not in take)}


def render_config_of(ckpt: dict, source: str | Path = "checkpoint") -> dict:
    """The skygen render config (camera, sensor, detector, storage) a checkpoint's model was trained for.

    Checkpoints written before this key existed get a one-line CheckpointError saying how to proceed.
    """
    rc = ckpt.get("render_config")
    if not isinstance(rc, dict) or "camera" not in rc:
        raise CheckpointError(f"{source}: this checkpoint predates camera data in checkpoints (no 'render_config'); "
                              "re-train it with this fusion, or pass --dataset DIR (its training dataset) to take "
                              "the camera and detector from there")
    return rc


def rng_state() -> dict:
    np_state = np.random.get_state()
    state = {"torch": torch.get_rng_state(), "numpy_keys": torch.from_numpy(np_state[1].astype(np.int64)),
             "numpy_pos": int(np_state[2]), "python": _py_state_to_list(random.getstate())}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(("MT19937", state["numpy_keys"].numpy().astype(np.uint32), state["numpy_pos"], 0, 0.0))
    random.setstate((state["python"][0], tuple(state["python"][1]), state["python"][2]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _py_state_to_list(s: tuple) -> list:
    return [s[0], list(s[1]), s[2]]


# --------------------------------------------------------------------------- run folders
def run_status(out: Path) -> tuple[str, dict | None]:
    """('empty'|'unfinished'|'finished', last checkpoint or None) of a run folder."""
    last = out / "last.pt"
    if (out / "summary.json").exists():
        return "finished", None
    if last.exists():
        return "unfinished", load_checkpoint(last)
    return "empty", None


def prepare_run_folder(out: str | Path, *, resume: bool, force: bool, epochs: int | None = None) -> dict | None:
    """Create or check ``out``; returns the checkpoint to resume from (or None for a fresh run).

    A finished run is never overwritten without ``force``; an unfinished one needs
    ``resume`` (continue) or ``force`` (start over). A finished run is *extended* by
    ``resume`` with more ``epochs`` than it ran (its summary.json is then removed).
    ``force`` deletes only the files a run writes (:data:`RUN_FILES`), nothing else in the folder.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise RunFolderError(f"--out {out} exists and is not a folder")
    status, last = run_status(out) if out.is_dir() else ("empty", None)
    if force:
        for name in RUN_FILES:
            (out / name).unlink(missing_ok=True)
        status, last = "empty", None
    elif status == "finished" and resume and (out / "last.pt").exists():
        last = load_checkpoint(out / "last.pt")
        if epochs is None or epochs <= int(last["epoch"]):
            raise RunFolderError(f"{out} holds a finished run ({last['epoch']} epochs); to train it further pass "
                                 f"--resume --set train.epochs=N with N > {last['epoch']} (or --force to start over)")
        (out / "summary.json").unlink()
        status = "unfinished"
    elif status == "finished":
        verb = "resume" if resume else "overwrite"
        raise RunFolderError(f"{out} holds a finished run (summary.json); refusing to {verb} it. "
                             "Choose another --out, --resume --set train.epochs=N to extend it, or --force to "
                             "delete it and train again")
    elif status == "unfinished" and not resume:
        raise RunFolderError(f"{out} holds an unfinished run (last.pt at epoch {last['epoch']}); pass --resume to "
                             "continue it, or --force to start over")
    elif status == "empty" and resume:
        raise RunFolderError(f"--resume: {out} holds no last.pt to resume from; drop --resume to start a new run")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunFolderError(f"cannot create run folder {out}: {exc.strerror or exc}") from None
    return last


def write_json(path: str | Path, data: dict) -> None:
    atomic_write_text(path, json.dumps(data, indent=1, sort_keys=True, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
