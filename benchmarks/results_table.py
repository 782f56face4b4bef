"""The table of docs/benchmarks.md, generated from benchmarks/results/*.json (the files benchmarks/bench.py writes).

Rule: for every scene at its width (a result row's ``scene`` and its file's ``width``), the newest row counts; a
results file is kept when it holds at least one such newest row. ``python benchmarks/results_table.py`` prints the
tables and the files the rule no longer needs; ``python docs/generate.py`` writes the tables into docs/benchmarks.md
(a test holds them equal).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def _load(results: Path) -> list[tuple[str, dict]]:
    return [(path.name, json.loads(path.read_text())) for path in sorted(results.glob("*.json"))]


def newest_rows(results: Path = RESULTS) -> list[tuple[str, dict, dict]]:
    """(file name, file, row) of the newest row of every (scene, width), ordered by width, views and scene."""
    newest: dict[tuple[str, int], tuple[str, dict, dict]] = {}
    for name, data in _load(results):
        for row in data["rows"]:
            key = (row["scene"], data["width"])
            if key not in newest or data["date"] > newest[key][1]["date"]:
                newest[key] = (name, data, row)
    return sorted(newest.values(), key=lambda t: (t[1]["width"], t[2]["scene"].split("-")[0].rstrip("0123456789"),
                                                   t[2].get("views") or 0, t[2]["scene"]))


def superseded_files(results: Path = RESULTS) -> list[str]:
    """Result files that hold no newest row (the rule above: they can leave the tree, git keeps them)."""
    kept = {name for name, _, _ in newest_rows(results)}
    return [name for name, _ in _load(results) if name not in kept]


def _fmt(x, spec: str) -> str:
    return "–" if x is None else format(x, spec)


def _ratio(a, b) -> float | None:
    return a / b if a is not None and b else None


def sparse_table(results: Path = RESULTS) -> str:
    head = ("scene", "width", "views", "date", "ours registered", "COLMAP registered", "ours AUC@1", "COLMAP AUC@1",
            "ours s", "COLMAP s", "ratio", "ours MB", "COLMAP MB", "file")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, data, row in newest_rows(results):
        ours, colmap = row["ours"], row.get("colmap") or {}
        om, cm = ours.get("metrics") or {}, colmap.get("metrics") or {}
        views = row.get("views") or om.get("images")
        cells = [row["scene"], str(data["width"]), _fmt(views, "d"), data["date"][:10],
                 str(ours.get("registered", "failed")), str(colmap.get("registered", "–")),
                 _fmt(om.get("auc@1"), ".2f"), _fmt(cm.get("auc@1"), ".2f"),
                 _fmt(ours.get("sparse_time_s"), ".1f"), _fmt(colmap.get("wall_time_s"), ".1f"),
                 _fmt(_ratio(ours.get("sparse_time_s"), colmap.get("wall_time_s")), ".2f"),
                 _fmt(ours.get("peak_rss_mb"), ".0f"), _fmt(colmap.get("peak_rss_mb"), ".0f"), f"`{name}`"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def dense_table(results: Path = RESULTS) -> str:
    head = ("scene", "width", "date", "pairs", "densify s", "s per panorama", "points", "median valid share",
            "accuracy", "completeness", "file")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, data, row in newest_rows(results):
        dense = row["ours"].get("densify")
        if not dense:
            continue
        shares = sorted((dense.get("valid_share") or {}).values())
        cloud = ((row["ours"].get("metrics") or {}).get("dense") or {}).get("cloud") or {}
        cells = [row["scene"], str(data["width"]), data["date"][:10], str(dense["pairs"]),
                 _fmt(dense.get("stage_time_s"), ".1f"),
                 _fmt(_ratio(dense.get("stage_time_s"), len(shares)), ".2f"), str(dense["points"]),
                 _fmt(shares[len(shares) // 2] if shares else None, ".2f"),
                 _fmt(cloud.get("accuracy"), ".3f"), _fmt(cloud.get("completeness"), ".3f"), f"`{name}`"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def tables_markdown(results: Path = RESULTS) -> str:
    return sparse_table(results) + "\n" + dense_table(results)


if __name__ == "__main__":
    print(tables_markdown())
    gone = superseded_files()
    if gone:
        print("superseded (no newest row):", *gone, sep="\n  ")
    sys.exit(0)
