"""Model inputs from skygen shards: frames of a split as :class:`Preprocessor` items, samplers, loaders.

Frames are read only through skygen's reader (:func:`skygen.datasets.shards.open_dataset`), which
opens the HDF5 shards lazily in each process; a :class:`FrameDataset` pickles without
open handles, so DataLoader workers work with the fork, spawn and forkserver start methods.
Training (with an augmentation), evaluation and the experiment runner share this module.

Frames with fewer than two detections are kept (their rows are mostly padding) and
counted: :func:`count_sparse_frames`.

Labels
    One class index per frame (``label``) and, with soft labels, a (K,) target (``soft``);
    with fine regions also ``label_fine``.

Randomness
    The sampler yields ``(j, epoch)`` keys; the augmentation generator of a sample is
    ``numpy.random.default_rng([seed, epoch, frame_index])`` — independent of the worker
    count and of persistent workers, so a resumed run sees the same samples.
"""

from __future__ import annotations

import math
from typing import Callable

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Sampler

from skygen.datasets.shards import Dataset as SkyDataset

from ..errors import DatasetError
from .inputs import FrameGeometry, Preprocessor, Sample

# OpenCV's own thread pool does not survive fork(): a DataLoader worker forked from a process
# whose pool had started deadlocks inside OpenCV. The parallelism here is the DataLoader's
# workers, so OpenCV stays single-threaded in every process that imports this module.
cv2.setNumThreads(1)

# an augmentation: (sample, generator, geometry) -> sample (fusion.train.augment.augment with its config bound)
Augment = Callable[[Sample, np.random.Generator, FrameGeometry], Sample]


def split_positions(ds: SkyDataset, split: str, max_frames: int | None = None) -> np.ndarray:
    """Frame positions of ``split``; a clear error if it holds no frame."""
    pos = ds.indices(split)
    if max_frames is not None:
        pos = pos[:max_frames]
    if len(pos) == 0:
        counts = {s: len(ds.indices(s)) for s in ("train", "val", "test")}
        raise DatasetError(
            f"split {split!r} of dataset {ds.root} holds no frames (frames per split: {counts}); "
            "re-render with output.split_fractions giving it frames, or choose another "
            "data.train_split / data.val_split"
        )
    return pos


def boresight_vectors(ds: SkyDataset, positions: np.ndarray) -> np.ndarray:
    """(N, 3) ICRS boresight unit vectors of the frames at ``positions``."""
    return np.asarray(ds.boresight["unit_vector"][positions], np.float64)


def count_sparse_frames(ds: SkyDataset, positions: np.ndarray) -> int:
    """Frames with fewer than two detections (kept in training, reported)."""
    return int(np.sum(ds.frames["n_detections"][positions] < 2))


def read_detections(ds: SkyDataset, i: int) -> tuple[np.ndarray, ...]:
    """(x_px, y_px, flux_adu, area_px) of frame ``i``, brightest first."""
    det = ds.detections(i)
    order = np.argsort(-np.asarray(det["flux_adu"]), kind="stable")
    return (
        np.asarray(det["x_px"], np.float64)[order],
        np.asarray(det["y_px"], np.float64)[order],
        np.asarray(det["flux_adu"], np.float32)[order],
        np.asarray(det["area_px"], np.int32)[order],
    )


def read_sample(ds: SkyDataset, i: int, geo: FrameGeometry, detections: tuple | None = None) -> Sample:
    """Frame ``i`` as a :class:`Sample` in ADU, detections brightest first."""
    x, y, flux, area = detections if detections is not None else read_detections(ds, i)
    return Sample(
        image=ds.image(i).astype(np.float32),
        x_px=x,
        y_px=y,
        flux_adu=flux,
        area_px=area,
        background_adu=float(ds.frames["background_adu"][i]),
        noise_adu=float(ds.frames["noise_adu"][i]) / geo.factor,
    )


