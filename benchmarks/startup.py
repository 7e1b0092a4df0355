"""Start-up of the command line: what a one-scan ``mpi-lidar correct`` pays before its scan's own work.

Run: .venv/bin/python -m benchmarks.startup [--work DIR] [--repeat 5] [--side 64]
Prints one markdown table of wall seconds, each the median (and the range) of ``--repeat`` fresh processes:

- ``python -c pass``: the interpreter alone, the floor under every row.
- ``import mpi_lidar.cli``: the command-line module, timed inside the process.
- ``mpi-lidar --help``: the whole process, as a shell runs it.
- ``correct``, ``--outputs data`` and ``light``: a ``--side`` x ``--side`` scan with a small model; "before
  the scan" is the time from starting the process to the call of
  :func:`~mpi_lidar.workflows.correct_archive.process_scan` for the scan (interpreter, imports, option
  checks, model loading), in wall and in CPU seconds of the process (robust where other jobs share the
  machine); "whole - warm scan" is the process from start to the command's end less the same scan corrected
  again in that process with everything warm: the start-up wherever it is paid, imports a scan's outputs
  pull in on the way included.

A second table lists the heavy libraries already imported when the scan's work begins (scikit-learn,
matplotlib, plotly, prefect, dask.distributed, xgboost); the goal of issue 37 is a start-up of at most 0.7 s.
The model (a small one, trained here) and the scan are kept in ``--work`` (default: a directory under the
system's temporary directory), so a second run starts at once.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import date
from pathlib import Path

HEAVY = ("sklearn", "matplotlib", "plotly", "prefect", "distributed", "xgboost", "optuna", "pandas")
GOAL_S = 0.7

# Run in a fresh process: records when the scan's own work begins (process_scan's call) and what is imported
# by then, then runs the command line as a shell would. Prints one JSON line on stderr's last line.
_DRIVER = """
import json, sys, time
import mpi_lidar.workflows.correct_archive as archive
seen = {}
original = archive.process_scan
def process_scan(**call):
    if not seen:
        seen["first_scan_s"] = time.time()
        seen["first_scan_cpu_s"] = time.process_time()
        seen["loaded"] = sorted({m.split(".")[0] for m in sys.modules} & set(HEAVY))
        seen["call"] = call
    return original(**call)
archive.process_scan = process_scan
from mpi_lidar import cli
sys.argv = ["mpi-lidar", *ARGS]
try:
    cli.main()
except SystemExit as exc:
    seen["code"] = exc.code
seen["exit_s"] = time.time()
call = {**seen.pop("call"), "out_dir": ARGS[ARGS.index("--out") + 1] + "-warm"}
started = time.perf_counter()
original(**call)  # the same scan again, imports and model warm: the scan's own work
seen["warm_scan_s"] = time.perf_counter() - started
print(json.dumps(seen), file=sys.stderr)
"""


def _setup(work: Path, side: int) -> tuple[Path, Path]:
    """A small model and one scan of ``side`` x ``side`` pixels in ``work`` (made once)."""
    from mpi_lidar.scans.store import write_scan
    from tests.model_factory import tiny_model
    from tests.scan_factory import two_path_scan

    model, scan = work / "model", work / f"scan{side}.scan.zarr"
    if not model.exists():
        tiny_model(model)
    if not scan.exists():
        write_scan(two_path_scan(f"scan{side}", height=side, width=side), scan)
    return model, scan


def _wall(command: list[str], env: dict[str, str]) -> tuple[float, str]:
    started = time.time()
    done = subprocess.run(command, capture_output=True, text=True, env=env, check=False)
    if done.returncode != 0:
        raise SystemExit(f"error: {' '.join(command)} failed ({done.returncode}): {done.stderr.strip()[-300:]}")
    return time.time() - started, done.stderr


@dataclass
class Correct:
    """One fresh ``mpi-lidar correct`` process of one scan [s]."""

    before_s: float  # from starting the process to the scan's work (wall)
    before_cpu_s: float  # the same in CPU seconds of the process (robust on a shared machine)
    whole_s: float  # from starting the process to the end of the command (wall)
    warm_scan_s: float  # the same scan again in that process, warm: the scan's own work
    loaded: list[str]  # heavy libraries imported when the scan's work began

    @property
    def overhead_s(self) -> float:
        """What the process cost beyond the scan's own work: start-up wherever it is paid."""
        return self.whole_s - self.warm_scan_s


