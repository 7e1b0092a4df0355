"""What the test suite itself must not do: install system or Python packages (the Makefile's set-up does that,
`make system-deps` and the .venv from uv.lock), and leave a test without exactly one of `unit`/`integration`."""

from __future__ import annotations

import ast
import re
from pathlib import Path
from types import SimpleNamespace

import pytest

from tests.conftest import INTEGRATION_FIXTURES, marker_kind

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
    """Just enough of a pytest.Item for :func:`tests.conftest.marker_kind`."""

    def __init__(self, path: str, fixturenames: tuple[str, ...] = (), marks: tuple[str, ...] = (),
                 name: str = "test_function__case"):
        self.path = TESTS / path
        self.name = name
        self.nodeid = f"{path}::{name}"
        self.fixturenames = fixturenames
        self._marks = [SimpleNamespace(name=name) for name in marks]

    def iter_markers(self):
        return iter(self._marks)

    def get_closest_marker(self, name):
        return next((mark for mark in self._marks if mark.name == name), None)


@pytest.mark.parametrize(("item", "kind"), [
    (_Item("physics/test_demod.py"), "unit"),
    (_Item("integration/test_load.py"), "integration"),
    (_Item("flows/test_learning.py"), "integration"),
    (_Item("learning/test_train.py", fixturenames=("small_model",)), "integration"),
    (_Item("physics/test_moments.py", marks=("slow",)), "integration"),
    (_Item("integration/test_load.py", marks=("unit",)), "unit"),
    (_Item("physics/test_demod.py", marks=("integration",)), "integration"),
    (_Item("learning/test_baselines.py", name="test_table2_cli__writes_report"), "integration"),
    (_Item("workflows/test_bench.py"), "integration"),
])
def test_marker_kind__by_directory_fixture_and_own_mark(item, kind):
    assert marker_kind(item) == kind


def test_marker_kind__both_marks_is_a_usage_error():
    with pytest.raises(pytest.UsageError, match="both unit and integration"):
        marker_kind(_Item("physics/test_demod.py", marks=("unit", "integration")))


def test_marker_kind__integration_fixtures_exist():
    defined = set()
    for conftest in [*TESTS.rglob("conftest.py"), *TESTS.rglob("test_*.py")]:
        for node in ast.walk(ast.parse(conftest.read_text())):
            if isinstance(node, ast.FunctionDef) and any("fixture" in ast.unparse(d) for d in node.decorator_list):
                defined.add(node.name)
    assert defined >= INTEGRATION_FIXTURES, INTEGRATION_FIXTURES - defined
