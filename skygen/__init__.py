"""skygen: a physically-based star-tracker frame generator writing shareable HDF5 shards.

The pipeline, one module per stage, in the order data flows::

    catalog -> attitude -> camera -> photometry -> psf -> sensor -> corruptions
            -> detect -> render (one frame) -> datasets (many frames, shards; the tools)

The detector emulator (:mod:`skygen.stream.emulator`, fitted by :mod:`skygen.stream.calibration`) and the
sample streams (:mod:`skygen.stream.samples`) stand beside the pipeline; :mod:`skygen.runtime` holds what
every command needs from its host (atomic files, strict JSON, hardware, devices). Read
conventions in :mod:`skygen.conventions`; read datasets with :func:`skygen.datasets.open_dataset`.
"""

__version__ = "0.1.0"

from skygen.errors import CatalogError, ConfigError, DatasetError, SkygenError  # noqa: E402

__all__ = ["__version__", "SkygenError", "ConfigError", "DatasetError", "CatalogError"]
