"""The installed gdpt version (from the package metadata, so pyproject.toml is the only source)."""

from importlib import metadata

try:
    __version__: str = metadata.version("gdpt")
except metadata.PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"
