"""Training: ``fusion train`` as library functions.

* :mod:`~fusion.train.run` — :func:`train`, the run in named steps;
* :mod:`~fusion.train.loop` — one epoch, one validation pass, the schedule;
* :mod:`~fusion.train.data` — dataset, regions and labels of a run; :mod:`~fusion.train.augment`;
* :mod:`~fusion.train.stream` — training on skygen's sample streams;
* :mod:`~fusion.train.losses`, :mod:`~fusion.train.distributed`, :mod:`~fusion.train.runfolder`.

Imports :mod:`fusion.model`, never :mod:`fusion.measure` or :mod:`fusion.solve`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from skygen.lazy import lazy_attributes

_LAZY = {"train": ".run", "prepare_data": ".data", "StreamBatches": ".stream"}

if TYPE_CHECKING:
    from .data import prepare_data
    from .run import train
    from .stream import StreamBatches


__getattr__ = lazy_attributes(__name__, _LAZY)


__all__ = list(_LAZY)
