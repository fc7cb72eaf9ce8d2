"""Datasets: the shard format and every tool that works on whole datasets.

* :mod:`~skygen.datasets.shards` — the format: one writer (:func:`write_shard`), one reader
  (:func:`open_dataset`, lazy, a context manager), schema versions, checksums;
* :mod:`~skygen.datasets.build` — ``skygen render``: frames rendered in parallel into shards, resume,
  slices, the manifest;
* :mod:`~skygen.datasets.merge`, :mod:`~skygen.datasets.validate`, :mod:`~skygen.datasets.card`
  (README + Croissant 1.1), :mod:`~skygen.datasets.summary` (``skygen inspect``),
  :mod:`~skygen.datasets.preview` (``skygen preview``).

``from skygen.datasets import open_dataset`` is the reader every consumer (fusion included) uses.
"""

from skygen.datasets.shards import Dataset, open_dataset, verify_checksums

__all__ = ["Dataset", "open_dataset", "verify_checksums"]
