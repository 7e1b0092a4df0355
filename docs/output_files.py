"""Write the docs' lists of the files each output level writes from the one registry of them,
:data:`mpi_lidar.reporting.output_levels.OUTPUT_FILES`.

Run: .venv/bin/python docs/output_files.py [--check]

Each list sits between ``<!-- output-files:KIND -->`` and ``<!-- /output-files:KIND -->`` in README.md or a page
under docs/: KIND ``table`` is a table of the levels and their files, what each holds; KIND a level's name
(``light``) is that level's files as an inline list of names. ``--check`` rewrites nothing and exits 1 where a
page is out of date (tests/cli/test_output_files_docs.py checks it on every run).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

from mpi_lidar.reporting.output_levels import DEFAULT_OUTPUTS, OUTPUT_LEVELS, OutputFile, level_files

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
MARKED = re.compile(r"(<!-- output-files:(?P<kind>[a-z]+) -->)(?P<body>.*?)(<!-- /output-files:(?P=kind) -->)", re.S)
LEVELS_UP = tuple(reversed(OUTPUT_LEVELS))  # from the least to the most


def pages(root: Path = ROOT) -> list[Path]:
    """README.md and every Markdown page under docs/."""
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def names(files: tuple[OutputFile, ...]) -> str:
    """File names as an inline list: ```a`, `b` and `c```."""
    quoted = [f"`{file.name}`" for file in files]
    return quoted[0] if len(quoted) == 1 else ", ".join(quoted[:-1]) + f" and {quoted[-1]}"


def table(page: Path) -> str:
    """The levels, from the least, and the files each adds to the level below it, with what each holds (links
    relative to ``page``)."""
    to_docs = Path(os.path.relpath(DOCS, page.parent)).as_posix()
    rows = ["| level | files (each level writes those of the level above it in this table too) |", "|---|---|"]
    below: set[str] = set()
    for level in LEVELS_UP:
        added = [file for file in level_files(level) if file.name not in below]
        listed = ", ".join(f"`{file.name}` ({file.holds})" for file in added)
        said = f"`{level}`" + (" (the default)" if level == DEFAULT_OUTPUTS else "")
        rows.append(f"| {said} | {listed} |".replace("](reference/", f"]({to_docs}/reference/"))
        below |= {file.name for file in added}
    return "\n".join(rows)


def block(kind: str, page: Path) -> str:
    """What the block of ``kind`` holds on ``page``."""
    if kind == "table":
        return f"\n{table(page)}\n"
    if kind in OUTPUT_LEVELS:
        return names(level_files(kind))
    raise ValueError(f"{page}: unknown output-files block {kind!r}; one of table, {', '.join(OUTPUT_LEVELS)}")


def refreshed(text: str, page: Path) -> str:
    """``text`` of ``page`` with every marked block made from the registry."""
    return MARKED.sub(lambda found: found[1] + block(found["kind"], page) + found[4], text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="rewrite nothing; exit 1 where a page is out of date")
    check = parser.parse_args(argv).check
    stale = []
    for page in pages():
        text = page.read_text()
        new = refreshed(text, page)
        if new != text:
            stale.append(page.relative_to(ROOT).as_posix())
            if not check:
                page.write_text(new)
    if stale:
        print(("out of date: " if check else "rewritten: ") + ", ".join(stale), file=sys.stderr)
    return 1 if stale and check else 0


if __name__ == "__main__":
    sys.exit(main())
