"""fullview benchmark: seeded synthetic scenes and the openMVG panoramas, ours against pycolmap in one run.

For every scene, in one process tree and one run:
- ours: `fullview run` in a fresh workspace (a subprocess): per-stage wall time and peak memory from the manifests,
  then `fullview eval` metrics when ground truth exists; the 6-view scene and 360_Flat also run `densify` (time per
  pair, depth and cloud metrics);
- COLMAP: `pycolmap.panorama.reconstruct` (SPHERICAL, exhaustive, CPU) on the same images in a subprocess, through
  the cached reference of `fullview compare` (forced to rerun): wall time, peak memory and the same metrics.
Prints a table with the ratio ours/COLMAP, writes benchmarks/results/<date>.json and a plot of time against views.

    python benchmarks/bench.py [--views 2 6 12 24] [--width 2048] [--no-colmap] [--no-real] [--scale]

`--scale` runs only the scaling rows instead (not part of the default `make bench`: COLMAP's exhaustive matching on
96 views and the 200-view walk take long on 2 cores): the synthetic room at 6, 24, 48 and 96 views and the corridor
walk of 50, 100 and 200 views (`fullview synth --scene corridor`), all at 1024x512, ours with `matches.pairs: auto`
(the pipeline.yaml default), COLMAP exhaustive on the room and sequential on the walk; plots time against views
(log-log), fits the growth exponent per scene (the room's rows with >= 48 views; every walk row) and projects time
and memory to 1,000 views.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from fullview.stages import PIPELINE

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "datasets" / "openmvg-360"
RESULTS = ROOT / "benchmarks" / "results"
SPARSE_STAGES = PIPELINE[:PIPELINE.index("triangulation") + 1]
log = logging.getLogger("bench")


def run(cmd: list[str]) -> subprocess.CompletedProcess:
    log.info("$ %s", " ".join(cmd))
    return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)


def synth_dataset(work: Path, views: int, width: int, seed: int) -> Path:
    path = work / "datasets" / f"synth{views}_w{width}_s{seed}"
    if not (path / "images").exists():
        proc = run([sys.executable, "-m", "fullview", "synth", str(path), "--views", str(views), "--width",
                    str(width), "--seed", str(seed)])
        if proc.returncode:
            raise RuntimeError(proc.stderr[-2000:])
    return path


def ours(dataset: Path, work: Path, label: str, extra: list[str], dense: bool = False, reuse: bool = False) -> dict:
    """reuse: keep fresh stages of an earlier run (their manifests hold the times measured then)."""
    ws = work / "ws" / label
    settings = ["-c", str(ROOT / "pipeline.yaml")] + [a for item in extra for a in ("--set", item)]
    cmd = [sys.executable, "-m", "fullview", "run", str(dataset), "-w", str(ws), *settings,
           "--until", "densify" if dense else "triangulation", *([] if reuse else ["--force"])]
    t0 = time.perf_counter()
    proc = run(cmd)
    wall = time.perf_counter() - t0
    if proc.returncode:
        return {"error": proc.stderr[-2000:]}
    from fullview.io.workspace import Workspace
    workspace = Workspace(ws, dataset.name)
    manifests = {s: workspace.read_manifest(s) for s in SPARSE_STAGES}
    out = {
        "wall_time_s": round(wall, 2),
        "stage_time_s": {s: m["wall_time_s"] for s, m in manifests.items()},
        "sparse_time_s": round(sum(m["wall_time_s"] for m in manifests.values()), 2),
        # CPU seconds of every thread (manifests written before the runner recorded them: None)
        "stage_cpu_s": {s: m.get("cpu_time_s") for s, m in manifests.items()},
        "sparse_cpu_s": (round(sum(m["cpu_time_s"] for m in manifests.values()), 2)
                         if all("cpu_time_s" in m for m in manifests.values()) else None),
        "peak_rss_mb": max(m["peak_rss_mb"] for m in manifests.values()),
        "registered": manifests["registration"]["summary"]["registered"],
        "models": manifests["registration"]["summary"].get("models"),
        "points": manifests["triangulation"]["summary"]["points"],
    }
    if dense:
        manifest = workspace.read_manifest("densify")
        out["densify"] = {k: manifest["summary"].get(k) for k in ("pairs", "points", "median_pair_time_s", "valid_share")}
        out["densify"]["stage_time_s"] = manifest["wall_time_s"]
        out["densify"]["cpu_time_s"] = manifest.get("cpu_time_s")
        out["densify"]["peak_rss_mb"] = manifest.get("peak_rss_mb")
        out["densify"]["width"] = manifest["summary"].get("width")
    if (dataset / "ground_truth" / "poses.yaml").exists():
        proc = run([sys.executable, "-m", "fullview", "eval", str(dataset), "-w", str(ws), *settings])
        out["metrics"] = json.loads(proc.stdout) if proc.returncode == 0 else {"error": proc.stderr[-2000:]}
    return out


def colmap(dataset: Path, work: Path, label: str, matcher: str = "exhaustive", reuse: bool = False) -> dict:
    proc = run([sys.executable, str(Path(__file__).resolve()), "--colmap-worker", str(dataset),
                str(work / "colmap" / label), "--colmap-matcher", matcher, *(["--reuse"] if reuse else [])])
    if proc.returncode:
        return {"error": proc.stderr[-2000:]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def colmap_worker(dataset: Path, work: Path, matcher: str = "exhaustive", reuse: bool = False) -> None:
    """Runs in its own process so that its peak memory is its own."""
    from fullview.io.colmap import load_reconstruction, model_arrays
    from fullview.io.dataset import Dataset
    from fullview.io.workspace import Workspace
    from fullview.sfm.metrics import pose_metrics
    from fullview.commands.compare import colmap_reference

    ds = Dataset(dataset)
    t0, cpu0 = time.perf_counter(), time.process_time()
    model_dir, manifest = colmap_reference(ds, Workspace(work, ds.name), render_type="spherical", matcher=matcher,
                                           force=not reuse)
    rss_file = work / "bench_peak_rss_mb.json"  # this process's peak is COLMAP's only when COLMAP ran here
    cpu_file = work / "bench_cpu_time_s.json"  # likewise its CPU time (all of COLMAP's threads)
    if time.perf_counter() - t0 >= 0.9 * manifest["wall_time_s"]:
        rss_file.write_text(json.dumps(round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)))
        cpu_file.write_text(json.dumps(round(time.process_time() - cpu0, 2)))
    out = {"wall_time_s": round(manifest["wall_time_s"], 2), "matcher": matcher,
           "peak_rss_mb": json.loads(rss_file.read_text()) if rss_file.exists() else None,
           "cpu_time_s": json.loads(cpu_file.read_text()) if cpu_file.exists() else None,
           "registered": 0, "points": 0}
    if model_dir is not None:
        rec = load_reconstruction(model_dir)
        model = model_arrays(rec, ds.image_names)
        out.update(registered=int(model["registered"].sum()), points=int(rec.num_points3D()))
        if ds.has_ground_truth():
            gt = ds.ground_truth_poses()
            R_gt = np.stack([gt[n].R_world_from_cam.T for n in ds.image_names])
            c_gt = np.stack([gt[n].center for n in ds.image_names])
            out["metrics"] = pose_metrics(model["R_cam_from_world"], model["centers"], R_gt, c_gt,
                                          model["registered"])
    print(json.dumps(out))


HOME = dict(rooms=12, views=30, width=1024)  # the hard scene: plain walls, doorways, 1-3 panoramas per room


def home_rows(args) -> list[dict]:
    """The hard synthetic home, with and without its hand points: ours (registered share, models, verified pairs,
    time, AUC) next to COLMAP's (which has no hand points to use)."""
    path = args.work / "datasets" / f"home{HOME['views']}_r{HOME['rooms']}_w{HOME['width']}_s{args.seed}"
    if not (path / "images").exists():
        proc = run([sys.executable, "-m", "fullview", "synth", str(path), "--scene", "home", "--rooms",
                    str(HOME["rooms"]), "--views", str(HOME["views"]), "--width", str(HOME["width"]), "--seed",
                    str(args.seed)])
        if proc.returncode:
            raise RuntimeError(proc.stderr[-2000:])
    rows = []
    for hand in (True, False):  # the bare capture, as a user makes it, has no hand points
        label = f"home{HOME['views']}-{'hand' if hand else 'bare'}"
        row = {"scene": label, "views": HOME["views"],
               "ours": ours(path, args.work, label, [f"filter.use_hand_points={str(hand).lower()}"])}
        from fullview.io.workspace import Workspace
        manifest = Workspace(args.work / "ws" / label, path.name).read_manifest("filter") or {}
        row["ours"]["verified_pairs"] = (manifest.get("summary") or {}).get("verified_pairs")
        if not args.no_colmap:
            row["colmap"] = rows[-1]["colmap"] if rows else colmap(path, args.work, f"home{HOME['views']}")
        log.info("%s: %s", label, json.dumps(row)[:400])
        rows.append(row)
    return rows


