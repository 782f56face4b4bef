"""`fullview export`: the reconstruction in formats other tools open.

- ``colmap`` / ``colmap-bin``: a COLMAP model (text / binary) written by pycolmap, EQUIRECTANGULAR cameras;
- ``nerfstudio``: ``transforms.json`` (``camera_model: EQUIRECTANGULAR``) plus the sparse points for splatting;
- ``ply``: the sparse and dense clouds as binary PLY with colours and normals, and the dense mesh (when densify
  made one) as PLY and OBJ with vertex colours.

Scale. With ``--camera-height M`` (metres from the floor to the lens) or ``--known-distance A B M`` (two hand
points' names and their distance in metres) every length of every format is in metres (`sfm.scale`); the
statement is kept in the workspace (``scale/statement.json``) and applies to every later export and the viewer
until another is made (``--model-units`` drops it). Each export's ``README.txt`` and manifest say the unit.
Images. ``nerfstudio`` holds its frames' images in ``<k>/images/`` (copied, or with ``--link`` hard-linked) and
its ``file_path``s are ``images/<name>``: the folder moves to another machine without the dataset.

Every model is written to its own subfolder, ``<k>/`` (model 0 is the largest; COLMAP's ``sparse/<k>`` convention);
the dense cloud and mesh belong to model 0 (``0/dense.ply``, ``0/dense_mesh.ply``). ``ply`` needs a fresh dense
cloud: when densify is stale or has not run, the export stops (exit 2) saying so, unless ``--sparse-only`` asks for
the sparse cloud alone.

The export goes to the workspace's ``export_<format>/`` folder, in a transaction (an interrupted export leaves the
previous one intact), or to ``--out DIR``: a new or empty folder, or one a previous export wrote. There the export
changes only what it wrote itself: its ``manifest.json`` lists every file it wrote (path, size, sha256), and the
next export into the folder replaces or removes only those, and only while unchanged; anything else there (notes,
the user's own files and folders) stays, and an export that would have to overwrite or remove such a file is
refused, naming it. A non-empty folder without that record is refused: choose a new or empty folder. Each file is
replaced atomically, the record last (`io.workspace.folder_update`).
"""

from __future__ import annotations

import logging
import shlex
from pathlib import Path

import numpy as np

from fullview.io.artifacts import ArtifactError, load_npz
from fullview.io.config import ConfigError
from fullview.io.exports import (ExportError, SparseModel, hold_images, scaled, sparse_point_normals, split_models,
                                 write_colmap_model, write_mesh, write_nerfstudio, write_point_cloud)
from fullview.io.workspace import (PAIRS_VERSION, RUN_LOCK, StageWriter, folder_of, folder_update, make_dirs,
                                   read_manifest_file)
from fullview.sfm import scale as metric
from fullview.sfm.camera import pixels_to_bearings
from fullview.sfm.scale import Scale, ScaleError
from fullview.stages.runner import Pipeline, RunnerError, record_fingerprint

log = logging.getLogger(__name__)

FORMATS = ("colmap", "colmap-bin", "nerfstudio", "ply")
EXPORT_KIND = "fullview export"  # marks a folder as a previous export, which --out may update


