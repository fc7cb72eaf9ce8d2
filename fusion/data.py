"""The input pipeline: skygen shards -> (image, coordinates, mask, label) tensors.

Frames are read only through skygen's reader (:func:`skygen.io.open_dataset`), which
opens the HDF5 shards lazily in each process; a :class:`FrameDataset` pickles without
open handles, so DataLoader workers work with the fork, spawn and forkserver start methods.

Image branch input
    The stored frame (S x S, ADU) mapped to [0, 1] by a fixed log stretch,
    ``x = log1p(max(adu - bias, 0) / s) / log1p((2**bits - 1 - bias) / s)`` with the
    dataset's ``sensor.bias_adu`` and ``sensor.bit_depth`` and ``s = data.norm_scale_adu``
    (8 ADU: the faint stars a tracker relies on stay visible next to saturated ones). One
    channel, shape (1, S, S); the model replicates it to 3 channels when it loads ImageNet
    weights.

Coordinate input (the explicit ordering/padding convention the paper asks for)
    Detections sorted by ``flux_adu`` descending (stable: ties keep skygen's order), the
    first ``max_stars`` kept, one row per star with features
    ``[x, y, log10(1 + flux_adu) - log_flux_offset]`` where ``x = (x_px + 0.5) / (W / 2) - 1``
    and ``y = (y_px + 0.5 - H / 2) / (W / 2)``: the sensor's outer pixel *edges* map to -1
    and +1 in x (the convention of ``torch.nn.functional.grid_sample(align_corners=False)``),
    the sensor centre to 0, and y uses the same scale (a non-square sensor spans
    ``[-H/W, H/W]`` in y), so distances and angles are preserved. Rows
    beyond the detected stars are zeros with ``mask = False``. The heatmap branch renders the
    same rows (see :mod:`fusion.heatmap`).

Frames with fewer than two detections are kept (their rows are mostly padding) and
counted: :func:`count_sparse_frames`.

Labels
    One class index per frame (``label``) and, with soft labels, a (K,) target (``soft``).

Randomness
    The sampler yields ``(j, epoch)`` keys; the augmentation generator of a sample is
    ``numpy.random.default_rng([seed, epoch, frame_index])`` — independent of the worker
    count and of persistent workers, so a resumed run sees the same samples.
"""

from __future__ import annotations

import math
import os

import numpy as np
import torch
from torch.utils.data import DataLoader, Sampler

from skygen.io import Dataset as SkyDataset

from .augment import FrameGeometry, Sample, augment
from .config import AugConfig
from .errors import DatasetError

COORD_FEATURES = ("x", "y", "log_flux")


def split_positions(ds: SkyDataset, split: str, max_frames: int | None = None) -> np.ndarray:
    """Frame positions of ``split``; a clear error if it holds no frame."""
    pos = ds.indices(split)
    if max_frames is not None:
        pos = pos[:max_frames]
    if len(pos) == 0:
        counts = {s: len(ds.indices(s)) for s in ("train", "val", "test")}
        raise DatasetError(f"split {split!r} of dataset {ds.root} holds no frames (frames per split: {counts}); "
                           "re-render with output.split_fractions giving it frames, or choose another "
                           "data.train_split / data.val_split")
    return pos


def boresight_vectors(ds: SkyDataset, positions: np.ndarray) -> np.ndarray:
    """(N, 3) ICRS boresight unit vectors of the frames at ``positions``."""
    return np.asarray(ds.boresight["unit_vector"][positions], np.float64)


def count_sparse_frames(ds: SkyDataset, positions: np.ndarray) -> int:
    """Frames with fewer than two detections (kept in training, reported)."""
    return int(np.sum(ds.frames["n_detections"][positions] < 2))


def normalise_image(adu: np.ndarray, geo: FrameGeometry, scale_adu: float) -> np.ndarray:
    """The documented log stretch of stored ADU to [0, 1] (values above the ADC range exceed 1)."""
    top = math.log1p((geo.max_adu - geo.bias_adu) / scale_adu)
    x = np.log1p(np.maximum(np.asarray(adu, np.float32) - geo.bias_adu, 0.0) / scale_adu) / top
    return x.astype(np.float32)


def encode_detections(sample: Sample, geo: FrameGeometry, max_stars: int,
                      log_flux_offset: float) -> tuple[np.ndarray, np.ndarray]:
    """(max_stars, 3) coordinate rows and (max_stars,) mask; ``sample`` must be sorted brightest first."""
    n = min(sample.n, max_stars)
    coords = np.zeros((max_stars, len(COORD_FEATURES)), np.float32)
    mask = np.zeros(max_stars, bool)
    coords[:n, 0], coords[:n, 1] = geo.normalised(sample.x_px[:n], sample.y_px[:n])
    coords[:n, 2] = np.log10(1.0 + np.maximum(sample.flux_adu[:n], 0.0)) - log_flux_offset
    mask[:n] = True
    return coords, mask


