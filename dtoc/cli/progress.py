"""Progress of long commands on stderr: a rich bar with ETA on a terminal, plain lines under a script or CI log.

Plain lines (stderr not a terminal) look like
``dtoc optimize: warm 120/400 (30 %), loss 0.01234, elapsed 12.3 s, ETA 28.7 s`` and come at the first
report of a stage, at most every ``every_s`` seconds after it, and at the stage's last iteration; the ETA
extrapolates the stage's rate since its first report ("ETA -" until there is one).
``quiet`` silences everything (errors still print). Nothing is printed before the first report, so a
command that fails early prints its one error line only.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


class ProgressReporter:
    """Report ``update(stage, it, total, value)`` (iterations) and ``step(text)`` (named stages).

    Args:
        command: prefix of the plain lines (``dtoc optimize``).
        quiet: print nothing.
        every_s: minimum spacing of plain lines within a stage, s.
        stream: where to write (default stderr); ``tty`` overrides the terminal detection.
        value_label: name of the figure reported with each update (``loss``).
    """

    def __init__(
        self,
        command: str,
        quiet: bool = False,
        every_s: float = 2.0,
        stream: TextIO | None = None,
        tty: bool | None = None,
        value_label: str = "loss",
    ):
        self.command = command
        self.quiet = quiet
        self.every_s = every_s
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty() if tty is None else tty
        self.value_label = value_label
        self.t0 = time.monotonic()
        self._stage_t0: dict[str, tuple[float, int]] = {}  # stage -> (time, iteration) of its first report
        self._last_line = -float("inf")
        self._bar = None
        self._tasks: dict[str, int] = {}

    # ---- iterations ------------------------------------------------------------------------------
    def update(self, stage: str, it: int, total: int, value: float | str | None = None) -> None:
        if self.quiet:
            return
        now = time.monotonic()
        first = stage not in self._stage_t0
        if first:
            self._stage_t0[stage] = (now, it)
        if self.tty:
            self._update_bar(stage, it, total, value)
            return
        if not (first or it >= total or now - self._last_line >= self.every_s):
            return
        self._last_line = now
        t_first, it_first = self._stage_t0[stage]
        rate_s = (now - t_first) / (it - it_first) if it > it_first else None  # s per iteration
        eta = rate_s * max(total - it, 0) if rate_s is not None else None
        parts = [f"{stage} {it}/{total} ({100.0 * it / max(total, 1):.0f} %)"]
        if value is not None:
            parts.append(_label(self.value_label, value))
        parts.append(f"elapsed {now - self.t0:.1f} s")
        parts.append("ETA -" if eta is None else f"ETA {eta:.1f} s")
        self._line(", ".join(parts))

    def _update_bar(self, stage: str, it: int, total: int, value: float | str | None) -> None:
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        if self._bar is None:
            self._bar = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                TextColumn("{task.completed}/{task.total}"),
                TextColumn("{task.fields[value]}"),
                TimeElapsedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                console=Console(file=self.stream, force_terminal=True),
                transient=True,
            )
            self._bar.start()
        if stage not in self._tasks:
            self._tasks[stage] = self._bar.add_task(stage, total=total, value=_label(self.value_label, "-"))
        text = _label(self.value_label, "-" if value is None else value)
        self._bar.update(self._tasks[stage], completed=it, value=text)

    # ---- named stages ----------------------------------------------------------------------------
    def step(self, text: str) -> None:
        """A named stage begins (``simulating: ideal``); one line each, also on a terminal."""
        if self.quiet:
            return
        self._line(f"{text} (elapsed {time.monotonic() - self.t0:.1f} s)")

    def _line(self, text: str) -> None:
        if self._bar is not None:
            self._bar.console.print(f"{self.command}: {text}")
            return
        self.stream.write(f"{self.command}: {text}\n")
        self.stream.flush()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None


def _label(label: str, value: float | str) -> str:
    """``loss 0.01234`` for a number, ``loss -`` for none yet; a text (``3 ran, 1 cached``) as it is."""
    if isinstance(value, str):
        return f"{label} {value}" if value == "-" else value
    return f"{label} {value:.4g}"
