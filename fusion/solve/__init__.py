"""Attitude solving: a user's frames -> detections -> (prior) -> full attitude or an explicit refusal.

* :mod:`~fusion.solve.base` — the :class:`Solver` protocol, :class:`Detections`, :class:`Solution`,
  :class:`Refusal`, attitude helpers;
* :mod:`~fusion.solve.registry` — every solver by name and :func:`build_solver` (predict and benchmark);
* :mod:`~fusion.solve.tetra` — tetra3rs lost-in-space (the classical baseline) and hinted tracking;
* :mod:`~fusion.solve.priors` — region priors: a fusion checkpoint, an oracle;
* :mod:`~fusion.solve.fine` — the fine stage: region prior -> region-restricted star identification
  -> tetra3rs verification (:mod:`~fusion.solve.match`, :mod:`~fusion.solve.pairs`: its compiled kernels and
  catalogue pair index);
* :mod:`~fusion.solve.track` — tracking: identifications near an attitude hint weighed by a likelihood;
* :mod:`~fusion.solve.frames`, :mod:`~fusion.solve.predict`, :mod:`~fusion.solve.benchmark` — reading
  frames, ``fusion predict`` and ``fusion benchmark``.

Names that need torch (priors, the predictor) load on first use, so ``import fusion.solve`` stays light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from skygen.lazy import lazy_attributes

from .base import Detections, FallbackSolver, Refusal, Solution, Solver
from .registry import SOLVERS, SolverContext, build_solver, register_solver

_LAZY = {
    "CoarseToFineSolver": ".fine",
    "Tetra3Solver": ".tetra",
    "RegionPrior": ".priors",
    "CheckpointPrior": ".priors",
    "OraclePrior": ".priors",
    "load_prior": ".priors",
    "Predictor": ".predict",
    "predict": ".predict",
    "read_frame": ".frames",
    "FrameError": ".frames",
    "run_benchmark": ".benchmark",
}

if TYPE_CHECKING:
    from .benchmark import run_benchmark
    from .fine import CoarseToFineSolver
    from .frames import FrameError, read_frame
    from .predict import Predictor, predict
    from .priors import CheckpointPrior, OraclePrior, RegionPrior, load_prior
    from .tetra import Tetra3Solver


__getattr__ = lazy_attributes(__name__, _LAZY)


__all__ = [
    "Detections",
    "FallbackSolver",
    "Refusal",
    "Solution",
    "Solver",
    "SOLVERS",
    "SolverContext",
    "build_solver",
    "register_solver",
    *_LAZY,
]
