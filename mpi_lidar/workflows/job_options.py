"""The numbers the jobs beside a batch correction take (tune, train, table2, pipeline, and the cluster of any
job), each declared once with its bounds.

``mpi-lidar``'s options take their ranges from these declarations (:func:`mpi_lidar.cli._declared.bounded`), and
the flows' parameters are annotated with them: Prefect's parameter schema shows the bounds, and
``python -m flows`` refuses a value past them with one line before a flow run starts. A dataset's own numbers
(samples, chunk rows, seed) are declared by :class:`mpi_lidar.config.DatasetConfig`, a batch correction's by
:class:`mpi_lidar.workflows.batch_options.BatchOptions` and :class:`mpi_lidar.correction.CorrectionOptions`.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from mpi_lidar.config import MAX_SAMPLES

# A seed of numpy's SeedSequence (a scene's rendering, a benchmark's rows): a non-negative integer.
Seed = Annotated[int, Field(ge=0)]
# Worker processes of a local Dask cluster; 0 runs the work in this process.
Workers = Annotated[int, Field(ge=0)]
# Finished trials an Optuna study should hold (tune, pipeline), or trials per baseline (table2).
Trials = Annotated[int, Field(ge=1)]
# Train rows each tuning trial learns from: fewer than 100 leave XGBoost's early stopping nothing to validate on.
TuneRows = Annotated[int, Field(ge=100, le=MAX_SAMPLES)]
# Rows a Table II baseline learns from (train_rows, svm_rows).
BaselineRows = Annotated[int, Field(ge=10, le=MAX_SAMPLES)]
