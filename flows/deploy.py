"""Deployments: scheduled dataset regeneration, and tuning, training and archive correction on demand.

Build them, or serve them all with ``python -m flows.deploy``; trigger an on-demand one with
``prefect deployment run 'tune/tune' --param data=...``.

Schedules only run against a real Prefect server (``prefect server start --host 127.0.0.1`` and
``PREFECT_API_URL=http://127.0.0.1:4200/api``): a temporary ephemeral server would take the schedule with it
when this process ends. See ``infra/README.md`` for the work-pool alternative (``prefect deploy``).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys
from pathlib import Path

from prefect.deployments.runner import RunnerDeployment
from prefect.exceptions import TerminationSignal
from prefect.runner import Runner
from prefect.settings import get_current_settings

from flows.correct import correct_archive_flow
from flows.regenerate import regenerate_dataset_flow
from flows.train import train_flow
from flows.tune import tune_flow
from mpi_lidar.config import PRESETS
from mpi_lidar.errors import EXIT_USER_ERROR
from mpi_lidar.workflows.cluster import check_scheduler_address

DEPLOYMENT_NAME = "nightly-regeneration"
DEFAULT_ROOT = "runs/nightly"
DEFAULT_CRON = "0 2 * * *"


def build_deployments(
    root: str = DEFAULT_ROOT, cron: str = DEFAULT_CRON, preset: str = "quick", workers: int = 2,
    scheduler: str | None = None,
) -> list[RunnerDeployment]:
    """The regeneration deployment(s) of ``regenerate_dataset_flow`` on a cron schedule."""
    parameters: dict[str, object] = {"root": root, "preset": preset, "workers": workers}
    if scheduler:
        parameters["scheduler"] = check_scheduler_address(scheduler)  # a flow-run parameter: never a password
    deployment = regenerate_dataset_flow.to_deployment(
        name=DEPLOYMENT_NAME,
        cron=cron,
        parameters=parameters,
        description="Regenerate the dataset of the current configuration and code version; skip when complete.",
        tags=["mpi-lidar", "dataset"],
    )
    return [deployment]


def on_demand_deployments(workers: int = 2, scheduler: str | None = None) -> list[RunnerDeployment]:
    """Tuning, training and archive correction, run when triggered with their data as parameters.

    Every option of the flow (for correction: ``gate``, ``min_bias_mm``, ``footprint_area_m2``, as
    ``mpi-lidar correct``) is a parameter of its deployment, set with ``--param`` when triggered. ``workers``
    is the LocalCluster of tuning and training; correction keeps the flow's default, as ``mpi-lidar correct``
    does: the scans run in the flow's process, every core on each scan (``--param workers=N`` for a cluster).
    """
    at_scheduler: dict[str, object] = {"scheduler": check_scheduler_address(scheduler)} if scheduler else {}
    cluster: dict[str, object] = {"workers": workers, **at_scheduler}
    return [
        tune_flow.to_deployment(name="tune", parameters=cluster, tags=["mpi-lidar", "tuning"],
                                description="Optuna TPE study on the shared storage; trials on Dask."),
        train_flow.to_deployment(name="train", parameters=cluster, tags=["mpi-lidar", "training"],
                                 description="Final model through xgboost.dask with a study's best parameters."),
        correct_archive_flow.to_deployment(name="correct-archive", parameters=at_scheduler, tags=["mpi-lidar", "scans"],
                                           description="Batch correction of an archive of scans, one task per scan."),
    ]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m flows.deploy", description=__doc__.splitlines()[0])
    parser.add_argument("--root", default=DEFAULT_ROOT, help=f"Directory of the stores (default {DEFAULT_ROOT}).")
    parser.add_argument("--cron", default=DEFAULT_CRON, help=f"Cron schedule (default '{DEFAULT_CRON}').")
    parser.add_argument("--preset", default="quick", choices=sorted(PRESETS))
    parser.add_argument("--workers", type=int, default=2,
                        help="LocalCluster worker processes per run of generation, tuning and training.")
    parser.add_argument("--scheduler", help="Address of a running Dask scheduler (tcp://host:8786).")
    return parser.parse_args(argv)


class _Runner(Runner):
    """Prefect's runner, stopped by SIGTERM as Ctrl-C stops it: out of its event loop, which then cancels its tasks
    and pauses the schedules. (Prefect's own SIGTERM handler calls a coroutine it never awaits, a RuntimeWarning,
    and exits from inside the loop.)"""

    def handle_sigterm(self, *args: object, **kwargs: object) -> None:
        _terminate()


def _terminate(*_: object) -> None:
    """SIGTERM: stop where the process is, as Ctrl-C would; the runner's own lines of pausing are left out (the
    one line after it says so)."""
    logging.getLogger("prefect.runner").setLevel(logging.WARNING)
    raise TerminationSignal(signal=signal.SIGTERM)


def serve(*deployments: RunnerDeployment) -> None:
    """Serve ``deployments`` until SIGTERM or Ctrl-C; on either, their schedules are paused."""
    runner = _Runner(pause_on_shutdown=True)
    for deployment in deployments:
        runner.add_deployment(deployment)
    names = ", ".join(f"{d.flow_name}/{d.name}" for d in deployments)
    print(f"serving {len(deployments)} deployments ({names}); trigger one with: prefect deployment run NAME; "
          "stop with Ctrl-C or SIGTERM", flush=True)
    asyncio.run(runner.start())


def main(argv: list[str] | None = None) -> None:
    """Serve the deployments until interrupted; refuse without a real server, where schedules would not run."""
    args = parse_args(argv)
    if not get_current_settings().api.url:
        print("error: no PREFECT_API_URL; start 'prefect server start --host 127.0.0.1' and set "
              "PREFECT_API_URL=http://127.0.0.1:4200/api (schedules do not run on an ephemeral server)",
              file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)
    root = str(Path(args.root).resolve())  # runs start in other directories than this one
    signal.signal(signal.SIGTERM, _terminate)  # from here on; the runner's handler, once it runs, does the same
    try:
        serve(*build_deployments(root, args.cron, args.preset, args.workers, args.scheduler),
              *on_demand_deployments(args.workers, args.scheduler))
    except (KeyboardInterrupt, TerminationSignal) as stop:
        why = "SIGTERM" if isinstance(stop, TerminationSignal) else "Ctrl-C"
        print(f"stopped ({why}): served deployments' schedules are paused until they are served again", flush=True)


if __name__ == "__main__":
    main()
