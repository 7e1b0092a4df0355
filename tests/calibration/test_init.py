"""The calibration package's public surface (mpi_lidar.calibration): each name from its module, on first use."""

from __future__ import annotations

import subprocess
import sys

import pytest

import mpi_lidar.calibration as calibration

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("name", calibration.__all__)
def test_calibration__each_public_name_is_its_module_s(name):
    value = getattr(calibration, name)
    assert value.__module__.startswith("mpi_lidar.calibration.") and value.__name__ == name


def test_calibration__an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'measure'"):
        calibration.measure  # noqa: B018


def test_import_profile__leaves_the_estimator_unimported():
    code = ("import sys\nfrom mpi_lidar.calibration import read_profile\n"
            "print('mpi_lidar.calibration.sensor_scale' in sys.modules, 'scipy.optimize' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["False", "False"]
