"""Command line: a thin layer over fullview's library code, with one error boundary.

Every fullview error and every OSError becomes one line naming the path and the problem (exit code 2); anything
else is an internal error (exit code 1). `--debug` shows the traceback.

Where results live: `-w ROOT` puts a dataset's workspace in ROOT/<dataset name>/; without -w it is the dataset's own
DATASET/.fullview/, so the same command finds the same results from any folder. The settings every command uses are
the ones recorded in that workspace (io/settings.py): `run -c FILE / --set` change and record them.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import logging
import os
import sys
import time
import traceback
from pathlib import Path

from tqdm.contrib.logging import logging_redirect_tqdm

from fullview.io.config import ConfigError, load_config
from fullview.io.dataset import Dataset
from fullview.io.errors import FullviewError
from fullview.io.settings import Settings, changes, effective_settings, record_settings
from fullview.io.workspace import DATASET_WORKSPACE, Workspace
from fullview.stages import PIPELINE
from fullview.stages.runner import Pipeline, peak_rss_mb, stage_module

log = logging.getLogger("fullview")
LEGACY_WORKSPACE = Path("workspace")  # the former default root (-w), relative to the current folder


def _workspace(args, dataset: Dataset) -> Workspace:
    """-w ROOT: ROOT/<dataset name>/; without -w: the dataset's own workspace, DATASET/.fullview/."""
    if args.workspace is not None:
        return Workspace(args.workspace, dataset.name)
    ws = Workspace.of_dataset(dataset.root)
    legacy = LEGACY_WORKSPACE / dataset.name
    if not ws.root.exists() and (legacy / "features").is_dir():
        log.warning("no workspace in %s yet; %s holds one of an earlier fullview: pass -w %s to use it", ws.root,
                    legacy, LEGACY_WORKSPACE)
    return ws


def _pipeline_and_settings(args) -> tuple[Pipeline, Settings]:
    """The dataset, its workspace and the settings recorded there, updated by this command's -c / --set."""
    dataset = Dataset(args.dataset)
    ws = _workspace(args, dataset)
    settings = effective_settings(ws, args.config, args.set or [])
    return Pipeline(dataset, ws, settings.config), settings


def _pipeline(args) -> Pipeline:
    return _pipeline_and_settings(args)[0]


def cmd_run(args) -> int:
    t0 = time.perf_counter()
    dataset = Dataset(args.dataset)
    ws = _workspace(args, dataset)
    if args.workspace is None and not ws.root.exists() and not os.access(dataset.root, os.W_OK):
        raise ConfigError(f"{dataset.root}: not writable, so its workspace {ws.root} cannot be made; pass -w FOLDER "
                          "to keep the results elsewhere (and the same -w to every later command)")
    # Settings are read and recorded under the run lock: a run waiting for another (--wait) builds on what it recorded.
    with ws.locked(wait=args.wait, command="fullview run"):
        settings = effective_settings(ws, args.config, args.set or [], reset=args.reset_settings)
        _record(ws, settings)
        pipeline = Pipeline(dataset, ws, settings.config)
        ran = pipeline.run(start=args.from_stage, until=args.until, only=args.only, force=args.force, wait=args.wait)
        page = None
        if args.only is None and args.until in (None, PIPELINE[-1]) and (ran or not ws.path("report_page").exists()):
            from fullview.commands.report import report
            page = report(pipeline)
    for line in _run_summary(args, pipeline, ran, time.perf_counter() - t0, page):
        print(line)
    return 0


def _record(ws: Workspace, settings: Settings) -> None:
    """Record the run's settings in the workspace; log what changed and which stages that makes stale."""
    path = record_settings(ws, settings)
    if settings.recorded is None:
        own = settings.non_default()
        log.info("settings recorded in %s: %s", path, "the defaults" if not own else "the defaults except " + ", ".join(
            f"{k}={v!r} ({source})" for k, v, source in own))
        return
    changed = changes(settings.recorded, settings.config)
    for key, old, new in changed:
        log.info("setting %s: %r -> %r (%s)", key, old, new, settings.sources[key])
    if changed:
        log.info("settings recorded in %s; the change makes stale: %s", path,
                 ", ".join(_stale_by(k for k, _, _ in changed)))


def _stale_by(keys) -> list[str]:
    """The stages a change of these keys ("section.key") reruns: their sections' stages and everything after them."""
    stale = {k.split(".", 1)[0] for k in keys}
    for stage in PIPELINE:
        if any(u in stale for u in stage_module(stage).UPSTREAM):
            stale.add(stage)
    return [s for s in PIPELINE if s in stale]


