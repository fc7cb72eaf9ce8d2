"""Region priors for the fine stage (:class:`~fusion.solve.fine.CoarseToFineSolver`): where on the sky to look first.

A prior (:class:`RegionPrior`) has ``centroids`` (K, 3) ICRS unit vectors (the regions,
max-cosine cells as in :mod:`fusion.model.regions`), a ``level`` (``"coarse"`` or ``"fine"``)
and ``probabilities(detections, image) -> (K,)``; ``both`` gives the coarse and fine
probabilities of one forward pass and ``at_level`` the same prior answering at another
level. Two are built in:

* :class:`CheckpointPrior`, a fusion checkpoint's model (the learned prior);
  it rebuilds the model's inputs from a detection table and the stored frame with the
  checkpoint's own preprocessing (:class:`fusion.model.inputs.Preprocessor`).
  ``level="coarse"``: the K regions the model classifies; ``level="fine"``: its fine regions
  (``labels.fine_k``, a few degrees across), which the fine stage prefers (how often the top
  20 hold the truth: ``benchmarks/prior_coverage.py``, results/benchmark/prior_coverage.md).
  A model without an image branch (the geometry priors the solver chain runs on) is traced and frozen
  (TorchScript) at its first frame, and used traced only if the traced logits equal the eager ones
  there (to 1e-4): a forward of the cpu-few prior takes ~0.5 ms instead of ~0.9 (one CPU thread);
  ``fast=False`` keeps it eager.
* :class:`OraclePrior`, benchmark only: the true region ranked first with
  probability ``top1`` (otherwise a random other region first), to show what a prior of
  known quality gives before a model of that quality exists. Never used by ``fusion predict``.

**Plugging in another model**: subclass :class:`RegionPrior` (set ``centroids``, implement
``probabilities``) and pass an instance to :func:`fusion.solve.build_solver` (``prior=``); the
fine stage, ``fusion predict`` and ``fusion benchmark`` only call the members above.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from ..model.checkpoint import Checkpoint, load_checkpoint
from ..model.inputs import Preprocessor
from ..model.regions import LEVELS
from .base import Detections


class RegionPrior:
    """The prior contract (see the module docstring); subclasses set ``centroids`` and ``probabilities``."""

    level: str = "coarse"
    centroids: np.ndarray

    def probabilities(self, detections: Detections, image: np.ndarray | None = None) -> np.ndarray:
        raise NotImplementedError

    def both(self, detections: Detections, image: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """(coarse probabilities, fine probabilities or None)."""
        return self.probabilities(detections, image), None

    def at_level(self, level: str) -> "RegionPrior":
        """This prior answering at ``level`` (itself when it has one level only)."""
        return self


class OraclePrior(RegionPrior):
    """The true region first with probability ``top1`` (deterministic per frame), the rest by distance."""

    def __init__(self, centroids: np.ndarray, top1: float = 1.0, seed: int = 0):
        self.centroids = np.asarray(centroids, np.float64)
        self.top1, self.seed = float(top1), seed

    def probabilities_for(self, v_true: np.ndarray, frame_index: int) -> np.ndarray:
        d = self.centroids @ np.asarray(v_true, np.float64)
        order = np.argsort(-d, kind="stable")  # true region, then its neighbours
        rng = np.random.default_rng([self.seed, frame_index])
        if rng.random() >= self.top1 and len(order) > 1:  # a miss: the true region drops to rank 2
            order[[0, 1]] = order[[1, 0]]
        p = np.zeros(len(order))
        p[order] = 0.5 ** np.arange(1, len(order) + 1)
        return p / p.sum()

    def probabilities(self, detections: Detections, image=None) -> np.ndarray:
        raise RuntimeError("OraclePrior needs the true boresight: call probabilities_for(v_true, frame_index)")


class CheckpointPrior(RegionPrior):
    """The region probabilities of a fusion checkpoint (loaded once).

    ``level``: ``"coarse"`` (the K regions), ``"fine"`` (the fine regions of a model trained with
    ``labels.fine_k``; a checkpoint without them stays coarse, :attr:`level` says which).
    ``render_config`` replaces the checkpoint's own (older checkpoints carry none).
    """

    def __init__(
        self,
        checkpoint: Checkpoint | str | Path,
        render_config: dict | None = None,
        level: str = "coarse",
        fast: bool = True,
    ):
        import torch

        ckpt = checkpoint if isinstance(checkpoint, Checkpoint) else load_checkpoint(checkpoint)
        self.render_config = render_config if render_config is not None else ckpt.require_render_config()
        self.model, self.cfg = ckpt.build_model(), ckpt.fusion_config
        self.regions = ckpt.regions
        self.pre = Preprocessor.from_configs(self.render_config, self.cfg.data, ckpt.max_stars)
        self.image_size, self.max_stars = ckpt.image_size, ckpt.max_stars
        self.source = ckpt.source
        self.level = self._resolve(level)
        self._torch = torch
        # the traced forward (module docstring): None until the first frame, False where it is not used
        self._traced = None if fast and not self.model.branches["image"] else False

    @property
    def centroids(self) -> np.ndarray:
        return self.regions.centroids(self.level)

    @property
    def coarse_centroids(self) -> np.ndarray:
        return self.regions.coarse

    @property
    def fine_centroids(self) -> np.ndarray | None:
        return self.regions.fine

    def _resolve(self, level: str) -> str:
        if level not in LEVELS:
            raise ValueError(f"level={level!r}: choose one of {LEVELS}")
        return level if self.regions.has(level) else "coarse"

    def at_level(self, level: str) -> "CheckpointPrior":
        """The same model (shared, not copied) answering at another level."""
        view = copy.copy(self)
        view.level = self._resolve(level)
        return view

    def _logits(self, x: tuple):
        """The model's logits of one frame's tensors: fine ones where the model has fine regions."""
        if self._traced:
            return self._traced(*x)
        out = self.model(*x, fine=True) if self.regions.fine is not None else self.model(*x)
        if self._traced is None:
            self._traced = self._trace(x, out)
        return out

    def _trace(self, x: tuple, eager):
        """The model traced and frozen on ``x``, or False where tracing fails or its logits differ from ``eager``."""
        import warnings

        torch, fine = self._torch, self.regions.fine is not None

        class Forward(torch.nn.Module):
            def __init__(self, model):
                super().__init__()
                self.model = model

            def forward(self, image, coords, mask):
                return self.model(image, coords, mask, fine=True) if fine else self.model(image, coords, mask)

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # TracerWarnings: the shapes are the checkpoint's, fixed
                traced = torch.jit.freeze(torch.jit.trace(Forward(self.model).eval(), x, check_trace=False))
                same = bool(torch.allclose(traced(*x), eager, atol=1e-4))
        except Exception:  # noqa: BLE001 - any model TorchScript cannot trace stays eager
            return False
        return traced if same else False

    def both(self, detections: Detections, image: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """(coarse probabilities (K,), fine probabilities (F,) or None) from one forward pass."""
        if not self.model.branches["image"]:
            image = None  # only the image branch reads the pixels: a blank frame, stretched once, not every frame's
        x = self.pre.tensors(detections.x_px, detections.y_px, detections.flux_adu, image)
        sm = lambda z: self._torch.softmax(z.float(), dim=1)[0].numpy().astype(np.float64)  # noqa: E731
        with self._torch.inference_mode():
            logits = self._logits(x)
            if self.regions.fine is None:
                return sm(logits), None
            return sm(self.model.coarse_logits(logits)), sm(logits)

    def probabilities(self, detections: Detections, image: np.ndarray | None = None) -> np.ndarray:
        coarse, fine = self.both(detections, image)
        return fine if self.level == "fine" else coarse


def load_prior(
    checkpoint: Checkpoint | str | Path, render_config: dict | None = None, level: str = "coarse", fast: bool = True
) -> CheckpointPrior:
    """The learned prior of a checkpoint (a file, a run folder or an already loaded :class:`Checkpoint`);
    ``fast``: trace its forward (:class:`CheckpointPrior`)."""
    return CheckpointPrior(checkpoint, render_config, level, fast)
