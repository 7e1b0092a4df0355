"""What the command line shows: tables and progress that read well on a terminal and in a log.

On a terminal (standard output is a TTY) tables are rich tables and long work shows a rich progress display
that disappears when it is done. Piped into a file or another program, tables are plain text in aligned
columns and progress is an occasional plain line: one when a step starts, then one every :data:`PLAIN_EVERY_S`
seconds while it runs (its count, or for a step without a count such as training, that it still runs), and one
for its last item. Markdown (``|---|`` tables, ``[report](...)``
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
    return _ESCAPED.sub(r"\1", text.replace("**", "")).replace("`", "")


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


def terminal_width(default: int = 80) -> int:
    """The columns a summary may take: the terminal's (or ``COLUMNS``), ``default`` when piped."""
    import shutil

    return max(40, shutil.get_terminal_size((default, 24)).columns)


def fitted_table_lines(headers: Sequence[str], rows: Sequence[Sequence[object]], width: int,
                       optional: Sequence[str] = ()) -> list[str]:
    """:func:`table_lines` without the columns that are empty in every row, and without the ``optional`` ones (the
    last named first) while a line is wider than ``width``; the other columns stay whole."""
    keep = [i for i in range(len(headers)) if any(plain_text(row[i]) for row in rows)] if rows else list(
        range(len(headers)))
    droppable = [headers.index(name) for name in optional if name in headers]

    def lines() -> list[str]:
        return table_lines([headers[i] for i in keep], [[row[i] for i in keep] for row in rows])

    table = lines()
    while max(map(len, table)) > width and any(i in keep for i in droppable):
        keep.remove(next(i for i in reversed(droppable) if i in keep))
        table = lines()
    return table


def note_codes(notes: Sequence[Sequence[str]]) -> tuple[list[str], list[tuple[str, str]]]:
    """Short codes for the notes of each row (``n1 n3``), one code per distinct note, and the legend: (code, note)
    in order of first use."""
    codes: dict[str, str] = {}
    for row in notes:
        for note in row:
            codes.setdefault(note, f"n{len(codes) + 1}")
    return [" ".join(codes[note] for note in dict.fromkeys(row)) for row in notes], [(c, n) for n, c in codes.items()]


def cut(text: str, width: int) -> str:
    """``text`` on one line of at most ``width`` characters, cut with ``...`` where longer."""
    text = plain_text(text)
    return text if len(text) <= width else text[: max(0, width - 3)].rstrip() + "..."


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
                Task,
                TextColumn,
                TimeElapsedColumn,
            )
            from rich.text import Text

            class Count(MofNCompleteColumn):  # nothing for a step without a count (rich shows "0/?")
                def render(self, task: Task) -> Text:
                    return Text("") if task.total is None else super().render(task)

            self._progress = Progress(SpinnerColumn(), TextColumn("{task.description}", markup=False), BarColumn(),
                                      Count(), TimeElapsedColumn(), transient=True, console=Console(file=self.stream))
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
    def step(self, description: str, total: int | None = None, announce: bool = True) -> Iterator[Advance]:
        """Show one step while the block runs; yields the function that counts an item done. ``announce=False``: no
        plain line when the step starts (a step that may be refused before its first item shows no "0/4"); the
        first comes with the first item done, or after ``every_s``."""
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
        with self._plain_step(description, total, announce) as advance:
            yield advance

    @contextmanager
    def _plain_step(self, description: str, total: int | None, announce: bool = True) -> Iterator[Advance]:
        """Plain lines: one when the step starts, then one whenever every_s seconds passed without one (from
        the items as they finish, or from a clock while none does), and one for the last item."""
        started = time.monotonic()
        done, last_line, now_label = 0, started, ""
        lock = threading.Lock()

        def line(now: float) -> str:
            elapsed = duration(now - started)
            if total is None:
                return f"{description}: still running" + (f" ({now_label})" if now_label else "") + f", {elapsed}"
            return f"{description}: {done}/{total}, {elapsed}" + (f"; last {now_label}" if now_label else "")

        def advance(label: str | None = None) -> None:
            nonlocal done, last_line, now_label
            with lock:
                now_label = label or ""
                if total is None:
                    return
                done += 1
                now = time.monotonic()
                if done == total or now - last_line >= self.every_s:
                    last_line = now
                    self._write(line(now))

        def beat() -> None:
            nonlocal last_line
            while not stop.wait(self.every_s / 4):
                with lock:
                    now = time.monotonic()
                    if now - last_line >= self.every_s:
                        last_line = now
                        self._write(line(now))

        if announce:
            self._write(f"{description} ..." if total is None else f"{description}: 0/{total}")
        stop = threading.Event()
        beater = threading.Thread(target=beat, name="mpi-lidar-progress", daemon=True)
        beater.start()
        try:
            yield advance
        finally:
            stop.set()
            beater.join()