def _run_summary(args, pipeline: Pipeline, ran: list[str], seconds: float, page: str | None) -> list[str]:
    """The lines `run` ends with: what ran, the models, the dense cloud and mesh, where to look next."""
    done = f"ran {', '.join(ran)}" if ran else "nothing to run (all fresh)"
    lines = [f"fullview run {pipeline.dataset.name}: {done} in {seconds:.1f} s, peak memory {peak_rss_mb():.0f} MB"]
    with pipeline.ws.reading():
        models = _models_line(pipeline)
        dense = pipeline.ws.read_manifest("densify") if pipeline.status("densify").state == "fresh" else None
    if models:
        lines.append(f"  {models}")
    if dense is not None:
        summary = dense.get("summary", {})
        shares = list((summary.get("valid_share") or {}).values())
        coverage = f", depth on {100 * sum(shares) / len(shares):.0f}% of the panoramas' pixels" if shares else ""
        lines.append(f"  dense cloud: {summary.get('points', 0)} points{coverage}")
        mesh = summary.get("mesh") or {}
        lines.append(f"  mesh: {mesh['vertices']} vertices, {mesh['triangles']} triangles" if mesh.get("triangles")
                     else "  mesh: none")
    lines.append(f"  workspace: {pipeline.ws.root}")
    if page:
        lines.append(f"  report: {page}")
    lines.append(f"  view: {_command('view', args)}")
    return lines


def _command(name: str, args) -> str:
    """The command line that runs `fullview NAME` on this command's dataset and workspace."""
    return f"fullview {name} {args.dataset}{f' -w {args.workspace}' if args.workspace is not None else ''}"


def cmd_status(args) -> int:
    from fullview.sfm.registration.evidence import verdict_line
    pipeline, settings = _pipeline_and_settings(args)
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
    print(f"workspace: {pipeline.ws.root}")
    for line in _settings_lines(settings):
        print(line)
    return 0


def _settings_lines(settings: Settings) -> list[str]:
    """`status`'s account of the settings: where they are recorded and every value that is not the default."""
    if settings.recorded is None:
        head = f"settings: none recorded yet ({settings.path} is written by `fullview run`)"
    else:
        head = f"settings: recorded in {settings.path}"
    own = settings.non_default()
    lines = [head + (", the defaults" if not own else ", not the defaults:")]
    for key, value, source in own:
        now = f"; the default is now {settings.earlier_defaults[key]!r}" if key in settings.earlier_defaults else ""
        lines.append(f"  {key} = {value!r}  ({source}{now})")
    unrecorded = changes(settings.recorded, settings.config) if settings.recorded is not None else []
    if unrecorded:
        lines.append(f"  this command's -c / --set change {', '.join(k for k, _, _ in unrecorded)}: "
                     "not recorded (`fullview run` records them)")
    return lines


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
    from fullview.commands.evaluate import eval_summary, evaluate
    json.dump(eval_summary(evaluate(_pipeline(args))), sys.stdout, indent=2)  # per image: eval/metrics.json
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
    print(export(_pipeline(args), args.format, args.out, sparse_only=args.sparse_only, link=args.link,
                 camera_height=args.camera_height, known_distance=args.known_distance, model_units=args.model_units))
    return 0


def cmd_report(args) -> int:
    from fullview.commands.report import report
    print(report(_pipeline(args)))
    return 0


def cmd_view(args) -> int:
    from fullview.commands.view import check_port, view
    check_port(args.port)  # a bad port is one line before anything is read
    pipeline = _pipeline(args)
    view(pipeline, pipeline.config, port=args.port, open_browser=not args.no_browser,
         note=_freshness(args, pipeline))
    return 0


def _freshness(args, pipeline: Pipeline) -> str:
    """One line: are the workspace's results those of its settings, and if not what brings them up to date."""
    with pipeline.ws.reading():
        behind = [stage for stage in PIPELINE if pipeline.status(stage).state != "fresh"]
    if not behind:
        return f"results of {pipeline.ws.root}: every stage fresh"
    return (f"results of {pipeline.ws.root}: {', '.join(behind)} not fresh for these settings; "
            f"`{_command('run', args)}` brings them up to date")


