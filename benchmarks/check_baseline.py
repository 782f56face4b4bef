"""The stored COLMAP-comparison baseline (benchmarks/baseline.json): record it from real runs, or gate results.

`fullview compare` gates itself (non-zero exit on a regression); this script works on the `compare_spherical/colmap.json`
files it leaves in the workspace:

    python benchmarks/check_baseline.py record WS/360_Flat/compare_spherical/colmap.json ... [--as NAME=KEY ...]
    python benchmarks/check_baseline.py check  WS/360_Flat/compare_spherical/colmap.json ...

`record` writes each result's gated metrics (sfm.compare.GATES) under its dataset key (the dataset folder's name;
`--as cmp_synth6=synth6` also stores the entry under a second key, for the same scene rendered elsewhere); the
tolerances already in the file are kept. `check` exits 1 when any result fails its baseline.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "benchmarks" / "baseline.json"


def _entry(result: dict) -> dict:
    from fullview.sfm.compare import gated_metrics

    a = result["agreement"]
    return {
        "render_type": result["render_type"],
        "images_sha256": result.get("images_sha256"),
        "metrics": gated_metrics(result),
        "recorded": {  # context only, not gated
            "date": dt.date.today().isoformat(), "pycolmap": result["pycolmap"],
            "colmap_registered": result["colmap"]["registered"], "images": result["ours"]["images"],
            "agreement_rotation_max_deg": a["rotation_max_deg"], "agreement_translation_max_deg": a["translation_max_deg"],
            "colmap_auc@1": result.get("ground_truth", {}).get("colmap", {}).get("auc@1"),
        },
    }


def record(paths: list[Path], baseline_path: Path, aliases: dict[str, str]) -> int:
    baseline = json.loads(baseline_path.read_text()) if baseline_path.exists() else {"datasets": {}}
    datasets = baseline.setdefault("datasets", {})
    for path in paths:
        result = json.loads(Path(path).read_text())
        entry = _entry(result)
        keys = [result["dataset"]] + ([aliases[result["dataset"]]] if result["dataset"] in aliases else [])
        for key in keys:
            old = datasets.get(key, {})
            datasets[key] = {**entry, **({"tolerances": old["tolerances"]} if "tolerances" in old else {})}
            print(f"recorded {key}: {entry['metrics']}")
    baseline_path.write_text(json.dumps(baseline, indent=2) + "\n")
    return 0


def check(paths: list[Path], baseline_path: Path) -> int:
    from fullview.commands.compare import check_against_baseline

    failed = False
    for path in paths:
        result = json.loads(Path(path).read_text())
        gate = check_against_baseline(result, baseline_path)
        print(f"{result['dataset']}: {gate['status']}" + (f" ({gate['reason']})" if gate.get("reason") else ""))
        for failure in gate["failures"]:
            print(f"  - {failure}")
        failed |= gate["status"] == "fail"
    return 1 if failed else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=("record", "check"))
    parser.add_argument("results", nargs="+", type=Path, help="compare_spherical/colmap.json files")
    parser.add_argument("--baseline", type=Path, default=DEFAULT)
    parser.add_argument("--as", dest="aliases", action="append", default=[], metavar="DATASET=KEY",
                        help="record: also store DATASET's entry under KEY")
    args = parser.parse_args()
    if args.mode == "record":
        aliases = dict(a.split("=", 1) for a in args.aliases)
        return record(args.results, args.baseline, aliases)
    return check(args.results, args.baseline)


if __name__ == "__main__":
    sys.exit(main())
