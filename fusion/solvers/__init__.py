"""Attitude solvers behind one interface (:mod:`fusion.solvers.base`), scored by ``fusion benchmark``.

* :mod:`~fusion.solvers.base` — :class:`Solver` protocol, :class:`Detections`, :class:`Solution`,
  :class:`Refusal`, attitude helpers;
* :mod:`~fusion.solvers.tetra` — tetra3rs lost-in-space (the classical baseline) and hinted tracking;
* :mod:`~fusion.solvers.priors` — region priors: a fusion checkpoint, an oracle, the whole sky;
* :mod:`~fusion.solvers.coarse_fine` — region prior -> region-restricted star identification ->
  tetra3rs verification: a full attitude or a refusal.
"""

from .base import Detections, Refusal, Solution, Solver

__all__ = ["Detections", "Refusal", "Solution", "Solver"]
