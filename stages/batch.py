"""Batches of datasets on a dask.distributed cluster: every dataset runs its stages in order, each stage a task of
its own; inside a stage, the work a stage fans out (features per image, matching per block of pairs) becomes tasks
on the same cluster.

Why stages as tasks: a worker that dies takes only its stage with it. The scheduler reruns that task elsewhere
(`allowed-failures`), and the stage's transaction makes the rerun safe: the dead attempt wrote only into its
temporary folder, which the next holder of the workspace lock removes (the lock is an fcntl lock, released by the
kernel when its process dies), and the stage is computed again from the same inputs, so the same bytes.

Every worker must see the datasets and the workspace at the same paths (one machine, or a shared filesystem).
"""

from __future__ import annotations

import logging
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from distributed import KilledWorker, WorkerPlugin, as_completed, worker_client
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from fullview.io.config import Config
from fullview.io.dataset import Dataset
from fullview.io.errors import FullviewError
from fullview.io.workspace import Workspace
from fullview.stages import PIPELINE
from fullview.stages.runner import Pipeline, RunnerError

log = logging.getLogger(__name__)

STAGE_RETRIES = 1  # a stage task that raised (not a fullview error: those are results) is tried once more; a
#                    worker's death is counted by the scheduler's distributed.scheduler.allowed-failures instead


class BatchError(FullviewError, ValueError):
    """The batch cannot start (two datasets sharing a workspace folder, no datasets)."""


@dataclass(kw_only=True)
class DatasetOutcome:
    """What became of one dataset of the batch (a row of the summary table)."""
    name: str  # the dataset folder's name, also its workspace folder
    status: str = "pending"  # ok | failed
    reason: str = ""  # failed: the one-line error of the stage that failed
    ran: list[str] = field(default_factory=list)  # stages that ran (the others were fresh)
    registered: int | None = None  # images in model 0 (registration or triangulation summary)
    points: int | None = None  # sparse points (triangulation summary)
    wall_time_s: float = 0.0  # from its first stage's submission to its last stage's end


def check_batch(datasets: list[Dataset]) -> None:
    """Refuse a batch whose datasets would share a workspace folder (named after the dataset folder)."""
    if not datasets:
        raise BatchError("batch: no datasets given")
    seen: dict[str, Path] = {}
    for ds in datasets:
        other = seen.setdefault(ds.name, ds.root)
        if other is not ds.root:
            what = "given twice" if other.resolve() == ds.root.resolve() else f"and {other} have the same folder name"
            raise BatchError(f"batch: {ds.root} {what}; their workspaces would collide (<workspace>/{ds.name}); "
                             f"rename one folder or run it with another -w")


def run_batch(datasets: list[Dataset], config: Config, workspace: Path, client, *, until: str | None = None,
              force: bool = False, progress: bool = True) -> list[DatasetOutcome]:
    """Run the pipeline (up to `until`) on every dataset on the cluster of `client`; one dataset's failure does not
    stop the others. Returns one outcome per dataset, in the order given."""
    check_batch(datasets)
    client.register_plugin(WorkerLogging(), name="fullview-logging")
    stages = list(PIPELINE[:PIPELINE.index(until) + 1] if until else PIPELINE)
    batch_id = uuid.uuid4().hex[:8]  # unique task keys: a long-lived cluster must not hand back an older result
    outcomes = {ds.name: DatasetOutcome(name=ds.name) for ds in datasets}
    by_name = {ds.name: ds for ds in datasets}
    started = {ds.name: time.perf_counter() for ds in datasets}
    tasks: dict[str, tuple[str, int]] = {}  # task key -> (dataset, stage index)

    def submit(name: str, k: int):
        future = client.submit(run_stage_task, by_name[name], Path(workspace), config, stages[k], force,
                               key=f"fullview-{stages[k]}-{name}-{batch_id}", pure=False, retries=STAGE_RETRIES)
        tasks[future.key] = (name, k)
        return future

    pending = as_completed([submit(ds.name, 0) for ds in datasets])
    with logging_redirect_tqdm(), \
            tqdm(total=len(datasets), desc="batch", unit="dataset", disable=not progress) as bar:
        for future in pending:
            name, k = tasks.pop(future.key)
            outcome = outcomes[name]
            done = _record_stage(outcome, stages[k], future)
            future.release()
            if not done and k + 1 < len(stages):
                pending.add(submit(name, k + 1))
                continue
            outcome.status = "failed" if outcome.reason else "ok"
            outcome.wall_time_s = round(time.perf_counter() - started[name], 2)
            bar.update()
    return [outcomes[ds.name] for ds in datasets]


