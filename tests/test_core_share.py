"""`protocol.thread_map` leaves a core to each `forked` child while it works (`protocol._CoreShare`): on two cores
the pool runs one item at a time beside the child and two again as soon as the child is done."""

from __future__ import annotations

import multiprocessing
import os
import threading
import time

import pytest

from fullview.stages import protocol


class _Concurrency:
    """How many items run at once (the most, and when each started)."""

    def __init__(self, seconds: float):
        self.seconds, self.now, self.most, self.log = seconds, 0, 0, []
        self._lock = threading.Lock()

    def __call__(self, item):
        with self._lock:
            self.now += 1
            self.most = max(self.most, self.now)
            self.log.append((time.perf_counter(), self.now))
        time.sleep(self.seconds)
        with self._lock:
            self.now -= 1
        return item * 2


@pytest.fixture
def two_cores(monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 2)


def test_a_pool_runs_one_item_at_a_time_beside_a_forked_child_and_two_after(two_cores):
    with protocol.forked(time.sleep, 60) as job:  # never asked: stopped on leaving the block
        beside = _Concurrency(0.1)
        assert list(protocol.thread_map(beside, range(8))) == [2 * k for k in range(8)]
        assert beside.most == 1
        del job
    after = _Concurrency(0.1)
    assert list(protocol.thread_map(after, range(4))) == [0, 2, 4, 6]
    assert after.most == 2  # the stopped child gave its core back


def test_the_core_comes_back_when_the_child_is_done_not_when_its_block_ends(two_cores):
    with protocol.forked(time.sleep, 0.5) as job:
        running = _Concurrency(0.05)
        start = time.perf_counter()
        assert len(list(protocol.thread_map(running, range(40)))) == 40
        assert running.most == 2
        assert all(now == 1 for t, now in running.log if t - start < 0.3)  # the child still at work
        job.result()


def test_a_pool_in_a_pool_item_beside_a_child_does_not_wait_forever(two_cores):
    with protocol.forked(time.sleep, 60):
        inner = _Concurrency(0.01)
        outer = list(protocol.thread_map(lambda k: sum(protocol.thread_map(inner, range(3))) + k, range(3)))
        assert outer == [6, 7, 8] and inner.most == 1


def test_a_failed_child_gives_its_core_back(two_cores):
    with pytest.raises(ValueError):
        with protocol.forked(lambda: (_ for _ in ()).throw(ValueError("in the child"))) as job:
            job.result()
    assert protocol._CORES.free() == 2
    after = _Concurrency(0.1)
    list(protocol.thread_map(after, range(4)))
    assert after.most == 2


def test_a_side_thread_in_a_daemonic_process_counts_as_a_child(two_cores, monkeypatch):
    monkeypatch.setattr(multiprocessing.current_process(), "daemon", True, raising=False)
    with protocol.forked(time.sleep, 0.3) as job:
        assert protocol._CORES.free() == 1
        job.result()
        time.sleep(0.01)  # the done callback runs as the result is set
        assert protocol._CORES.free() == 2
    assert protocol._CORES.free() == 2
