"""The package imports, the extension loads, and the CLI answers."""

import os
import subprocess
import sys

import evgs
import numpy as np
import pytest
from evgs import _core


def test_version_matches_extension():
    assert evgs.__version__ == _core.__version__


def test_validate_events_names_source_and_index():
    t = np.arange(3, dtype=np.int64)
    x = np.array([0, 1, 9], dtype=np.uint16)
    y = np.zeros(3, dtype=np.uint16)
    p = np.ones(3, dtype=np.int8)
    with pytest.raises(ValueError, match=r"mem: event 2: \(9, 0\) outside the 4x4 sensor"):
        _core.validate_events(t, x, y, p, 4, 4, "mem")


def test_cli_help():
    out = subprocess.run(
        [sys.executable, "-m", "evgs.cli", "--help"], capture_output=True, text=True, check=True
    )
    assert "events" in out.stdout


@pytest.mark.parametrize("module", ["evgs", "evgs.cli"])
def test_cli_as_module_reports_user_errors_in_one_line(module):
    """Run as a module, the command must still catch the subcommands' UserError (one line, exit 2)."""
    out = subprocess.run(
        [sys.executable, "-m", module, "bench", "slam", "--presets", "no_such", "--frames", "2"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 2, out.stderr
    assert "Traceback" not in out.stderr
    assert out.stderr.startswith("evgs: error: preset 'no_such'")


@pytest.mark.parametrize(("preset", "expected"), [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_cli_sets_omp_wait_policy_before_torch_loads(preset, expected):
    """The command sleeps idle OpenMP threads (runs sharing cores spin otherwise) unless the user chose;
    the setting only takes if torch has not loaded yet, so importing the CLI must not import torch."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if preset is not None:
        env["OMP_WAIT_POLICY"] = preset
    script = "import os, sys, evgs.cli; print(os.environ['OMP_WAIT_POLICY'], 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split() == [expected, "False"]
