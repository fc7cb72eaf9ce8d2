"""Rendering: the instrument applied to the sky, one frame or a batch.

* :mod:`~skygen.render.frame` — the NumPy reference renderer (:class:`Renderer`: frame ``i``
  is a pure function of the config and ``i``);
* :mod:`~skygen.render.torch_frames` — the same scenes rasterised in batches on a torch
  device;
* :mod:`~skygen.render.scenes` and :mod:`~skygen.render.binned` (numba loops in
  :mod:`~skygen.render.binned_kernels`) — vectorised scenes and frames drawn directly at the
  stored size, for the sample streams;
* :mod:`~skygen.render.perturb` — stored frames rendered again with extra corruption.

``from skygen.render import Renderer`` keeps working; the names load on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from skygen.lazy import lazy_attributes

_LAZY = {name: "skygen.render.frame" for name in ("Renderer", "Scene", "Frame")}

if TYPE_CHECKING:
    from skygen.render.frame import Frame, Renderer, Scene

__getattr__ = lazy_attributes(__name__, _LAZY)
__all__ = list(_LAZY)