def read_detections(ds: SkyDataset, i: int) -> tuple[np.ndarray, ...]:
    """(x_px, y_px, flux_adu, area_px) of frame ``i``, brightest first."""
    det = ds.detections(i)
    order = np.argsort(-np.asarray(det["flux_adu"]), kind="stable")
    return (np.asarray(det["x_px"], np.float64)[order], np.asarray(det["y_px"], np.float64)[order],
            np.asarray(det["flux_adu"], np.float32)[order], np.asarray(det["area_px"], np.int32)[order])


def read_sample(ds: SkyDataset, i: int, geo: FrameGeometry, detections: tuple | None = None) -> Sample:
    """Frame ``i`` as a :class:`Sample` in ADU, detections brightest first."""
    x, y, flux, area = detections if detections is not None else read_detections(ds, i)
    return Sample(image=ds.image(i).astype(np.float32), x_px=x, y_px=y, flux_adu=flux, area_px=area,
                  background_adu=float(ds.frames["background_adu"][i]),
                  noise_adu=float(ds.frames["noise_adu"][i]) / geo.factor)


class FrameDataset(torch.utils.data.Dataset):
    """Frames of one split as model inputs. Keys are ``j`` or ``(j, epoch)``; j indexes ``positions``.

    Items are dicts: ``image`` (1, S, S) float32, ``coords`` (max_stars, 3) float32,
    ``mask`` (max_stars,) bool, ``label`` int64, ``soft`` (K,) float32 when soft targets are
    given, ``index`` (frame position in the dataset) and ``n_detections`` (before truncation).
    """

    def __init__(self, ds: SkyDataset, positions: np.ndarray, labels: np.ndarray, *, max_stars: int = 6,
                 norm_scale_adu: float = 8.0, log_flux_offset: float = 3.0, soft: np.ndarray | None = None,
                 aug: AugConfig | None = None, seed: int = 0, fine: np.ndarray | None = None):
        if len(positions) != len(labels) or (soft is not None and len(soft) != len(labels)):
            raise ValueError("positions, labels and soft targets must have the same length")
        self.ds = ds
        self.positions = np.asarray(positions, np.int64)
        self.labels = np.asarray(labels, np.int64)
        self.soft = None if soft is None else np.asarray(soft, np.float32)
        self.fine = None if fine is None else np.asarray(fine, np.int64)   # fine-region labels (labels.fine_k)
        self.geo = FrameGeometry.from_render_config(ds.config)
        self.max_stars, self.norm_scale_adu, self.log_flux_offset = max_stars, norm_scale_adu, log_flux_offset
        self.aug, self.seed = aug, seed
        self._detections: dict[int, tuple] = {}   # per-process cache: the tables are small, reads are not

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
        if self.aug is not None:
            s = augment(s, self.aug, np.random.default_rng([self.seed, epoch, i]), self.geo)
        return s

    def __getitem__(self, key) -> dict:
        j = key[0] if isinstance(key, tuple) else key
        s = self.sample(key)
        coords, mask = encode_detections(s, self.geo, self.max_stars, self.log_flux_offset)
        item = {"image": torch.from_numpy(normalise_image(s.image, self.geo, self.norm_scale_adu)[None]),
                "coords": torch.from_numpy(coords), "mask": torch.from_numpy(mask),
                "label": torch.tensor(self.labels[j]), "index": torch.tensor(self.positions[j]),
                "n_detections": torch.tensor(s.n)}
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
        return order[self.rank::self.world]

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


def make_loader(dataset: FrameDataset, batch_size: int, *, shuffle: bool, seed: int = 0, workers: int = 0,
                rank: int = 0, world: int = 1, pad: bool = True, start_method: str | None = None,
                pin_memory: bool = False) -> DataLoader:
    """A DataLoader over ``dataset`` with an :class:`EpochSampler` (call ``loader.sampler.set_epoch``)."""
    sampler = EpochSampler(len(dataset), shuffle=shuffle, seed=seed, rank=rank, world=world, pad=pad)
    kw = {}
    if workers > 0:
        kw = {"worker_init_fn": worker_init, "persistent_workers": True, "prefetch_factor": 4}
        if start_method:
            import multiprocessing as mp
            kw["multiprocessing_context"] = mp.get_context(start_method)
    return DataLoader(dataset, batch_size=batch_size, sampler=sampler, num_workers=workers,
                      pin_memory=pin_memory, drop_last=False, **kw)


def default_workers() -> int:
    """A sensible worker count for this machine: the usable cores minus one for the trainer."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:
        n = os.cpu_count() or 1
    return max(n - 1, 0)
