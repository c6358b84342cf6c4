"""warpdem: rock and structures breaking under blast and impact, on NVIDIA Warp.

The package is split into host code (this package: scene loading, model building, the step pipeline,
output) and Warp kernels (:mod:`warpdem.kernels`). Imports run one way: host → kernels.
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__"]