def viewer_timing(dataset: Path, ws: Path) -> dict:
    """Seconds from opening the viewer page until it is interactive, and from clicking a camera until its panorama
    is shown in the tour (first visit: cold panorama cache), in headless chromium; {} without chromium/Playwright."""
    import shutil
    chromium = shutil.which("chromium")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return {}
    if chromium is None:
        return {}
    proc = subprocess.Popen([sys.executable, "-m", "fullview", "view", str(dataset), "-w", str(ws), "-c",
                             str(ROOT / "pipeline.yaml"), "--no-browser"], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        url = proc.stdout.readline().split()[-4]
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=["--use-gl=swiftshader"])
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            t0 = time.perf_counter()
            page.goto(url)
            page.wait_for_function("() => window.fullview && window.fullview.ready", timeout=120000)  # a function: the CSP forbids eval
            ready = time.perf_counter() - t0
            name = page.evaluate("window.fullview.registeredNames()[0]")
            t0 = time.perf_counter()
            page.mouse.click(*page.evaluate(f"window.fullview.cameraScreenPosition({json.dumps(name)})"))
            page.wait_for_function("() => window.fullview.tour && window.fullview.tour.ready", timeout=120000)
            tour = time.perf_counter() - t0
            browser.close()
        return {"page_ready_s": round(ready, 2), "tour_open_s": round(tour, 2)}
    finally:
        proc.kill()
        proc.wait()