def cmd_batch(args) -> int:
    from fullview.commands.batch import batch
    from fullview.stages.batch import summary_table
    outcomes = batch(args.datasets, args.glob, load_config(args.config, args.set or []), args.workspace,
                     scheduler=args.scheduler, workers=args.workers, until=args.until, force=args.force)
    print(summary_table(outcomes))
    return 1 if any(o.status != "ok" for o in outcomes) else 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder (images/, optional hand_points.yaml, ground_truth/)")
    p.add_argument("-w", "--workspace", type=Path, default=None,
                   help=f"workspace root: results in ROOT/<dataset name>/ (default: DATASET/{DATASET_WORKSPACE}/)")
    p.add_argument("-c", "--config", type=Path, default=None,
                   help="a pipeline.yaml: the defaults updated by it, instead of the workspace's recorded settings")
    p.add_argument("--set", action="append", metavar="STAGE.KEY=VALUE",
                   help="change one setting (run records it in the workspace)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fullview", description="3-D reconstruction from 360° panoramas")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging (the internals)")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="run stale stages of the pipeline")
    _common(p)
    p.add_argument("--from", dest="from_stage", choices=PIPELINE, help="rerun from this stage on")
    p.add_argument("--until", choices=PIPELINE, help="stop after this stage")
    p.add_argument("--only", choices=PIPELINE, help="run just this stage (upstream must be fresh)")
    p.add_argument("--force", action="store_true", help="rerun every stage")
    p.add_argument("--wait", action="store_true", help="wait for another run on this workspace instead of failing")
    p.add_argument("--reset-settings", action="store_true",
                   help="start from the defaults, not from the workspace's recorded settings")
    p.set_defaults(func=cmd_run)
    p = sub.add_parser("batch", help="run many datasets on a Dask cluster (local processes by default)")
    p.add_argument("datasets", type=Path, nargs="*", help="dataset folders (each gets WORKSPACE/<folder name>)")
    p.add_argument("--glob", metavar="PATTERN", help="also every folder this pattern matches, e.g. 'data/*'")
    p.add_argument("-w", "--workspace", type=Path, default=Path("workspace"), help="workspace root")
    p.add_argument("-c", "--config", type=Path, default=None, help="pipeline.yaml (default: the code's defaults)")
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
    p.add_argument("--out", type=Path, default=None, help="output folder (default: WORKSPACE/DATASET/export_FORMAT); "
                   "new, empty or a previous export, of which only the files it wrote are replaced")
    p.add_argument("--sparse-only", action="store_true",
                   help="ply: the sparse cloud alone (otherwise a stale or missing densify is an error)")
    images = p.add_mutually_exclusive_group()  # nerfstudio: the export holds its images (docs/exports.md)
    images.add_argument("--copy-images", dest="link", action="store_false", help="nerfstudio: copy the images into "
                        "<k>/images/ (default)")
    images.add_argument("--link", dest="link", action="store_true", help="nerfstudio: hard-link them instead (copied "
                        "where a link cannot be made: another file system)")
    scale = p.add_mutually_exclusive_group()  # a metric scale, kept in the workspace for later exports and the viewer
    scale.add_argument("--camera-height", type=float, default=None, metavar="METRES",
                       help="metres from the floor to the lens: every export in metres from now on")
    scale.add_argument("--known-distance", nargs=3, default=None, metavar=("NAME_A", "NAME_B", "METRES"),
                       help="two hand points (hand_points.yaml names) and their distance: exports in metres")
    scale.add_argument("--model-units", action="store_true", help="forget a stated scale: exports in model units")
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
    _configure_logging(args.verbose)
    try:
        with logging_redirect_tqdm():  # log lines above the progress bars, not inside them
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


class _UserFormatter(logging.Formatter):
    """INFO lines as "time message"; warnings and errors name their level; -v adds the logger of every line."""

    def __init__(self, verbose: bool):
        super().__init__("%(asctime)s %(levelname)s %(name)s: %(message)s" if verbose else "%(asctime)s %(message)s",
                         datefmt="%H:%M:%S")
        self.verbose = verbose

    def formatMessage(self, record: logging.LogRecord) -> str:
        text = super().formatMessage(record)
        if not self.verbose and record.levelno >= logging.WARNING:
            time_part, _, message = text.partition(" ")
            return f"{time_part} {record.levelname.lower()}: {message}"
        return text


def _configure_logging(verbose: bool) -> None:
    handler = logging.StreamHandler()
    handler.setFormatter(_UserFormatter(verbose))
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, handlers=[handler])


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
