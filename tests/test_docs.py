"""The docs hold together: every relative link of README.md and docs/ resolves, the README stays short, and the
command-line reference lists every command and option of the click app.

Regenerate docs/reference/cli.md after changing the command line: ``.venv/bin/python -m tests.test_docs``.
"""

from __future__ import annotations

import re
from pathlib import Path

import click
import pytest

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
CLI_PAGE = DOCS / "reference" / "cli.md"
PAGES = [README, *sorted(DOCS.rglob("*.md"))]

# [text](target) and ![alt](target), not inside inline code; the target up to a space or ")"
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^```.*?^```", flags=re.S | re.M)
INLINE_CODE = re.compile(r"`[^`\n]*`")


def relative_links(page: Path) -> list[str]:
    """The link targets of ``page`` that point into the repository (no scheme, no pure anchor)."""
    text = INLINE_CODE.sub("", FENCE.sub("", page.read_text()))
    return [t for t in LINK.findall(text) if not re.match(r"[a-z][a-z0-9+.-]*:", t) and not t.startswith("#")]


def anchors(page: Path) -> set[str]:
    """GitHub's anchors of the headings of ``page``."""
    text = FENCE.sub("", page.read_text())
    slugs = set()
    for heading in re.findall(r"^#+\s+(.*?)\s*$", text, flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.lower().replace("`", "")).replace(" ", "-")
        slugs.add(slug)
    return slugs


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_docs__every_relative_link_resolves(page):
    broken = []
    for target in relative_links(page):
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve()
        anchor_missing = anchor and resolved.suffix == ".md" and anchor not in anchors(resolved)
        if not resolved.exists() or anchor_missing:
            broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)}: broken links {broken}"


def test_docs__no_page_cites_a_moved_page():
    moved = ("docs/scenes.md", "docs/benchmarks.md", "docs/tradeoff.md", "docs/limits.md")
    for page in PAGES:
        text = page.read_text()
        assert not any(name in text for name in moved), page


def test_readme__at_most_15000_characters():
    assert len(README.read_text()) <= 15_000


def cli_reference() -> str:
    """docs/reference/cli.md as generated from :data:`mpi_lidar.cli.cli` (every command's ``--help``)."""
    from mpi_lidar import cli

    app = cli.cli
    root = click.Context(app, info_name="mpi-lidar", terminal_width=80, max_content_width=80)
    lines = [
        "# Command-line reference", "",
        "Every command of `mpi-lidar` with every option, as `mpi-lidar COMMAND --help` prints it. This page is",
        "generated from the command line's own definitions (`.venv/bin/python -m tests.test_docs`), and",
        "`tests/test_docs.py` checks that every command and option is here. For every command: a user error",
        "prints one line starting with `error:` and exits with code 2, leaving nothing half-written; anything",
        "unexpected is one `error: unexpected ...` line and exit 1 (`--debug` prints the traceback). Commands",
        "that use Dask take `--workers N` (a LocalCluster of N processes) or `--scheduler tcp://host:8786`.",
        "",
        *(f"- [`mpi-lidar {name}`](#mpi-lidar-{name})" for name in app.commands), "",
        "## mpi-lidar", "", "```text", app.get_help(root).rstrip(), "```", "",
    ]
    for name, command in app.commands.items():
        context = click.Context(command, info_name=name, parent=root, terminal_width=80, max_content_width=80)
        lines += [f"## mpi-lidar {name}", "", "```text", command.get_help(context).rstrip(), "```", ""]
    return "\n".join(lines)


def test_cli_reference__lists_every_command_and_option():
    from mpi_lidar import cli

    page = CLI_PAGE.read_text()
    for name, command in cli.cli.commands.items():
        section = page.split(f"\n## mpi-lidar {name}\n", 1)
        assert len(section) == 2, f"no section for mpi-lidar {name}"
        text = section[1].split("\n## ", 1)[0]
        for parameter in command.params:
            for option in parameter.opts if isinstance(parameter, click.Option) else ():
                assert option in text, f"mpi-lidar {name}: {option} is not in {CLI_PAGE.name}"


if __name__ == "__main__":
    CLI_PAGE.write_text(cli_reference())
    print(f"wrote {CLI_PAGE}")
