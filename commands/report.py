"""`fullview report`: one static HTML page about a run, `report/index.html` in the workspace (opens from disk, no
server, no network): stages with timings, cache state and config; the pair × pair matrix of verified matches; the
strongest pair with its inlier matches drawn; cameras from above with headings; reprojection errors and track
lengths; every panorama's depth map and valid share; the eval metrics and the COLMAP comparison when present; the
command that starts the viewer."""

from __future__ import annotations

import html
import io
import json
import logging

import cv2
import numpy as np

from fullview.io.artifacts import ArtifactError
from fullview.io.config import params_of
from fullview.io.workspace import StageWriter, folder_of, image_stem
from fullview.sfm.camera import camera_up
from fullview.sfm.compare import top_view_basis
from fullview.stages import PIPELINE
from fullview.stages.runner import Pipeline, record_fingerprint

log = logging.getLogger(__name__)

THUMB_WIDTH = 1024  # panoramas and depth maps in the report are this wide at most
MAX_MATCH_LINES = 200  # inlier matches drawn for the strongest pair (a seeded random subset beyond this)


def report(pipeline: Pipeline) -> str:
    """Write the report; returns the path of its index.html."""
    ws = pipeline.ws
    with ws.locked(command="fullview report"), ws.transaction(folder_of("report_page")) as out:
        with ws.reading():
            sections = [_stages(pipeline), _pairs(pipeline, out), _cameras(pipeline, out), _placements(pipeline),
                        _pose_check(pipeline), _errors(pipeline, out), _dense(pipeline, out),
                        _depth(pipeline, out), _metrics(pipeline), _viewer(pipeline)]
        page = _PAGE.format(title=html.escape(pipeline.dataset.name), body="\n".join(s for s in sections if s))
        out.save_text("report_page", page)
        fingerprints = {s: pipeline.fingerprint(s) for s in PIPELINE}
        out.commit_manifest({"fingerprint": record_fingerprint(fingerprints), "upstream": fingerprints,
                             "summary": {"sections": len([s for s in sections if s])}})
    return str(ws.path("report_page"))


# ------------------------------------------------------------------------------------------------ sections
def _stages(pipeline: Pipeline) -> str:
    rows = []
    for stage in PIPELINE:
        status = pipeline.status(stage)
        manifest = pipeline.ws.read_manifest(stage) or {}
        summary = {k: v for k, v in (manifest.get("summary") or {}).items() if isinstance(v, (int, float, str))}
        rows.append(f"<tr><td>{stage}</td><td class='{status.state}'>{status.state}</td>"
                    f"<td>{_num(manifest.get('wall_time_s'))}</td><td>{_num(manifest.get('peak_rss_mb'))}</td>"
                    f"<td>{html.escape(', '.join(f'{k}={v}' for k, v in list(summary.items())[:6]))}</td>"
                    f"<td>{html.escape('; '.join(status.reasons))}</td></tr>")
    config = {s: params_of(o) for s, o in pipeline.config.items()}
    return ("<h2>Stages</h2><table><tr><th>stage</th><th>state</th><th>wall time (s)</th><th>peak memory (MB)</th>"
            "<th>summary</th><th>why not fresh</th></tr>" + "".join(rows) + "</table>"
            f"<details><summary>configuration used</summary><pre>{html.escape(json.dumps(config, indent=2))}</pre>"
            "</details>")


