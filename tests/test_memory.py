"""Process-level memory settings of the CLI (issue 12: peak memory at 48 views)."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys

import pytest


_ARENAS_SCRIPT = """
import ctypes, os, sys, tempfile, threading
if sys.argv[1] == "bound":
    from fullview.cli import bound_malloc_arenas
    assert bound_malloc_arenas()
barrier = threading.Barrier(8)
def allocate():  # eight threads allocating at once: each that finds the arenas busy gets a new one
    barrier.wait()
    for _ in range(200):
        blocks = [ctypes.create_string_buffer(20_000) for _ in range(50)]
        del blocks
threads = [threading.Thread(target=allocate) for _ in range(8)]
[t.start() for t in threads]
[t.join() for t in threads]
libc = ctypes.CDLL(None)
libc.fopen.restype = ctypes.c_void_p
path = os.path.join(tempfile.mkdtemp(), "malloc_info.xml")
f = libc.fopen(path.encode(), b"w")
libc.malloc_info(0, ctypes.c_void_p(f))
libc.fclose(ctypes.c_void_p(f))
print(open(path).read().count("<heap nr="))
"""


def test_malloc_arenas_are_bounded_to_one_per_core():
    """glibc gives concurrently allocating threads arenas of their own (up to 8 per core); after
    `bound_malloc_arenas` (what `fullview` does at start) there are at most max(2, cores)."""
    libc = ctypes.CDLL(None)
    if not (hasattr(libc, "mallopt") and hasattr(libc, "malloc_info")):
        pytest.skip("not glibc")
    arenas = {mode: int(subprocess.run([sys.executable, "-c", _ARENAS_SCRIPT, mode], capture_output=True, text=True,
                                       check=True).stdout) for mode in ("default", "bound")}
    assert arenas["bound"] <= max(2, os.cpu_count() or 1) < arenas["default"]
