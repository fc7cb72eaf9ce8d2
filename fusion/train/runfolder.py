"""Run folders of ``fusion train``: what a run writes, when a folder may be (re)used, resume state.

A run folder holds :data:`RUN_FILES`. A finished run (``summary.json``) is never
overwritten without ``--force``; an unfinished one (``last.pt``, no summary) needs
``--resume`` (continue) or ``--force`` (start over); a finished run is *extended* by
``--resume`` with more epochs than it ran. ``--force`` deletes only the files a run writes,
nothing else in the folder. A training holds the folder's lock (:class:`RunFolderLock`) from
before these checks until it ends, so a second training into a busy folder is refused before
it reads or deletes anything.
"""

from __future__ import annotations

import csv
import io
import random
from pathlib import Path

import numpy as np
import torch
import yaml

from skygen.configlib import flatten
from skygen.lock import FolderLock
from skygen.runtime import atomic_write_text

from ..config import FusionConfig, build_config, config_dict
from ..errors import CheckpointError, RunFolderError
from ..model.checkpoint import Checkpoint, load_checkpoint

RUN_FILES = (
    "best.pt",
    "last.pt",
    "metrics.csv",
    "config.yaml",
    "centroids.npy",
    "summary.json",
    "loss_curves.png",
    "lr_schedule.png",
)
METRIC_COLUMNS = (
    "epoch",
    "train_loss",
    "train_top1",
    "val_loss",
    "val_top1",
    "val_top3",
    "val_top5",
    "lr",
    "epoch_time_s",
    "best",
)
# keys a resumed run may change (where the data lives, how it is loaded, how long it runs)
RESUMABLE_KEYS = ("data.path", "train.workers", "train.progress", "train.device", "train.threads", "train.epochs")


def rng_state() -> dict:
    np_state = np.random.get_state()
    state = {
        "torch": torch.get_rng_state(),
        "numpy_keys": torch.from_numpy(np_state[1].astype(np.int64)),
        "numpy_pos": int(np_state[2]),
        "python": _py_state_to_list(random.getstate()),
    }
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
def run_status(out: Path) -> tuple[str, Checkpoint | None]:
    """('empty'|'unfinished'|'finished', last checkpoint or None) of a run folder."""
    last = out / "last.pt"
    if (out / "summary.json").exists():
        return "finished", None
    if last.exists():
        return "unfinished", load_checkpoint(last)
    return "empty", None


class RunFolderLock:
    """The lock of run folder ``out`` (:class:`skygen.lock.FolderLock`, "fusion train"): one training
    writes a run folder at a time; a second is refused with one line naming the first.

    The folder is created for the lock; :meth:`release` removes it again if it was created here
    and the run left nothing in it (a refused ``--resume`` into a new name leaves no folder)."""

    def __init__(self, out: Path):
        self.out = out
        if out.exists() and not out.is_dir():
            raise RunFolderError(f"--out {out} exists and is not a folder")
        self.created = not out.exists()
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RunFolderError(f"cannot create run folder {out}: {exc.strerror or exc}") from None
        try:
            self.lock = FolderLock(out, what="fusion train").acquire()
        except BaseException:
            self._remove_if_new()
            raise

    def release(self) -> None:
        self.lock.release()
        self._remove_if_new()

    def _remove_if_new(self) -> None:
        if self.created:
            try:
                self.out.rmdir()  # only when empty
            except OSError:
                pass


def lock_run_folder(out: str | Path) -> RunFolderLock:
    """Create ``out`` if needed and hold its lock (see :class:`RunFolderLock`)."""
    return RunFolderLock(Path(out))


def prepare_run_folder(out: str | Path, *, resume: bool, force: bool, epochs: int | None = None) -> Checkpoint | None:
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
        if epochs is None or epochs <= int(last.epoch):
            raise RunFolderError(
                f"{out} holds a finished run ({last.epoch} epochs); to train it further pass "
                f"--resume --set train.epochs=N with N > {last.epoch} (or --force to start over)"
            )
        (out / "summary.json").unlink()
        status = "unfinished"
    elif status == "finished":
        verb = "resume" if resume else "overwrite"
        raise RunFolderError(
            f"{out} holds a finished run (summary.json); refusing to {verb} it. "
            "Choose another --out, --resume --set train.epochs=N to extend it, or --force to "
            "delete it and train again"
        )
    elif status == "unfinished" and not resume:
        raise RunFolderError(
            f"{out} holds an unfinished run (last.pt at epoch {last.epoch}); pass --resume to "
            "continue it, or --force to start over"
        )
    elif status == "empty" and resume:
        raise RunFolderError(f"--resume: {out} holds no last.pt to resume from; drop --resume to start a new run")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunFolderError(f"cannot create run folder {out}: {exc.strerror or exc}") from None
    return last


def write_metrics_csv(path: Path, history: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=METRIC_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for row in history:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    atomic_write_text(path, buf.getvalue())


def write_config_yaml(path: Path, cfg: FusionConfig) -> None:
    init = (
        f"image backbone initialised from {cfg.model.pretrained}"
        if cfg.model.pretrained
        else "image backbone trained from scratch (model.pretrained: null)"
    )
    text = f"# resolved fusion training config ({init})\n" + yaml.safe_dump(
        config_dict(cfg), sort_keys=False, default_flow_style=None
    )
    atomic_write_text(path, text)


def check_resume_config(cfg: FusionConfig, ckpt: Checkpoint) -> FusionConfig:
    """The checkpoint's config, with only :data:`RESUMABLE_KEYS` taken from ``cfg``; other differences raise."""
    saved, asked = flatten(ckpt.config), flatten(config_dict(cfg))
    diff = sorted(k for k in set(saved) | set(asked) if saved.get(k) != asked.get(k) and k not in RESUMABLE_KEYS)
    if diff:
        details = ", ".join(f"{k}: {saved.get(k)!r} -> {asked.get(k)!r}" for k in diff[:8])
        raise CheckpointError(
            f"--resume: the config differs from the one the run was started with ({details}); "
            "resume takes the run's config.yaml (only data.path and train.workers/progress/device "
            "may change): drop those overrides, or start a new run (--force or another --out)"
        )
    data = ckpt.config
    for key in RESUMABLE_KEYS:
        section, name = key.split(".")
        data[section][name] = getattr(getattr(cfg, section), name)
    return build_config(data)
