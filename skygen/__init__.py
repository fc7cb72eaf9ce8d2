"""skygen: a physically-based star-tracker frame generator writing shareable HDF5 shards.

The pipeline, one module per stage, in the order data flows::

    catalog -> attitude -> camera -> photometry -> psf -> sensor -> corruptions
            -> detect -> render (one frame) -> dataset (many frames, shards) -> io

Read conventions in :mod:`skygen.conventions`; read datasets with
:func:`skygen.io.open_dataset`.
"""

__version__ = "0.1.0"

from .errors import CatalogError, ConfigError, DatasetError, SkygenError  # noqa: E402

__all__ = ["__version__", "SkygenError", "ConfigError", "DatasetError", "CatalogError"]
