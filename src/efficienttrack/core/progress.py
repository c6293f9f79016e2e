"""Progress of long loops: a rich bar on a terminal, plain lines at a steady interval anywhere else.

Output piped to a file or a CI log is not a terminal; rich draws nothing there until the end. There
:class:`ProgressDisplay` prints one line per task every ``interval`` seconds and a last one when the
display closes, e.g. ``train model 1,200/4,000 loss 0.0123 (35 s, ~80 s left)``.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TextIO

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    Task,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text

PLAIN_INTERVAL = 10.0
"""Seconds between plain progress lines when the output is not a terminal."""


def format_count(value: float) -> str:
    """A task's count as a plain line shows it: ``12,361,696`` for a whole number (not ``1.23617e+07``), else ``:g``.

    Args:
        value: units done, or the task's total.
    """
    return f"{value:,.0f}" if float(value).is_integer() else f"{value:g}"


def format_fields(fields: dict[str, Any]) -> str:
    """``{"loss": 0.01234}`` → ``"loss 0.01234"``: numbers with 4 significant digits, in the given order.

    Args:
        fields: name → value shown after the count.
    """
    return " ".join(f"{name} {value:.4g}" if isinstance(value, float) else f"{name} {value}" for name, value in fields.items())


class _FieldsColumn(ProgressColumn):
    """The task's extra fields (e.g. the loss), as :func:`format_fields` writes them."""

    def render(self, task: Task) -> Text:
        """The fields of ``task`` as text."""
        return Text(format_fields(task.fields))


@dataclass
class _PlainTask:
    description: str
    total: float
    completed: float
    fields: dict[str, Any]
    started: float
    first: float
    """``completed`` when the task was added (a resumed run's rate counts only its own steps)."""


class ProgressDisplay:
    """Progress of one or more tasks; use as a context manager, then ``add_task`` / ``update`` / ``advance``.

    On a terminal it is a rich progress bar; otherwise it prints a plain line per task every ``interval``
    seconds (all tasks shown, when one advances) and a last line per remaining task when it closes. Disabled, it shows nothing.

    Args:
        enabled: show progress at all.
        stream: where to write (``sys.stdout`` when None); rich decides whether it is a terminal.
        interval: seconds between plain lines.
        transient: on a terminal, remove the bars when done.
        clock: monotonic time source in seconds (tests pass their own).
    """

    def __init__(
        self,
        enabled: bool = True,
        stream: TextIO | None = None,
        interval: float = PLAIN_INTERVAL,
        transient: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.stream = stream if stream is not None else sys.stdout
        self.interval, self.clock = interval, clock
        console = Console(file=self.stream)
        self.terminal = enabled and console.is_terminal
        self.enabled = enabled
        self._bar: Progress | None = None
        if self.terminal:
            columns = (
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                _FieldsColumn(),
                TimeElapsedColumn(),
                TimeRemainingColumn(),
            )
            self._bar = Progress(*columns, console=console, transient=transient)
        self._tasks: dict[int, _PlainTask] = {}
        self._next_id = 0
        self._last_line = clock()

    def __enter__(self) -> ProgressDisplay:
        """Start showing progress."""
        if self._bar is not None:
            self._bar.start()
        return self

    def __exit__(self, *exc: object) -> None:
        """Stop; in plain mode, print a last line for every task still shown."""
        if self._bar is not None:
            self._bar.stop()
        elif self.enabled:
            for task in self._tasks.values():
                self._print(task)

    def add_task(self, description: str, total: float, completed: float = 0, **fields: Any) -> int:
        """Add a task; returns its id.

        Args:
            description: the task's name, printed first.
            total: units of work of the whole task.
            completed: units already done (e.g. steps of a resumed run).
            **fields: extra values shown after the count (``loss=0.1``), updated with :meth:`update`.
        """
        if self._bar is not None:
            # rich annotates ``completed`` as int but keeps it as a float, as it does ``total``.
            return int(self._bar.add_task(description, total=total, completed=completed, **fields))  # type: ignore[arg-type]
        task_id, self._next_id = self._next_id, self._next_id + 1
        self._tasks[task_id] = _PlainTask(description, total, completed, dict(fields), self.clock(), completed)
        return task_id

    def update(self, task_id: int, completed: float | None = None, advance: float = 0, **fields: Any) -> None:
        """Set a task's progress and fields; in plain mode, print every task's line when ``interval`` has passed.

        Args:
            task_id: from :meth:`add_task`.
            completed: units done so far, or None to keep.
            advance: units to add.
            **fields: new values of the task's fields.
        """
        if self._bar is not None:
            self._bar.update(task_id, completed=completed, advance=advance, **fields)  # type: ignore[arg-type]
            return
        if not self.enabled:
            return
        task = self._tasks[task_id]
        task.completed = (task.completed if completed is None else completed) + advance
        task.fields.update(fields)
        if self.clock() - self._last_line >= self.interval:
            for shown in self._tasks.values():
                self._print(shown)

    def resume(self, task_id: int, completed: float) -> None:
        """Continue a task from ``completed`` units (a run resumed from its saved state) without a line of its own.

        Its rate and time left count only the units done from here, as if it had been added with ``completed``.

        Args:
            task_id: from :meth:`add_task`.
            completed: units the saved state had done.
        """
        if self._bar is not None:
            self._bar.reset(task_id, completed=completed)  # type: ignore[arg-type]
        elif task_id in self._tasks:
            task = self._tasks[task_id]
            task.completed = task.first = completed
            task.started = self.clock()

    def advance(self, task_id: int, amount: float = 1) -> None:
        """Add ``amount`` units of work to a task (see :meth:`update`).

        Args:
            task_id: from :meth:`add_task`.
            amount: units done since the last call.
        """
        self.update(task_id, advance=amount)

    def remove_task(self, task_id: int) -> None:
        """Stop showing a task (its last plain line is not printed).

        Args:
            task_id: from :meth:`add_task`.
        """
        if self._bar is not None:
            self._bar.remove_task(task_id)  # type: ignore[arg-type]
        else:
            self._tasks.pop(task_id, None)

    def _print(self, task: _PlainTask) -> None:
        now = self.clock()
        elapsed = now - task.started
        line = f"{task.description} {format_count(task.completed)}/{format_count(task.total)}"
        if task.fields:
            line += f" {format_fields(task.fields)}"
        done, remaining = task.completed - task.first, task.total - task.completed
        left = f", ~{remaining * elapsed / done:.0f} s left" if done > 0 and remaining > 0 else ""
        print(f"{line} ({elapsed:.0f} s{left})", file=self.stream, flush=True)
        self._last_line = now