def _record_stage(outcome: DatasetOutcome, stage: str, future) -> bool:
    """Log one finished stage task and note it in the outcome; True when the dataset stops here (it failed)."""
    if future.status != "finished":
        error = future.exception() if future.status == "error" else f"task {future.status}"
        outcome.reason = f"{stage}: {task_error(error, stage) if isinstance(error, BaseException) else error}"
        log.error("%s: %s", outcome.name, outcome.reason)
        return True
    result = future.result()
    if "error" in result:
        outcome.reason = f"{stage}: {result['error']}"
        log.error("%s: %s", outcome.name, outcome.reason)
        return True
    summary = result["summary"]
    if result["ran"]:
        outcome.ran.append(stage)
    for key in ("registered", "points"):  # registration's, then triangulation's
        if isinstance(summary.get(key), int):
            setattr(outcome, key, summary[key])
    state = f"done in {result['wall_time_s']:.1f} s" if result["ran"] else "fresh"
    log.info("%s: %-13s %s %s", outcome.name, stage, state, _short(summary))
    return False


def task_error(error: BaseException, stage: str) -> str:
    """A stage task's error in one line: the message of a fullview error, else what happened."""
    if isinstance(error, KilledWorker):
        return f"its worker died every time it ran {stage} ({error})"
    if isinstance(error, FullviewError):
        return " ".join(str(error).split())
    return " ".join(f"internal error: {type(error).__name__}: {error}".split())


def run_stage_task(dataset: Dataset, workspace: Path, config: Config, stage: str, force: bool) -> dict:
    """One stage of one dataset, on a worker: run when stale (or forced), under the workspace lock, its fan-out on
    this cluster. Returns {"ran", "wall_time_s", "summary"} (the manifest's), or {"error": one line} for a fullview
    error (bad input, a busy workspace)."""
    pipeline = Pipeline(dataset, Workspace(workspace, dataset.name), config, map=cluster_map)
    try:
        ran = pipeline.run(only=stage) if force else pipeline.run(until=stage)
    except FullviewError as e:  # bad input explains itself and fails the same way again: a result, not a retry
        return {"error": " ".join(str(e).split())}
    if ran and ran != [stage]:
        # Only `stage` can be stale here: its upstream stages were just brought up to date by earlier tasks.
        log.warning("%s: reran %s (changed meanwhile)", dataset.name, ", ".join(ran[:-1]))
    manifest = pipeline.ws.read_manifest(stage)
    if manifest is None:
        raise RunnerError(f"{pipeline.ws.folder(stage)}: no manifest after the stage ran")
    return {"ran": stage in ran, "wall_time_s": manifest.get("wall_time_s", 0.0),
            "summary": manifest.get("summary", {})}


def cluster_map(fn: Callable[[Any], Any], items: Iterable[Any], *, threads: int | None = None) -> Iterator[Any]:
    """The stages' fan-out on the cluster this task runs on: one task per item, results in order. The calling task
    secedes from its worker's thread pool meanwhile, so its subtasks can run there too (no deadlock on a full
    cluster). A worker dying under a subtask only reruns that subtask."""
    items = list(items)
    with worker_client() as client:
        futures = client.map(fn, items, pure=False)
        try:
            for future in futures:
                yield future.result()
        finally:
            client.cancel([f for f in futures if not f.done()])


class WorkerLogging(WorkerPlugin):
    """A worker plugin: fullview's warnings and errors on a worker are printed, marked as coming from one (without
    it a worker's root logger has no handler and only Python's last-resort one prints warnings, bare); a failed
    task's traceback is not (distributed logs one per failed task: a bad dataset's nine images gave nine)."""

    def setup(self, worker) -> None:
        worker_log = logging.getLogger("distributed.worker")
        if not any(isinstance(f, TaskFailureFilter) for f in worker_log.filters):
            worker_log.addFilter(TaskFailureFilter())
        logger = logging.getLogger("fullview")
        if not any(getattr(h, "fullview_worker", False) for h in logger.handlers):
            handler = logging.StreamHandler()
            handler.fullview_worker = True
            handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s worker %(name)s: %(message)s",
                                                   datefmt="%H:%M:%S"))
            handler.setLevel(logging.WARNING)
            logger.addHandler(handler)


class TaskFailureFilter(logging.Filter):
    """Drops distributed's "Compute Failed" record (key, task, exception, traceback) of a task that raised: the
    exception travels to the batch with the task's result, which reports it once, in one line naming the dataset
    (`_record_stage`)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Compute Failed")


def _short(summary: dict) -> str:
    items = [f"{k}={v}" for k, v in summary.items() if isinstance(v, (int, str))]
    return ", ".join(items[:4])


def summary_table(outcomes: list[DatasetOutcome]) -> str:
    """The batch's summary as a fixed-width table."""
    rows = [("dataset", "status", "registered", "points", "wall s", "stages run / reason")]
    for o in outcomes:
        detail = o.reason if o.status == "failed" else (", ".join(o.ran) or "none (all fresh)")
        rows.append((o.name, o.status, "-" if o.registered is None else str(o.registered),
                     "-" if o.points is None else str(o.points), f"{o.wall_time_s:.1f}", detail))
    widths = [max(len(r[c]) for r in rows) for c in range(len(rows[0]) - 1)]
    return "\n".join("  ".join(v.ljust(w) for v, w in zip(r, widths)) + "  " + r[-1] for r in rows)
