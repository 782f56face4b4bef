"""Process start-up: what a sparse run imports outside the stages' work (a fixed cost of every `fullview` command)."""

from __future__ import annotations

import subprocess
import sys

SPARSE_STAGES = ("features", "matches", "filter", "epipoles", "registration", "triangulation")
# Imported only by the code that uses them: scipy.optimize by resection (0.1-0.16 CPU s: linprog, HiGHS and
# scipy.fft come with it; most runs never resect), the others by exports, densify, the viewer, reports and batches.
NOT_AT_START = ("scipy.optimize", "open3d", "pycolmap", "matplotlib", "dask", "distributed")


def _imported_after(code: str) -> set[str]:
    probe = f"import sys\n{code}\nprint(' '.join(m for m in {NOT_AT_START!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    return set(out.split())


def test_the_cli_and_the_sparse_stages_import_none_of_the_modules_they_may_not_use():
    code = "import importlib, fullview.cli\n" + "".join(
        f"importlib.import_module('fullview.stages.{s}')\n" for s in SPARSE_STAGES)
    assert _imported_after(code) == set()


def test_resection_imports_scipy_optimize_when_it_refines():
    # The deferred import still happens where it is needed (resection's soft-L1 refinement).
    code = ("import numpy as np\n"
            "from fullview.sfm.resection import refine_pose\n"
            "rng = np.random.default_rng(0)\n"
            "X = rng.normal(size=(20, 3)) + [0, 0, 5]\n"
            "refine_pose(np.eye(3), np.zeros(3), X / np.linalg.norm(X, axis=1, keepdims=True), X, 0.01)")
    assert "scipy.optimize" in _imported_after(code)
