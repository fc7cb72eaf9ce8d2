"""Measuring trained models: ``fusion evaluate``, ``robustness``, ``timing``, ``export`` and ``experiment``.

Imports :mod:`fusion.model`; only :mod:`~fusion.measure.experiment` (which trains the runs it
measures) may import :mod:`fusion.train`; nothing here imports :mod:`fusion.solve`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

_LAZY = {"evaluate_checkpoint": ".evaluate", "run_sweep": ".robustness", "robustness": ".robustness",
         "run_timing": ".timing", "export_onnx": ".export", "run_experiment": ".experiment"}

if TYPE_CHECKING:
    from .evaluate import evaluate_checkpoint
    from .experiment import run_experiment
    from .export import export_onnx
    from .robustness import robustness, run_sweep
    from .timing import run_timing


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = list(_LAZY)
