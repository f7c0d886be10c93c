"""evgs: event-only SLAM with 3D Gaussian Splatting for spacecraft proximity operations.

The heavy lifting (event I/O, event frames, the Gaussian rasterizer, event simulation) lives in the
Rust extension ``evgs._core``; this package is the thin optimisation layer on top of it.
"""

from evgs._core import __version__

__all__ = ["__version__"]
