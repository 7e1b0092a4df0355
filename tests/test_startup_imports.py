"""Start-up: the command line and the correction path import no library they do not need before a scan's work.

Each check runs in a fresh interpreter (``sys.modules`` of this test process holds everything the suite
imported). Importing XGBoost imports scikit-learn (~1 s; ``xgboost/compat.py`` does it whenever scikit-learn is
installed), matplotlib costs ~0.5 s, Prefect and Dask's distributed more: benchmarks/startup.py measures it.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# Libraries that the command line's start-up must not pay for.
HEAVY = ("sklearn", "matplotlib", "plotly", "prefect", "distributed", "xgboost", "optuna")


def _loaded_after(statement: str) -> list[str]:
    """The top-level packages of HEAVY that a fresh interpreter holds after ``statement``."""
    code = (f"import json, sys\n{statement}\n"
            f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r}))))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.integration
def test_import_cli__loads_no_heavy_library():
    assert _loaded_after("import mpi_lidar.cli") == []


@pytest.mark.unit
def test_cli_help__the_whole_process_loads_no_heavy_library():
    done = subprocess.run([sys.executable, "-X", "importtime", "-m", "mpi_lidar.cli", "--help"],
                          capture_output=True, text=True, check=True)
    assert "correct" in done.stdout
    imported = {line.rsplit("|", 1)[-1].strip().split(".")[0] for line in done.stderr.splitlines()
                if line.startswith("import time:")}
    assert "mpi_lidar" in imported, "the import log was read"
    assert imported.isdisjoint(HEAVY), sorted(imported & set(HEAVY))


@pytest.mark.unit
@pytest.mark.parametrize("module", ["mpi_lidar.correction.correct", "mpi_lidar.learning.model",
                                    "mpi_lidar.learning.train", "mpi_lidar.learning.evaluate",
                                    "mpi_lidar.scans.importers"])
def test_import_correction_path__xgboost_waits_for_a_booster(module):
    """XGBoost (and with it scikit-learn) is imported where a booster is loaded or trained, not on import."""
    assert _loaded_after(f"import {module}") == []


@pytest.mark.unit
def test_import_correct_archive__reporting_waits_for_a_figure():
    """The default output levels draw no matplotlib figure: their modules import none until level full draws."""
    assert _loaded_after("import mpi_lidar.workflows.correct_archive") == []


@pytest.mark.unit
def test_load_model__imports_xgboost_without_scikit_learn_which_still_imports_after(tmp_path):
    """Loading a booster needs none of XGBoost's scikit-learn estimators; scikit-learn stays importable."""
    from tests.model_factory import tiny_model

    model = tiny_model(tmp_path / "model")
    statement = (f"from mpi_lidar.learning.model import load_model\nmodel = load_model({str(model)!r})\n"
                 "assert model.booster.num_boosted_rounds() > 0")
    assert _loaded_after(statement) == ["xgboost"]
    after = _loaded_after(f"{statement}\nimport sklearn.neighbors")
    assert after == ["sklearn", "xgboost"]


@pytest.mark.unit
def test_import_flows__the_temporary_server_waits_for_a_process_without_an_api():
    """Prefect's server modules (about 2 s of imports) load where a process starts its own server, not in every
    process that runs a flow or a task (Dask workers, runs reporting to a configured API)."""
    code = ("import sys\nimport flows.correct, flows.generate_dataset, flows.regenerate\n"
            "print('prefect.server.api.server' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip().splitlines()[-1] == "False"
