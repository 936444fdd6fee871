"""adnmesh: adaptive cross-voltage-level power flow control of active distribution networks.

The package holds the pure numerics (reference model, margins, step information, tuning,
analyses), the configuration loader and the command-line interface. See ``README.md``.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("adnmesh")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.1.0"

__all__ = ["__version__"]
