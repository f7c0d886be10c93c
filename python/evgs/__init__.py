"""evgs: event-only SLAM with 3D Gaussian Splatting for spacecraft proximity operations.

The heavy lifting (event I/O, event frames, the Gaussian rasterizer, event simulation) lives in the
Rust extension ``evgs._core``; this package is the thin optimisation layer on top of it.
"""

from evgs import cpu_dispatch

# First thing, before anything imports numpy or torch: their CPU code paths decide a run's last bits.
cpu_dispatch.pin()

from evgs._core import __version__  # noqa: E402

__all__ = ["__version__"]
