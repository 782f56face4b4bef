"""The reference pages in docs/ stay true to what they are generated from and point at things that exist: the
benchmark tables equal the ones benchmarks/results_table.py makes from benchmarks/results/, that folder holds only
the runs the rule keeps, every test docs/guarantees.md names exists, and every relative link of the README and
docs/ leads to a file (and heading) that exists."""

from __future__ import annotations

import ast
import importlib.util
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _module(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


generate = _module(DOCS / "generate.py", "fullview_docs_generate")
results_table = _module(ROOT / "benchmarks" / "results_table.py", "fullview_results_table_under_test")


@pytest.mark.parametrize("file", sorted(generate.generated()))
def test_each_generated_table_is_current(file):
    name, markdown = generate.generated()[file]
    committed = generate.block((DOCS / file).read_text(), name)
    assert committed is not None, f"docs/{file} lost the markers of its {name}"
    assert committed == markdown, f"docs/{file}: the {name} is stale: run python docs/generate.py"


def test_the_results_folder_holds_only_the_runs_that_matter():
    assert results_table.superseded_files() == [], (
        "benchmarks/results/ holds files whose every row a later run measured again; git rm them (git keeps them), "
        "then python docs/generate.py")


def _result(path: Path, date: str, width: int, scenes: list[str]) -> None:
    rows = [{"scene": s, "views": 6, "ours": {"registered": 6, "sparse_time_s": 1.0, "peak_rss_mb": 100.0},
             "colmap": {"registered": 6, "wall_time_s": 2.0}} for s in scenes]
    path.write_text(json.dumps({"date": date, "width": width, "rows": rows}))


def test_the_rule_keeps_each_scenes_newest_run(tmp_path):
    _result(tmp_path / "old.json", "2026-01-01T00:00:00", 1024, ["room6", "room24"])
    _result(tmp_path / "newer.json", "2026-01-02T00:00:00", 1024, ["room6"])
    _result(tmp_path / "other_width.json", "2026-01-01T00:00:00", 2048, ["room6"])
    _result(tmp_path / "superseded.json", "2025-12-31T00:00:00", 1024, ["room24"])
    newest = {(row["scene"], data["width"]): name for name, data, row in results_table.newest_rows(tmp_path)}
    assert newest == {("room6", 1024): "newer.json", ("room24", 1024): "old.json",
                      ("room6", 2048): "other_width.json"}
    assert results_table.superseded_files(tmp_path) == ["superseded.json"]
    table = results_table.sparse_table(tmp_path)
    assert table.count("`newer.json`") == 1 and "superseded.json" not in table and "| 0.50 |" in table


def _test_names(path: Path) -> set[str]:
    return {node.name for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name.startswith("test_")}


def test_every_guarantee_names_tests_that_exist():
    rows = [line for line in (DOCS / "guarantees.md").read_text().splitlines() if line.startswith("| ")][1:]
    assert len(rows) >= 10
    default = _test_names(ROOT / "tests" / "test_guarantees.py")
    for row in rows:
        cell = row.rstrip(" |").rsplit(" | ", 1)[1]
        named = re.findall(r"`(tests/[\w/]+\.py)(?:::(\w+))?`|`(test_\w+?)(\*?)`", cell)
        assert named, f"guarantee without a test: {row[:80]}"
        for file, in_file, name, star in named:
            if file:
                assert (ROOT / file).is_file(), f"{file} named in docs/guarantees.md does not exist"
                assert not in_file or in_file in _test_names(ROOT / file), f"{file}::{in_file} does not exist"
            elif star:
                assert any(t.startswith(name) for t in default), f"no test_guarantees.py test starts with {name}"
            else:
                assert name in default, f"docs/guarantees.md names {name}, not a test in tests/test_guarantees.py"


def _anchors(path: Path) -> set[str]:
    """GitHub's heading anchors of a markdown file."""
    headings = re.findall(r"^#+ (.+)$", re.sub(r"^```.*?^```", "", path.read_text(), flags=re.S | re.M), re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in headings}


PAGES = [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_relative_links_lead_somewhere(page):
    for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
        if re.match(r"[a-z]+://", target):
            continue
        file, _, anchor = target.partition("#")
        dest = (page.parent / file).resolve() if file else page
        assert dest.exists(), f"{page.name} links to {target}, which does not exist"
        assert not anchor or anchor in _anchors(dest), f"{page.name} links to {target}: no such heading"
