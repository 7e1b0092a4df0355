"""Physical constants, each defined once, its unit in its name.

Two sets, on purpose:

- The CODATA 2018 / SI values. Since the 2019 redefinition of the SI the speed of light, the elementary
  charge, the Boltzmann and the Planck constants are exact by definition (BIPM, *The International System
  of Units*, 9th edition, 2019; CODATA 2018, Tiesinga et al., Rev. Mod. Phys. 93, 025010, 2021).
- The rounded values of the paper's sensor table (Table I), which :class:`mpi_lidar.config.SensorConfig`
  uses as its defaults. They differ from CODATA in the last digits (c = 3.0e8 instead of 299 792 458 m/s;
  an older CODATA electron charge and Planck constant), and they must keep these values: the
  configuration's hash (:func:`mpi_lidar.config.config_sha256`) and every byte of a simulated dataset
  depend on them. Code that models the sensor of the paper takes its constants from the configuration
  (whose defaults are these); the CODATA values serve conversions that are not part of the sensor
  table, such as an energy given in electronvolts.
"""

from __future__ import annotations

# --- CODATA 2018 / SI (exact since 2019) ---------------------------------------------------------------

SPEED_OF_LIGHT_M_PER_S = 299_792_458.0
"""Speed of light in vacuum, c. Exact (SI definition of the metre). [m/s]"""

ELEMENTARY_CHARGE_C = 1.602176634e-19
"""Elementary charge, e. Exact (SI definition of the ampere). [C]"""

ELECTRON_VOLT_J = ELEMENTARY_CHARGE_C
"""One electronvolt, the energy e gains across one volt: numerically e. Exact. [J]"""

BOLTZMANN_J_PER_K = 1.380649e-23
"""Boltzmann constant, k_B. Exact (SI definition of the kelvin). [J/K]"""

PLANCK_J_S = 6.62607015e-34
"""Planck constant, h. Exact (SI definition of the kilogram). [J s]"""

# --- the sensor table's own values (paper, Table I) ----------------------------------------------------
# Rounded or older values, kept as printed: they are the simulator's defaults, and the configuration hash
# and the dataset bytes depend on them. Do not replace them by the CODATA values above.

TABLE_SPEED_OF_LIGHT_M_PER_S = 3.0e8
"""Speed of light of Table I, rounded to 3.0e8 (0.07 % above c). [m/s]"""

TABLE_ELECTRON_CHARGE_C = 1.60217663e-19
"""Electron charge of Table I, 1.60217663e-19 (rounded to 9 digits; CODATA: 1.602176634e-19). [C]"""

TABLE_PLANCK_J_S = 6.62606896e-34
"""Planck constant of Table I, 6.62606896e-34 (CODATA 2006; CODATA 2018: 6.62607015e-34). [J s]"""

TABLE_BOLTZMANN_J_PER_K = BOLTZMANN_J_PER_K
"""Boltzmann constant of Table I: the exact SI value. [J/K]"""
