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

class CameraWriter:
    """A camera-format file (evt2, evt3, aedat4 = aedat4-lz4, aedat4-zstd, aedat4-none) written batch by
    batch; write to a temporary path and rename it after ``close``."""

    def __init__(
        self, path: str, format: str, width: int = 0, height: int = 0, *, name: str | None = None
    ) -> None: ...
    def write(
        self,
        t: npt.NDArray[np.int64],
        x: npt.NDArray[np.uint16],
        y: npt.NDArray[np.uint16],
        p: npt.NDArray[np.int8],
    ) -> None: ...
    def close(self) -> None: ...

# --- events: chunks, windows, event frames (src/py/frames.rs) ---

def chunk_bounds(t: npt.NDArray[np.int64], frame_t: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]: ...

class WindowSampler:
    def __init__(
        self,
        start: int,
        end: int,
        min_n_winsize: int,
        max_n_winsize: int,
        seed: int,
        mode: str = "paper",
        seg_num: int = 100,
    ) -> None: ...
    def sample(self, batch: int) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]: ...
    @property
    def sizes(self) -> tuple[int, int]: ...

def accumulate_frames(
    t: npt.NDArray[np.int64],
    x: npt.NDArray[np.uint16],
    y: npt.NDArray[np.uint16],
    p: npt.NDArray[np.int8],
    width: int,
    height: int,
    starts: npt.NDArray[np.int64],
    ends: npt.NDArray[np.int64],
    c_on: float,
    c_off: float,
    downsample_log2: int = 0,
    undistort_map: npt.NDArray[np.float32] | None = None,
    out: npt.NDArray[np.float32] | None = None,
) -> tuple[npt.NDArray[np.float32], int, int, npt.NDArray[np.uint64]]: ...
def undistort_map(
    width: int, height: int, fx: float, fy: float, cx: float, cy: float, distortion: list[float]
) -> npt.NDArray[np.float32]: ...

# --- raster (src/py/raster.rs) ---

_F32 = npt.NDArray[np.float32]
_F64 = npt.NDArray[np.float64]

class RasterState:
    """Opaque saved forward pass (tile lists, final transmittance, last contributors)."""

    @property
    def forward_evaluations(self) -> int: ...
    @property
    def forward_evaluations_standard(self) -> int: ...
    @property
    def backward_evaluations_standard(self) -> int: ...

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

def rasterize_pose_jvp(
    means: _F32,
    log_scales: _F32,
    quats: _F32,
    opacities: _F32,
    colors: _F32,
    channels: int,
    viewmats: _F32,
    tangents: _F32,
    width: int,
    height: int,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    background: _F32,
) -> tuple[_F32, _F32, _F32]:
    """Flat (color, alpha, d_color): a render and, in forward mode, the colour's derivative along six
    tangents (B, 6, 4, 4) of each view, laid out (B, H, W, 6, C)."""

# --- loss (src/py/loss.rs) ---

def ssim_f32(
    a: _F32, b: _F32, shape: tuple[int, int, int], taps: _F32, c1: float, c2: float, with_grad: bool
) -> tuple[_F32, tuple[_F32, _F32] | None]:
    """Mean SSIM of each (B, H, W) image pair and, with ``with_grad``, the flat gradients of each
    image's value with respect to ``a`` and ``b`` (src/loss/ssim.rs)."""

def ssim_f64(
    a: _F64, b: _F64, shape: tuple[int, int, int], taps: _F64, c1: float, c2: float, with_grad: bool
) -> tuple[_F64, tuple[_F64, _F64] | None]: ...
def depth_variation_f32(
    depth: _F32, alpha: _F32, shape: tuple[int, int, int], min_alpha: float, with_grad: bool
) -> tuple[float, tuple[_F32, _F32] | None]:
    """The relief prior of (B, H, W) depth and opacity and, with ``with_grad``, its flat gradients with
    respect to both (src/loss/relief.rs)."""

def depth_variation_f64(
    depth: _F64, alpha: _F64, shape: tuple[int, int, int], min_alpha: float, with_grad: bool
) -> tuple[float, tuple[_F64, _F64] | None]: ...

# --- sim (src/py/sim.rs) ---

class EventSimulator:
    """ESIM event simulator (src/sim/esim.rs) fed flattened float32 frames in time order."""

    def __init__(
        self,
        width: int,
        height: int,
        *,
        c_on: float = 0.2,
        c_off: float = 0.2,
        sigma_c: float = 0.0,
        refractory_us: float = 0.0,
        log_eps: float = 1e-3,
        shot_rate_hz: float = 0.0,
        shot_dark_level: float = 0.01,
        leak_rate_hz: float = 0.0,
        hot_pixel_fraction: float = 0.0,
        hot_pixel_rate_hz: float = 0.0,
        seed: int = 0,
    ) -> None: ...
    def push_frame(self, t_us: int, intensity: npt.NDArray[np.float32]) -> int: ...
    def push_log_frame(self, t_us: int, log: npt.NDArray[np.float32]) -> int: ...
    def log_change_quantile(
        self, intensity: npt.NDArray[np.float32], q: float, min_level: float
    ) -> float: ...
    def take_events(self) -> dict: ...
    @property
    def num_events(self) -> int: ...
    @property
    def hot_pixel_count(self) -> int: ...
    @property
    def last_time(self) -> int | None: ...
