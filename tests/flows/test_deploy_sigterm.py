"""``python -m flows.deploy`` stopped by SIGTERM (as a service manager stops it): one line, exit 0, no warning."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
START_S = 120  # the serving process imports Prefect and registers four deployments


@pytest.mark.slow
def test_main__sigterm_stops_serving_with_one_line_and_no_warning(prefect_api: str, tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "PREFECT_API_URL": prefect_api, "PYTHONWARNINGS": "default"}
    served = subprocess.Popen([sys.executable, "-m", "flows.deploy", "--root", str(tmp_path / "nightly")],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO,
                              start_new_session=True)
    try:
        assert served.stdout is not None
        first = served.stdout.readline()  # printed once the deployments are registered
        assert first.startswith("serving 4 deployments"), (first, served.stderr and served.stderr.read())
        time.sleep(2.0)  # the runner's loop is polling by now: the SIGTERM lands inside it
        served.send_signal(signal.SIGTERM)
        rest, stderr = served.communicate(timeout=START_S)
    finally:
        if served.poll() is None:
            os.killpg(served.pid, signal.SIGKILL)
            served.wait()
    assert served.returncode == 0, stderr
    assert rest.strip().splitlines() == ["stopped (SIGTERM): served deployments' schedules are paused until they are "
                                         "served again"]
    assert "Warning" not in stderr and "Traceback" not in stderr, stderr