SCALE_VIEWS = (6, 24, 48, 96)  # the synthetic room
WALK_VIEWS = (50, 100, 200)  # the corridor walk: one scene grown along its path, for the growth exponent
SCALE_WIDTH = 1024
SCALE_FIT_FROM = 48  # the room's growth exponent is fitted on its rows with at least this many views
PROJECT_TO = 1000
# The corridor's cameras are level by construction; its busy textures give the vanishing-point gravity estimate
# (filter.upright: vanishing) too few clean vertical lines at this width, so the walk takes gravity as the image's
# down axis, as a zenith-corrected Theta capture would.
WALK_SETTINGS = ["filter.upright=level"]


def scale_dataset(work: Path, kind: str, views: int, seed: int) -> Path:
    path = work / "datasets" / f"{kind}{views}_w{SCALE_WIDTH}_s{seed}"
    if not (path / "images").exists():
        proc = run([sys.executable, "-m", "fullview", "synth", str(path), "--scene", kind, "--views", str(views),
                    "--width", str(SCALE_WIDTH), "--seed", str(seed)])
        if proc.returncode:
            raise RuntimeError(proc.stderr[-2000:])
    return path


def scale_rows(args) -> list[dict]:
    """Ours (auto pairs) and COLMAP on the room at args.scale_views and on the corridor walk."""
    rows = []
    scenes = [("room", v, "exhaustive", []) for v in args.scale_views]
    scenes += [("corridor", v, "sequential", WALK_SETTINGS) for v in args.walk_views if v > 0]
    for kind, views, matcher, settings in scenes:
        dataset = scale_dataset(args.work, kind, views, args.seed)
        label = f"scale-{kind}{views}"
        row = {"scene": label, "kind": kind, "views": views, "ours": ours(dataset, args.work, label, settings, reuse=args.reuse)}
        from fullview.io.workspace import Workspace
        manifest = Workspace(args.work / "ws" / label, dataset.name).read_manifest("matches") or {}
        row["ours"]["pairs"] = (manifest.get("summary") or {}).get("pairs")
        if not args.no_colmap:
            row["colmap"] = colmap(dataset, args.work, label, matcher, reuse=args.reuse)
        log.info("%s: %s", label, json.dumps(row)[:400])
        rows.append(row)
        save_scale(rows, args.tag)  # after every row: a long run stopped early keeps what it measured
    return rows


