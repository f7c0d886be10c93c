"""Config files: inheritance, overrides, validation, round trip."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest
import tomllib
from evgs.config import (
    CONFIG_DIR,
    DEFAULT_CONFIG,
    Config,
    ConfigError,
    add_config_arguments,
    config_from_args,
    config_from_snapshot,
    load_config,
    save_config,
)


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_default_sets_every_key_with_reference_values():
    # default.toml sets every key; reference.toml (inheriting it) undoes its CPU economy cuts.
    cfg = load_config("reference")
    assert isinstance(cfg, Config)
    assert cfg.trajectory.pose_lr == 1e-4
    assert cfg.gaussians.num_init == 100_000
    assert cfg.tracking.num_opti_steps == 201
    assert cfg.tracking.mask_border == 20 and cfg.tracking.mask_alpha == 0.8
    assert cfg.mapping.num_opti_steps_for_BA == 3001
    assert cfg.loss.ssim_window == 11 and cfg.loss.ssim_sigma == 1.5
    assert cfg.strategy.prune_opa == 0.1 and cfg.strategy.prune_scale3d == 0.1
    assert cfg.loss.event_loss == "l1" and cfg.trajectory.interpolation == "geodesic"
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.seed = 3  # type: ignore[misc]


@pytest.mark.parametrize("path", sorted(p for p in CONFIG_DIR.rglob("*.toml")), ids=lambda p: p.name)
def test_every_shipped_config_resolves(path: Path):
    load_config(path)


def test_inheritance_chain_overrides_by_section(tmp_path: Path):
    write(tmp_path / "set.toml", f'inherit = "{DEFAULT_CONFIG}"\n[loss]\nlambda_ssim = 0.05\n')
    seq = write(
        tmp_path / "set" / "seq.toml",
        'inherit = "../set.toml"\nseq = "data/x"\n[loss]\nevent_loss = "mse"\n[data]\nstart_frame = 7\n',
    )
    cfg = load_config(seq)
    assert cfg.seq == "data/x"
    assert cfg.loss.lambda_ssim == 0.05 and cfg.loss.event_loss == "mse"  # both levels kept
    assert cfg.data.start_frame == 7
    assert cfg.loss.ssim_window == 11  # untouched keys come from the default
    assert load_config("synthetic/orbit_ambient").data.event_contrast == 0.25  # the simulator's C


def test_int_accepted_for_float_and_converted(tmp_path: Path):
    p = write(tmp_path / "a.toml", f'inherit = "{DEFAULT_CONFIG}"\n[trajectory]\npose_lr = 1\n')
    cfg = load_config(p)
    assert cfg.trajectory.pose_lr == 1.0 and isinstance(cfg.trajectory.pose_lr, float)


def test_unknown_key_names_file_key_and_suggestion(tmp_path: Path):
    p = write(tmp_path / "bad.toml", f'inherit = "{DEFAULT_CONFIG}"\n[strategy]\nprune_opacity = 0.2\n')
    with pytest.raises(ConfigError) as e:
        load_config(p)
    msg = str(e.value)
    assert str(p) in msg and "strategy.prune_opacity" in msg and "'prune_opa'" in msg


def test_unknown_section_and_bad_types(tmp_path: Path):
    cases = {
        "[mappin]\nevery = 1\n": ("unknown key 'mappin'", "'mapping'"),
        "[data]\nstart_frame = 1.5\n": ("data.start_frame", "expected int"),
        "[loss]\nevent_loss = 'l2'\n": ("loss.event_loss", "'l1', 'mse'"),
        "[strategy]\nreset_at_stage_start = 1\n": ("reset_at_stage_start", "expected bool"),
        "loss = 3\n": ("'loss' must be a table",),
        "[data.start_frame]\nx = 1\n": ("is a value, not a table",),
    }
    for i, (body, needles) in enumerate(cases.items()):
        p = write(tmp_path / f"c{i}.toml", f'inherit = "{DEFAULT_CONFIG}"\n{body}')
        with pytest.raises(ConfigError) as e:
            load_config(p)
        assert str(p) in str(e.value)
        for n in needles:
            assert n in str(e.value), (body, str(e.value))


def test_missing_key_without_default_root(tmp_path: Path):
    p = write(tmp_path / "alone.toml", "seed = 1\n")
    with pytest.raises(ConfigError, match="missing key 'seq'"):
        load_config(p)


def test_cycle_missing_parent_and_syntax_error(tmp_path: Path):
    write(tmp_path / "a.toml", 'inherit = "b.toml"\n')
    write(tmp_path / "b.toml", 'inherit = "a.toml"\n')
    with pytest.raises(ConfigError, match="inheritance cycle"):
        load_config(tmp_path / "a.toml")
    write(tmp_path / "c.toml", 'inherit = "nope.toml"\n')
    with pytest.raises(ConfigError, match="nope.toml: config file not found"):
        load_config(tmp_path / "c.toml")
    bad = write(tmp_path / "d.toml", "seed = = 1\n")
    with pytest.raises(ConfigError, match="d.toml"):
        load_config(bad)
    with pytest.raises(ConfigError, match="no such config"):
        load_config("no/such/sequence")


def test_overrides_typed_by_the_field():
    cfg = load_config(
        overrides=[
            "loss.lambda_ssim=0.05",
            "data.training_batch_size=5",
            "strategy.reset_at_stage_start=true",
            "trajectory.interpolation=lerp",
            "seq=data/seenic/orbit_ambient",
            "output.runs_dir='out dir'",
            "trajectory.pose_lr=1e-5",
        ]
    )
    assert cfg.loss.lambda_ssim == 0.05
    assert cfg.data.training_batch_size == 5
    assert cfg.strategy.reset_at_stage_start is True
    assert cfg.trajectory.interpolation == "lerp"
    assert cfg.seq == "data/seenic/orbit_ambient"
    assert cfg.output.runs_dir == "out dir"
    assert cfg.trajectory.pose_lr == 1e-5


@pytest.mark.parametrize(
    ("item", "needle"),
    [
        ("loss.lamda_ssim=1", "did you mean 'lambda_ssim'"),
        ("los.lambda_ssim=1", "did you mean 'loss'"),
        ("loss=1", "is a section"),
        ("seed.x=1", "not a section"),
        ("data.start_frame=1.5", "expected int"),
        ("loss.lambda_ssim=abc", "expected float"),
        ("strategy.reset_at_stage_start=1", "expected true or false"),
        ("trajectory.interpolation=cubic", "must be one of"),
        ("noequals", "expected KEY=VALUE"),
    ],
)
def test_bad_overrides(item: str, needle: str):
    with pytest.raises(ConfigError) as e:
        load_config(overrides=[item])
    assert needle in str(e.value) and "--set" in str(e.value)


def test_save_round_trip(tmp_path: Path):
    cfg = load_config("synthetic/orbit_ambient", ["loss.event_loss=mse"])
    out = tmp_path / "run" / "config.toml"
    save_config(cfg, out)
    assert load_config(out) == cfg
    with open(out, "rb") as f:
        doc = tomllib.load(f)
    assert "inherit" not in doc and doc["seq"] == cfg.seq
    assert config_from_snapshot(doc) == (cfg, [])
    doc["loss"]["bogus"] = 1
    with pytest.raises(ConfigError, match="loss.bogus"):
        config_from_snapshot(doc, "snapshot")


def test_an_older_snapshot_takes_the_defaults_of_keys_it_lacks():
    """A run written before a key existed resumes with that key at default.toml's value (its feature
    off); the keys are named. A value the snapshot does hold is kept."""
    cfg = load_config("synthetic/orbit_ambient")
    doc = cfg.to_dict()
    del doc["init"]["branches"], doc["tracking"]["velocity_prior_frames"]
    old, filled = config_from_snapshot(doc, "snapshot")
    assert old == cfg and filled == ["init.branches", "tracking.velocity_prior_frames"]
    assert old.tracking.velocity_prior == 3.0  # the orbit's, not default.toml's 0
    doc["tracking"]["velocity_prior"] = -1.0
    with pytest.raises(ConfigError, match="tracking.velocity_prior must be >= 0"):
        config_from_snapshot(doc, "snapshot")


def test_range_checks_name_the_keys():
    with pytest.raises(ConfigError, match="min_n_winsize <= data.max_n_winsize"):
        load_config(overrides=["data.min_n_winsize=200000"])
    with pytest.raises(ConfigError) as e:
        load_config(overrides=["gaussians.init_opacity=1.0", "strategy.refine_every=0"])
    assert "gaussians.init_opacity must be in (0, 1)" in str(e.value)
    assert "strategy.refine_every must be > 0" in str(e.value)
    for sets in (["tracking.velocity_prior=-1"], ["tracking.solver=adam", "tracking.velocity_prior=1"]):
        with pytest.raises(ConfigError, match="tracking.velocity_prior must be >= 0, and > 0 only with"):
            load_config(overrides=sets)
    for floor in ("-0.1", "1.5"):
        with pytest.raises(ConfigError, match=r"tracking.velocity_prior_floor must be in \[0, 1\]"):
            load_config(overrides=[f"tracking.velocity_prior_floor={floor}"])
    for order in ("0", "5"):
        with pytest.raises(ConfigError, match="trajectory.smoothing_order must be 1–4"):
            load_config(overrides=[f"trajectory.smoothing_order={order}"])
    with pytest.raises(ConfigError, match="trajectory.smoothing_end_fit must be >= 0"):
        load_config(overrides=["trajectory.smoothing_end_fit=-1"])
    with pytest.raises(ConfigError, match="tracking.velocity_prior_frames must be >= 0"):
        load_config(overrides=["tracking.velocity_prior_frames=-1"])
    with pytest.raises(ConfigError, match="loss.depth_tv must be >= 0"):
        load_config(overrides=["loss.depth_tv=-1"])


def test_command_line_arguments():
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    args = parser.parse_args(
        ["--config", "seenic/orbit_ambient", "--set", "seed=3", "--set", "loss.lambda_ssim=0.2"]
    )
    cfg = config_from_args(args)
    assert cfg.seed == 3 and cfg.loss.lambda_ssim == 0.2 and cfg.data.start_frame == 375
    assert config_from_args(parser.parse_args([])) == load_config()