def _correct(model: Path, scan: Path, out: Path, outputs: str, env: dict[str, str]) -> Correct:
    args = ["correct", str(scan), "--model", str(model), "--out", str(out), "--outputs", outputs]
    driver = _DRIVER.replace("HEAVY", repr(HEAVY)).replace("ARGS", repr(args))
    started = time.time()
    _, stderr = _wall([sys.executable, "-c", driver], env)
    seen = json.loads(stderr.strip().splitlines()[-1])
    if seen.get("code") not in (None, 0) or "first_scan_s" not in seen:
        raise SystemExit(f"error: the benchmark's correct did not reach its scan ({seen}); run it by hand to see why")
    return Correct(seen["first_scan_s"] - started, seen["first_scan_cpu_s"], seen["exit_s"] - started,
                   seen["warm_scan_s"], seen["loaded"])


def _row(name: str, values: list[float], note: str = "") -> str:
    return (f"| {name} | {statistics.median(values):.2f} | {min(values):.2f}-{max(values):.2f} | "
            f"{'yes' if statistics.median(values) <= GOAL_S else 'no'} | {note} |")


def startup_tables(work: Path, repeat: int = 5, side: int = 64) -> str:
    """The start-up tables as markdown: ``repeat`` fresh processes of each row, a ``side`` x ``side`` scan."""
    work.mkdir(parents=True, exist_ok=True)
    model, scan = _setup(work, side)
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    cli = [str(Path(sys.executable).with_name("mpi-lidar"))]
    cli = cli if Path(cli[0]).exists() else [sys.executable, "-m", "mpi_lidar.cli"]
    timed_import = "import time; t = time.perf_counter(); import mpi_lidar.cli; print(time.perf_counter() - t)"
    rows: dict[str, list[float]] = {"pass": [], "import": [], "help": []}
    loaded: dict[str, list[str]] = {}
    for i in range(repeat):
        rows["pass"].append(_wall([sys.executable, "-c", "pass"], env)[0])
        done = subprocess.run([sys.executable, "-c", timed_import], capture_output=True, text=True, env=env,
                              check=True)
        rows["import"].append(float(done.stdout))
        rows["help"].append(_wall([*cli, "--help"], env)[0])
        for outputs in ("data", "light"):
            out = work / f"out-{outputs}-{i}"
            for old in (out, Path(f"{out}-warm")):
                shutil.rmtree(old, ignore_errors=True)  # a fresh correction each time, never a skipped one
            run = _correct(model, scan, out, outputs, env)
            for key, value in (("before", run.before_s), ("before cpu", run.before_cpu_s), ("whole", run.whole_s),
                               ("warm", run.warm_scan_s), ("overhead", run.overhead_s)):
                rows.setdefault(f"{outputs} {key}", []).append(value)
            loaded[outputs] = run.loaded
    lines = [f"Start-up, seconds, median of {repeat} fresh processes ({platform.node()}, {os.cpu_count()} cores, "
             f"Python {platform.python_version()}, {date.today()}); goal <= {GOAL_S} s", "",
             "| what | median [s] | range [s] | <= 0.7 s | note |", "|---|---|---|---|---|",
             _row("`python -c pass`", rows["pass"], "wall; the interpreter alone"),
             _row("`import mpi_lidar.cli`", rows["import"], "wall, inside the process"),
             _row("`mpi-lidar --help`", rows["help"], "wall, whole process")]
    for outputs in ("data", "light"):
        note = (f"{side} x {side} scan; whole process {statistics.median(rows[f'{outputs} whole']):.2f} s, "
                f"the scan's own work (warm) {statistics.median(rows[f'{outputs} warm']):.2f} s")
        lines += [_row(f"`correct --outputs {outputs}`: before the scan", rows[f"{outputs} before"], "wall; " + note),
                  _row(f"`correct --outputs {outputs}`: before the scan, CPU", rows[f"{outputs} before cpu"],
                       "CPU seconds of the process"),
                  _row(f"`correct --outputs {outputs}`: whole - warm scan", rows[f"{outputs} overhead"],
                       "wall; start-up wherever it is paid")]
    lines += ["", "| outputs | heavy libraries imported when the scan's work begins |", "|---|---|"]
    lines += [f"| {outputs} | {', '.join(names) or 'none'} |" for outputs, names in loaded.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "mpi-lidar-startup")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--side", type=int, default=64)
    args = parser.parse_args(argv)
    print(startup_tables(args.work, args.repeat, args.side))


if __name__ == "__main__":
    main()