def growth_fit(views: list[int], values: list[float]) -> dict | None:
    """value ≈ a · views^exponent, least squares in log-log; None with fewer than two usable points."""
    v, y = np.asarray(views, float), np.asarray(values, float)
    ok = np.isfinite(y) & (y > 0)
    if ok.sum() < 2:
        return None
    exponent, log_a = np.polyfit(np.log(v[ok]), np.log(y[ok]), 1)
    return {"exponent": round(float(exponent), 3), "a": float(np.exp(log_a)), "views": [int(x) for x in v[ok]],
            f"projected_{PROJECT_TO}": round(float(np.exp(log_a) * PROJECT_TO**exponent), 1)}


def _kind(row: dict) -> str:
    return row.get("kind") or row["scene"].removeprefix("scale-").rstrip("0123456789")


def scale_summary(rows: list[dict]) -> dict:
    """Growth fits per scene: the room from SCALE_FIT_FROM views, the walk over all its rows (one scene each, so
    an exponent is not bent by two scenes' different costs per view)."""
    # CPU time too: on a shared machine the wall time of one row can be stretched by load the next row did not see
    keys = {"time": ("sparse_time_s", "wall_time_s"), "cpu": ("sparse_cpu_s", "cpu_time_s"),
            "memory": ("peak_rss_mb", "peak_rss_mb")}
    out = {}
    for kind, first in (("room", SCALE_FIT_FROM), ("corridor", 0)):
        fit_rows = [r for r in rows if _kind(r) == kind and r["views"] >= first]
        views = [r["views"] for r in fit_rows]
        for measure, (ours_key, colmap_key) in keys.items():
            for who, key in (("ours", ours_key), ("colmap", colmap_key)):
                values = [r.get(who, {}).get(key) or np.nan for r in fit_rows]
                out[f"{kind}_{who}_{measure}"] = growth_fit(views, values)
    return out


def scale_table(rows: list[dict], summary: dict) -> str:
    head = ("scene", "views", "ours pairs", "ours reg", "colmap reg", "ours AUC@1", "colmap AUC@1", "ours s",
            "colmap s", "ratio", "ours CPU s", "colmap CPU s", "CPU ratio", "ours MB", "colmap MB")
    lines = [" | ".join(head), " | ".join("---" for _ in head)]
    for r in rows:
        o, c = r["ours"], r.get("colmap", {})
        ratio = o.get("sparse_time_s", 0) / c["wall_time_s"] if c.get("wall_time_s") else None
        cpu_ratio = o["sparse_cpu_s"] / c["cpu_time_s"] if o.get("sparse_cpu_s") and c.get("cpu_time_s") else None
        lines.append(" | ".join([
            r["scene"], str(r["views"]), str(o.get("pairs", "—")), str(o.get("registered", "err")),
            str(c.get("registered", "—")), fmt(o.get("metrics", {}).get("auc@1"), ".1f"),
            fmt(c.get("metrics", {}).get("auc@1"), ".1f"), fmt(o.get("sparse_time_s"), ".1f"),
            fmt(c.get("wall_time_s"), ".1f"), fmt(ratio, ".2f"), fmt(o.get("sparse_cpu_s"), ".1f"),
            fmt(c.get("cpu_time_s"), ".1f"), fmt(cpu_ratio, ".2f"), fmt(o.get("peak_rss_mb"), ".0f"),
            fmt(c.get("peak_rss_mb"), ".0f")]))
    for key, fit in summary.items():
        if fit:
            unit = "MB" if key.endswith("memory") else "CPU s" if key.endswith("cpu") else "s"
            lines.append(f"\n{key}: exponent {fit['exponent']} over views {fit['views']}, projected to "
                         f"{PROJECT_TO} views: {fit[f'projected_{PROJECT_TO}']} {unit}")
    return "\n".join(lines)