def export(pipeline: Pipeline, fmt: str, out: Path | None = None, *, sparse_only: bool = False, link: bool = False,
           camera_height: float | None = None, known_distance: tuple[str, str, float] | None = None,
           model_units: bool = False) -> Path:
    """Write the current reconstruction in `fmt`; returns the folder written. `sparse_only`: ``ply`` without the
    dense cloud and mesh (otherwise they must be fresh). `link`: ``nerfstudio`` hard-links its images instead of
    copying them. `camera_height` (m), `known_distance` (name, name, m): a new statement of the metric scale, kept
    in the workspace for the exports after; `model_units`: drop the kept statement; none of the three: the kept
    statement (if any) applies."""
    if fmt not in FORMATS:
        raise ConfigError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    if sum(x is not None and x is not False for x in (camera_height, known_distance, model_units)) > 1:
        raise ConfigError("--camera-height, --known-distance and --model-units: give one of them")
    ws = pipeline.ws
    status = pipeline.chain_status("triangulation")
    if status.state != "fresh":
        raise RunnerError(f"{ws.root}: the sparse model is {status.state} ({'; '.join(status.reasons)}); "
                          "run the pipeline first")
    out = _checked_out(Path(out)) if out is not None else None
    dense = fmt == "ply" and not sparse_only
    if dense:
        _require_dense(pipeline)
    new = {} if model_units else _statement(camera_height, known_distance)
    statement = stated_scale(pipeline) if new is None else new
    models = sparse_models(pipeline)
    scales = metric_scales(pipeline, models, statement)  # an ExportError when the statement cannot be measured
    if new is not None:
        _keep_statement(pipeline, new)
    for k, sc in enumerate(scales):
        log.info("model %d: %s", k, f"scale: {sc.describe()}" if sc else "unit: model units (arbitrary)")
    if out is not None:  # nothing is written in the workspace: reading under the commit lock is enough
        with folder_update(out) as writer:
            _write(pipeline, fmt, writer, dense, models, scales, link)
        return out
    with ws.locked(command="fullview export"), ws.transaction(folder_of("export_dir", format=fmt)) as writer:
        _write(pipeline, fmt, writer, dense, models, scales, link)
    return ws.path("export_dir", format=fmt)


# ------------------------------------------------------------------------------------------------------------------
# metric scale: the user's statement, kept in the workspace, measured on the current model

def _statement(camera_height: float | None, known_distance) -> dict | None:
    """The statement of a new scale as kept in scale/statement.json (None: no new one)."""
    if camera_height is not None:
        if not (np.isfinite(camera_height) and camera_height > 0):
            raise ConfigError(f"--camera-height {camera_height}: expected a positive height in metres")
        return {"camera_height_m": float(camera_height)}
    if known_distance is not None:
        a, b, metres = known_distance
        try:
            metres = float(metres)
        except ValueError:
            raise ConfigError(f"--known-distance {a} {b} {metres}: the distance must be a number of metres") from None
        if not (np.isfinite(metres) and metres > 0) or a == b:
            raise ConfigError(f"--known-distance {a} {b} {metres}: expected two different hand points and a "
                              "positive distance in metres")
        return {"known_distance": {"a": str(a), "b": str(b), "metres": metres}}
    return None


def stated_scale(pipeline: Pipeline) -> dict:
    """The kept statement of the metric scale ({} when none: model units)."""
    kept = pipeline.ws.load_json("scale_statement")
    if kept is None:
        return {}
    if not isinstance(kept, dict) or not set(kept) <= {"camera_height_m", "known_distance"}:
        raise ArtifactError(f"{pipeline.ws.path('scale_statement')}: not a scale statement; state the scale again "
                            "(fullview export ... --camera-height M, or --model-units)")
    return kept


def _keep_statement(pipeline: Pipeline, statement: dict) -> None:
    """Write scale/statement.json in a transaction of its own (the statement outlives every export)."""
    ws = pipeline.ws
    with ws.locked(command="fullview export"), ws.transaction(folder_of("scale_statement")) as writer:
        writer.save_json("scale_statement", statement)
        writer.commit_manifest({"fingerprint": record_fingerprint(statement), "upstream": {},
                                "summary": {"statement": statement}})


def metric_scale(pipeline: Pipeline, model: int = 0) -> Scale | None:
    """The metric scale of model `model` from the kept statement (for the viewer): None when no statement is kept
    or it cannot be measured on the current model (logged)."""
    statement = stated_scale(pipeline)
    if not statement:
        return None
    try:
        scales = metric_scales(pipeline, sparse_models(pipeline), statement)
    except ExportError as e:
        log.warning("metric scale: %s", e)
        return None
    return scales[model] if model < len(scales) else None


