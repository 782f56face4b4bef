"""Command line: a thin layer over fullview's library code, with one error boundary.

Every fullview error and every OSError becomes one line naming the path and the problem (exit code 2); anything
else is an internal error (exit code 1). `--debug` shows the traceback.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import logging
import os
import sys
import traceback
from pathlib import Path

from fullview.io.config import ConfigError, load_config
from fullview.io.dataset import Dataset
from fullview.io.errors import FullviewError
from fullview.io.workspace import Workspace
from fullview.stages import PIPELINE
from fullview.stages.runner import Pipeline

log = logging.getLogger("fullview")
DEFAULT_CONFIG = Path("pipeline.yaml")


def _pipeline(args) -> Pipeline:
    config_path = args.config if args.config is not None else (DEFAULT_CONFIG if DEFAULT_CONFIG.exists() else None)
    config = load_config(config_path, args.set or [])
    dataset = Dataset(args.dataset)
    return Pipeline(dataset, Workspace(args.workspace, dataset.name), config)


def cmd_run(args) -> int:
    pipeline = _pipeline(args)
    ran = pipeline.run(start=args.from_stage, until=args.until, only=args.only, force=args.force, wait=args.wait)
    log.info("ran: %s", ", ".join(ran) or "nothing (all fresh)")
    return 0


def cmd_status(args) -> int:
    from fullview.sfm.registration.evidence import verdict_line
    pipeline = _pipeline(args)
    pipeline.ws.check_root()
    with pipeline.ws.reading():
        for stage in PIPELINE:
            st = pipeline.status(stage, deep=args.verify)
            why = f" ({'; '.join(st.reasons)})" if st.state != "fresh" else ""
            print(f"{stage:<14}{st.state}{why}")
        line = _models_line(pipeline)
        verdicts = verdict_line((pipeline.ws.read_manifest("registration") or {}).get("summary", {})) \
            if pipeline.status("registration").state == "fresh" else None  # docs/trust.md
    for text in (line, verdicts):
        if text:
            print(text)
    return 0


def _models_line(pipeline) -> str | None:
    """The models of the fresh reconstruction, largest first, e.g. "models: 0: 28 images, 4012 points; 1: 2 images"."""
    for stage in ("triangulation", "registration"):
        if pipeline.status(stage).state != "fresh":
            continue
        summary = (pipeline.ws.read_manifest(stage) or {}).get("summary", {})
        models = summary.get("models")
        if models is None:
            return None
        parts = [f"{k}: {m['images']} images, {m['points']} points" if isinstance(m, dict) else f"{k}: {m} images"
                 for k, m in enumerate(models)]
        total = int(summary.get("images", 0)) or None
        placed = sum(m["images"] if isinstance(m, dict) else m for m in models)
        rest = f"; {total - placed} image(s) in no model (reasons: registration/registration.json)" \
            if total and placed < total else ""
        return f"models: {'; '.join(parts) or 'none'}{rest}"
    return None


def cmd_synth(args) -> int:
    from fullview.synth import write_synthetic_dataset
    from fullview.synth.capture import CaptureTraits
    from fullview.synth.home import check_closed_door, views_per_room
    if args.views < 2 or args.width < 64 or args.width % 2 or args.seed < 0:
        raise ConfigError("synth needs --views >= 2, an even --width >= 64 and --seed >= 0")
    if args.scene == "home":
        try:
            views_per_room(args.views, args.rooms)
            check_closed_door(args.closed_door, args.rooms)
        except ValueError as e:
            raise ConfigError(f"synth --scene home: {e}") from None
    elif args.closed_door is not None:
        raise ConfigError("synth: --closed-door needs --scene home")
    try:
        capture = CaptureTraits(tilt_deg=args.tilt_deg, exposure_stops=args.exposure_stops, noise=args.noise,
                                shuffle=args.shuffle)
    except ValueError as e:
        raise ConfigError(f"synth: --{str(e).replace('_', '-')}") from None
    print(write_synthetic_dataset(args.out, views=args.views, width=args.width, seed=args.seed, kind=args.scene,
                                  rooms=args.rooms, closed_door=args.closed_door, hand_points=args.hand_points,
                                  capture=capture))
    return 0


def cmd_eval(args) -> int:
    from fullview.commands.evaluate import evaluate
    json.dump(evaluate(_pipeline(args)), sys.stdout, indent=2)
    print()
    return 0


def cmd_colmap_check(args) -> int:
    from fullview.commands.colmap_check import colmap_check
    pipeline = _pipeline(args)
    report = colmap_check(pipeline.dataset, pipeline.ws, pipeline, max_features=args.colmap_max_features)
    print(report["markdown"])
    print(f"written: {pipeline.ws.path('check_report')}, check.md")
    return 0


def cmd_compare(args) -> int:
    from fullview.commands.compare import DEFAULT_BASELINE, compare
    if args.baseline is not None and not args.baseline.is_file():
        raise ConfigError(f"--baseline {args.baseline}: no such file")
    pipeline = _pipeline(args)
    baseline = None if args.no_gate else (args.baseline or DEFAULT_BASELINE)
    result = compare(pipeline.dataset, pipeline.ws, pipeline, render_type=args.render_type,
                     force_colmap=args.force_colmap, baseline_path=baseline)
    print(result["markdown"])
    print(f"written: {pipeline.ws.path('compare_report', render_type=args.render_type).parent}/")
    if result["gate"]["status"] == "fail":
        print("fullview: regression against the baseline: " + "; ".join(result["gate"]["failures"]),
              file=sys.stderr)
        return 1
    return 0


def cmd_export(args) -> int:
    from fullview.commands.export import export
    print(export(_pipeline(args), args.format, args.out))
    return 0


def cmd_report(args) -> int:
    from fullview.commands.report import report
    print(report(_pipeline(args)))
    return 0


def cmd_view(args) -> int:
    from fullview.commands.view import view
    pipeline = _pipeline(args)
    view(pipeline, pipeline.config, port=args.port, open_browser=not args.no_browser)
    return 0


def cmd_batch(args) -> int:
    from fullview.commands.batch import batch
    from fullview.stages.batch import summary_table
    config_path = args.config if args.config is not None else (DEFAULT_CONFIG if DEFAULT_CONFIG.exists() else None)
    outcomes = batch(args.datasets, args.glob, load_config(config_path, args.set or []), args.workspace,
                     scheduler=args.scheduler, workers=args.workers, until=args.until, force=args.force)
    print(summary_table(outcomes))
    return 1 if any(o.status != "ok" for o in outcomes) else 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder (images/, optional hand_points.yaml, ground_truth/)")
    p.add_argument("-w", "--workspace", type=Path, default=Path("workspace"), help="workspace root")
    p.add_argument("-c", "--config", type=Path, default=None, help="pipeline.yaml (default: ./pipeline.yaml)")
    p.add_argument("--set", action="append", metavar="STAGE.KEY=VALUE", help="override a config value")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fullview", description="3-D reconstruction from 360° panoramas")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="run stale stages of the pipeline")
    _common(p)
    p.add_argument("--from", dest="from_stage", choices=PIPELINE, help="rerun from this stage on")
    p.add_argument("--until", choices=PIPELINE, help="stop after this stage")
    p.add_argument("--only", choices=PIPELINE, help="run just this stage (upstream must be fresh)")
    p.add_argument("--force", action="store_true", help="rerun every stage")
    p.add_argument("--wait", action="store_true", help="wait for another run on this workspace instead of failing")
    p.set_defaults(func=cmd_run)
    p = sub.add_parser("batch", help="run many datasets on a Dask cluster (local processes by default)")
    p.add_argument("datasets", type=Path, nargs="*", help="dataset folders (each gets WORKSPACE/<folder name>)")
    p.add_argument("--glob", metavar="PATTERN", help="also every folder this pattern matches, e.g. 'data/*'")
    p.add_argument("-w", "--workspace", type=Path, default=Path("workspace"), help="workspace root")
    p.add_argument("-c", "--config", type=Path, default=None, help="pipeline.yaml (default: ./pipeline.yaml)")
    p.add_argument("--set", action="append", metavar="STAGE.KEY=VALUE", help="override a config value")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="use this cluster instead of a local one")
    p.add_argument("--workers", type=int, default=None, help="local cluster: worker processes (default: cores)")
    p.add_argument("--until", choices=PIPELINE, help="stop after this stage")
    p.add_argument("--force", action="store_true", help="rerun every stage")
    p.set_defaults(func=cmd_batch)
    p = sub.add_parser("status", help="fresh / stale / missing per stage")
    _common(p)
    p.add_argument("--verify", action="store_true", help="also check every output's sha256, not only its size")
    p.set_defaults(func=cmd_status)
    p = sub.add_parser("synth", help="render a synthetic scene with exact ground truth")
    p.add_argument("out", type=Path)
    p.add_argument("--views", type=int, default=6)
    p.add_argument("--width", type=int, default=2048)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scene", choices=("room", "home", "corridor"), default="room",
                   help="room: one textured room; home: rooms with plain walls and doorways (hard case); corridor: "
                        "a long walk through textured bays (sparse view graph)")
    p.add_argument("--rooms", type=int, default=4, help="rooms of the home (views must be 1-3 per room)")
    p.add_argument("--closed-door", type=int, default=None, metavar="K",
                   help="home: close the doorway between room K and K+1 (0-based) with a windowed door leaf, splitting the walk")
    p.add_argument("--hand-points", choices=("all", "crossing", "none"), default="all",
                   help="hand_points.yaml: every track, the 8 joining the sides of --closed-door, or no file")
    p.add_argument("--tilt-deg", type=float, default=0.0, metavar="DEG",
                   help="capture trait: each panorama tilted by up to DEG about a random horizontal axis "
                        "(an inexact zenith correction)")
    p.add_argument("--exposure-stops", type=float, default=0.0, metavar="S",
                   help="capture trait: each image's exposure off by up to +-S stops (auto exposure)")
    p.add_argument("--noise", type=float, default=0.0, metavar="SIGMA",
                   help="capture trait: Gaussian sensor noise of SIGMA 8-bit levels")
    p.add_argument("--shuffle", action="store_true",
                   help="capture trait: image names in a random order, not the walk's")
    p.set_defaults(func=cmd_synth)
    p = sub.add_parser("eval", help="metrics of the current reconstruction against ground_truth/")
    _common(p)
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
    p.add_argument("--baseline", type=Path, default=None, help="stored baseline (default: benchmarks/baseline.json)")
    p.add_argument("--no-gate", action="store_true", help="compare without checking the baseline")
    p.set_defaults(func=cmd_compare)
    p = sub.add_parser("export", help="the reconstruction as COLMAP, nerfstudio or PLY files")
    _common(p)
    p.add_argument("--format", required=True, help="colmap | colmap-bin | nerfstudio | ply")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: WORKSPACE/DATASET/export_FORMAT)")
    p.set_defaults(func=cmd_export)
    p = sub.add_parser("report", help="a static HTML report of the run: workspace/<dataset>/report/index.html")
    _common(p)
    p.set_defaults(func=cmd_report)
    p = sub.add_parser("view", help="the viewer: 3-D scene, virtual tour, correlated views, hand-point picker")
    _common(p)
    p.add_argument("--port", type=int, default=0, help="port on 127.0.0.1 (default: a free one, printed)")
    p.add_argument("--no-browser", action="store_true", help="do not open a browser")
    p.set_defaults(func=cmd_view)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    bound_malloc_arenas()
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    try:
        return args.func(args)
    except FullviewError as e:
        return _fail(args, str(e), 2)
    except BrokenPipeError:
        # The reader of our output went away (`status | head -1`): not an error; silence the final flush.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as e:
        where = f"{e.filename}: " if e.filename else ""
        return _fail(args, f"{where}{e.strerror or e}", 2)
    except KeyboardInterrupt:
        print("fullview: interrupted; previous artifacts are intact", file=sys.stderr)
        return 130
    except Exception as e:  # noqa: BLE001 — the boundary: anything else is our bug, reported in one line
        return _fail(args, f"internal error: {type(e).__name__}: {e} (rerun with --debug for the traceback)", 1)


M_ARENA_MAX = -8  # glibc's mallopt parameter


def bound_malloc_arenas() -> bool:
    """At most one glibc malloc arena per core (glibc's default: up to 8 per core). Each thread that allocates while
    another does gets an arena of its own, and an arena keeps what it frees for its own reuse: the stages' worker
    threads (matching blocks, the bundle adjustment's halves) left memory that later stages on other threads could
    not use. At 48 views the peak went from 654 to 493 MB at the same CPU time (README, "Seventh speed pass").
    Returns whether it applied (not glibc: nothing to do)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_ARENA_MAX, max(2, os.cpu_count() or 1)))


def _fail(args, message: str, code: int) -> int:
    if args.debug:
        traceback.print_exc()
    print(f"fullview: error: {' '.join(message.split())}", file=sys.stderr)
    return code
