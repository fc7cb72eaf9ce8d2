"""Training data: open the dataset, fit (or reuse) the regions, label the splits, build the datasets.

Frames are read through :mod:`fusion.model.shards` (skygen's one reader, lazy HDF5 handles per
process); the training split is augmented (:class:`fusion.train.augment.Augmenter`), the
validation split is not. Streams (:mod:`fusion.train.stream`) replace the training split but
validate on the same rendered frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skygen.config import build_config as build_render_config
from skygen.datasets.shards import Dataset as SkyDataset
from skygen.datasets.shards import open_dataset, verify_checksums

from ..config import FusionConfig
from ..errors import CheckpointError, ConfigError
from ..model.regions import KMeansResult, Regions, class_weights, sky_directions, soft_targets
from ..model.shards import FrameDataset, boresight_vectors, count_sparse_frames, split_positions
from .augment import Augmenter


@dataclass
class PreparedData:
    ds: SkyDataset
    regions: Regions
    train: FrameDataset
    val: FrameDataset
    alpha: np.ndarray  # (K,) class weights of the loss
    kmeans: KMeansResult | None  # None when the regions came from a checkpoint
    sparse_frames: dict  # split -> frames with < 2 detections


def prepare_data(cfg: FusionConfig, regions: Regions | None = None) -> PreparedData:
    """Open the dataset, fit (or reuse, on resume) the regions, label the training and validation splits.

    The K regions are fitted on the training split's boresights when training on it (the paper's
    recipe), on directions drawn from the dataset's attitude distribution when training on a stream;
    fine regions (``labels.fine_k``) always on such directions, so their number does not depend on
    the dataset's size (:func:`fusion.model.regions.sky_directions`)."""
    if not cfg.data.path:
        raise ConfigError("data.path: no dataset given; pass --data DIR (a folder written by `skygen render`)")
    ds = open_dataset(cfg.data.path)
    verify_checksums(ds, log=print)
    d, lab = cfg.data, cfg.labels
    pos = {name: split_positions(ds, getattr(d, f"{name}_split"), d.max_frames) for name in ("train", "val")}
    vec = {name: boresight_vectors(ds, p) for name, p in pos.items()}
    km = None
    fit = dict(seed=lab.seed, n_init=lab.n_init, max_iter=lab.max_iter, tol_deg=lab.tol_deg)
    if regions is None:
        on = (
            vec["train"]
            if cfg.stream.kind == "none"
            else sky_directions(build_render_config(ds.config).attitude, lab.k, lab.seed)
        )
        regions, km = Regions.fit(on, lab.k, **fit)
    elif regions.k != lab.k:
        raise CheckpointError(f"the checkpoint's centroids define K={regions.k} classes but labels.k={lab.k}")
    if lab.fine_k and regions.fine is None:
        att = build_render_config(ds.config).attitude
        if att.mode == "list" and len(set(zip(att.ra_deg, att.dec_deg))) < lab.fine_k:
            raise ConfigError(
                f"labels.fine_k={lab.fine_k}: the dataset points at {len(set(zip(att.ra_deg, att.dec_deg)))} "
                "distinct pointings (attitude.mode=list); fine regions need a sky to tile: "
                "drop labels.fine_k or use a dataset with attitude.mode=uniform or region"
            )
        regions = regions.with_fine(sky_directions(att, lab.fine_k, lab.seed), lab.fine_k, **fit)
    labels = {name: regions.assign(v) for name, v in vec.items()}
    fine = {name: regions.assign(v, "fine") for name, v in vec.items()} if lab.fine_k else None
    soft = {name: (soft_targets(v, regions.coarse, lab.kappa) if lab.soft_labels else None) for name, v in vec.items()}
    common = dict(max_stars=d.max_stars, norm_scale_adu=d.norm_scale_adu, log_flux_offset=d.log_flux_offset)
    train = FrameDataset(
        ds,
        pos["train"],
        labels["train"],
        soft=soft["train"],
        augment=Augmenter(cfg.aug),
        seed=cfg.train.seed,
        fine=None if fine is None else fine["train"],
        **common,
    )
    val = FrameDataset(ds, pos["val"], labels["val"], soft=soft["val"], seed=cfg.train.seed, **common)
    return PreparedData(
        ds,
        regions,
        train,
        val,
        class_weights(labels["train"], lab.k, cfg.loss.alpha),
        km,
        {name: count_sparse_frames(ds, p) for name, p in pos.items()},
    )