def metric_scales(pipeline: Pipeline, models: list[SparseModel], statement: dict) -> list[Scale | None]:
    """Per model, its metric scale under `statement` (None: model units). A camera height measures every model
    whose cameras see a floor (an ExportError when model 0's do not); a known distance measures the model that
    holds both points (an ExportError when none does)."""
    if not statement:
        return [None] * len(models)
    if "camera_height_m" in statement:
        down = _model_down(pipeline, models)
        tri = pipeline.config["triangulation"]
        floor = tri.height_prior_sigma if tri.bundle_adjust and tri.height_prior else 0.0  # see sfm.scale
        out = []
        for k, m in enumerate(models):
            try:
                out.append(metric.camera_height_scale(float(statement["camera_height_m"]), m.centers, down[k],
                                                      m.points, m.track_point3d, m.track_image,
                                                      min_spread=floor))
            except ScaleError as e:
                if k == 0:
                    raise ExportError(f"--camera-height: model 0: {e}") from None
                log.warning("model %d: no metric scale (%s); exported in model units", k, e)
                out.append(None)
        return out
    a, b, metres = (statement["known_distance"][key] for key in ("a", "b", "metres"))
    stated = f"{a} to {b} {float(metres):g} m"
    sigma = _angular_sigma(pipeline)
    out = [None] * len(models)
    names = [t.name for t in pipeline.dataset.hand_tracks()]
    for k, m in enumerate(models):
        ends = [_hand_point(pipeline, m, name) for name in (a, b)]
        if all(e is not None for e in ends):
            clicked = [h for h in (_hand_point(pipeline, m, n) for n in names) if h is not None]
            hand_sigma = metric.residual_sigma([(x, m.centers[cams], rays) for x, cams, rays in clicked])
            covs = [metric.point_covariance(x, m.centers[cams], np.fmax(sigma, hand_sigma)) for x, cams, _ in ends]
            try:
                out[k] = metric.known_distance_scale(float(metres), ends[0][0], ends[1][0], *covs, stated=stated)
            except ScaleError as e:
                raise ExportError(f"--known-distance: {e}") from None
            return out
    known = {t.name for t in pipeline.dataset.hand_tracks()}
    missing = [n for n in (a, b) if n not in known]
    if missing:
        raise ExportError(f"--known-distance: {', '.join(missing)} not in {pipeline.dataset.hand_points_path} "
                          f"(its points: {', '.join(sorted(known)) or 'none'})")
    raise ExportError(f"--known-distance: {a} and {b} are not both triangulated in one model (a hand point needs "
                      "two registered views that keep it); mark them in more panoramas, or state --camera-height")


def _model_down(pipeline: Pipeline, models: list[SparseModel]) -> list[np.ndarray]:
    """Per model, (N, 3) its down direction in its world frame for its cameras (nan elsewhere): the mean of its
    images' gravity as the filter measured it (vertical lines), carried to the world by the poses; where none of
    its images has one, the mean of its cameras' y axes (levelled panoramas: y points down)."""
    try:
        filt = load_npz(pipeline.ws.path("inliers"), PAIRS_VERSION, ("gravity", "gravity_std_rad"), only=True)
        g, std = filt["gravity"], filt["gravity_std_rad"]
    except (ArtifactError, KeyError):
        g = std = None
    out = []
    for m in models:
        reg = np.asarray(m.registered, bool)
        R = np.asarray(m.R_cam_from_world, np.float64)
        measured = reg & (np.isfinite(std) & (np.linalg.norm(g, axis=1) > 0) if g is not None else False)
        world = (np.einsum("nji,nj->i", R[measured], g[measured]) if measured.any()
                 else R[reg, 1, :].sum(axis=0))
        down = np.full((len(reg), 3), np.nan)
        down[reg] = world / np.linalg.norm(world)
        out.append(down)
    return out


def _angular_sigma(pipeline: Pipeline) -> float:
    with pipeline.ws.reading():
        return metric.angular_sigma(pipeline.ws.load_sparse()["obs_error_rad"])


