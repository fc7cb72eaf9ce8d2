"""Region priors for :class:`~fusion.solvers.coarse_fine.CoarseToFineSolver`: where on the sky to look first.

A prior has ``centroids`` (K, 3) ICRS unit vectors (the regions, max-cosine cells as in
:mod:`fusion.labels`) and ``probabilities(detections, image) -> (K,)``. Implemented:

* :class:`CheckpointPrior` — a fusion checkpoint's model (the learned prior); it rebuilds the
  model's inputs from a detection table and the stored frame with the checkpoint's own
  preprocessing (:func:`model_inputs`). ``level="coarse"``: the K regions the model
  classifies; ``level="fine"``: its fine regions (``labels.fine_k``, a few degrees across),
  which the coarse-to-fine search prefers: with 1000 fine regions the top 20 cover 2 % of
  the sky and hold the true boresight as often as the top 3 of 15 regions (20 % of the sky)
  or more (``benchmarks/prior_coverage.py``). **Plugging in another model**: write a class with
  these two members (or register a builder in :data:`PRIOR_BUILDERS` keyed by the
  checkpoint's ``model_name``) — the solver, ``fusion predict`` and ``fusion benchmark``
  only call ``probabilities``.
* :class:`OraclePrior` — benchmark only: the true region ranked first with probability
  ``top1`` (otherwise a random other region first), to show what a prior of known quality
  gives before a model of that quality exists. Never used for ``fusion predict``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import CheckpointError
from .base import Detections


class OraclePrior:
    """The true region first with probability ``top1`` (deterministic per frame), the rest by distance."""

    def __init__(self, centroids: np.ndarray, top1: float = 1.0, seed: int = 0):
        self.centroids = np.asarray(centroids, np.float64)
        self.top1, self.seed = float(top1), seed

    def probabilities_for(self, v_true: np.ndarray, frame_index: int) -> np.ndarray:
        d = self.centroids @ np.asarray(v_true, np.float64)
        order = np.argsort(-d, kind="stable")                       # true region, then its neighbours
        rng = np.random.default_rng([self.seed, frame_index])
        if rng.random() >= self.top1 and len(order) > 1:            # a miss: the true region drops to rank 2
            order[[0, 1]] = order[[1, 0]]
        p = np.zeros(len(order))
        p[order] = 0.5 ** np.arange(1, len(order) + 1)
        return p / p.sum()

    def probabilities(self, detections: Detections, image=None) -> np.ndarray:
        raise RuntimeError("OraclePrior needs the true boresight: call probabilities_for(v_true, frame_index)")


def model_inputs(detections: Detections, image: np.ndarray | None, render_config: dict, data_cfg,
                 image_size: int, max_stars: int):
    """(image (1, 1, S, S), coords (1, M, 3), mask (1, M)) tensors, as :mod:`fusion.data` builds them."""
    import torch
    from ..augment import FrameGeometry, Sample
    from ..data import encode_detections, normalise_image
    geo = FrameGeometry.from_render_config(render_config)
    if image is None:
        image = np.full((geo.image_h, geo.image_px), geo.bias_adu, np.float32)
    s = Sample(image=np.asarray(image, np.float32), x_px=detections.x_px, y_px=detections.y_px,
               flux_adu=np.asarray(detections.flux_adu, np.float32), area_px=np.zeros(len(detections), np.int32),
               background_adu=0.0, noise_adu=0.0)
    coords, mask = encode_detections(s, geo, max_stars, data_cfg.log_flux_offset)
    img = normalise_image(s.image, geo, data_cfg.norm_scale_adu)
    return (torch.from_numpy(img)[None, None], torch.from_numpy(coords)[None], torch.from_numpy(mask)[None])


class CheckpointPrior:
    """The region probabilities of a fusion checkpoint (current ``fusion train`` models).

    ``level``: ``"coarse"`` (the K regions), ``"fine"`` (the fine regions of a model trained with
    ``labels.fine_k``; a checkpoint without them stays coarse, :attr:`level` says which).
    """

    def __init__(self, checkpoint: str | Path, render_config: dict | None = None, level: str = "coarse"):
        import torch
        from ..checkpoint import load_checkpoint, render_config_of
        from ..train import load_trained_model
        ckpt = load_checkpoint(checkpoint)
        self.render_config = render_config if render_config is not None else render_config_of(ckpt, checkpoint)
        self.model, self.cfg = load_trained_model(ckpt, str(checkpoint))
        self.model.eval()
        self.coarse_centroids = ckpt["centroids"].numpy().astype(np.float64)
        fine = ckpt.get("fine_centroids")
        has_fine = fine is not None and bool(getattr(self.model, "fine_classes", None))
        self.fine_centroids = fine.numpy().astype(np.float64) if has_fine else None
        self.level = self._resolve(level)
        self.image_size, self.max_stars = int(ckpt["image_size"]), int(ckpt["max_stars"])
        self.source = str(checkpoint)
        self._torch = torch

    @property
    def centroids(self) -> np.ndarray:
        return self.fine_centroids if self.level == "fine" else self.coarse_centroids

    def _resolve(self, level: str) -> str:
        if level not in ("coarse", "fine"):
            raise ValueError(f"level={level!r}: choose 'coarse' or 'fine'")
        return "fine" if level == "fine" and self.fine_centroids is not None else "coarse"

    def at_level(self, level: str) -> "CheckpointPrior":
        """The same model (shared, not copied) answering at another level."""
        import copy
        view = copy.copy(self)
        view.level = self._resolve(level)
        return view

    def both(self, detections: Detections, image: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """(coarse probabilities (K,), fine probabilities (F,) or None) from one forward pass."""
        x = model_inputs(detections, image, self.render_config, self.cfg.data, self.image_size, self.max_stars)
        sm = lambda z: self._torch.softmax(z.float(), dim=1)[0].numpy().astype(np.float64)
        with self._torch.no_grad():
            if self.fine_centroids is None:
                return sm(self.model(*x)), None
            fine = self.model(*x, fine=True)
            return sm(self.model.coarse_logits(fine)), sm(fine)

    def probabilities(self, detections: Detections, image: np.ndarray | None = None) -> np.ndarray:
        coarse, fine = self.both(detections, image)
        return fine if self.level == "fine" else coarse


PRIOR_BUILDERS: dict[str, Callable[..., object]] = {}


def load_prior(checkpoint: str | Path, render_config: dict | None = None, level: str = "coarse"):
    """The region prior of a checkpoint: a registered builder for its model, else :class:`CheckpointPrior`."""
    from ..checkpoint import load_checkpoint
    name = load_checkpoint(checkpoint).get("model_name")
    builder = PRIOR_BUILDERS.get(name, CheckpointPrior)
    try:
        return builder(checkpoint, render_config, level)
    except KeyError as exc:
        raise CheckpointError(f"{checkpoint}: lacks {exc} needed to apply it; re-train with this fusion") from None
