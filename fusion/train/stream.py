"""Training on skygen's sample streams: a torch ``IterableDataset`` of ready batches.

``fusion train --data DIR --stream detections|frames`` trains on samples synthesised on
the fly from the render configuration of dataset ``DIR`` (same camera, sensor and
detector; the stream's own seed space, so no sample is ever a frame of ``DIR``), and
validates and tests on ``DIR``'s rendered splits: every reported figure is on frames the
real renderer and detector made.

Determinism and resume
    An epoch is ``stream.samples_per_epoch`` samples (rounded down to whole batches). Step
    ``s`` of epoch ``e`` takes stream indices
    ``(e * steps + s) * batch + rank * per_rank + [0, per_rank)``: a pure function of the
    step, so a run resumed at an epoch boundary continues exactly, DDP ranks never share a
    sample, and DataLoader workers (worker ``w`` makes steps ``s = w mod workers``, which
    the DataLoader returns round-robin, i.e. in step order) change nothing.

``--stream frames`` draws each image at the stored size (``stream.frames_renderer=binned``,
:mod:`skygen.render.binned`: equal in distribution to render-then-downsample) with detections from the
calibrated emulator, or renders full frames (``full``); both hand the same stored-size uint16
image to the same :class:`fusion.model.inputs.Preprocessor`.

Batches are the same dicts :class:`fusion.model.shards.FrameDataset` items collate to
(``coords``, ``mask``, ``label``, ``index``, ``n_detections``, ``soft``; ``image`` for
the ``frames`` kind), made by the same :class:`fusion.model.inputs.Preprocessor`, so the
model and the training step do not know where a batch came from. One exception, for speed on a
GPU (``stream.image_transfer``): a ``frames`` batch may carry its stored uint16 ADU
(``image_adu``, half the bytes of float32 between processes) and the stretch constants
(``image_stretch``) in place of ``image``; :func:`fusion.model.inference.batch_inputs` stretches
them on the training device, with the Preprocessor's formula.

Corruption-aware training: ``stream.dropout``, ``stream.false_stars``,
``stream.centroid_noise`` and ``stream.magnitude_noise`` are ``[lo, hi]`` ranges; each
sample draws its severities uniformly in them (skygen's registry code and units).

Few-star training: a share ``stream.few_prob`` of the samples keeps only its brightest N
detections (after the corruptions, so false stars compete for the slots), N drawn uniformly
in the integers ``stream.few_stars = [lo, hi]``: the frames a lost-in-space solver cannot
solve (few stars in the field, a short exposure, a bright Moon) are where a learned prior
must work. The cut is a pure function of (stream seed, sample index).

Brightness: ``stream.brightness_mag = [lo, hi]`` shifts every flux of a sample by one offset
drawn in that range (magnitudes): a real camera's exposure, gain and atmospheric extinction
are never exactly the render config's, and the coordinate rows carry absolute log flux.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from skygen import hashrng
from skygen.config import build_config as build_render_config
from skygen.stream.samples import RANGED, SampleStream

from ..errors import ConfigError
from ..model.inputs import Preprocessor
from ..model.regions import Regions, assign, soft_targets


def stream_render_config(dataset_config: dict, seed: int, render_backend: str | None = None, device: str | None = None):
    """The dataset's render config with the stream's seed (a different seed space than the
    dataset's) and, optionally, the torch renderer on ``device`` for the frames."""
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in dataset_config.items()}
    data["seed"] = int(seed)
    if render_backend:
        data.setdefault("render", {})
        data["render"] = {**data["render"], "backend": render_backend}
        if render_backend == "torch" and device:
            data["render"]["device"] = device
    return build_render_config(data)


def level_ranges(scfg) -> dict:
    return {name: tuple(getattr(scfg, name)) for name in RANGED}


def few_star_limits(seed: int, index: np.ndarray, prob: float, lo: int, hi: int) -> np.ndarray | None:
    """Per-sample detection limit of few-star training (a huge number where a sample is not cut);
    None when ``prob`` is 0."""
    if prob <= 0:
        return None
    key = hashrng.stream_key(seed, "fusion/few_stars")
    cut = hashrng.uniform(key, index, 0) < prob
    n = lo + np.minimum((hashrng.uniform(key, index, 1) * (hi - lo + 1)).astype(np.int64), hi - lo)
    return np.where(cut, n, np.iinfo(np.int64).max)