def _pairs(pipeline: Pipeline, out: StageWriter) -> str:
    try:
        verified = pipeline.ws.load_inliers()
    except ArtifactError:
        return "<h2>Verified pairs</h2><p class='missing'>no filter results yet</p>"
    names = pipeline.dataset.image_names
    counts = np.zeros((len(names), len(names)), int)
    for (i, j), m in zip(verified.pairs, verified.matches):
        counts[i, j] = counts[j, i] = len(m)
    top = max(counts.max(), 1)
    head = "".join(f"<th class='rot'>{html.escape(n)}</th>" for n in names)
    rows = "".join(f"<tr><th>{html.escape(a)}</th>" + "".join(
        f"<td style='background:rgba(59,111,182,{c / top:.2f})'>{c if c else ''}</td>" for c in counts[i])
        + "</tr>" for i, a in enumerate(names))
    best = max(zip(verified.pairs, verified.matches), key=lambda pm: len(pm[1]), default=None)
    figure = ""
    if best is not None and len(best[1]):
        (i, j), m = best
        obs = pipeline.ws.load_observations(pipeline.dataset)
        picture = _matches_picture(pipeline, names[i], names[j], obs[i]["pixels"][m[:, 0]], obs[j]["pixels"][m[:, 1]])
        _save_png(out, "pair_matches.png", picture)
        figure = (f"<figure><img src='pair_matches.png' alt='inlier matches'><figcaption>"
                  f"{min(len(m), MAX_MATCH_LINES)} of the {len(m)} inlier matches of "
                  f"{html.escape(names[i])} (top) and {html.escape(names[j])} (bottom), the strongest pair"
                  "</figcaption></figure>")
    return f"<h2>Verified pairs</h2><table class='matrix'><tr><th></th>{head}</tr>{rows}</table>{figure}"


def _matches_picture(pipeline: Pipeline, a: str, b: str, px_a: np.ndarray, px_b: np.ndarray) -> np.ndarray:
    """The two panoramas stacked, each inlier match a line of its own colour."""
    top, bottom = (pipeline.dataset.load_image(n, width=THUMB_WIDTH) for n in (a, b))
    scale_a = top.shape[1] / pipeline.dataset.image_sizes[a][0]
    scale_b = bottom.shape[1] / pipeline.dataset.image_sizes[b][0]
    canvas = np.vstack([top, bottom])
    rng = np.random.default_rng(0)
    keep = np.sort(rng.permutation(len(px_a))[:MAX_MATCH_LINES])
    for pa, pb in zip(px_a[keep] * scale_a, px_b[keep] * scale_b):
        color = tuple(int(c) for c in rng.integers(64, 256, 3))
        pb = pb + [0, top.shape[0]]
        cv2.line(canvas, tuple(np.round(pa).astype(int)), tuple(np.round(pb).astype(int)), color, 1, cv2.LINE_AA)
    return canvas


def _cameras(pipeline: Pipeline, out: StageWriter) -> str:
    try:
        poses, source = pipeline.ws.load_poses()
    except ArtifactError:
        return "<h2>Cameras</h2><p class='missing'>no registration yet</p>"
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reg = poses["registered"].astype(bool)
    R, c = poses["R_cam_from_world"][reg], poses["centers"][reg]
    names = [str(n) for n, ok in zip(poses["image_names"], reg) if ok]
    basis = top_view_basis(c, camera_up(R)) if len(c) >= 2 else np.eye(3)[:2]
    xy = (c - c.mean(0)) @ basis.T
    heading = (R[:, 2, :] @ basis.T)  # each panorama's centre direction (camera +z) seen from above
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.plot(xy[:, 0], xy[:, 1], "-", color="#66aaff", lw=1)
    ax.quiver(xy[:, 0], xy[:, 1], heading[:, 0], heading[:, 1], color="#ff6633", angles="xy", width=0.004)
    ax.plot(xy[:, 0], xy[:, 1], "o", color="#ffcc33", mec="k")
    for name, p in zip(names, xy):
        ax.annotate(image_stem(name), p, textcoords="offset points", xytext=(5, 5), fontsize=7)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"cameras from above ({source} poses), arrows: panorama centre")
    _save_figure(out, "cameras.png", fig)
    missing = [str(n) for n, ok in zip(poses["image_names"], poses["registered"]) if not ok]
    why = ((pipeline.ws.read_manifest("registration") or {}).get("summary") or {}).get("unregistered_reasons", {})
    note = ("<p class='missing'>not registered:</p><ul>" + "".join(
        f"<li>{html.escape(n)}: {html.escape(why.get(n, 'no reason recorded'))}</li>" for n in missing) + "</ul>"
        if missing else "")
    return f"<h2>Cameras</h2>{note}<img src='cameras.png' alt='cameras from above'>"