def scale_plot(rows: list[dict], summary: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    v = np.array([r["views"] for r in rows], float)
    for key, label, marker, get in (("ours", "fullview (auto pairs)", "o", lambda r: r["ours"].get("sparse_time_s")),
                                    ("colmap", "COLMAP SPHERICAL", "s",
                                     lambda r: r.get("colmap", {}).get("wall_time_s"))):
        t = np.array([get(r) or np.nan for r in rows], float)
        if np.isfinite(t).any():
            ax.loglog(v, t, marker, label=label)
            for kind in ("room", "corridor"):
                fit = summary.get(f"{kind}_{key}_time")
                if fit:
                    xs = np.geomspace(min(fit["views"]), PROJECT_TO, 20)
                    ax.loglog(xs, fit["a"] * xs ** fit["exponent"], "--", alpha=0.6,
                              label=f"{key}, {kind} {min(fit['views'])}-{max(fit['views'])} views: "
                                    f"exponent {fit['exponent']}")
    ax.set_xlabel("views")
    ax.set_ylabel("wall time (s)")
    ax.set_title(f"time against views ({SCALE_WIDTH}×{SCALE_WIDTH // 2}; room, corridor walk)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def save_scale(rows: list[dict], tag: str) -> tuple[Path, dict]:
    summary = scale_summary(rows)
    RESULTS.mkdir(parents=True, exist_ok=True)
    stamp = dt.datetime.now().strftime("%Y-%m-%d")
    out = RESULTS / f"{stamp}-scale{tag}.json"
    out.write_text(json.dumps({"date": dt.datetime.now().isoformat(timespec="seconds"), "width": SCALE_WIDTH,
                               "rows": rows, "fits": summary}, indent=2) + "\n")
    scale_plot(rows, summary, RESULTS / f"{stamp}-scale{tag}-time-vs-views.png")
    return out, summary


def scale_main(args) -> int:
    out, summary = save_scale(scale_rows(args), args.tag)
    rows = json.loads(out.read_text())["rows"]
    print(scale_table(rows, summary))
    print(f"\nratio = ours sparse-pipeline wall time / COLMAP wall time, same run. Results: {out}")
    return 0


def fmt(x, spec=".2f"):
    return "—" if x is None else format(x, spec)


def table(rows: list[dict]) -> str:
    head = ("scene", "ours reg", "colmap reg", "ours AUC@0.5/1/5", "colmap AUC@0.5/1/5", "ours rot°", "colmap rot°",
            "ours s", "colmap s", "ratio", "ours MB", "colmap MB")
    lines = [" | ".join(head), " | ".join("---" for _ in head)]
    for r in rows:
        o, c = r["ours"], r.get("colmap", {})
        om, cm = o.get("metrics", {}), c.get("metrics", {})
        ratio = o.get("sparse_time_s", 0) / c["wall_time_s"] if c.get("wall_time_s") else None
        cpu_ratio = o["sparse_cpu_s"] / c["cpu_time_s"] if o.get("sparse_cpu_s") and c.get("cpu_time_s") else None
        lines.append(" | ".join([
            r["scene"], str(o.get("registered", "err")), str(c.get("registered", "—")),
            f"{fmt(om.get('auc@0.5'), '.1f')}/{fmt(om.get('auc@1'), '.1f')}/{fmt(om.get('auc@5'), '.1f')}",
            f"{fmt(cm.get('auc@0.5'), '.1f')}/{fmt(cm.get('auc@1'), '.1f')}/{fmt(cm.get('auc@5'), '.1f')}",
            fmt(om.get("median_relative_rotation_error_deg"), ".4f"),
            fmt(cm.get("median_relative_rotation_error_deg"), ".4f"),
            fmt(o.get("sparse_time_s"), ".1f"), fmt(c.get("wall_time_s"), ".1f"), fmt(ratio, ".2f"),
            fmt(o.get("peak_rss_mb"), ".0f"), fmt(c.get("peak_rss_mb"), ".0f")]))
    return "\n".join(lines)


def dense_table(rows: list[dict]) -> str:
    head = ("scene", "width", "pairs", "median s/pair", "stage s", "s/panorama", "CPU s", "peak MB", "points",
            "max median rel. depth err", "min valid share", "accuracy", "completeness")
    lines = [" | ".join(head), " | ".join("---" for _ in head)]
    for r in rows:
        d = r["ours"].get("densify")
        if not d:
            continue
        m = r["ours"].get("metrics", {}).get("dense", {})
        cloud = m.get("cloud", {})
        per_panorama = d["stage_time_s"] / len(d["valid_share"]) if d.get("valid_share") else None
        lines.append(" | ".join([r["scene"], str(d.get("width")), str(d["pairs"]), fmt(d["median_pair_time_s"]),
                                 fmt(d["stage_time_s"], ".1f"), fmt(per_panorama, ".2f"), fmt(d.get("cpu_time_s"), ".1f"),
                                 fmt(d.get("peak_rss_mb"), ".0f"), str(d["points"]), fmt(m.get("max_median_rel_error"), ".4f"),
                                 fmt(m.get("min_valid_share"), ".3f"), fmt(cloud.get("accuracy"), ".3f"),
                                 fmt(cloud.get("completeness"), ".3f")]))
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    synth = [r for r in rows if r.get("views") and r["scene"].endswith("-hand")]
    if not synth:
        return
    v = [r["views"] for r in synth]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(v, [r["ours"].get("sparse_time_s", np.nan) for r in synth], "o-", label="fullview (sparse)")
    if any("colmap" in r for r in synth):
        ax.plot(v, [r.get("colmap", {}).get("wall_time_s", np.nan) for r in synth], "s-", label="COLMAP SPHERICAL")
    ax.set_xlabel("views")
    ax.set_ylabel("wall time (s)")
    ax.set_title("time against number of views (2048×1024)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, nargs="+", default=[2, 6, 12, 24])
    parser.add_argument("--width", type=int, default=2048)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--dense-views", type=int, default=6, help="synthetic scene that also runs densify")
    parser.add_argument("--no-colmap", action="store_true")
    parser.add_argument("--no-real", action="store_true")
    parser.add_argument("--no-home", action="store_true", help="skip the hard synthetic home (30 views, 12 rooms)")
    parser.add_argument("--work", type=Path, default=ROOT / "workspace" / "bench")
    parser.add_argument("--scale", action="store_true", help="run only the scaling rows (see the module doc)")
    parser.add_argument("--scale-views", type=int, nargs="*", default=list(SCALE_VIEWS))
    parser.add_argument("--tag", default="", help="--scale: suffix of the result files (runs split in parts)")
    parser.add_argument("--walk-views", type=int, nargs="*", default=list(WALK_VIEWS),
                        help="--scale: views of the corridor walk, one row each (0 or none: no walk)")
    parser.add_argument("--colmap-worker", nargs=2, type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--colmap-matcher", default="exhaustive", help=argparse.SUPPRESS)
    parser.add_argument("--reuse", action="store_true", help="--scale: keep the results of an earlier run whose "
                        "stages (ours) and COLMAP reference are still fresh (times as measured then)")
    args = parser.parse_args()
    if args.colmap_worker:
        colmap_worker(*args.colmap_worker, matcher=args.colmap_matcher, reuse=args.reuse)
        return 0
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if args.scale:
        return scale_main(args)
    rows = []
    for views in args.views:
        dataset = synth_dataset(args.work, views, args.width, args.seed)
        for hand in (True, False):
            label = f"synth{views}-{'hand' if hand else 'nohand'}"
            dense = hand and views == args.dense_views
            row = {"scene": label, "kind": "room", "views": views, "ours": ours(dataset, args.work, label,
                                                                [f"filter.use_hand_points={str(hand).lower()}"], dense)}
            if hand and not args.no_colmap:
                row["colmap"] = colmap(dataset, args.work, label)
            elif not hand and rows and "colmap" in rows[-1]:
                row["colmap"] = rows[-1]["colmap"]  # same images: COLMAP has no hand points to use
            rows.append(row)
            log.info("%s: %s", label, json.dumps(row)[:400])
    if not args.no_home:
        rows.extend(home_rows(args))
    if not args.no_real:
        if SHARED.exists():
            for name in ("360_Flat", "360_school"):
                row = {"scene": name, "ours": ours(SHARED / name, args.work, name, [], dense=name == "360_Flat")}
                if name == "360_Flat":
                    row["viewer"] = viewer_timing(SHARED / name, args.work / "ws" / name)
                if not args.no_colmap:
                    row["colmap"] = colmap(SHARED / name, args.work, name)
                rows.append(row)
                log.info("%s: %s", name, json.dumps(row)[:400])
        else:
            print(f"skipping real datasets: {SHARED} not found")
    RESULTS.mkdir(parents=True, exist_ok=True)
    stamp = dt.datetime.now().strftime("%Y-%m-%d")
    out = RESULTS / f"{stamp}.json"
    out.write_text(json.dumps({"date": dt.datetime.now().isoformat(timespec="seconds"), "width": args.width,
                               "rows": rows}, indent=2) + "\n")
    plot(rows, RESULTS / f"{stamp}-time-vs-views.png")
    print(table(rows))
    print()
    print(dense_table(rows))
    viewer = next((r["viewer"] for r in rows if r.get("viewer")), None)
    if viewer:
        print(f"\nviewer on 360_Flat (5376x2688, cold cache): interactive after {viewer['page_ready_s']} s, "
              f"a panorama in the tour {viewer['tour_open_s']} s after clicking its camera")
    print(f"\nratio = ours sparse-pipeline wall time / COLMAP wall time, same run. Results: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
