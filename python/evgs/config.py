"""Run configuration: TOML files in ``configs/`` with inheritance, ``--set`` overrides and validation.

A config file may name a parent with ``inherit = "../default.toml"`` (relative to the file); its keys
override the parent's, section by section. ``configs/default.toml`` is the root of every chain and sets
every key, so the values live in exactly one place and the dataclasses below only fix names and types.
Unknown keys and ill-typed values are rejected with the file, the key and the closest valid key.
"""

from __future__ import annotations

import argparse
import difflib
import typing
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any, Literal

import tomli_w
import tomllib

from evgs.io_util import atomic_path

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"
DEFAULT_CONFIG = CONFIG_DIR / "default.toml"


class ConfigError(ValueError):
    """An invalid config file or override (the message names the file or ``--set`` and the key)."""


@dataclass(frozen=True)
class DataConfig:
    start_frame: int
    num_frames: int
    event_contrast: float
    max_n_winsize: int
    min_n_winsize: int
    seg_num: int
    training_batch_size: int
    window_mode: Literal["paper", "reference"]


@dataclass(frozen=True)
class TrajectoryConfig:
    interpolation: Literal["geodesic", "lerp"]
    pose_lr: float
    init_pose_noise: float
    smoothness: float
    smoothing_time: float
    smoothing_order: int
    smoothing_end_fit: float


@dataclass(frozen=True)
class InitConfig:
    num_frames: int
    num_opti_steps_for_init: int
    lr_boost: float
    train_knots: bool
    train_knot_rotation: bool
    motion_search: bool
    search_steps: int
    search_finalists: int
    search_final_steps: int
    search_final_depth_tv: float
    search_rate: float
    search_range: float
    search_polls: int
    search_frames: int
    search_holdout: int
    search_half_rate: bool
    search_sized: int
    search_starts: int
    search_families: Literal["all", "orbit", "translate"]
    search_tilt: float
    search_orbit_depth: float
    search_veer: float
    search_smooth: bool
    search_range_weight: float
    search_meter_advance: bool
    branches: int
    branch_frames: int
    branch_score: Literal["events", "range", "tracking"]
    branch_directions: bool
    branch_restarts: int


@dataclass(frozen=True)
class TrackingConfig:
    solver: Literal["adam", "lm"]
    num_opti_steps: int
    mask_border: int
    mask_alpha: float
    lm_step: float
    lm_damping: float
    lm_tolerance: float
    velocity_prior: float
    velocity_prior_floor: float
    velocity_prior_frames: int
    span_frames: int
    lm_windows: int
    lm_jacobian: Literal["central", "analytic"]


@dataclass(frozen=True)
class MappingConfig:
    every: int
    window: int
    num_opti_steps_for_BA: int  # noqa: N815 (the paper's name)
    max_new_gaussians: int
    new_gaussian_alpha: float
    new_gaussian_depth: float
    train_poses: bool
    replay_every: int


@dataclass(frozen=True)
class GlobalBAConfig:
    every: int
    num_opti_steps: int
    num_opti_steps_final: int
    final_early_stop: bool
    lr_boost: float
    tv_weight: float
    max_n_winsize: int
    rate_check: float
    rate_check_steps: int
    rate_check_seedings: int
    rate_check_depth_tv: float
    final_depth_tv: float
    final_hold_positions: bool


@dataclass(frozen=True)
class GaussiansConfig:
    num_init: int
    bounding_size: float
    init_depth: float
    init_seeding: Literal["box", "events"]
    init_depth_spread: float
    init_tilt_deg: float
    init_min_events: int
    init_fill_gap: int
    init_opacity: float
    init_color: float
    background: float
    means_lr: float
    scales_lr: float
    quats_lr: float
    opacities_lr: float
    colors_lr: float
    adam_eps: float


@dataclass(frozen=True)
class LossConfig:
    lambda_ssim: float
    event_loss: Literal["l1", "mse"]
    log_mode: Literal["log", "linlog"]
    log_eps: float
    linlog_threshold: float
    ssim_window: int
    ssim_sigma: float
    event_mask_threshold: float
    depth_tv: float


