"""One set of CPU code paths for torch, MKL, numpy and OpenBLAS on every x86-64 machine.

These libraries pick their kernels at run time by the CPU they find: torch's AVX-512 loops, MKL's per-CPU
BLAS and vector maths (which takes other paths on AMD than on Intel), numpy's AVX-512 ``exp``/``log``,
OpenBLAS's SkylakeX kernels. Each gives other last bits than the AVX2 path, and a SLAM run amplifies a
last bit into another trajectory: the tiny sequence's ATE moved from 0.126 to 0.085 by MKL's choice alone,
and swirl_good's seeds drew other motions on an Intel Xeon than on an AMD EPYC (docs/ablations.md §86, §92).
The Rust core is built for x86-64-v3 (AVX2, FMA) and never dispatches, so pinning the libraries to the same
level runs the same instructions on any x86-64-v3 machine, Intel or AMD, as the thread pins
(``torch_threads``) make the bits those of any core count (checked so far on one CPU, with MKL held to
AVX2 as a CPU without AVX-512 would run it). On this project's runs the pins cost no measurable time:
the hot loops are the Rust core's.

:func:`pin` must run before numpy is imported and before torch's first operation; ``import evgs``
calls it first thing. Each pin is a default: a variable already set in the environment wins.
"""

from __future__ import annotations

import os
import platform

PINS: dict[str, str] = {
    # torch's own vectorised kernels (reductions, element-wise loops).
    "ATEN_CPU_CAPABILITY": "avx2",
    # MKL, torch's BLAS, LAPACK and vector maths (log, exp): the one branch MKL keeps alike on Intel and
    # AMD (its AVX2 branch is Intel's only: elsewhere MKL falls back to its own choice).
    "MKL_CBWR": "COMPATIBLE",
    # oneDNN, torch's convolutions (the LPIPS network of the image metrics).
    "ONEDNN_MAX_CPU_ISA": "AVX2",
    # numpy's SIMD loops, at the level of numpy ≥ 2.4's dispatch targets.
    "NPY_ENABLE_CPU_FEATURES": "X86_V3",
    # numpy's and scipy's OpenBLAS kernels (the smoother's solves).
    "OPENBLAS_CORETYPE": "Haswell",
}


X86_64 = platform.machine().lower() in ("x86_64", "amd64")
"""The pins' names mean something on x86-64 only."""


def pin() -> None:
    """Set every pin the environment does not set already. Libraries imported before the call keep
    the machine's own code paths."""
    if X86_64:
        for name, value in PINS.items():
            os.environ.setdefault(name, value)


def in_effect() -> dict[str, str | None]:
    """The dispatch a run's bits come from, for its ``metrics.json``: each pin's value in the
    environment and the capability torch reports (``AVX2`` when its pin took)."""
    import torch

    return {name: os.environ.get(name) for name in PINS} | {
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability()
    }


def unpinned() -> str | None:
    """Why this process's bits are its CPU's own, when they are (torch ran before evgs was imported, or
    the environment chose another capability); None when torch runs the pinned kernels."""
    import torch

    pinned, got = PINS["ATEN_CPU_CAPABILITY"], torch.backends.cpu.get_cpu_capability()
    if not X86_64 or got.lower() == pinned:
        return None
    chosen = os.environ.get("ATEN_CPU_CAPABILITY") != pinned
    cause = "ATEN_CPU_CAPABILITY is set" if chosen else "torch ran before evgs was imported"
    return f"torch runs its {got} kernels, not the pinned {pinned.upper()} ones ({cause}): bits of this CPU"
