"""Pairs of a batch on a Dask cluster (``dask.distributed``).

``plenocl run --workers N`` starts a local cluster of N single-threaded worker processes
(spawned, so safe wherever ``fork`` is not); ``--scheduler ADDRESS`` uses an existing
cluster (e.g. one started by ``dask-jobqueue`` on SLURM, docs/batch.md). Every worker
gets the :class:`PlenoclWorker` plugin (pickled with the run's
:class:`~plenocl.batch.worker.RunSettings`), which makes one
:class:`~plenocl.batch.worker.PairProcessor` (OpenCL context, projector, compiled
kernels) per worker; tasks carry :class:`~plenocl.batch.worker.PairTask` file paths and
return small :class:`~plenocl.batch.worker.PairOutcome` records, never contexts or
volumes. Each worker picks its device from the run's ``device`` argument, else its own
``PLENOCL_DEVICE`` or ``PYOPENCL_CTX`` variable, else the machine's GPUs: a name that
matches several devices, or the default on a machine with several GPUs, spreads the
workers over them by worker number (worker k takes the k-th, in turn).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

from distributed import Client, LocalCluster, WorkerPlugin, as_completed, get_worker

from ..opencl.device import spread_device
from ..opencl.threads import thread_count
from .worker import PairOutcome, PairProcessor, PairTask, RunSettings

PLUGIN = "plenocl"


class PlenoclWorker(WorkerPlugin):
    """Worker plugin: one :class:`PairProcessor` per worker, made when it joins."""

    name = PLUGIN

    def __init__(self, run_folder: str, settings: RunSettings,
                 device: str | None = None) -> None:
        self.run_folder, self.settings, self.device = str(run_folder), settings, device
        self.processor: PairProcessor | None = None

    def setup(self, worker) -> None:
        """Make the worker's processor (its OpenCL context comes with the first pair) on
        its device: the run's or its own ``PLENOCL_DEVICE`` name, or by default the
        machine's GPUs, spread over the workers by their number
        (:func:`plenocl.opencl.device.spread_device`)."""
        device = self.device or os.environ.get("PLENOCL_DEVICE") or None
        device = spread_device(device, worker_number(worker.name))
        self.processor = PairProcessor(self.run_folder, self.settings, device)


def worker_number(name) -> int:
    """A Dask worker's number: its name where that is a number (a local cluster's
    workers are 0, 1, ...), else the number its name ends with (``"SLURMCluster-3"``),
    else 0."""
    digits = str(name)[len(str(name).rstrip("0123456789")):]
    return int(digits) if digits else 0


def process_on_worker(task: PairTask) -> PairOutcome:
    """The Dask task: one pair through this worker's processor."""
    return get_worker().plugins[PLUGIN].processor(task)


@contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None) -> Iterator[Client]:
    """A client of an existing scheduler, or of a local cluster of ``workers`` processes
    that share this machine's cores (closed on exit)."""
    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
    if not workers or workers < 1:
        raise ValueError(f"workers must be a positive number of processes, got {workers!r}")
    threads = str(max(1, thread_count(-1) // workers))
    env = {"PLENOCL_THREADS": threads, "POCL_MAX_PTHREAD_COUNT": threads,
           "POCL_CPU_MAX_CU_COUNT": threads, "OMP_NUM_THREADS": threads}
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      dashboard_address=None, env=env) as cluster, Client(cluster) as client:
        yield client


def run_on_dask(client: Client, tasks: Sequence[PairTask], run_folder, settings: RunSettings,
                device, on_done: Callable[[PairOutcome], None]) -> None:
    """Process ``tasks`` on the cluster, calling ``on_done`` as each pair finishes.

    Interrupted (Ctrl-C), it cancels the pairs not yet done; those done are written.
    """
    client.register_plugin(PlenoclWorker(str(run_folder), settings, device), name=PLUGIN)
    futures = client.map(process_on_worker, list(tasks), pure=False)
    try:
        for future in as_completed(futures):
            on_done(future.result())
    finally:
        client.cancel(futures)
