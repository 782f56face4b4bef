"""`fullview batch`: many datasets through the pipeline on a dask.distributed cluster — a LocalCluster of worker
processes on 127.0.0.1 by default, or an existing cluster (`--scheduler tcp://HOST:PORT`). The orchestration is
`fullview.stages.batch`; this module finds the datasets and owns the cluster."""

from __future__ import annotations

import glob
import logging
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from fullview.io.config import Config
from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace
from fullview.stages.batch import BatchError, DatasetOutcome, check_batch, run_batch

log = logging.getLogger(__name__)

ALLOWED_FAILURES = 3  # worker deaths a task may see before it is failed (a task that kills every worker it meets)
CONNECT_TIMEOUT_S = 20  # to reach --scheduler
WORKER_ENVIRON = {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1}  # set before a worker starts


def batch(paths: list[Path], pattern: str | None, config: Config, workspace: Path, *, scheduler: str | None = None,
          workers: int | None = None, until: str | None = None, force: bool = False,
          progress: bool = True) -> list[DatasetOutcome]:
    """Open the datasets (a bad path is an error before the cluster starts) and run them on the cluster."""
    datasets = [Dataset(p) for p in dataset_paths(paths, pattern)]
    check_batch(datasets)
    for ds in datasets:
        Workspace(workspace, ds.name).check_root()
    with cluster_client(scheduler, workers) as client:
        return run_batch(datasets, config, workspace, client, until=until, force=force, progress=progress)


def dataset_paths(paths: list[Path], pattern: str | None) -> list[Path]:
    """The given folders, then the folders `pattern` matches (sorted); an empty pattern match is an error."""
    found = list(paths)
    if pattern is not None:
        matched = sorted(Path(p) for p in glob.glob(os.path.expanduser(pattern)) if Path(p).is_dir())
        if not matched:
            raise BatchError(f"batch: --glob {pattern!r} matches no folder")
        found += matched
    if not found:
        raise BatchError("batch: no datasets given (name dataset folders or pass --glob PATTERN)")
    return found


def default_workers() -> int:
    """One worker process per core this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@contextmanager
def cluster_client(scheduler: str | None, workers: int | None) -> Iterator:
    """A client of the given scheduler, or of a LocalCluster (processes, 127.0.0.1, no dashboard) closed on exit."""
    import dask
    from distributed import Client, LocalCluster

    quiet_distributed()
    # distributed's default worker environment also sets MALLOC_TRIM_THRESHOLD_, which disables glibc's adaptive
    # mmap threshold: every large numpy temporary is then mapped and unmapped afresh (triangulation ran 1.2-1.7x
    # slower in measurements). Single-threaded BLAS/OpenMP is kept: a worker is a core.
    with dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES,
                          "distributed.nanny.pre-spawn-environ": WORKER_ENVIRON}):
        if scheduler is not None:
            if workers is not None:
                raise BatchError("batch: --workers sizes the local cluster; it cannot be combined with --scheduler")
            try:
                client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
            except (OSError, TimeoutError, ValueError) as e:
                raise BatchError(f"batch: cannot reach the scheduler {scheduler} ({' '.join(str(e).split())})") \
                    from None
            with client:
                yield client
            return
        if workers is not None and workers < 1:
            raise BatchError(f"batch: --workers {workers}: need at least one worker")
        # Worker processes, not threads: SIFT, matching and bundle adjustment hold the GIL in places, and a
        # process can die alone. Their progress bars are off (the batch has its own); BLAS is single-threaded
        # there by distributed's defaults, as in the stages.
        with LocalCluster(n_workers=workers or default_workers(), threads_per_worker=1, processes=True,
                          host="127.0.0.1", dashboard_address=None, env={"TQDM_DISABLE": "1"}) as cluster, \
                Client(cluster) as client:
            yield client


def quiet_distributed() -> None:
    """distributed logs every worker start, stop and restart at INFO/WARNING; the batch reports what matters."""
    for name in ("distributed", "bokeh", "tornado"):
        logging.getLogger(name).setLevel(logging.ERROR)
