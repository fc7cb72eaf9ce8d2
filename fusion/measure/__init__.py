"""Measuring trained models: ``fusion evaluate``, ``robustness``, ``timing``, ``export`` and ``experiment``.

Imports :mod:`fusion.model`; only :mod:`~fusion.measure.experiment` (which trains the runs it
measures) may import :mod:`fusion.train`; nothing here imports :mod:`fusion.solve`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from skygen.lazy import lazy_attributes

_LAZY = {
    "evaluate_checkpoint": ".evaluate",
    "run_sweep": ".robustness",
    "robustness": ".robustness",
    "run_timing": ".timing",
    "export_onnx": ".export",
    "run_experiment": ".experiment",
}

if TYPE_CHECKING:
    from .evaluate import evaluate_checkpoint
    from .experiment import run_experiment
    from .export import export_onnx
    from .robustness import robustness, run_sweep
    from .timing import run_timing


__getattr__ = lazy_attributes(__name__, _LAZY)


__all__ = list(_LAZY)
