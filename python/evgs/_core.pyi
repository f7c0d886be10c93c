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
def detect_format(path: str) -> str: ...

class EventReader:
    """A file decoded in Rust (text, npy, evt2, evt3, aedat4), batch by batch, GIL released."""

    def __init__(
        self,
        path: str,
        format: str | None = None,
        *,
        delimiter: str | None = None,
        has_header: bool | None = None,
        columns: str | None = None,
        time_unit: str | None = None,
        width: int = 0,
        height: int = 0,
        require_sorted: bool = False,
        drop_outside: bool = False,
        time_shift: bool = False,
    ) -> None: ...
    def next_batch(self, max_events: int) -> dict | None: ...
    def read_all(self) -> dict: ...
    @property
    def format(self) -> str: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def file_size(self) -> int: ...
    @property
    def bytes_done(self) -> int: ...
    def skipped(self) -> dict[str, int]: ...
    def text_layout(self) -> dict | None: ...

class BatchCheck:
    """Sensor-bounds (optionally dropping) and sortedness checks for batches decoded in Python."""

    def __init__(
        self,
        path: str,
        width: int = 0,
        height: int = 0,
        *,
        drop_outside: bool = False,
        require_sorted: bool = False,
    ) -> None: ...
    def check(
        self,
        t: npt.NDArray[np.int64],
        x: npt.NDArray[np.uint16],
        y: npt.NDArray[np.uint16],
        p: npt.NDArray[np.int8],
    ) -> npt.NDArray[np.uintp] | None: ...
    @property
    def dropped(self) -> int: ...

def encode_text_bytes(
    t: npt.NDArray[np.int64],
    x: npt.NDArray[np.uint16],
    y: npt.NDArray[np.uint16],
    p: npt.NDArray[np.int8],
    *,
    delimiter: str = ",",
    time_unit: str = "us",
    header: bool = True,
    zero_one: bool = True,
) -> npt.NDArray[np.uint8]: ...
def encode_npy_header(rows: int, style: str = "structured") -> bytes: ...
def encode_npy_data(
    t: npt.NDArray[np.int64],
    x: npt.NDArray[np.uint16],
    y: npt.NDArray[np.uint16],
    p: npt.NDArray[np.int8],
    style: str = "structured",
) -> npt.NDArray[np.uint8]: ...
def encode_camera(
    format: str,
    t: npt.NDArray[np.int64],
    x: npt.NDArray[np.uint16],
    y: npt.NDArray[np.uint16],
    p: npt.NDArray[np.int8],
    width: int,
    height: int,
) -> npt.NDArray[np.uint8]: ...

# --- events: chunks, windows, event frames (src/py/frames.rs) ---

# --- raster (src/py/raster.rs) ---

# --- sim (src/py/sim.rs) ---
