"""How every long command of the command line tells what it is doing, on stderr.

On a terminal: a rich progress bar that redraws itself (and vanishes when done). Elsewhere (a CI
log, ``make demo > log 2>&1``) a bar is nothing but escape codes, and silence for minutes looks
like a hang, so the same progress comes as plain lines, as pytest and asv print them: one when
the step starts (at its first count: an input refused before it is one error line, not two),
one at most every ``SLAMREPLAY_PROGRESS_INTERVAL_S`` seconds (default 10), one when it ends::

    run dslam on sim.mcap: started (3,000 messages)
    run dslam on sim.mcap: 40% (1,200/3,000 messages, 12 s, ETA 18 s)
    run dslam on sim.mcap: done (3,000 messages in 30 s)

:func:`say` prints a one-off note (``building the environment for abc123...``) before a slow
step that has no count. ``--quiet`` silences both.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

Update = Callable[[int, int], None]
DEFAULT_INTERVAL_S = 10.0


def interval_s() -> float:
    """Seconds between two progress lines: ``$SLAMREPLAY_PROGRESS_INTERVAL_S`` (tests set it low), else 10."""
    try:
        return max(0.0, float(os.environ.get("SLAMREPLAY_PROGRESS_INTERVAL_S", DEFAULT_INTERVAL_S)))
    except ValueError:
        return DEFAULT_INTERVAL_S


def say(text: str, quiet: bool = False) -> None:
    """One note on stderr (terminal or not), flushed at once so that a log shows it before the slow step."""
    if not quiet:
        print(text, file=sys.stderr, flush=True)


def duration(seconds: float) -> str:
    """``12 s``, ``3.5 min``, ``1.2 h``: how long, as a person reads it in a log line."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


class PlainProgress:
    """Plain progress lines for ``update(done, total)`` calls (the module docstring shows them).

    Parameters
    ----------
    description : what is running, the start of every line (``run dslam on sim.mcap``)
    unit : what ``done`` counts (``messages``, ``cells``)
    reused : when the first update already counts some done (cells served from a cache), name them
        so (``2 reused``) and leave them out of the rate that the ETA comes from
    clock : seconds, monotonic (tests pass a fake one)
    every_s : least time between two periodic lines, seconds (default: :func:`interval_s`)
    """

    def __init__(self, description: str, unit: str = "steps", reused: str | None = None,
                 clock: Callable[[], float] = time.monotonic, every_s: float | None = None) -> None:
        self.description, self.unit, self.reused_word = description, unit, reused
        self.clock = clock
        self.every_s = interval_s() if every_s is None else every_s
        self.start = clock()
        self.last_line = self.start
        self.done, self.total = 0, 0
        self.reused: int | None = None
        self.announced = False
        self.first, self.first_done = self.start, 0
        self.warm: tuple[float, int] | None = None  # (when, count) of the first item done after the first count

    def _print(self, text: str) -> None:
        """One line, prefixed with the description."""
        say(f"{self.description}: {text}")

    def _counts(self) -> str:
        reused = f", {self.reused:,} {self.reused_word}" if self.reused_word and self.reused else ""
        return f"{self.done:,}/{self.total:,} {self.unit}{reused}"

    def update(self, done: int, total: int) -> None:
        """Record progress; print a line when the last one is ``every_s`` old."""
        if self.reused is None:
            self.reused = done if self.reused_word else 0
        self.done, self.total = done, max(total, done)
        if not self.announced:
            self.announced = True
            # the rate (and ETA) counts from here: the work before the first count (a reference solution
            # computed up front, cells served from a cache) would make it absurd
            self.first, self.first_done = self.clock(), done
            reused = f", {self.reused:,} {self.reused_word}" if self.reused_word and self.reused else ""
            self._print(f"started ({self.total:,} {self.unit}{reused})")
        now = self.clock()
        if self.warm is None and done > self.first_done:
            self.warm = (now, done)  # the first item done: later ones leave out what it alone paid for
        if now - self.last_line < self.every_s or done >= self.total:
            return  # the end has its own line
        self.last_line = now
        elapsed = now - self.start
        pct = f"{100.0 * done / self.total:.0f}% " if self.total else ""
        # The rate of the items done since the first one, once there are some: the first may carry a one-off cost
        # (the environment `history` builds for a commit's dependencies, minutes; then seconds a commit).
        first, first_done = self.warm if self.warm is not None and done > self.warm[1] else (self.first,
                                                                                              self.first_done)
        fresh, counted = done - first_done, now - first
        eta = f", ETA {duration(counted * (self.total - done) / fresh)}" if fresh > 0 and counted > 0 else ""
        self._print(f"{pct}({self._counts()}, {duration(elapsed)}{eta})")

    def finished(self) -> None:
        """Print the end line: the counts and how long it took."""
        counts = self._counts() if self.total else ""
        self._print(f"done ({counts + ' in ' if counts else 'in '}{duration(self.clock() - self.start)})")


@contextmanager
def progress_bar(description: str, quiet: bool, unit: str = "steps", reused: str | None = None) -> Iterator[Update]:
    """Progress of one long step on stderr, yielding ``update(done, total)``.

    A rich bar on a terminal; plain lines otherwise (:class:`PlainProgress`); nothing with ``--quiet``.
    ``unit`` and ``reused`` are :class:`PlainProgress`'s.
    """
    if quiet:
        yield lambda done, total: None
        return
    if not sys.stderr.isatty():
        plain = PlainProgress(description, unit, reused)
        yield plain.update
        plain.finished()  # not on an error: the error line says how it ended
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TextColumn("eta"), TimeRemainingColumn())
    with Progress(*columns, console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task(description, total=None)

        def update(done: int, total: int) -> None:
            bar.update(task, completed=done, total=max(total, done))

        yield update
