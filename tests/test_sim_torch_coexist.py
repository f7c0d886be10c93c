"""Simulating and then optimising in one process must not crash: Mesa's llvmpipe and triton (pulled in
lazily by torch optimizers) each carry an LLVM, and triton segfaults if it loads second. Runs in a fresh
interpreter because the outcome depends on what the process has loaded before."""

import subprocess
import sys

SCRIPT = """
from evgs.data.sequence import Camera
from evgs.sim.lights import LIGHTING
from evgs.sim.render import Renderer
from evgs.sim.scene import make_scene
import numpy as np, torch
with Renderer(make_scene("satellite"), Camera(32, 24, 30.0, 30.0, 16.0, 12.0), LIGHTING["ambient"]) as r:
    pass
torch.optim.Adam([torch.zeros(1, requires_grad=True)]).step()
print("ok")
"""


def test_render_then_torch_optimizer_in_one_process():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "ok"
