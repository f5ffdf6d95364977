"""The warpis version (pyproject.toml's), readable from every floor without importing Warp."""

__version__ = "0.1.0"
