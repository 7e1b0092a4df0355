"""What the test suite itself must not do: install system or Python packages (the Makefile's set-up does that,
`make system-deps` and the .venv from uv.lock), and leave a test without exactly one of `unit`/`integration`."""

from __future__ import annotations

import ast
import re
from pathlib import Path
from types import SimpleNamespace

import pytest

from tests.conftest import mark_directory, marker_kind

pytestmark = pytest.mark.unit

TESTS = Path(__file__).resolve().parent

# A shell command (or one segment of a `a && b; c` chain) that installs packages.
INSTALL = re.compile(r"^\s*(sudo\s+)?(\S*python\S*\s+)?(-m\s+)?(apt-get|apt|dnf|yum|apk|pip3?|uv\s+pip)\s+"
                     r"(-\S+\s+)*(install|add)\b")


def install_commands(source: str) -> list[str]:
    """The package installations that ``source`` (Python) spells as a command: a string such as
    ``"apt-get install -y x"`` or ``"pip install x"``, or a list/tuple literal ``["apt-get", "install", ...]``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            commands = re.split(r"&&|\|\||;|\n", node.value)
        elif isinstance(node, ast.List | ast.Tuple):
            words = [e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]
            commands = [" ".join(words)] if words else []
        else:
            continue
        found += [command.strip() for command in commands if INSTALL.match(command)]
    return found


def test_install_commands__finds_the_usual_spellings():
    source = """
for command in (["apt-get", "update", "-q"], ["apt-get", "install", "-y", "-q", "chromium"]):
    subprocess.run(command)
os.system("apt-get update && apt-get install -y chromium")
subprocess.run([sys.executable, "-m", "pip", "install", "x"])
subprocess.run("pip install --quiet x", shell=True)
pytest.fail("chromium is missing: run `make system-deps`")
"""
    assert sorted(install_commands(source)) == ["-m pip install x", "apt-get install -y -q chromium",
                                                "apt-get install -y chromium", "pip install --quiet x"]


def test_tests__install_no_package():
    offenders = {str(path.relative_to(TESTS)): commands for path in sorted(TESTS.rglob("*.py"))
                 if path.name != Path(__file__).name and (commands := install_commands(path.read_text()))}
    assert offenders == {}, "tests must not install packages; put it in the Makefile's set-up (make system-deps)"


class _Item:
    """Just enough of a pytest.Item for :func:`tests.conftest.marker_kind` and :func:`tests.conftest.mark_directory`:
    the marks it carries, its own and those of its class, module and directory alike."""

    def __init__(self, path: str, marks: tuple[str, ...] = (), name: str = "test_function__case"):
        self.path = TESTS / path
        self.nodeid = f"{path}::{name}"
        self._marks = [SimpleNamespace(name=name) for name in marks]

    def iter_markers(self):
        return iter(self._marks)

    def add_marker(self, name: str) -> None:
        self._marks.append(SimpleNamespace(name=name))


@pytest.mark.parametrize(("marks", "kind"), [
    (("unit",), "unit"),
    (("integration",), "integration"),
    (("slow", "integration"), "integration"),
    (("parametrize", "unit", "timeout"), "unit"),
])
def test_marker_kind__is_the_one_kind_the_test_carries(marks, kind):
    assert marker_kind(_Item("physics/test_demod.py", marks=marks)) == kind


@pytest.mark.parametrize(("marks", "said"), [
    ((), "neither unit nor integration"),
    (("slow",), "neither unit nor integration"),
    (("unit", "integration"), "both unit and integration"),
    (("unit", "slow"), "slow and unit"),
])
def test_marker_kind__a_test_without_exactly_one_kind_is_a_usage_error(marks, said):
    with pytest.raises(pytest.UsageError, match=said):
        marker_kind(_Item("physics/test_demod.py", marks=marks))


def test_mark_directory__marks_the_items_below_it_and_no_other():
    inside, nested, outside = _Item("flows/test_learning.py"), _Item("flows/x/test_y.py"), _Item("test_flows.py")
    mark_directory([inside, nested, outside], TESTS / "flows", "integration")
    assert [marker_kind(item) for item in (inside, nested)] == ["integration", "integration"]
    assert list(outside.iter_markers()) == []