def _hand_point(pipeline: Pipeline, model: SparseModel, name: str
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(position, observing camera indices, their observed world bearings) of the sparse point of `model` that
    holds the hand point `name`'s observations (most of them, when tracks split), or None when the model holds none
    of them."""
    tracks = [t.name for t in pipeline.dataset.hand_tracks()]
    if name not in tracks:
        return None
    want = tracks.index(name)
    hand = pipeline.dataset.hand_observations
    image, feature, point = (np.asarray(a, np.int64) for a in (model.track_image, model.track_point2d,
                                                               model.track_point3d))
    keep = np.asarray(model.registered, bool)[image]
    votes = []
    for k in np.unique(image[keep]).tolist():
        ids = np.asarray(hand[model.image_names[k]][0], np.int64)
        num_sift = len(model.pixels[k]) - len(ids)
        sel = keep & (image == k) & (feature >= num_sift)
        hit = ids[feature[sel] - num_sift] == want
        votes.append(point[sel][hit])
    votes = np.concatenate(votes) if votes else np.zeros(0, np.int64)
    if not len(votes):
        return None
    p = int(np.bincount(votes).argmax())
    sel = np.flatnonzero(keep & (point == p))
    cams = image[sel]
    rays = np.array([pixels_to_bearings(model.pixels[k][f], *model.image_sizes[k]) @ model.R_cam_from_world[k]
                     for k, f in zip(cams.tolist(), feature[sel].tolist())]).reshape(-1, 3)
    return np.asarray(model.points[p], np.float64), cams, rays


def _require_dense(pipeline: Pipeline) -> None:
    """A RunnerError unless the dense cloud on disk is fresh (``ply`` exports it beside the sparse one)."""
    status = pipeline.chain_status("densify")
    if status.state == "fresh":
        return
    ws = pipeline.ws
    run = shlex.join(["fullview", "run", str(pipeline.dataset.root), "-w", str(ws.root.parent)])
    what = "has not run" if status.state == "missing" and status.reasons == ["never run"] else \
        f"is {status.state} ({'; '.join(status.reasons)})"
    raise RunnerError(f"{ws.root}: densify {what}, so the dense cloud is not the current model's; run `{run}` "
                      "(with the same settings) first, or pass --sparse-only to export the sparse cloud alone")


def _checked_out(out: Path) -> Path:
    """A user-chosen export folder: new, empty or a previous export (never a folder of other files), outside every
    workspace."""
    out = out.resolve()
    if out == Path.cwd() or out in Path.cwd().parents:
        raise ConfigError(f"--out {out}: is the current folder or contains it; choose a new folder")
    inside = next((p for p in out.parents if (p / RUN_LOCK).is_file()), None)
    if inside is not None:
        raise ConfigError(f"--out {out}: lies inside the workspace {inside}; leave out --out to export there")
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not _is_export(out))):
        raise ConfigError(f"--out {out}: exists and is not empty nor a previous fullview export; choose a new or "
                          "empty folder")
    return out


def _is_export(folder: Path) -> bool:
    """A folder a previous `fullview export` wrote: its manifest says so."""
    manifest = read_manifest_file(folder)
    return manifest is not None and manifest.get("summary", {}).get("kind") == EXPORT_KIND


def _write(pipeline: Pipeline, fmt: str, writer: StageWriter, dense: bool, models: list[SparseModel],
           scales: list[Scale | None], link: bool) -> None:
    ws = pipeline.ws
    for k, (model, sc) in enumerate(zip(models, scales)):
        _write_model(pipeline, fmt, model, writer, str(k), dense=dense and k == 0,
                     factor=1.0 if sc is None else sc.metres_per_unit, link=link)
    units = [{"unit": "model unit"} if sc is None else sc.as_dict() for sc in scales]
    (writer.dir / README_NAME).write_text(_readme(fmt, models, scales))
    writer.commit_manifest({"fingerprint": record_fingerprint({"triangulation": pipeline.fingerprint("triangulation"),
                                                               "format": fmt, "scale": units, "link": link}),
                            "upstream": {"triangulation": pipeline.fingerprint("triangulation")},
                            "summary": {"kind": EXPORT_KIND, "format": fmt,
                                        "models": [{"images": int(m.registered.sum()), "points": int(len(m.points)),
                                                    **u} for m, u in zip(models, units)]}})
    log.info("exported %s: %d model(s) of %s registered images to %s", fmt, len(models),
             "+".join(str(int(m.registered.sum())) for m in models), ws.root)


README_NAME = "README.txt"  # what the export holds and its unit, for whoever receives the folder


def _readme(fmt: str, models: list[SparseModel], scales: list[Scale | None]) -> str:
    lines = [f"fullview export, format {fmt}: one folder per model (0 is the largest).", ""]
    for k, (m, sc) in enumerate(zip(models, scales)):
        unit = (f"metres ({sc.describe()})" if sc is not None else
                "model units (arbitrary: re-export with --camera-height M or --known-distance A B M for metres)")
        lines.append(f"{k}/: {int(m.registered.sum())} images, {len(m.points)} points; unit: {unit}")
    if fmt == "nerfstudio":
        lines += ["", "Each <k>/ holds transforms.json, sparse_points.ply and images/: train with "
                  "`ns-train splatfacto --data <k>` (or nerfacto) on any machine."]
    return "\n".join(lines) + "\n"


def _write_model(pipeline: Pipeline, fmt: str, model: SparseModel, writer: StageWriter, sub: str,
                 dense: bool, factor: float = 1.0, link: bool = False) -> None:
    """One model into the subfolder `sub` of the export (the dense cloud too when `dense`), every length times
    `factor` (metres per model unit, 1: model units)."""
    folder = writer.dir / sub  # the export's files go straight into the transaction's folder
    make_dirs(folder)
    model = scaled(model, factor) if factor != 1.0 else model
    if fmt in ("colmap", "colmap-bin"):
        write_colmap_model(model, folder, binary=fmt == "colmap-bin")
    elif fmt == "nerfstudio":
        sources = [pipeline.dataset.image_path(n) for n in model.image_names]
        write_nerfstudio(model, folder, image_paths=hold_images(model, folder, sources, link=link))
    else:
        normals = sparse_point_normals(model.points, model.centers, track_point3d=model.track_point3d,
                                       track_image=model.track_image)
        write_point_cloud(folder / "sparse.ply", model.points, model.colors, normals)
        cloud = pipeline.ws.load_dense_cloud() if dense else None
        if cloud is not None:
            xyz = np.column_stack([cloud["x"], cloud["y"], cloud["z"]]) * factor
            normals = np.column_stack([cloud["nx"], cloud["ny"], cloud["nz"]]) if "nx" in cloud else None
            write_point_cloud(folder / "dense.ply", xyz, np.column_stack([cloud["red"], cloud["green"], cloud["blue"]]),
                              normals)
            mesh = pipeline.ws.load_dense_mesh()
            for name in ("dense_mesh.ply", "dense_mesh.obj") if mesh is not None else ():
                write_mesh(folder / name, np.asarray(mesh["vertices"], np.float64) * factor, mesh["triangles"],
                           mesh["colors"])


def sparse_models(pipeline: Pipeline) -> list[SparseModel]:
    """Every bundle-adjusted sparse model (model 0 first) with every observation's pixel, as the exporters take
    them."""
    ws, dataset = pipeline.ws, pipeline.dataset
    with ws.reading():
        sparse = ws.load_sparse()
        obs = ws.load_observations(dataset)
        # approximate cameras (placed by a join nothing confirms, docs/trust.md) are not exported as fact
        model_id = np.where(ws.verified_mask(), sparse["model_id"], -1)
    whole = SparseModel(
        image_names=list(dataset.image_names), image_sizes=[tuple(int(v) for v in o["image_size"]) for o in obs],
        registered=model_id >= 0, R_cam_from_world=sparse["R_cam_from_world"],
        t_cam_from_world=sparse["t_cam_from_world"], points=sparse["points"], colors=sparse["colors"],
        point_errors_rad=sparse["point_error_rad"], track_point3d=sparse["track_ids"],
        track_image=sparse["image_ids"], track_point2d=sparse["feature_ids"], pixels=[o["pixels"] for o in obs])
    return split_models(whole, model_id)
