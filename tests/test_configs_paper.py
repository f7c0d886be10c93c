"""The shipped configs: every file loads, and the paper's sequences use the paper's frame ranges.

The tables below are copied from the paper (§5, Tables 1–4, "Frames" column, ``A-B`` = frames A..B,
i.e. ``start_frame = A``, ``num_frames = B - A``), so a config edited away from the paper fails here.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from evgs.config import CONFIG_DIR, load_config
from evgs.sim.driver import _regular_times
from evgs.sim.presets import PRESETS

PAPER_FRAMES = {
    # Table 1, SEENIC.
    "seenic/orbit_ambient": (375, 425),
    "seenic/approach_ambient": (90, 140),
    "seenic/orbit_centre": (20, 120),
    # Table 2, E-M-S.
    "ems/0": (0, 60),
    "ems/69": (0, 65),
    "ems/100": (0, 75),
    "ems/420": (0, 65),
    "ems/479": (0, 100),
    # Table 4, ELOPE.
    "elope/0000": (50, 120),
    "elope/0007": (50, 120),
    "elope/0013": (50, 120),
    "elope/0015": (50, 120),
    "elope/0016": (50, 120),
}
# Table 3, the Blender scenes, mirrored by the simulator presets of the same name.
PAPER_SYNTHETIC_FRAMES = {
    "synthetic/docking_low": (0, 75),
    "synthetic/docking_good": (0, 75),
    "synthetic/swirl_low": (0, 75),
    "synthetic/swirl_good": (0, 75),
    "synthetic/orbit": (31, 129),
}

ALL_FILES = sorted(p for p in CONFIG_DIR.rglob("*") if p.is_file())
SEQUENCE_FILES = [p for p in ALL_FILES if not p.name.startswith("_") and p.parent != CONFIG_DIR]


def name_of(path: Path) -> str:
    return path.relative_to(CONFIG_DIR).with_suffix("").as_posix()


def preset_chunks(name: str) -> int:
    """Chunks (frame intervals) of a simulator preset's sequence, from its duration and frame rate."""
    cfg = PRESETS[name]
    return len(_regular_times(cfg.frame_rate, round(cfg.make_trajectory().t_end * 1e6))) - 1


@pytest.mark.parametrize("path", ALL_FILES, ids=name_of)
def test_every_file_is_a_loadable_config_with_a_leading_comment(path: Path):
    assert path.suffix == ".toml", f"{path}: every file under configs/ must be a .toml config"
    assert path.read_text().startswith("# "), f"{path}: first line must say what it is and where from"
    load_config(path)


@pytest.mark.parametrize("path", SEQUENCE_FILES, ids=name_of)
def test_sequence_config_names_its_own_sequence(path: Path):
    """``evgs run --seq D/S`` picks ``configs/D/S.toml``; its ``seq`` must be that same sequence."""
    assert load_config(path).seq == f"data/{name_of(path)}"


def test_every_paper_sequence_has_a_config():
    shipped = {name_of(p) for p in SEQUENCE_FILES}
    missing = (PAPER_FRAMES.keys() | PAPER_SYNTHETIC_FRAMES.keys()) - shipped
    assert not missing


@pytest.mark.parametrize("name", sorted(PAPER_FRAMES))
def test_real_and_challenge_sequences_use_the_papers_frames(name: str):
    first, last = PAPER_FRAMES[name]
    data = load_config(name).data
    assert (data.start_frame, data.num_frames) == (first, last - first)


@pytest.mark.parametrize("name", sorted(PAPER_SYNTHETIC_FRAMES))
def test_synthetic_presets_use_the_papers_frames_where_the_simulation_has_them(name: str):
    """The paper's range where the simulated sequence is long enough, else as many frames from the start;
    either way within the simulated sequence (the pipeline would otherwise silently run fewer)."""
    first, last = PAPER_SYNTHETIC_FRAMES[name]
    data = load_config(name).data
    chunks = preset_chunks(name.split("/")[1])
    expected = (first, last - first) if last <= chunks else (0, last - first)
    assert (data.start_frame, data.num_frames) == expected
    assert data.start_frame + data.num_frames <= chunks


@pytest.mark.parametrize("path", [p for p in SEQUENCE_FILES if p.parent.name == "synthetic"], ids=name_of)
def test_synthetic_configs_name_a_preset_with_their_contrast(path: Path):
    """Built-in synthetic sequences are simulated from the preset of the same name on first use; the
    event frame's contrast must be the threshold it was simulated with."""
    sim = PRESETS[path.stem]
    assert load_config(path).data.event_contrast == sim.c_on == sim.c_off


@pytest.mark.parametrize("name", [n for n in PAPER_FRAMES if n.startswith("ems/")])
def test_ems_uses_the_reference_pose_learning_rate(name: str):
    assert load_config(name).trajectory.pose_lr == 1e-5
