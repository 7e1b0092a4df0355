"""Pixels corrected beyond the training prior: their own flag, the model's depth, an uncertainty that widens."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, correct_scan
from mpi_lidar.correction.options import Estimate, Flag, ScanStatus
from mpi_lidar.correction.outcome import scan_status
from mpi_lidar.learning.model import load_model
from mpi_lidar.learning.model_card import UncertaintyCard
from mpi_lidar.simulation.scenes import corner, render
from tests.model_factory import tiny_model

UNCERTAINTY = UncertaintyCard(noise_factor=1.0, model_sd_m=0.002, reference_correction_m=0.01,
                              correction_exponent=0.0, validation_rows=1_000, validation_coverage=0.68)


@pytest.mark.unit
def test_correct_scan__pixels_beyond_the_prior_get_their_own_flag_and_a_wider_sigma(tmp_path):
    # The paper's prior: rho_ABA <= 1, d_AB <= 0.15 m, which a sharp corner's edge exceeds.
    model = load_model(tiny_model(tmp_path / "model", geometric=True, rows=1_500, rounds=20))
    model = replace(model, card=model.card.model_copy(update={"uncertainty_model": UNCERTAINTY}))
    scan = render(corner(60.0, 2.0, 0.8, height=24, width=64), Config(), np.random.default_rng(2))
    correction = correct_scan(scan, model, CorrectionOptions(gate="all", footprint_area_m2=0.041))
    beyond = correction.flags == Flag.BEYOND_PRIOR
    assert 0 < beyond.sum() == correction.beyond_prior_pixels
    assert (correction.estimate[beyond] == Estimate.CORRECTED).all(), "valid: the model's depth"
    # The law alone gives 2 mm (exponent 0) with the fused sd; beyond the prior the share left out adds to it.
    assert (correction.uncertainty_m[beyond] > 0.002).all()
    inside = correction.flags == Flag.CORRECTED
    assert np.median(correction.uncertainty_m[beyond]) > np.median(correction.uncertainty_m[inside])
    counts = correction.counts()
    only_beyond = {**counts, "corrected": 0}
    assert scan_status(only_beyond, 0.5) == ScanStatus.CORRECTED, "a scan corrected beyond the prior is corrected"
