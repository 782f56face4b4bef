"""`protocol.process_map`: forked workers give the thread pool's results, and the runner counts their CPU time."""

from __future__ import annotations

import multiprocessing
import os
import time

import numpy as np
import pytest

from fullview.stages import filter as filter_stage
from fullview.stages import protocol
from fullview.stages.protocol import cpu_seconds


def test_results_come_back_in_order_from_forked_workers():
    parent = os.getpid()
    table = {k: np.arange(k) for k in range(40)}  # reached through a lambda: inherited by the fork, never pickled
    out = list(protocol.process_map(lambda k: (int(table[k].sum()), os.getpid()), range(40)))
    assert [s for s, _ in out] == [k * (k - 1) // 2 for k in range(40)]
    assert all(pid != parent for _, pid in out)


def test_a_workers_error_reaches_the_caller():
    def fail_on_7(k):
        if k == 7:
            raise ValueError("pair 7")
        return k
    with pytest.raises(ValueError, match="pair 7"):
        list(protocol.process_map(fail_on_7, range(10)))


def test_one_item_or_a_daemonic_process_runs_on_threads(monkeypatch):
    parent = os.getpid()
    assert list(protocol.process_map(lambda k: os.getpid(), [0])) == [parent]
    monkeypatch.setattr(multiprocessing.current_process(), "daemon", True, raising=False)
    assert list(protocol.process_map(lambda k: os.getpid(), range(4))) == [parent] * 4


def test_runner_counts_the_workers_cpu_time():
    def spin(_):
        end = time.process_time() + 0.3
        while time.process_time() < end:
            pass
    before, own = cpu_seconds(), time.process_time()
    list(protocol.process_map(spin, range(2)))
    assert time.process_time() - own < 0.2  # the parent only waited
    assert cpu_seconds() - before >= 0.55


def test_a_forked_call_returns_the_direct_calls_result_and_its_cpu_time_is_counted():
    parent = os.getpid()
    table = np.arange(10.0)  # reached through the arguments: inherited by the fork, never pickled

    def spin(values, scale):
        end = time.process_time() + 0.3
        while time.process_time() < end:
            pass
        return values * scale, os.getpid()

    before, own = cpu_seconds(), time.process_time()
    values, pid = protocol.fork_call(spin, table, 3.0)
    assert pid != parent and np.array_equal(values, table * 3.0)
    assert time.process_time() - own < 0.2 and cpu_seconds() - before >= 0.28
    with pytest.raises(ValueError, match="in the child"):
        protocol.fork_call(lambda: (_ for _ in ()).throw(ValueError("in the child")))


def test_a_forked_job_runs_beside_this_process_and_an_unasked_one_is_stopped():
    parent = os.getpid()
    with protocol.forked(lambda: os.getpid()) as job:
        busy = sum(range(10**5))  # this process works meanwhile
        assert job.result() != parent and busy
    start = time.perf_counter()
    with protocol.forked(time.sleep, 30):  # left without asking: stopped, not waited for
        pass
    assert time.perf_counter() - start < 10


def test_a_forked_call_in_a_daemonic_process_runs_here(monkeypatch):
    monkeypatch.setattr(multiprocessing.current_process(), "daemon", True, raising=False)
    assert protocol.fork_call(os.getpid) == os.getpid()
    with protocol.forked(os.getpid) as job:
        assert job.result() == os.getpid()


def test_filter_stage_in_workers_equals_threads(tiny_dataset, make_pipeline, monkeypatch):
    forks = []
    monkeypatch.setattr(filter_stage, "FORK_MIN_PAIRS", 1)
    monkeypatch.setattr(filter_stage, "process_map", lambda *a, **k: forks.append(1) or protocol.process_map(*a, **k))
    pipe = make_pipeline(tiny_dataset)
    pipe.run(until="filter")
    assert forks
    forked = pipe.ws.folder("filter") / "inliers.npz"
    forked_bytes = forked.read_bytes()
    monkeypatch.setattr(filter_stage, "FORK_MIN_PAIRS", 10**9)
    assert pipe.run(start="filter", until="filter") == ["filter"]
    assert forked.read_bytes() == forked_bytes


def test_npz_headers_are_never_parsed_by_two_threads_at_once(tmp_path, monkeypatch):
    """CPython 3.11's AST constructor is not thread-safe (python/cpython#106905) and numpy parses every .npy header
    with ast.literal_eval: the stages' threads that load features at once must take turns."""
    import ast
    import threading

    from fullview.io.artifacts import load_npz, save_npz
    from fullview.stages.protocol import thread_map
    paths = [save_npz(tmp_path / f"{k}.npz", 1, a=np.arange(k + 3)) for k in range(8)]
    inside, overlaps, lock, parse = [0], [0], threading.Lock(), ast.literal_eval

    def slow_parse(text):
        with lock:
            inside[0] += 1
            overlaps[0] += inside[0] > 1
        time.sleep(0.005)  # widen the window a racing thread would hit
        try:
            return parse(text)
        finally:
            with lock:
                inside[0] -= 1
    monkeypatch.setattr(ast, "literal_eval", slow_parse)
    loaded = list(thread_map(lambda p: load_npz(p, 1)["a"], paths * 4, threads=4))
    assert [len(a) for a in loaded] == [k + 3 for k in range(8)] * 4
    assert overlaps[0] == 0
