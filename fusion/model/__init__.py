"""The model contract: what every other part of fusion agrees on.

* :mod:`~fusion.model.inputs` — frame geometry, samples, the one :class:`Preprocessor` (frame -> tensors);
* :mod:`~fusion.model.shards` — model inputs from skygen shards (datasets, samplers, loaders);
* :mod:`~fusion.model.networks` — the networks and their registry (:func:`create_model`);
* :mod:`~fusion.model.canonical`, :mod:`~fusion.model.heatmap` — roll canonicalisation, the heatmap rasteriser;
* :mod:`~fusion.model.regions` — spherical K-means and the region hierarchy (:class:`Regions`);
* :mod:`~fusion.model.metrics` — top-k, angular error, confusion, neighbour errors;
* :mod:`~fusion.model.inference` — batched logits with optional mixed precision;
* :mod:`~fusion.model.checkpoint` — the typed :class:`Checkpoint` (save, load once, version, migrate).

This package imports none of :mod:`fusion.train`, :mod:`fusion.measure` or :mod:`fusion.solve`
(``tests/test_architecture.py`` checks it). Names load on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from skygen.lazy import lazy_attributes

_LAZY = {
    "FrameGeometry": ".inputs",
    "Sample": ".inputs",
    "Preprocessor": ".inputs",
    "Regions": ".regions",
    "Checkpoint": ".checkpoint",
    "load_checkpoint": ".checkpoint",
    "create_model": ".networks",
    "StarFusion": ".networks",
    "MODELS": ".networks",
    "predict_batches": ".inference",
}

if TYPE_CHECKING:
    from .checkpoint import Checkpoint, load_checkpoint
    from .inference import predict_batches
    from .inputs import FrameGeometry, Preprocessor, Sample
    from .networks import MODELS, StarFusion, create_model
    from .regions import Regions


__getattr__ = lazy_attributes(__name__, _LAZY)


__all__ = list(_LAZY)