def brightness_offsets(seed: int, index: np.ndarray, lo: float, hi: float) -> np.ndarray | None:
    """Per-sample log10 flux offsets of ``stream.brightness_mag`` (None when the range is [0, 0])."""
    if lo == 0 and hi == 0:
        return None
    u = hashrng.uniform(hashrng.stream_key(seed, "fusion/brightness"), index, 0)
    return (-0.4 * (lo + (hi - lo) * u)).astype(np.float32)


@dataclass(frozen=True)
class _DataSettings:
    """The ``data.*`` values the preprocessor reads (a stream is built from them, not from a whole config)."""

    max_stars: int
    log_flux_offset: float
    norm_scale_adu: float


class StreamBatches(torch.utils.data.IterableDataset):
    """One epoch of ready batches from a skygen stream (see the module docstring)."""

    def __init__(
        self,
        dataset_config: dict,
        kind: str,
        centroids: np.ndarray,
        *,
        seed: int,
        batch: int,
        steps: int,
        rank: int = 0,
        world: int = 1,
        max_stars: int = 6,
        log_flux_offset: float = 3.0,
        norm_scale_adu: float = 8.0,
        soft_kappa: float | None = None,
        ranges: dict | None = None,
        calibration: str | None = None,
        device: str | None = None,
        render_backend: str | None = None,
        fine_centroids: np.ndarray | None = None,
        few_prob: float = 0.0,
        few_stars: tuple[int, int] = (3, 8),
        brightness_mag: tuple[float, float] = (0.0, 0.0),
        frames_renderer: str = "binned",
        adu_images: bool = False,
    ):
        if steps < 1:
            raise ConfigError(
                f"stream.samples_per_epoch gives {steps} steps of {batch * world} samples; raise it "
                "to at least one global batch"
            )
        self.config, self.kind = dataset_config, kind
        self.centroids = np.asarray(centroids, np.float64)
        self.fine_centroids = None if fine_centroids is None else np.asarray(fine_centroids, np.float64)
        self.seed, self.batch, self.steps, self.rank, self.world = seed, batch, steps, rank, world
        self.max_stars, self.log_flux_offset, self.norm_scale_adu = max_stars, log_flux_offset, norm_scale_adu
        self.soft_kappa, self.ranges, self.calibration = soft_kappa, ranges or {}, calibration
        self.pre = Preprocessor.from_configs(dataset_config, _DataSettings(max_stars, log_flux_offset, norm_scale_adu))
        self.geo = self.pre.geo
        self.device, self.render_backend, self.frames_renderer = device, render_backend, frames_renderer
        self.few_prob, self.few_stars = float(few_prob), (int(few_stars[0]), int(few_stars[1]))
        self.brightness_mag = (float(brightness_mag[0]), float(brightness_mag[1]))
        self.adu_images = bool(adu_images)
        self.epoch = 0
        self._stream = None
        # fail early (config, calibration, detectability) in the main process, not in a worker
        self.stream()

    @classmethod
    def from_config(
        cls, cfg, dataset_config: dict, regions: Regions, *, rank: int = 0, world: int = 1, device=None
    ) -> "StreamBatches":
        """The training stream of a resolved :class:`fusion.config.FusionConfig` (``stream.*``, ``data.*``,
        ``labels.*``) for a dataset's render config; ``device`` is used by ``stream.render_backend=torch``."""
        sc, tc = cfg.stream, cfg.train
        on_gpu = device is not None and torch.device(device).type == "cuda"
        return cls(
            dataset_config,
            sc.kind,
            regions.coarse,
            seed=tc.seed if sc.seed is None else sc.seed,
            batch=tc.batch_size // world,
            steps=sc.samples_per_epoch // tc.batch_size,
            rank=rank,
            world=world,
            max_stars=cfg.data.max_stars,
            log_flux_offset=cfg.data.log_flux_offset,
            norm_scale_adu=cfg.data.norm_scale_adu,
            soft_kappa=cfg.labels.kappa if cfg.labels.soft_labels else None,
            ranges=level_ranges(sc),
            calibration=sc.calibration,
            fine_centroids=regions.fine if cfg.labels.fine_k else None,
            few_prob=sc.few_prob,
            few_stars=sc.few_stars,
            brightness_mag=sc.brightness_mag,
            device=str(device) if sc.render_backend == "torch" and device is not None else None,
            render_backend=sc.render_backend,
            frames_renderer=sc.frames_renderer,
            adu_images=sc.image_transfer == "adu" or (sc.image_transfer == "auto" and on_gpu),
        )

    def stream(self) -> SampleStream:
        if self._stream is None:
            self._stream = SampleStream(
                stream_render_config(self.config, self.seed, self.render_backend, self.device),
                self.kind,
                calibration=self.calibration,
                level_ranges=self.ranges,
                frames_renderer=self.frames_renderer,
            )
        return self._stream

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_stream"] = None  # rebuilt lazily in each worker (catalog index, sensor maps)
        return state

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.steps

    def indices(self, step: int) -> np.ndarray:
        base = ((self.epoch * self.steps + step) * self.world + self.rank) * self.batch
        return base + np.arange(self.batch)

    def make_batch(self, step: int) -> dict:
        idx = self.indices(step)
        s = self.stream()
        if self.kind == "detections":
            b = s.batch(idx)
            offsets, det, unit = b.offsets, b.detections, b.labels["unit_vector"]
            images = {}
        else:
            from skygen.stream.samples import frames_as_batch

            frames, dev_images = s.frames_batch(idx, self.device)
            b = frames_as_batch(frames)
            offsets, det, unit = b.offsets, b.detections, b.labels["unit_vector"]
            if (
                dev_images is not None
            ):  # rendered on the device (render.backend=torch): the same stretch, in torch, stays there
                images = {"image": self.pre.images_torch(dev_images)}
            elif self.adu_images:  # stretched on the training device (batch_inputs)
                images = {
                    "image_adu": torch.from_numpy(np.stack([np.asarray(f.image, np.uint16) for f in frames])),
                    "image_stretch": torch.tensor(self.pre.stretch(), dtype=torch.float64),
                }
            else:
                images = {"image": torch.from_numpy(np.stack([self.pre.image(f.image)[None] for f in frames]))}
        limits = few_star_limits(self.seed, idx, self.few_prob, *self.few_stars)
        coords, mask, counts = self.pre.batch(offsets, det, limits)
        shift = brightness_offsets(self.seed, idx, *self.brightness_mag)
        if shift is not None:
            coords[..., 2] += shift[:, None] * mask
        out = {
            "coords": torch.from_numpy(coords),
            "mask": torch.from_numpy(mask),
            "label": torch.from_numpy(assign(unit, self.centroids).astype(np.int64)),
            "index": torch.from_numpy(idx.astype(np.int64)),
            "n_detections": torch.from_numpy(counts),
        }
        out.update(images)
        if self.fine_centroids is not None:
            out["label_fine"] = torch.from_numpy(assign(unit, self.fine_centroids).astype(np.int64))
        if self.soft_kappa is not None:
            out["soft"] = torch.from_numpy(soft_targets(unit, self.centroids, self.soft_kappa).astype(np.float32))
        return out

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        w, n = (0, 1) if info is None else (info.id, info.num_workers)
        for step in range(w, self.steps, n):
            yield self.make_batch(step)


def make_stream_loader(ds: StreamBatches, workers: int, pin_memory: bool = False) -> torch.utils.data.DataLoader:
    """A DataLoader over ready batches (``batch_size=None``); call ``loader.dataset.set_epoch(e)``.
    ``pin_memory`` (for a GPU): batches land in page-locked memory, so their copy to the device
    runs beside the step."""
    kw = {}
    if workers > 0:
        from ..model.shards import worker_init

        kw = {"worker_init_fn": worker_init, "prefetch_factor": 4, "persistent_workers": False}
    return torch.utils.data.DataLoader(ds, batch_size=None, num_workers=workers, pin_memory=pin_memory, **kw)
