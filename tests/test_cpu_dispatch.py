"""The CPU dispatch pins (evgs/cpu_dispatch.py): ``import evgs`` sets them before numpy and torch load,
the libraries take them, a user's own setting wins, and a late pin is reported. Each case runs in a fresh
interpreter, since the libraries read the pins once, at their import."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from evgs.cpu_dispatch import PINS, X86_64

pytestmark = pytest.mark.skipif(not X86_64, reason="x86-64 pins")

PROBE = """
import json, os
{first}
import numpy as np
from evgs import cpu_dispatch
exp = np.lib.introspect.opt_func_info(func_name="exp", signature="float64.*")["exp"]["dd"]["current"]
print(json.dumps({{"env": {{k: os.environ.get(k) for k in cpu_dispatch.PINS}},
                  "torch": torch.backends.cpu.get_cpu_capability(), "numpy_exp": exp,
                  "unpinned": cpu_dispatch.unpinned()}}))
"""


def probe(first: str, **env: str) -> dict:
    """Import evgs and torch in the order ``first`` gives, in a clean environment plus ``env``."""
    clean = {k: v for k, v in os.environ.items() if k not in PINS} | env
    code = PROBE.format(first=first)
    out = subprocess.run([sys.executable, "-c", code], env=clean, capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def has_avx512() -> bool:
    return "avx512f" in Path("/proc/cpuinfo").read_text()


def test_import_evgs_pins_numpy_and_torch_to_avx2():
    got = probe("import evgs, torch")
    assert got["env"] == PINS
    assert got["torch"] == "AVX2"
    assert got["numpy_exp"] == "X86_V3"  # not X86_V4 (AVX-512), whatever the CPU
    assert got["unpinned"] is None


def test_a_users_setting_wins():
    got = probe("import evgs, torch", ATEN_CPU_CAPABILITY="default", MKL_CBWR="AUTO")
    assert got["env"]["ATEN_CPU_CAPABILITY"] == "default" and got["env"]["MKL_CBWR"] == "AUTO"
    assert got["torch"] == "DEFAULT"
    assert "ATEN_CPU_CAPABILITY is set" in got["unpinned"]


def test_torch_run_first_is_reported_where_it_matters():
    got = probe("import torch; torch.ones(3).sum(); import evgs")  # torch picks its kernels at its first op
    if has_avx512():  # torch chose AVX-512 before the pin
        assert got["torch"].startswith("AVX512") and "ran before evgs was imported" in got["unpinned"]
    else:  # AVX2 is this CPU's best: the bits are the pinned ones anyway
        assert got["torch"] == "AVX2" and got["unpinned"] is None
