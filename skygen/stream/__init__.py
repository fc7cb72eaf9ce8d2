"""Samples without files: endless, deterministic streams for training.

* :mod:`~skygen.stream.samples` — :class:`SampleStream` (``frames`` or ``detections``), a pure
  function of (config, seed, kind, index), split over workers and ranks by ``partition``;
* :mod:`~skygen.stream.emulator` — the detector emulator: detection sets from a scene's light
  sources without pixels, calibrated on the real detector;
* :mod:`~skygen.stream.calibration` — fitting that emulator (``skygen calibrate-detector``);
  the default camera's calibration ships in ``data/``.

Detection sets are written to disk by :func:`skygen.datasets.detection_sets.write_detection_sets`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from skygen.lazy import lazy_attributes

_LAZY = {name: "skygen.stream.samples" for name in ("SampleStream", "stream_summary", "partition")}

if TYPE_CHECKING:
    from skygen.stream.samples import SampleStream, partition, stream_summary

__getattr__ = lazy_attributes(__name__, _LAZY)
__all__ = list(_LAZY)
