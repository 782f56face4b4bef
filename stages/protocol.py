"""What a pipeline stage is: a module with a format version, its upstream stages, the dataset inputs it reads and a
`run` function that reads upstream artifacts through the workspace and writes its own through a writer bound to
its transaction."""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import resource
import signal
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from typing import Any, Callable, Iterable, Iterator, Protocol

from fullview.io.dataset import Dataset
from fullview.io.workspace import StageWriter, Workspace, close_inherited_locks

# How a stage fans work out: map(fn, items, threads=None) -> the results in the order of `items`. `fn` must be
# picklable (a top-level function, or a functools.partial of one) because a cluster runs it in other processes.
Mapper = Callable[..., Iterator[Any]]


def thread_map(fn: Callable[[Any], Any], items: Iterable[Any], *, threads: int | None = None) -> Iterator[Any]:
    """The local executor: a thread pool in this process (OpenCV and numpy release the GIL). `threads` caps the
    pool (memory-heavy work); a cluster executor ignores it. While a `forked` child is at work the pool runs one
    item fewer at once (at least one), and the full number again as soon as the child is done (`_CoreShare`)."""
    workers = min(threads or os.cpu_count() or 1, os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        yield from pool.map(partial(_CORES.run, _PoolSlots(workers), fn), items)


class _CoreShare:
    """The cores this process's local pools may use: all of them, less one for each `forked` child at work.

    Why: the world planes' child (about 4.5 CPU s of Python on the bench's room) runs beside the stereo check and
    the region fill on two pool threads. Three busy threads on two cores each get two thirds of a core, so the pool
    was done first and the child then ran on one core while the other stayed idle (about 1 s on the room). With
    one pool thread while the child works, each has a core and they end together; when the child ends first, its
    core goes back to the pool at its next item."""

    def __init__(self):
        self._changed = threading.Condition()
        self._children = 0

    def child_started(self) -> Callable[[Any], None]:
        """Count a child at work; returns the call that counts it done (once, whatever calls it again)."""
        with self._changed:
            self._children += 1
        ended = threading.Lock()

        def done(_: Any = None) -> None:
            if ended.acquire(blocking=False):
                with self._changed:
                    self._children -= 1
                    self._changed.notify_all()
        return done

    def free(self) -> int:
        return max(1, (os.cpu_count() or 1) - self._children)

    def run(self, slots: _PoolSlots, fn: Callable[[Any], Any], item: Any) -> Any:
        """``fn(item)`` once the pool has a free core (each pool its own count: a pool inside another's item
        always runs one at least, so nested pools cannot wait on each other)."""
        with self._changed:
            self._changed.wait_for(lambda: slots.active < min(slots.workers, self.free()))
            slots.active += 1
        try:
            return fn(item)
        finally:
            with self._changed:
                slots.active -= 1
                self._changed.notify_all()


@dataclass
class _PoolSlots:
    workers: int  # the pool's threads
    active: int = 0  # items running now


_CORES = _CoreShare()


def process_map(fn: Callable[[Any], Any], items: Iterable[Any], *, processes: int | None = None) -> Iterator[Any]:
    """`thread_map` on forked worker processes, for work whose Python between numpy calls holds the GIL: two threads
    of it contend for the GIL and use the two cores only 1.4 times (the filter's verification). The workers are
    forked, so `fn` and what it refers to are inherited, not pickled; only the items and the results travel (both
    must pickle). Falls back to threads where forking is not allowed (a daemonic process, such as a Dask worker) or
    not safe (only Linux: macOS's system libraries do not survive a fork, Windows has none). The runner counts the
    workers' CPU time with the stage's."""
    items = list(items)
    workers = min(processes or os.cpu_count() or 1, os.cpu_count() or 1, len(items))
    if workers < 2 or multiprocessing.current_process().daemon or not sys.platform.startswith("linux"):
        yield from thread_map(fn, items, threads=processes)
        return
    # Several tasks per message on long lists (the pipe's cost per task ~0.1 ms), but many more tasks than workers, so
    # that both finish together whatever each item costs.
    chunk = max(1, len(items) // (32 * workers))
    with multiprocessing.get_context("fork").Pool(workers, initializer=_install_forked,
                                                  initargs=(fn, os.getpid())) as pool:
        yield from pool.imap(_call_forked, items, chunk)
        pool.close()
        pool.join()  # reaped: their CPU time is in RUSAGE_CHILDREN now


def cpu_seconds() -> float:
    """CPU seconds of every thread of this process and of its reaped child processes (a stage's forked workers,
    `process_map`, `forked`)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def fork_call(fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)`` in one forked child process, for C++ work that holds the GIL throughout (open3d's Poisson), so
    that this process's threads can run Python meanwhile (`forked`)."""
    with forked(fn, *args) as job:
        return job.result()


@contextmanager
def forked(fn: Callable[..., Any], *args: Any) -> Iterator[Any]:
    """A job whose ``result()`` is ``fn(*args)``, computed meanwhile in one forked child process: for long Python
    work (the world planes' search) that would hold the GIL against this process's threads, or C++ work that holds
    it throughout. Inherited like `process_map`'s workers: only the result travels (it must pickle). A lock another
    thread holds at the fork stays held in the child: fork where no other thread is at work (the world planes), or
    where ``fn`` needs nothing they may hold (Poisson: open3d and the result's pickling, while the side thread draws
    with numpy and OpenCV; glibc's malloc is made consistent across a fork). Falls back to a local thread where
    `process_map` falls back to threads. The child is ended on leaving the block; the runner counts its CPU time
    with the stage's."""
    done = _CORES.child_started()  # the local pools leave it a core until it is done (`_CoreShare`)
    try:
        if multiprocessing.current_process().daemon or not sys.platform.startswith("linux"):
            with ThreadPoolExecutor(max_workers=1) as side:
                job = side.submit(fn, *args)
                job.add_done_callback(done)
                yield job
            return
        pool = multiprocessing.get_context("fork").Pool(1, initializer=_install_forked,
                                                        initargs=(lambda _: fn(*args), os.getpid()))
        job = pool.apply_async(_call_forked, (None,), callback=done, error_callback=done)
        job.result = job.get  # the interface of a future
        try:
            yield job
            pool.close()
        finally:
            pool.terminate()  # stops a child whose result was not asked for; nothing to stop otherwise
            pool.join()  # reaped: its CPU time is in RUSAGE_CHILDREN now
    finally:
        done()


_FORKED: Callable[[Any], Any] | None = None  # a worker process's function (set in the child only)
PR_SET_PDEATHSIG = 1  # prctl(2): the signal the calling process gets when its parent (the forking thread) ends


def _install_forked(fn: Callable[[Any], Any], parent: int) -> None:
    """A forked worker's start: it dies with the run that forked it and holds none of its workspace locks.

    Why: after a kill -9 of the run, a pool worker waits forever for its next task (it holds the pipes' other ends
    itself), and its inherited copy of the run lock's descriptor kept the workspace locked ("in use by" the dead
    pid) until it ended. SIGKILL on the parent's death (Linux's PR_SET_PDEATHSIG; the pools are made, and left,
    on the thread that uses them, which the signal follows) ends it; its lock descriptors are closed in any case."""
    global _FORKED
    _FORKED = fn
    close_inherited_locks()
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent:  # the parent died before the signal was armed
        os._exit(1)


def _call_forked(item: Any) -> Any:
    return _FORKED(item)


@dataclass(frozen=True, kw_only=True)
class StageContext:
    options: Any  # the stage's options dataclass (fullview.sfm.options)
    dataset: Dataset  # the input images, hand points, ground truth
    ws: Workspace  # read access to the upstream stages' artifacts
    out: StageWriter  # the only way to write this stage's artifacts
    map: Mapper = thread_map  # fan-out of independent work (images, blocks of pairs): threads or a Dask cluster


class Stage(Protocol):
    VERSION: int  # format version of the stage's artifacts (bump to invalidate old ones)
    UPSTREAM: tuple[str, ...]  # stages whose artifacts it reads
    INPUTS: tuple[str, ...]  # dataset inputs it reads: "images", "hand_points"

    def run(self, ctx: StageContext) -> dict:  # returns a JSON-able summary for the manifest
        ...