@dataclass(frozen=True)
class StrategyConfig:
    prune_opa: float
    prune_scale3d: float
    prune_scale3d_start: int
    grow_grad2d: float
    grow_scale3d: float
    event_threshold: float
    refine_start: int
    refine_stop: int
    refine_every: int
    reset_every: int
    reset_at_stage_start: bool
    reset_opacity: float


@dataclass(frozen=True)
class GuardsConfig:
    max_color: float
    brightness_weight: float
    near_margin: float
    max_footprint: float
    footprint_min_opacity: float


@dataclass(frozen=True)
class EconomyConfig:
    patience: int
    min_rel_change: float
    min_fraction: float
    coarse_factor: int
    coarse_fraction: float


@dataclass(frozen=True)
class OutputConfig:
    runs_dir: str
    diagnostics_every: int
    diagnostics_rows: int
    checkpoint_every: int


@dataclass(frozen=True)
class ScaleConfig:
    source: Literal["none", "range", "target_size"]
    target_size: float
    min_alpha: float
    range_weight: float
    rate_weight: float
    closing_min_explained: float
    surface_read: Literal["before_final_ba", "end"]


@dataclass(frozen=True)
class Config:
    seq: str
    seed: int
    torch_threads: int
    data: DataConfig
    trajectory: TrajectoryConfig
    init: InitConfig
    tracking: TrackingConfig
    mapping: MappingConfig
    global_ba: GlobalBAConfig
    gaussians: GaussiansConfig
    loss: LossConfig
    strategy: StrategyConfig
    guards: GuardsConfig
    economy: EconomyConfig
    scale: ScaleConfig
    output: OutputConfig

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _suggest(key: str, valid: Iterable[str]) -> str:
    close = difflib.get_close_matches(key, list(valid), n=1, cutoff=0.5)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _check_value(value: Any, tp: Any, where: str) -> Any:
    """Check one TOML value against a field type; ints are accepted (and converted) for floats."""
    if typing.get_origin(tp) is Literal:
        choices = typing.get_args(tp)
        if value not in choices:
            raise ConfigError(f"{where}: must be one of {', '.join(map(repr, choices))}, got {value!r}")
        return value
    ok = {
        bool: isinstance(value, bool),
        int: isinstance(value, int) and not isinstance(value, bool),
        float: isinstance(value, int | float) and not isinstance(value, bool),
        str: isinstance(value, str),
    }[tp]
    if not ok:
        raise ConfigError(f"{where}: expected {tp.__name__}, got {type(value).__name__} {value!r}")
    return float(value) if tp is float else value


def _validate(doc: Mapping[str, Any], cls: type, source: str, prefix: str = "") -> dict[str, Any]:
    """Validate a (partial) document against ``cls``: every key known, every value well typed."""
    hints = _hints(cls)
    out: dict[str, Any] = {}
    for key, value in doc.items():
        name = f"{prefix}{key}"
        if key not in hints:
            where = f"section [{prefix[:-1]}]" if prefix else "top level"
            raise ConfigError(f"{source}: unknown key {name!r} at {where}{_suggest(key, hints)}")
        tp = hints[key]
        if is_dataclass(tp):
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: {name!r} must be a table [{name}]")
            out[key] = _validate(value, tp, source, f"{name}.")
        else:
            if isinstance(value, dict):
                raise ConfigError(f"{source}: {name!r} is a value, not a table")
            out[key] = _check_value(value, tp, f"{source}: {name}")
    return out