def _placements(pipeline: Pipeline) -> str:
    """Each camera's verdict and how it was placed, and the weakest links with what would confirm them
    (registration.json; docs/trust.md)."""
    summary = (pipeline.ws.read_manifest("registration") or {}).get("summary") or {}
    records = summary.get("placements")
    if not records:
        return ""
    rows = []
    for name, r in records.items():
        pairs = r["evidence"].get("verified_pairs", [])
        evidence = f"{len(pairs)} verified pairs" + (f" (best {pairs[0][1]} inliers)" if pairs else "")
        if "inliers_2d3d" in r["evidence"]:
            evidence += f", {r['evidence']['inliers_2d3d']} 2D-3D inliers"
        joins = "; ".join(f"{j['kind']}: {j['confirmed_by']}" for j in r["joins"]) or "—"
        rows.append(f"<tr class='{html.escape(r['verdict'])}'><td>{html.escape(name)}</td>"
                    f"<td>{html.escape(r['verdict'])}</td><td>{html.escape(r['how'])}</td>"
                    f"<td>{html.escape(evidence)}</td><td>{html.escape(joins)}</td>"
                    f"<td>{html.escape(r['scale'])}</td></tr>")
    counts = summary.get("verdicts", {})
    head = ", ".join(f"{counts.get(k, 0)} {k.replace('_', ' ')}" for k in ("verified", "approximate", "own_model"))
    weak = summary.get("weakest_links") or []
    links = ("<h3>Weakest links</h3><table><tr><th>link</th><th>evidence</th><th>would confirm it</th></tr>" + "".join(
        f"<tr><td>{html.escape(w['link'])}</td><td>{html.escape(w['evidence'])}</td>"
        f"<td>{html.escape(w['confirm'])}</td></tr>" for w in weak) + "</table>") if weak else ""
    return ("<h2>Placements</h2>"
            f"<p>{html.escape(head)}. Approximate cameras (placed by a join nothing confirms) are left out of "
            "densify and the exports.</p><table><tr><th>image</th><th>verdict</th><th>placed by</th><th>evidence</th>"
            f"<th>joins that carried it</th><th>scale</th></tr>{''.join(rows)}</table>{links}")


def _errors(pipeline: Pipeline, out: StageWriter) -> str:
    try:
        sparse = pipeline.ws.load_sparse_model(0)
    except ArtifactError:
        return "<h2>Sparse model</h2><p class='missing'>no triangulation yet</p>"
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.5))
    errors = np.degrees(sparse["obs_error_rad"])
    a.hist(errors, bins=50, color="#3b6fb6")
    a.set_xlabel("angular reprojection error (°)")
    a.set_title(f"median {np.median(errors) if len(errors) else 0:.4f}°")
    lengths = np.bincount(sparse["track_ids"]) if len(sparse["track_ids"]) else np.zeros(0, int)
    b.hist(lengths, bins=np.arange(1.5, max(lengths.max() if len(lengths) else 2, 2) + 1.5), color="#ff9933")
    b.set_xlabel("track length (images)")
    b.set_title(f"{len(sparse['points'])} points, mean length {lengths.mean() if len(lengths) else 0:.2f}")
    _save_figure(out, "errors.png", fig)
    return "<h2>Sparse model</h2><img src='errors.png' alt='reprojection errors and track lengths'>"


def _pose_check(pipeline: Pipeline) -> str:
    """The leave-one-out pose check of the last `fullview eval` (docs/pose-check.md): each camera re-estimated from
    the other cameras' points alone, disagreeing and unverifiable cameras first."""
    metrics = pipeline.ws.load_json("eval_metrics") or {}
    check = metrics.get("pose_check")
    if not check or not check.get("per_image"):
        return ""
    order = {"disagrees": 0, "unverifiable": 1}
    rows = sorted(check["per_image"].items(), key=lambda item: (order.get(item[1]["status"], 2), item[0]))
    body = "".join(
        f"<tr class='{html.escape(str(r['status']))}'><td>{html.escape(name)}</td><td>{r.get('model', '—')}</td>"
        f"<td>{html.escape(str(r['status']))}</td><td>{_num(r.get('rotation_deg'))}</td>"
        f"<td>{_num(r.get('centre_rel'))}</td><td>{_num(r.get('shift_deg'))}</td>"
        f"<td>{html.escape(str(r.get('reason') or ''))}</td></tr>" for name, r in rows)
    flagged = ", ".join(check.get("flagged") or []) or "none"
    return ("<h2>Pose check</h2><p>Each camera's pose estimated again from the other cameras' points alone and "
            f"compared with the model's (bound: a median shift of {_num(check.get('threshold_deg'))}°, the "
            f"triangulation's inlier threshold). Flagged: {html.escape(flagged)}.</p><table><tr><th>image</th>"
            "<th>model</th><th>check</th><th>rotation (°)</th><th>centre / model size</th><th>median shift (°)</th>"
            f"<th>why</th></tr>{body}</table>")


