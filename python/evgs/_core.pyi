"""Type stubs for the Rust extension module (see src/py/)."""

import numpy as np
import numpy.typing as npt

__version__: str

# --- events: validation and I/O (src/py/events.rs) ---

def validate_events(
    t: npt.NDArray[np.int64],
    x: npt.NDArray[np.uint16],
    y: npt.NDArray[np.uint16],
    p: npt.NDArray[np.int8],
    width: int,
    height: int,
    source: str,
) -> None: ...

# --- events: chunks, windows, event frames (src/py/frames.rs) ---

# --- raster (src/py/raster.rs) ---

_F32 = npt.NDArray[np.float32]

class RasterState:
    """Opaque saved forward pass (tile lists, final transmittance, last contributors)."""

    @property
    def forward_evaluations(self) -> int: ...

def rasterize_forward(
    means: _F32,
    log_scales: _F32,
    quats: _F32,
    opacities: _F32,
    colors: _F32,
    channels: int,
    viewmats: _F32,
    width: int,
    height: int,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    background: _F32,
) -> tuple[_F32, _F32, _F32, npt.NDArray[np.int32], RasterState]:
    """Flat float32 inputs; returns flat (color, depth, alpha, radii, state). Use ``evgs.render.render``."""

def rasterize_backward(
    state: RasterState,
    means: _F32,
    log_scales: _F32,
    quats: _F32,
    opacities: _F32,
    colors: _F32,
    channels: int,
    viewmats: _F32,
    grad_color: _F32,
    grad_depth: _F32,
    grad_alpha: _F32,
) -> tuple[_F32, _F32, _F32, _F32, _F32, _F32, _F32, int]:
    """Flat gradients (means, log_scales, quats, opacities, colors, viewmats, grad2d_norm, evaluations)."""

# --- sim (src/py/sim.rs) ---
