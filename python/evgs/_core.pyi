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

# --- sim (src/py/sim.rs) ---
