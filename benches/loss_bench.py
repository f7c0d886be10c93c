"""The SSIM term of the event loss, forward and backward, with its Gaussian window blurred three ways.

Run: ``make dev && PYTHONPATH=python $VENV/bin/python benches/loss_bench.py`` (or ``make bench``).
Prints milliseconds per ``(1 − SSIM).backward()`` on a batch of two float32 renders at the coarse
(160×120) and full (640×480) levels, on the SLAM's two torch threads with its OpenMP wait policy
(``PASSIVE``, as the ``evgs`` command sets it: idle threads sleep, so every small op pays a wake-up):
- ``evgs``: the Rust core's separable blur (``evgs.slam.loss``, what the SLAM runs);
- ``torch loop``: the same fused multiply-adds as 44 torch ops (evgs's blur before §68, bit-identical);
- ``torch conv2d``: two 1-D convolutions with torch's autograd.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads, as evgs.cli does

import time
from collections.abc import Callable
from unittest import mock

import torch
import torch.nn.functional as F
from evgs.slam import loss
from torch import Tensor

Blur = Callable[[Tensor, Tensor], Tensor]


def torch_loop(x: Tensor, k: Tensor) -> Tensor:
    """The peer: one ``mul`` and ``n − 1`` ``add_(alpha=k[i])`` per pass, autograd through them."""
    n, taps = len(k), k.tolist()
    w, h = x.shape[-1] - n + 1, x.shape[-2] - n + 1
    rows = x[..., :, :w] * taps[0]
    for i in range(1, n):
        rows = rows.add(x[..., :, i : i + w], alpha=taps[i])
    out = rows[..., :h, :] * taps[0]
    for i in range(1, n):
        out = out.add(rows[..., i : i + h, :], alpha=taps[i])
    return out


def torch_conv2d(x: Tensor, k: Tensor) -> Tensor:
    flat = x.reshape(-1, 1, *x.shape[-2:])
    out = F.conv2d(F.conv2d(flat, k.view(1, 1, 1, -1)), k.view(1, 1, -1, 1))
    return out.reshape(*x.shape[:-2], *out.shape[-2:])


def ssim_term(a: Tensor, b: Tensor, blur: Blur) -> Tensor:
    """``1 − SSIM`` by ``evgs.slam.loss.ssim`` itself, with its blur swapped for ``blur``."""
    with mock.patch.object(loss, "_blur_valid", blur):
        return 1 - loss.ssim(a, b).mean()


def ms_per_call(a: Tensor, b: Tensor, blur: Blur, reps: int) -> float:
    def step() -> None:
        a.grad = None
        ssim_term(a, b, blur).backward()

    step()
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(reps):
            step()
        best = min(best, (time.perf_counter() - t0) / reps)
    return best * 1e3


def main() -> None:
    torch.set_num_threads(2)
    gen = torch.Generator().manual_seed(0)
    blurs: dict[str, Blur] = {
        "evgs": loss._blur_valid,
        "torch loop": torch_loop,
        "torch conv2d": torch_conv2d,
    }
    print(f"{'renders':>14} " + " ".join(f"{name:>13}" for name in blurs) + "   (ms per forward + backward)")
    for h, w, reps in [(120, 160, 50), (480, 640, 5)]:
        a = torch.rand(2, h, w, generator=gen, requires_grad=True)
        b = torch.rand(2, h, w, generator=gen)
        times = {name: ms_per_call(a, b, blur, reps) for name, blur in blurs.items()}
        speedup = min(v for k, v in times.items() if k != "evgs") / times["evgs"]
        cells = " ".join(f"{t:13.2f}" for t in times.values())
        print(f"{f'2 × {w}×{h}':>14} {cells}   evgs {speedup:.1f}× the faster peer")


if __name__ == "__main__":
    main()
