"""Training: ``fusion train`` as library functions.

* :mod:`~fusion.train.run` — :func:`train`, the run in named steps;
* :mod:`~fusion.train.loop` — one epoch, one validation pass, the schedule;
* :mod:`~fusion.train.data` — dataset, regions and labels of a run; :mod:`~fusion.train.augment`;
* :mod:`~fusion.train.stream` — training on skygen's sample streams;
* :mod:`~fusion.train.losses`, :mod:`~fusion.train.distributed`, :mod:`~fusion.train.runfolder`.

Imports :mod:`fusion.model`, never :mod:`fusion.measure` or :mod:`fusion.solve`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

_LAZY = {"train": ".run", "prepare_data": ".data", "StreamBatches": ".stream"}

if TYPE_CHECKING:
    from .data import prepare_data
    from .run import train
    from .stream import StreamBatches


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = list(_LAZY)
