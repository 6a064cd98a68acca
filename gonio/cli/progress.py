"""Progress on a terminal, silence in a pipe.

A step that makes a person wait (``fit --model auto``, ``calibrate``, ``report``, a batch fit)
shows a bar on stderr while it runs: what it is doing, the steps done of the steps it has and
the time left. The library reports through a callback ``progress(done, total, label)`` (done
of total steps; ``label`` the step now running), passed where the long work is
(`gonio.fitting.selection`, `gonio.bench.calibrate`); a step that reports nothing shows a
pulsing bar and the time it has taken. Nothing is shown when stderr is not a terminal (a
pipe, a file, a CI log) or with ``--quiet``, so what the command prints is all a script sees.
The bar goes away when the step ends; it fits an 80-column terminal.
"""

from __future__ import annotations

import os
import sys
import time

__all__ = ["Steps", "on_terminal", "stderr_console"]

#: the widest a step's label is shown (the bar, the count and the time keep their width)
LABEL_WIDTH = 30


def on_terminal(stream=None) -> bool:
    """Whether ``stream`` (default stderr) is an interactive terminal that can redraw a line."""
    stream = sys.stderr if stream is None else stream
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError, OSError):
        return False
    return bool(tty) and os.environ.get("TERM", "") != "dumb"


def stderr_console():
    """The console progress is drawn on (rich, imported when a bar is drawn: ``gonio --help``
    stays quick)."""
    from rich.console import Console

    return Console(stderr=True)


def _time_left_column(**kw):
    """A rich column: ``0:01:23 left`` once the work has said how many steps it has and done
    one; before that (and for work that never says), the time the step has taken so far,
    ``0:00:07 in`` (from the task's ``started`` field: a new phase does not restart it)."""
    from rich.progress import ProgressColumn
    from rich.text import Text

    class TimeLeft(ProgressColumn):
        def render(self, task) -> Text:
            if task.total is None or task.completed <= 0 or task.finished:
                started = task.fields.get("started")
                elapsed = time.perf_counter() - started if started is not None else task.elapsed
                return Text(f"{_clock(elapsed)} in", style="progress.elapsed")
            left = task.time_remaining
            return Text(f"{_clock(left)} left" if left is not None else "-:--:-- left", style="progress.remaining")

    return TimeLeft(**kw)


def _count_column(**kw):
    """A rich column: ``3/9`` steps done, nothing while the work has not said how many it has."""
    from rich.progress import ProgressColumn
    from rich.text import Text

    class Count(ProgressColumn):
        def render(self, task) -> Text:
            if task.total is None:
                return Text("")
            width = len(str(int(task.total)))
            return Text(f"{int(task.completed):>{width}}/{int(task.total)}", style="progress.download")

    return Count(**kw)


def _clock(seconds) -> str:
    seconds = int(max(0, seconds or 0))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class Steps:
    """One long step's progress on stderr, as a context manager and a callback.

    ``with Steps("fit", enabled=not quiet) as progress: work(progress=progress)``: the work
    calls ``progress(done, total, label)``; ``total`` None keeps the bar pulsing. Where
    ``enabled`` is false or stderr is not a terminal, nothing is drawn and the callback does
    nothing (it is always safe to pass).
    """

    def __init__(self, title: str, *, enabled: bool = True, console=None, stream=None):
        self.title = title
        self.enabled = bool(enabled) and (console is not None or on_terminal(stream))
        self.console = console
        self._p = None
        self._task = None
        self.t0 = time.perf_counter()

    def __enter__(self):
        if self.enabled:
            from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn
            from rich.table import Column

            self._p = Progress(
                SpinnerColumn(table_column=Column(no_wrap=True, width=1)),
                TextColumn("{task.description}", table_column=Column(no_wrap=True, overflow="ellipsis",
                                                                     max_width=LABEL_WIDTH)),
                BarColumn(bar_width=None, table_column=Column(ratio=1, min_width=6)),
                _count_column(table_column=Column(no_wrap=True, min_width=5)),
                _time_left_column(table_column=Column(no_wrap=True, min_width=12)),
                # what the work prints goes above the bar where it shares the terminal; printed
                # to a file or a pipe, stdout stays there (a script reads it as without the bar)
                console=self.console or stderr_console(), transient=True, redirect_stdout=on_terminal(sys.stdout),
                redirect_stderr=True)
            self._task = self._p.add_task(self.title, total=None, started=self.t0)
            self._p.start()
        return self

    def __call__(self, done, total=None, label=None) -> None:
        """The work's report: ``done`` of ``total`` steps, now ``label``."""
        if self._p is None:
            return
        done = max(0, int(done))
        total = None if total is None else max(int(total), done, 1)
        description = f"{self.title}: {label}" if label else self.title
        task = self._p.tasks[0]
        if total != task.total or done < task.completed:
            # a new phase (the renders after the fits): its own count and speed
            self._p.reset(self._task, total=total, completed=done, description=description)
        else:
            self._p.update(self._task, completed=done, description=description)
        if total is None:
            task.total = None                   # rich's update and reset keep a total once given

    def __exit__(self, *exc) -> None:
        if self._p is not None:
            self._p.stop()
            self._p = None
