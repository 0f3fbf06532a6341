"""One progress-bar style for every long step: rate, elapsed and ETA (rich)."""
from __future__ import annotations

import contextlib

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

console = Console(stderr=True)


class RateColumn(TextColumn):
    """Items per second with the unit named by the task (``unit`` field)."""

    def __init__(self):
        super().__init__("")

    def render(self, task):
        speed = task.finished_speed or task.speed
        unit = task.fields.get("unit", "it")
        return f"{speed:,.1f} {unit}/s" if speed else f"- {unit}/s"


@contextlib.contextmanager
def progress_bar(description: str, total: int, unit: str = "it"):
    """Yields ``advance(n=1, **fields)``; the bar goes to stderr so ``--json`` output stays clean."""
    prog = Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), RateColumn(),
        TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), console=console,
    )
    with prog:
        task = prog.add_task(description, total=total, unit=unit)

        def advance(n: int = 1, **fields):
            prog.update(task, advance=n, **fields)

        yield advance