def _merge(base: dict[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and key in out else value
    return out


def _build(cls: type, doc: Mapping[str, Any], source: str, prefix: str = "") -> Any:
    kwargs = {}
    for f in fields(cls):
        name = f"{prefix}{f.name}"
        if f.name not in doc:
            raise ConfigError(f"{source}: missing key {name!r} (set neither there nor in a file it inherits)")
        tp = _hints(cls)[f.name]
        kwargs[f.name] = _build(tp, doc[f.name], source, f"{name}.") if is_dataclass(tp) else doc[f.name]
    return cls(**kwargs)


def _check_ranges(cfg: Config, source: str) -> None:
    """Relations a single type check cannot see; each message names the offending keys."""
    problems = []
    d, g, s = cfg.data, cfg.gaussians, cfg.strategy
    if not 0 < d.min_n_winsize <= d.max_n_winsize:
        problems.append("need 0 < data.min_n_winsize <= data.max_n_winsize")
    if cfg.global_ba.max_n_winsize != 0 and cfg.global_ba.max_n_winsize < d.min_n_winsize:
        problems.append("global_ba.max_n_winsize must be 0 (data.max_n_winsize) or >= data.min_n_winsize")
    for key, value in [
        ("gaussians.init_opacity", g.init_opacity),
        ("strategy.reset_opacity", s.reset_opacity),
    ]:
        if not 0 < value < 1:
            problems.append(f"{key} must be in (0, 1)")
    if min(cfg.scale.range_weight, cfg.scale.rate_weight, cfg.init.search_range_weight) < 0:
        problems.append(
            "scale.range_weight, scale.rate_weight and init.search_range_weight must be >= 0 (0 = off)"
        )
    rc = cfg.global_ba
    if not 0 <= rc.rate_check < 1 or rc.rate_check_steps < 1 or rc.rate_check_seedings < 1:
        problems.append(
            "global_ba.rate_check must be in [0, 1) (0 = off), rate_check_steps and rate_check_seedings >= 1"
        )
    if rc.rate_check > 0 and cfg.scale.source == "range" and cfg.scale.surface_read != "end":
        problems.append(
            "global_ba.rate_check moves the cameras after tracking: with scale.source = 'range' it needs "
            "scale.surface_read = 'end' (the first surface read from the map refitted to them)"
        )
    if cfg.trajectory.smoothing_time < 0:
        problems.append("trajectory.smoothing_time must be >= 0 (seconds; 0 = off)")
    if not 1 <= cfg.trajectory.smoothing_order <= 4:
        problems.append("trajectory.smoothing_order must be 1–4 (the derivative the smoother's prior is on)")
    if cfg.trajectory.smoothing_end_fit < 0:
        problems.append("trajectory.smoothing_end_fit must be >= 0 (in units of smoothing_time; 0 = off)")
    if not 0 <= cfg.scale.closing_min_explained <= 1:
        problems.append("scale.closing_min_explained must be in [0, 1]")
    if cfg.scale.source == "target_size" and cfg.scale.target_size <= 0:
        problems.append("scale.source = 'target_size' needs scale.target_size > 0 (metres)")
    if cfg.init.motion_search and (
        cfg.init.search_steps < 1
        or cfg.init.search_finalists < 0
        or cfg.init.search_final_steps < 1
        or cfg.init.search_rate <= 0
        or cfg.init.search_range <= 1
        or cfg.init.search_holdout < 0
        or cfg.init.search_sized < 1
        or not 1 <= cfg.init.search_starts <= 2 * cfg.init.search_sized
        or not 0 <= cfg.init.search_tilt < 90
        or not 0 <= cfg.init.search_veer < 90
        or cfg.init.search_orbit_depth < 0
    ):
        problems.append(
            "init.motion_search needs search_steps >= 1, search_finalists >= 0 (0 = off), "
            "search_final_steps >= 1, search_rate > 0, search_range > 1, "
            "search_holdout >= 0, search_sized >= 1, 1 <= search_starts <= 2 × search_sized (the sized "
            "orbits and translations), 0 <= search_tilt < 90, 0 <= search_veer < 90 and "
            "search_orbit_depth >= 0"
        )
    if not cfg.init.train_knots and not cfg.init.motion_search:
        problems.append(
            "init.train_knots = false needs init.motion_search = true (the knots stay on its best motion)"
        )
    if not cfg.init.train_knot_rotation and not cfg.init.motion_search:
        problems.append(
            "init.train_knot_rotation = false needs init.motion_search = true (the knots keep its best "
            "motion's turn)"
        )
    if cfg.init.branches < 1 or cfg.init.branch_frames < 0:
        problems.append("init.branches must be >= 1 (1 = off) and init.branch_frames >= 0")
    elif cfg.init.branches > 1 and not cfg.init.motion_search:
        problems.append("init.branches > 1 needs init.motion_search = true (branches start from its best)")
    elif cfg.init.branch_restarts < 1:
        problems.append("init.branch_restarts must be >= 1 (1 = the kept branch is not run again)")
    elif cfg.init.branch_restarts > 1 and not cfg.init.motion_search:
        problems.append("init.branch_restarts > 1 needs init.motion_search = true (restarts run its best)")
    elif max(cfg.init.branches, cfg.init.branch_restarts) > 1 and (
        cfg.init.branch_score == "tracking" and cfg.init.branch_frames < 1
    ):
        problems.append("init.branch_score = 'tracking' needs init.branch_frames >= 1 (the frames it scores)")
    if cfg.mapping.replay_every < 0 or cfg.mapping.replay_every == 1:
        problems.append("mapping.replay_every must be 0 (off) or >= 2 (1 would leave no window of its own)")
    if cfg.tracking.span_frames < 1:
        problems.append("tracking.span_frames must be >= 1 (1 = the new chunk only)")
    if cfg.tracking.velocity_prior < 0 or (cfg.tracking.velocity_prior > 0 and cfg.tracking.solver != "lm"):
        problems.append("tracking.velocity_prior must be >= 0, and > 0 only with tracking.solver = 'lm'")
    if not 0 <= cfg.tracking.velocity_prior_floor <= 1:
        problems.append(
            "tracking.velocity_prior_floor must be in [0, 1] (a fraction of the best-seen coordinate)"
        )
    if cfg.tracking.lm_windows < 0:
        problems.append("tracking.lm_windows must be >= 0 (0 = fresh windows every LM step)")
    if cfg.tracking.velocity_prior_frames < 0:
        problems.append("tracking.velocity_prior_frames must be >= 0 (0 = the whole run)")
    if g.init_fill_gap < 0:
        problems.append("gaussians.init_fill_gap must be >= 0 (0 = off)")
    if not 0 <= cfg.loss.lambda_ssim <= 1:
        problems.append("loss.lambda_ssim must be in [0, 1]")
    if cfg.loss.depth_tv < 0:
        problems.append("loss.depth_tv must be >= 0 (0 = off)")
    positive = {
        "data.training_batch_size": d.training_batch_size,
        "init.num_frames": cfg.init.num_frames,
        "gaussians.num_init": g.num_init,
        "gaussians.bounding_size": g.bounding_size,
        "strategy.refine_every": s.refine_every,
        "mapping.window": cfg.mapping.window,
        "torch_threads": cfg.torch_threads,
    }
    problems += [f"{key} must be > 0" for key, value in positive.items() if value <= 0]
    if problems:
        raise ConfigError(f"{source}: " + "; ".join(problems))


def _read_chain(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """Read ``path`` and its ancestors, validating each file on its own so errors name the right file."""
    path = path.resolve()
    if path in seen:
        chain = " -> ".join(str(p) for p in (*seen, path))
        raise ConfigError(f"{path}: inheritance cycle: {chain}")
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: {e}") from None
    parent = doc.pop("inherit", None)
    own = _validate(doc, Config, str(path))
    if parent is None:
        return own
    if not isinstance(parent, str):
        raise ConfigError(f"{path}: 'inherit' must be a path string")
    return _merge(_read_chain(path.parent / parent, (*seen, path)), own)


def _parse_override(item: str) -> tuple[list[str], str]:
    key, sep, raw = item.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. loss.lambda_ssim=0.05")
    return key.strip().split("."), raw.strip()


def _coerce(raw: str, tp: Any, where: str) -> Any:
    """Parse an override's text by the type of the key it sets."""
    if typing.get_origin(tp) is Literal or tp is str:
        value: Any = raw[1:-1] if len(raw) >= 2 and raw[0] == raw[-1] and raw[0] in "'\"" else raw
    elif tp is bool:
        if raw.lower() not in ("true", "false"):
            raise ConfigError(f"{where}: expected true or false, got {raw!r}")
        value = raw.lower() == "true"
    else:
        try:
            value = tp(raw)
        except ValueError:
            raise ConfigError(f"{where}: expected {tp.__name__}, got {raw!r}") from None
    return _check_value(value, tp, where)


def _apply_override(doc: dict[str, Any], item: str) -> dict[str, Any]:
    path, raw = _parse_override(item)
    cls: Any = Config
    node = doc = dict(doc)
    for i, key in enumerate(path):
        hints = _hints(cls)
        dotted = ".".join(path[: i + 1])
        if key not in hints:
            raise ConfigError(f"--set {item!r}: unknown key {dotted!r}{_suggest(key, hints)}")
        tp = hints[key]
        last = i == len(path) - 1
        if is_dataclass(tp) == last:
            kind = "a section; set one of its keys" if last else "not a section"
            raise ConfigError(f"--set {item!r}: {dotted!r} is {kind}")
        if last:
            node[key] = _coerce(raw, tp, f"--set {dotted}")
        else:
            node[key] = dict(node.get(key, {}))
            node, cls = node[key], tp
    return doc


def resolve_config_path(name: str | Path) -> Path:
    """An existing file path as given, else ``configs/<name>.toml`` (e.g. ``synthetic/orbit_ambient``)."""
    path = Path(name)
    if path.is_file():
        return path
    candidate = CONFIG_DIR / f"{name}.toml"
    if candidate.is_file():
        return candidate
    raise ConfigError(f"{name}: no such config file (nor {candidate})")


def load_config(path: str | Path = DEFAULT_CONFIG, overrides: Iterable[str] = ()) -> Config:
    """Resolve ``path`` with its inheritance chain, apply ``--set`` style overrides, validate."""
    path = resolve_config_path(path)
    doc = _read_chain(path)
    for item in overrides:
        doc = _apply_override(doc, item)
    cfg = _build(Config, doc, str(path))
    _check_ranges(cfg, str(path))
    return cfg


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """``--config NAME|FILE`` and repeatable ``--set KEY=VALUE`` for commands that take a config."""
    parser.add_argument(
        "--config",
        default=None,
        metavar="NAME|FILE",
        help="config file, or a name under configs/ such as synthetic/orbit_ambient (default: default.toml)",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one key, e.g. --set loss.lambda_ssim=0.05 (repeatable)",
    )


def config_from_args(args: argparse.Namespace) -> Config:
    return load_config(args.config or DEFAULT_CONFIG, args.overrides)


def config_from_snapshot(doc: Mapping[str, Any], source: str = "config") -> tuple[Config, list[str]]:
    """The config of a run's resolved ``config.toml`` snapshot, and the keys it lacked.

    A snapshot is complete for the evgs that wrote it; a key a later version added is missing from it and
    takes default.toml's value, which leaves the feature it brought off, so an older run resumes as it was
    configured. Unknown keys and bad values are errors as in any config."""
    own = _validate(doc, Config, source)
    defaults = _read_chain(DEFAULT_CONFIG)
    cfg = _build(Config, _merge(defaults, own), source)
    _check_ranges(cfg, source)
    return cfg, _missing_keys(defaults, own)


def _missing_keys(full: Mapping[str, Any], doc: Mapping[str, Any], prefix: str = "") -> list[str]:
    missing = []
    for key, value in full.items():
        if key not in doc:
            missing.append(f"{prefix}{key}")
        elif isinstance(value, dict):
            missing += _missing_keys(value, doc[key], f"{prefix}{key}.")
    return missing


def save_config(config: Config, path: str | Path) -> None:
    """Write the fully resolved config (no ``inherit``), atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(tomli_w.dumps(config.to_dict()))


__all__ = [
    "CONFIG_DIR",
    "DEFAULT_CONFIG",
    "Config",
    "ConfigError",
    "add_config_arguments",
    "config_from_args",
    "config_from_snapshot",
    "load_config",
    "resolve_config_path",
    "save_config",
]
