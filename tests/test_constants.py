"""Physical constants: the exact SI values, and the sensor table's rounded ones the configuration keeps."""

from __future__ import annotations

import pytest

from mpi_lidar import constants
from mpi_lidar.config import SensorConfig
from mpi_lidar.physics import sensor

pytestmark = pytest.mark.unit


def test_si_constants__are_the_exact_2019_si_values():
    # BIPM, The International System of Units, 9th edition (2019), table 1
    assert constants.SPEED_OF_LIGHT_M_PER_S == 299_792_458.0
    assert constants.ELEMENTARY_CHARGE_C == 1.602176634e-19
    assert constants.BOLTZMANN_J_PER_K == 1.380649e-23
    assert constants.PLANCK_J_S == 6.62607015e-34
    assert constants.ELECTRON_VOLT_J == 1.602176634e-19


def test_table_constants__keep_the_sensor_tables_values():
    # Table I as printed: the configuration hash and every dataset byte depend on these exact numbers
    assert constants.TABLE_SPEED_OF_LIGHT_M_PER_S == 3.0e8
    assert constants.TABLE_ELECTRON_CHARGE_C == 1.60217663e-19
    assert constants.TABLE_PLANCK_J_S == 6.62606896e-34
    assert constants.TABLE_BOLTZMANN_J_PER_K == 1.380649e-23
    # they differ from CODATA in the last digits, by design
    assert constants.TABLE_SPEED_OF_LIGHT_M_PER_S != constants.SPEED_OF_LIGHT_M_PER_S
    assert abs(constants.TABLE_ELECTRON_CHARGE_C / constants.ELEMENTARY_CHARGE_C - 1) < 1e-8
    assert abs(constants.TABLE_PLANCK_J_S / constants.PLANCK_J_S - 1) < 1e-6


def test_sensor_config__defaults_are_the_table_constants():
    s = SensorConfig()
    assert s.speed_of_light_m_per_s == constants.TABLE_SPEED_OF_LIGHT_M_PER_S
    assert s.electron_charge_c == constants.TABLE_ELECTRON_CHARGE_C
    assert s.planck_j_s == constants.TABLE_PLANCK_J_S
    assert s.boltzmann_j_per_k == constants.TABLE_BOLTZMANN_J_PER_K


def test_band_gap_conversion__uses_the_exact_electronvolt():
    assert sensor.ELECTRON_VOLT_J is constants.ELECTRON_VOLT_J
