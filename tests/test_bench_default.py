"""`make bench`'s default path (synthetic scenes at 2048-wide by default, no --scale) runs to its result table.

The scaling rows have their own runs (docs/benchmarks.md); this keeps the default command from breaking unnoticed (a
row's ``kind`` once named a variable that only the scaling path defines)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench.py"


def _bench_module():
    spec = importlib.util.spec_from_file_location("fullview_bench_under_test", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_default_bench_runs_a_small_scene_to_its_table(tmp_path, monkeypatch, capsys):
    bench = _bench_module()
    monkeypatch.setattr(bench, "RESULTS", tmp_path / "results")
    monkeypatch.setattr(sys, "argv", ["bench.py", "--views", "2", "--width", "256", "--dense-views", "0",
                                      "--no-colmap", "--no-real", "--no-home", "--work", str(tmp_path / "work")])
    assert bench.main() == 0
    (result,) = (tmp_path / "results").glob("*.json")
    rows = json.loads(result.read_text())["rows"]
    assert [(r["scene"], r["kind"], r["views"]) for r in rows] == [("synth2-hand", "room", 2),
                                                                 ("synth2-nohand", "room", 2)]
    assert all(r["ours"]["sparse_time_s"] > 0 for r in rows)
    assert "synth2-hand" in capsys.readouterr().out
