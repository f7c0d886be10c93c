"""The loss terms the Rust core computes, forward and backward, beside their torch form.

Run: ``make dev && PYTHONPATH=python $VENV/bin/python benches/loss_bench.py`` (or ``make bench``).
Prints milliseconds per ``term.backward()`` on what one mapping step evaluates, at the coarse
(320×240) and full (640×480) levels, on the SLAM's two torch threads with its OpenMP wait policy
(``PASSIVE``, as the ``evgs`` command sets it: idle threads sleep, so every small op pays a wake-up):
- the SSIM term ``1 − SSIM`` of a window's two float32 renders: ``evgs.slam.loss.ssim`` (the Rust
  kernel, its gradient in the forward pass) against ``evgs.slam.loss_torch.ssim`` (torch autograd, the
  blur by two 1-D ``conv2d``);
- the relief prior ``depth_variation`` of both views' depth and opacity (a render-like target: an
  opaque disc of varying depth on a transparent background): ``evgs.slam.loss`` against
  ``evgs.slam.loss_torch`` (boolean indexing and ``median`` in torch).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads, as evgs.cli does

import time
from collections.abc import Callable

import torch
from evgs.slam import loss, loss_torch
from torch import Tensor


def ms_per_call(step: Callable[[], Tensor], inputs: list[Tensor], reps: int) -> float:
    def once() -> None:
        for t in inputs:
            t.grad = None
        step().backward()

    once()
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(reps):
            once()
        best = min(best, (time.perf_counter() - t0) / reps)
    return best * 1e3


def disc_views(h: int, w: int, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Depth and opacity of two views of an opaque disc (radius 0.35 of the height) at depth ≈ 3."""
    y, x = torch.meshgrid(
        torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij"
    )
    r = torch.hypot(y - h / 2, x - w / 2) / h
    alpha = torch.sigmoid((0.35 - r) * 60).expand(2, h, w).contiguous()
    depth = (3 + 0.3 * torch.rand(2, h, w, generator=gen)) * alpha
    return depth.requires_grad_(), alpha.requires_grad_()


def bench_level(h: int, w: int, reps: int, gen: torch.Generator) -> None:
    a = torch.rand(1, h, w, generator=gen, requires_grad=True)
    b = (0.7 * a.detach() + 0.3 * torch.rand(1, h, w, generator=gen)).requires_grad_()
    depth, alpha = disc_views(h, w, gen)
    terms = {
        ("1 − SSIM", f"1 × {w}×{h}"): ([a, b], lambda m: 1 - m.ssim(a, b).mean()),
        ("depth_variation", f"2 × {w}×{h}"): ([depth, alpha], lambda m: m.depth_variation(depth, alpha)),
    }
    for (name, size), (inputs, term) in terms.items():
        ours = ms_per_call(lambda term=term: term(loss), inputs, reps)
        peer = ms_per_call(lambda term=term: term(loss_torch), inputs, reps)
        print(f"{name:>16} {size:>14} {ours:8.2f} {peer:8.2f}   evgs {peer / ours:.1f}× torch")


def main() -> None:
    torch.set_num_threads(2)
    gen = torch.Generator().manual_seed(0)
    print(f"{'term':>16} {'renders':>14} {'evgs':>8} {'torch':>8}   (ms per forward + backward)")
    for h, w, reps in [(240, 320, 40), (480, 640, 10)]:
        bench_level(h, w, reps, gen)


if __name__ == "__main__":
    main()