def _dense(pipeline: Pipeline, out: StageWriter) -> str:
    """The dense cloud's and the mesh's previews that densify renders, and whether it judged the scene indoors."""
    ws = pipeline.ws
    manifest = ws.read_manifest("densify")
    if manifest is None:
        return ""
    summary = manifest.get("summary") or {}
    parts = []
    scene = summary.get("scene") or {}
    if scene.get("kind"):
        parts.append(f"<p>Scene: {html.escape(str(scene.get('reason') or scene['kind']))}</p>")  # the reason names it
    for artifact, caption in (("dense_preview", f"dense cloud, {summary.get('points', 0):,} points"),
                              ("dense_mesh_preview", "mesh")):
        path = ws.path(artifact)
        if path.is_file():
            out.save_bytes("report_asset", path.read_bytes(), file=path.name)
            parts.append(f"<figure><img src='{html.escape(path.name)}' alt='{html.escape(caption)}'><figcaption>"
                         f"{html.escape(caption)}</figcaption></figure>")
    return "<h2>Dense model</h2>" + "".join(parts) if parts else ""


def _depth(pipeline: Pipeline, out: StageWriter) -> str:
    """Every panorama's depth map on one colour scale (inverse range, so near detail shows), with a colour bar in
    metres when a scale is stated (`fullview export --camera-height`), else in model units."""
    manifest = pipeline.ws.read_manifest("densify")
    if manifest is None:
        return "<h2>Depth maps</h2><p class='missing'>densify has not run</p>"
    shares = manifest.get("summary", {}).get("valid_share", {})
    maps = {name: pipeline.ws.load_depth(name) for name in pipeline.dataset.image_names}
    inverse = [1.0 / d["range"][d["valid"] & (d["range"] > 0)] for d in maps.values() if d is not None]
    inverse = np.concatenate(inverse) if inverse else np.zeros(0)
    if not len(inverse):
        return "<h2>Depth maps</h2><p class='missing'>no panorama has a depth</p>"
    lo, hi = np.percentile(inverse, [2, 98])
    hi = max(hi, lo * 1.001 + 1e-12)
    unit, factor = _length_unit(pipeline)
    cells = []
    for name, depth in maps.items():
        if depth is None:
            cells.append(f"<figure><figcaption>{html.escape(name)}: no depth map</figcaption></figure>")
            continue
        picture = _colour_depth(depth["range"], depth["valid"], lo, hi)
        if picture.shape[1] > THUMB_WIDTH:
            picture = cv2.resize(picture, (THUMB_WIDTH, THUMB_WIDTH // 2), interpolation=cv2.INTER_NEAREST)
        file = f"depth_{image_stem(name)}.png"
        _save_png(out, file, picture)
        cells.append(f"<figure><img src='{html.escape(file)}' alt='depth of {html.escape(name)}'><figcaption>"
                     f"{html.escape(name)}: {100 * shares.get(name, 0):.0f}% of pixels have a depth</figcaption>"
                     "</figure>")
    _save_figure(out, "depth_scale.png", _colour_bar(lo, hi, unit, factor))
    return ("<h2>Depth maps</h2><p>Black: no depth. Colour: distance from the camera.</p>"
            f"<img src='depth_scale.png' alt='depth colour scale in {html.escape(unit)}'>"
            "<div class='grid'>" + "".join(cells) + "</div>")


def _length_unit(pipeline: Pipeline) -> tuple[str, float]:
    """("m", metres per model unit) when a metric scale is stated and measurable, else ("model units", 1)."""
    from fullview.commands.export import metric_scale
    scale = metric_scale(pipeline)
    return ("m", scale.metres_per_unit) if scale is not None else ("model units", 1.0)


def _colour_depth(rng: np.ndarray, valid: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """BGR picture of a range map on the report's shared scale: inverse range lo..hi -> TURBO, invalid black."""
    ok = valid & (rng > 0)
    inv = np.divide(1.0, rng, out=np.zeros(rng.shape, np.float64), where=ok)
    grey = np.clip((inv - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)
    return cv2.applyColorMap(grey, cv2.COLORMAP_TURBO) * ok[..., None].astype(np.uint8)


def _colour_bar(lo: float, hi: float, unit: str, factor: float):
    """A horizontal colour bar of `_colour_depth`'s scale, ticks labelled as distances."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(8, 0.9))
    bar = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[None, :], cv2.COLORMAP_TURBO)[..., ::-1]
    ax.imshow(np.repeat(bar, 12, axis=0), aspect="auto", extent=(0, 255, 0, 1))
    ticks = np.linspace(0, 255, 6)
    ax.set_xticks(ticks, [f"{factor / (lo + t / 255 * (hi - lo)):.3g}" for t in ticks])
    ax.set_yticks([])
    ax.set_xlabel(f"distance ({unit}); far on the left, near on the right")
    fig.tight_layout()
    return fig


def _metrics(pipeline: Pipeline) -> str:
    parts = []
    metrics = pipeline.ws.load_json("eval_metrics")
    if metrics:
        rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{_num(v)}</td></tr>" for k, v in metric_rows(metrics))
        parts.append(f"<h3>eval</h3><table>{rows}</table>")
    for render_type in ("spherical", "perspective_overlapping", "perspective_non_overlapping"):
        path = pipeline.ws.path("compare_markdown", render_type=render_type)
        if path.exists():
            parts.append(f"<h3>COLMAP comparison ({render_type})</h3><pre>{html.escape(path.read_text())}</pre>")
    return "<h2>Metrics</h2>" + ("".join(parts) or "<p class='missing'>run fullview eval / fullview compare</p>")


def metric_rows(metrics: dict) -> list[tuple[str, object]]:
    """(name, value) of the eval's scalars, with those of its sections one level down as "section.name" (the
    leave-one-out agreement and the dense figures of a dataset without ground truth live there); per-image and
    per-model lists are left to the JSON."""
    rows = []
    for key, value in metrics.items():
        if isinstance(value, dict):
            rows += [(f"{key}.{k}", v) for k, v in value.items() if isinstance(v, (int, float, str))]
        elif isinstance(value, (int, float, str)):
            rows.append((key, value))
    return rows


def _viewer(pipeline: Pipeline) -> str:
    command = f"fullview view {pipeline.dataset.root}{pipeline.ws.workspace_option(pipeline.dataset.root)}"
    return f"<h2>Viewer</h2><p>Walk the tour and pick hand points: <code>{html.escape(command)}</code></p>"


# ------------------------------------------------------------------------------------------------ helpers
def _num(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v)) if v is not None else "—"


def _save_png(out: StageWriter, file: str, picture: np.ndarray) -> None:
    ok, png = cv2.imencode(".png", picture)
    if not ok:
        raise ArtifactError(f"cannot encode {file}")
    out.save_bytes("report_asset", png.tobytes(), file=file)


def _save_figure(out: StageWriter, file: str, fig) -> None:
    import matplotlib.pyplot as plt
    buffer = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buffer, dpi=100, format="png")
    plt.close(fig)
    out.save_bytes("report_asset", buffer.getvalue(), file=file)


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>fullview report · {title}</title><link rel="icon" href="data:,">
<style>
body {{ font: 14px system-ui, sans-serif; margin: 2em; background: #fafafa; color: #222; }}
table {{ border-collapse: collapse; margin: 0.5em 0; }} td, th {{ border: 1px solid #ccc; padding: 2px 6px; }}
td.fresh {{ color: #1a7f37; }} td.stale, td.missing {{ color: #b35900; }} p.missing {{ color: #b35900; }}
table.matrix td {{ text-align: center; min-width: 2.5em; }} th.rot {{ writing-mode: vertical-rl; }}
img {{ max-width: 100%; }} .grid {{ display: grid; grid-template-columns: repeat(3, 1fr); gap: 8px; }}
figure {{ margin: 0; }} tr.approximate {{ background: #fde8d0; }} tr.own_model {{ background: #eef; }}
</style></head>
<body><h1>fullview report · {title}</h1>
{body}
</body></html>
"""
