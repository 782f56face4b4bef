"""Command line: a thin layer over fullview's library code."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from fullview.io.artifacts import ArtifactError
from fullview.io.config import ConfigError, load_config
from fullview.io.dataset import Dataset, DatasetError
from fullview.io.workspace import Workspace
from fullview.stages.runner import PIPELINE_STAGES, Pipeline, RunnerError

log = logging.getLogger("fullview")
DEFAULT_CONFIG = Path("pipeline.yaml")


def _pipeline(args) -> Pipeline:
    config_path = args.config if args.config is not None else (DEFAULT_CONFIG if DEFAULT_CONFIG.exists() else None)
    config = load_config(config_path, args.set or [])
    dataset = Dataset(args.dataset)
    return Pipeline(dataset, Workspace(args.workspace, dataset.name), config)


def cmd_run(args) -> int:
    pipeline = _pipeline(args)
    ran = pipeline.run(start=args.from_stage, until=args.until, only=args.only, force=args.force)
    log.info("ran: %s", ", ".join(ran) or "nothing (all fresh)")
    return 0


def cmd_status(args) -> int:
    pipeline = _pipeline(args)
    for stage in PIPELINE_STAGES:
        st = pipeline.status(stage)
        why = f" ({'; '.join(st.reasons)})" if st.state != "fresh" else ""
        print(f"{stage:<14}{st.state}{why}")
    return 0


def cmd_synth(args) -> int:
    from fullview.io.synth_io import write_synthetic_dataset
    path = write_synthetic_dataset(args.out, views=args.views, width=args.width, seed=args.seed)
    print(path)
    return 0


def cmd_eval(args) -> int:
    from fullview.stages.evaluate import evaluate
    dataset = Dataset(args.dataset)
    metrics = evaluate(dataset, Workspace(args.workspace, dataset.name))
    json.dump(metrics, sys.stdout, indent=2)
    print()
    return 0


def cmd_colmap_check(args) -> int:
    from fullview.stages.colmap_check import colmap_check
    pipeline = _pipeline(args)
    report = colmap_check(pipeline.dataset, pipeline.ws, pipeline, max_features=args.colmap_max_features)
    print(report["markdown"])
    print(f"written: {pipeline.ws.root / 'colmap_check' / 'check.json'}, check.md")
    return 0


def cmd_compare(args) -> int:
    from fullview.stages.compare import compare
    pipeline = _pipeline(args)
    result = compare(pipeline.dataset, pipeline.ws, pipeline, render_type=args.render_type,
                     force_colmap=args.force_colmap, baseline_path=None if args.no_gate else args.baseline)
    print(result["markdown"])
    print(f"written: {pipeline.ws.root / 'compare'}/")
    if result["gate"]["status"] == "fail":
        print("fullview: regression against the baseline: " + "; ".join(result["gate"]["failures"]),
              file=sys.stderr)
        return 1
    return 0


def _common(p: argparse.ArgumentParser, config: bool = True) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder (images/, optional hand_points.yaml, ground_truth/)")
    p.add_argument("-w", "--workspace", type=Path, default=Path("workspace"), help="workspace root")
    if config:
        p.add_argument("-c", "--config", type=Path, default=None, help="pipeline.yaml (default: ./pipeline.yaml)")
        p.add_argument("--set", action="append", metavar="STAGE.KEY=VALUE", help="override a config value")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fullview", description="3-D reconstruction from 360° panoramas")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="run stale stages of the pipeline")
    _common(p)
    p.add_argument("--from", dest="from_stage", choices=PIPELINE_STAGES, help="rerun from this stage on")
    p.add_argument("--until", choices=PIPELINE_STAGES, help="stop after this stage")
    p.add_argument("--only", choices=PIPELINE_STAGES, help="run just this stage (upstream must be fresh)")
    p.add_argument("--force", action="store_true", help="rerun every stage")
    p.set_defaults(func=cmd_run)
    p = sub.add_parser("status", help="fresh / stale / missing per stage")
    _common(p)
    p.set_defaults(func=cmd_status)
    p = sub.add_parser("synth", help="render a synthetic scene with exact ground truth")
    p.add_argument("out", type=Path)
    p.add_argument("--views", type=int, default=6)
    p.add_argument("--width", type=int, default=2048)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_synth)
    p = sub.add_parser("eval", help="metrics against ground_truth/")
    _common(p, config=False)
    p.set_defaults(func=cmd_eval)
    p = sub.add_parser("colmap-check", help="our SIFT stage against COLMAP's SIFT on the same cube faces")
    _common(p)
    p.add_argument("--colmap-max-features", type=int, default=None, metavar="N",
                   help="COLMAP features per face (default: ours, features.max_features_per_face; 0: COLMAP's)")
    p.set_defaults(func=cmd_colmap_check)
    p = sub.add_parser("compare", help="our reconstruction against pycolmap's panorama pipeline (+ baseline gate)")
    _common(p)
    p.add_argument("--render-type", default="spherical",
                   choices=("spherical", "perspective_overlapping", "perspective_non_overlapping"))
    p.add_argument("--force-colmap", action="store_true", help="rerun COLMAP even when its cached run is fresh")
    p.add_argument("--baseline", type=Path, default=Path(__file__).resolve().parent / "benchmarks" / "baseline.json",
                   help="stored baseline (default: benchmarks/baseline.json)")
    p.add_argument("--no-gate", action="store_true", help="compare without checking the baseline")
    p.set_defaults(func=cmd_compare)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    try:
        return args.func(args)
    except (ConfigError, DatasetError, RunnerError, ArtifactError) as e:
        print(f"fullview: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("fullview: interrupted; previous artifacts are intact", file=sys.stderr)
        return 130
