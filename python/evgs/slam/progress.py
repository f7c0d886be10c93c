"""What a running stage shows and leaves behind: a rich progress bar per stage (iteration, loss,
events/s, ETA) and the diagnostic grids every ``output.diagnostics_every`` iterations (and at the end
of the final global BA), written to ``diagnostics/<stage>_<frame>_<iter>.png``."""

from __future__ import annotations

from pathlib import Path

import torch
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from evgs.events.frames import WindowSampler
from evgs.slam.optimize import StageSpec, render_windows
from evgs.slam.state import SlamState, StageRecord
from evgs.slam.viz import diagnostics_image, write_png
from evgs.slam.windows import EventData


def diagnostic_sampler(data: EventData, spec: StageSpec) -> WindowSampler:
    """Its own stream (seed differs from the stage's), so diagnostics never change a run's windows."""
    return data.sampler(spec.span, spec.seed ^ 0x5BD1E995, spec.max_window)


@torch.no_grad()
def write_diagnostics(
    state: SlamState, spec: StageSpec, sampler: WindowSampler, iteration: int, out: Path
) -> Path:
    win = state.data.windows(sampler, state.cfg.output.diagnostics_rows)
    res = render_windows(state, win, state.data.camera)
    b = len(win.starts)
    gray = res.color[..., 0]
    prefix = f"{state.branch}_" if state.branch else ""
    path = out / f"{prefix}{spec.stage}_{spec.frame:06d}_{iteration:05d}.png"
    write_png(path, diagnostics_image(gray[:b], gray[b:], win.frames, state.cfg.loss))
    return path


class RunReporter:
    """Progress bars (when ``show``) and diagnostic grids (into ``diagnostics_dir``)."""

    def __init__(self, diagnostics_dir: Path, show: bool = True, console: Console | None = None):
        self.diagnostics_dir = diagnostics_dir
        self.progress = Progress(
            TextColumn("{task.description:<16}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("loss {task.fields[loss]:.5f}  {task.fields[rate]:>6.2f} Mev/s"),
            TimeRemainingColumn(),
            console=console,
            disable=not show,
            transient=True,
        )
        self._task: int | None = None
        self._sampler: tuple[StageSpec, WindowSampler] | None = None

    def __enter__(self) -> RunReporter:
        self.progress.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.progress.__exit__(*exc)

    def _diagnostics(self, state: SlamState, spec: StageSpec, iteration: int) -> None:
        if self._sampler is None or self._sampler[0] is not spec:
            self._sampler = (spec, diagnostic_sampler(state.data, spec))
        write_diagnostics(state, spec, self._sampler[1], iteration, self.diagnostics_dir)

    def advance(
        self, state: SlamState, spec: StageSpec, it: int, loss: float, events: int, seconds: float
    ) -> None:
        if it == 0:
            self._task = self.progress.add_task(
                f"{spec.stage} {spec.frame}", total=spec.iterations, loss=loss, rate=0.0
            )
        assert self._task is not None
        self.progress.update(self._task, completed=it + 1, loss=loss, rate=events / max(seconds, 1e-9) / 1e6)
        every = state.cfg.output.diagnostics_every
        if every > 0 and (it + 1) % every == 0:
            self._diagnostics(state, spec, it + 1)

    def stage_end(self, state: SlamState, spec: StageSpec, record: StageRecord) -> None:
        if self._task is not None:
            self.progress.remove_task(self._task)
            self._task = None
        every = state.cfg.output.diagnostics_every
        if spec.stage == "final" and every > 0 and record.iterations % every != 0:
            self._diagnostics(state, spec, record.iterations)
        self._sampler = None