class FrameDataset(torch.utils.data.Dataset):
    """Frames of one split as model inputs. Keys are ``j`` or ``(j, epoch)``; j indexes ``positions``.

    Items are the :meth:`Preprocessor.item` dicts (``image`` (1, H/f, S) float32, ``coords``
    (max_stars, 3) float32, ``mask`` (max_stars,) bool, ``n_detections`` before truncation) plus
    ``label`` int64, ``index`` (frame position in the dataset), ``soft`` (K,) float32 when soft
    targets are given and ``label_fine`` with fine-region labels. ``augment`` (training) is
    applied to each sample with the generator of (seed, epoch, frame). ``keep_brightest`` = N
    (evaluation of few-star frames) keeps the brightest N detection rows and masks the rest;
    the image is left as it is.
    """

    def __init__(
        self,
        ds: SkyDataset,
        positions: np.ndarray,
        labels: np.ndarray,
        *,
        max_stars: int = 6,
        norm_scale_adu: float = 8.0,
        log_flux_offset: float = 3.0,
        soft: np.ndarray | None = None,
        augment: Augment | None = None,
        seed: int = 0,
        fine: np.ndarray | None = None,
        keep_brightest: int | None = None,
    ):
        if len(positions) != len(labels) or (soft is not None and len(soft) != len(labels)):
            raise ValueError("positions, labels and soft targets must have the same length")
        self.ds = ds
        self.positions = np.asarray(positions, np.int64)
        self.labels = np.asarray(labels, np.int64)
        self.soft = None if soft is None else np.asarray(soft, np.float32)
        self.fine = None if fine is None else np.asarray(fine, np.int64)  # fine-region labels (labels.fine_k)
        self.geo = FrameGeometry.from_render_config(ds.config)
        self.pre = Preprocessor(self.geo, max_stars, log_flux_offset, norm_scale_adu)
        self.augment, self.seed = augment, seed
        self.keep_brightest = None if keep_brightest is None else int(keep_brightest)
        self._detections: dict[int, tuple] = {}  # per-process cache: the tables are small, reads are not

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_detections"] = {}
        return state

    def __len__(self) -> int:
        return len(self.positions)

    def sample(self, key) -> Sample:
        """The (augmented, for training) :class:`Sample` behind item ``key``."""
        j, epoch = key if isinstance(key, tuple) else (key, 0)
        i = int(self.positions[j])
        if i not in self._detections:
            self._detections[i] = read_detections(self.ds, i)
        s = read_sample(self.ds, i, self.geo, self._detections[i])
        if self.augment is not None:
            s = self.augment(s, np.random.default_rng([self.seed, epoch, i]), self.geo)
        return s

    def __getitem__(self, key) -> dict:
        j = key[0] if isinstance(key, tuple) else key
        s = self.sample(key)
        item = {**self.pre.item(s), "label": torch.tensor(self.labels[j]), "index": torch.tensor(self.positions[j])}
        if self.keep_brightest is not None:  # a few-star frame: only the brightest N detections, image untouched
            item["mask"][self.keep_brightest :] = False
            item["coords"][self.keep_brightest :] = 0.0
        if self.soft is not None:
            item["soft"] = torch.from_numpy(self.soft[j])
        if self.fine is not None:
            item["label_fine"] = torch.tensor(self.fine[j])
        return item


class EpochSampler(Sampler):
    """Yields ``(j, epoch)`` keys: a seeded permutation per epoch (or the natural order), sharded.

    With ``world > 1`` each rank takes every ``world``-th key. ``pad=True`` (training)
    repeats the first keys so every rank gets the same count, as DDP needs; ``pad=False``
    (evaluation) gives each sample to exactly one rank.
    """

    def __init__(self, n: int, *, shuffle: bool, seed: int = 0, rank: int = 0, world: int = 1, pad: bool = True):
        self.n, self.shuffle, self.seed, self.rank, self.world, self.pad = n, shuffle, seed, rank, world, pad
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _order(self) -> np.ndarray:
        if self.shuffle:
            order = np.random.default_rng([self.seed, self.epoch]).permutation(self.n)
        else:
            order = np.arange(self.n)
        if self.pad and self.world > 1:
            total = math.ceil(self.n / self.world) * self.world
            order = np.concatenate([order, order[: total - self.n]])
        return order[self.rank :: self.world]

    def __iter__(self):
        return iter([(int(j), self.epoch) for j in self._order()])

    def __len__(self) -> int:
        return len(self._order())


def worker_init(worker_id: int) -> None:
    """Per-worker setup: own HDF5 handles, one thread for OpenCV and torch (the workers are the parallelism).

    With the fork start method a worker inherits the parent's open HDF5 handles, which
    must not be shared between processes; a pickle round trip (skygen's reader drops
    open handles when pickled) gives the worker its own, opened lazily on first read.
    """
    import pickle

    import cv2

    cv2.setNumThreads(1)
    torch.set_num_threads(1)
    info = torch.utils.data.get_worker_info()
    if info is not None and isinstance(info.dataset, FrameDataset):
        info.dataset.ds = pickle.loads(pickle.dumps(info.dataset.ds))


def make_loader(
    dataset: FrameDataset,
    batch_size: int,
    *,
    shuffle: bool,
    seed: int = 0,
    workers: int = 0,
    rank: int = 0,
    world: int = 1,
    pad: bool = True,
    start_method: str | None = None,
    pin_memory: bool = False,
) -> DataLoader:
    """A DataLoader over ``dataset`` with an :class:`EpochSampler` (call ``loader.sampler.set_epoch``)."""
    sampler = EpochSampler(len(dataset), shuffle=shuffle, seed=seed, rank=rank, world=world, pad=pad)
    kw = {}
    if workers > 0:
        kw = {"worker_init_fn": worker_init, "persistent_workers": True, "prefetch_factor": 4}
        if start_method:
            import multiprocessing as mp

            kw["multiprocessing_context"] = mp.get_context(start_method)
    return DataLoader(
        dataset,
        batch_size=batch_size,
        sampler=sampler,
        num_workers=workers,
        pin_memory=pin_memory,
        drop_last=False,
        **kw,
    )
