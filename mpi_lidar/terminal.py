"""What the command line shows: tables and progress that read well on a terminal and in a log.

On a terminal (standard output is a TTY) tables are rich tables and long work shows a rich progress display
that disappears when it is done. Piped into a file or another program, tables are plain text in aligned
columns and progress is an occasional plain line: the first item of a step, then at most one line every
:data:`PLAIN_EVERY_S` seconds, and the last; a step without a count (training) says when it starts and, while
it runs, every :data:`PLAIN_EVERY_S` seconds that it still does. Markdown (``|---|`` tables, ``[report](...)``
links) is what report files hold; it never reaches the terminal: cells are shown as their plain text.

Everything goes to standard output; standard error holds error lines only.
"""

from __future__ import annotations

import re
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from rich.progress import Progress

PLAIN_EVERY_S = 20.0  # at most one plain progress line per step this often [s]

_LINK = re.compile(r"\[([^\]]*)\]\([^)]*\)")
_ESCAPED = re.compile(r"\\([\\`*_\[\]|#])")


def plural(count: int, noun: str, nouns: str | None = None) -> str:
    """``1 scan``, ``2 scans`` (``nouns`` where the plural is not ``noun + "s"``)."""
    return f"{count:,} {noun if count == 1 else nouns or noun + 's'}"


def duration(seconds: float) -> str:
    """``42 s``, ``3 min 05 s``, ``1 h 02 min``."""
    seconds = max(0, round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"


def plain_text(cell: object) -> str:
    """A report cell as the text a reader sees: links as their text, markdown escapes and code marks removed."""
    text = _LINK.sub(r"\1", " ".join(str(cell).splitlines()))
    return _ESCAPED.sub(r"\1", text).replace("`", "")


def is_terminal(stream: TextIO | None = None) -> bool:
    """Whether ``stream`` (standard output) is an interactive terminal."""
    stream = stream or sys.stdout
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # closed or not a real stream
        return False


def table_lines(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> list[str]:
    """A table as plain aligned text: the headers, a rule of dashes, one line per row (no trailing spaces)."""
    cells = [[plain_text(c) for c in headers], *[[plain_text(c) for c in row] for row in rows]]
    widths = [max(len(row[i]) for row in cells) for i in range(len(headers))]

    def line(row: list[str]) -> str:
        return "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip()

    return [line(cells[0]), line(["-" * w for w in widths]), *(line(row) for row in cells[1:])]


def print_table(headers: Sequence[str], rows: Sequence[Sequence[object]], title: str | None = None,
                stream: TextIO | None = None, clip: Sequence[str] = ()) -> None:
    """A table on ``stream`` (standard output): a rich table on a terminal, aligned plain text otherwise.

    On a terminal the columns named in ``clip`` (long notes) keep one line per row, cut with an ellipsis where
    the window ends; the plain text and the report files hold them whole.
    """
    stream = stream or sys.stdout
    if is_terminal(stream):
        from rich.console import Console
        from rich.table import Column, Table
        from rich.text import Text

        console = Console(file=stream)
        cells = [[plain_text(c) for c in row] for row in rows]
        columns = [Column(Text(h)) for h in headers]
        if clip:  # the other columns keep their width; the clipped ones share what is left of the window
            widths = [max([len(h), *(len(row[i]) for row in cells)]) for i, h in enumerate(headers)]
            clipped = [i for i, h in enumerate(headers) if h in clip]
            left = console.width - 3 * len(headers) - 1 - sum(w for i, w in enumerate(widths) if i not in clipped)
            columns = [Column(Text(h), no_wrap=True, overflow="ellipsis", max_width=max(12, left // len(clipped)))
                       if i in clipped else Column(Text(h), no_wrap=True, min_width=widths[i])
                       for i, h in enumerate(headers)]
        table = Table(*columns, title=title and Text(title), title_justify="left")
        for row in cells:  # Text: a "[mm]" in a cell is text, not rich markup
            table.add_row(*map(Text, row))
        console.print(table)
        return
    lines = ([title] if title else []) + table_lines(headers, rows)
    stream.write("\n".join(lines) + "\n")
    stream.flush()


Advance = Callable[..., None]  # advance(label=None): one item done (or, without a count, what runs now)


class Display:
    """The progress of a command's steps, for the workflows' progress callbacks.

    ``with display.step("trials", total=6) as advance:`` shows a step; ``advance()`` counts one item done,
    ``advance("scan_3: corrected")`` also names it. ``total=None`` is a step without a count (a spinner and the
    elapsed time on a terminal), where ``advance(label)`` says what runs now. Use the display as a context
    manager around its steps. ``every_s`` is the least time between two plain lines of a step.
    """

    def __init__(self, stream: TextIO | None = None, every_s: float = PLAIN_EVERY_S) -> None:
        self.stream = stream or sys.stdout
        self.every_s = every_s
        self.live = is_terminal(self.stream)
        self._progress: Progress | None = None
        self._lock = threading.Lock()

    def __enter__(self) -> Display:
        if self.live:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                SpinnerColumn,
                TextColumn,
                TimeElapsedColumn,
            )

            self._progress = Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(),
                                      MofNCompleteColumn(), TimeElapsedColumn(), transient=True,
                                      console=Console(file=self.stream))
            self._progress.__enter__()
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._progress is not None:
            self._progress.__exit__(None, None, None)
            self._progress = None

    def echo(self, line: str) -> None:
        """A line of output that stays (above a live progress display)."""
        if self._progress is not None:
            self._progress.console.print(line, markup=False, highlight=False, soft_wrap=True)
        else:
            self._write(line)

    def _write(self, line: str) -> None:
        with self._lock:
            self.stream.write(line + "\n")
            self.stream.flush()

    @contextmanager
    def step(self, description: str, total: int | None = None) -> Iterator[Advance]:
        """Show one step while the block runs; yields the function that counts an item done."""
        if total == 0:
            yield lambda label=None: None
            return
        if self._progress is not None:
            progress = self._progress
            task = progress.add_task(description, total=total)

            def advance(label: str | None = None) -> None:
                progress.update(task, advance=0 if total is None else 1,
                                description=description if label is None else f"{description}: {label}")

            try:
                yield advance
            finally:
                progress.remove_task(task)
            return
        with self._plain_step(description, total) as advance:
            yield advance

    @contextmanager
    def _plain_step(self, description: str, total: int | None) -> Iterator[Advance]:
        started = time.monotonic()
        if total is None:  # no count: say it started, then that it still runs, every every_s seconds
            self._write(f"{description} ...")
            stop = threading.Event()
            now_running = [""]

            def beat() -> None:
                while not stop.wait(self.every_s):
                    label = f" ({now_running[0]})" if now_running[0] else ""
                    self._write(f"{description}: still running{label}, {duration(time.monotonic() - started)}")

            def name(label: str | None = None) -> None:
                now_running[0] = label or ""

            beater = threading.Thread(target=beat, name="mpi-lidar-progress", daemon=True)
            beater.start()
            try:
                yield name
            finally:
                stop.set()
                beater.join()
            return
        done = 0
        last = -float("inf")

        def advance(label: str | None = None) -> None:
            nonlocal done, last
            done += 1
            now = time.monotonic()
            if done == 1 or done == total or now - last >= self.every_s:
                last = now
                self._write(f"{description}: {done}/{total}, {duration(now - started)}"
                            + (f"; last {label}" if label else ""))

        yield advance

