"""fusion: Star-Fusion training and evaluation on skygen shards."""

__version__ = "0.1.0"
