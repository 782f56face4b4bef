"""`fullview export`: the reconstruction in formats other tools open.

- ``colmap`` / ``colmap-bin``: a COLMAP model (text / binary) written by pycolmap, EQUIRECTANGULAR cameras;
- ``nerfstudio``: ``transforms.json`` (``camera_model: EQUIRECTANGULAR``) plus the sparse points for splatting;
- ``ply``: the sparse and dense clouds as binary PLY with colours and normals, and the dense mesh (when densify
  made one) as PLY and OBJ with vertex colours.

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
import os
import shlex
from pathlib import Path

import numpy as np

from fullview.io.config import ConfigError
from fullview.io.exports import (SparseModel, sparse_point_normals, split_models, write_colmap_model,
                                 write_mesh, write_nerfstudio, write_point_cloud)
from fullview.io.workspace import RUN_LOCK, StageWriter, folder_of, folder_update, make_dirs, read_manifest_file
from fullview.stages.runner import Pipeline, RunnerError, record_fingerprint

log = logging.getLogger(__name__)

FORMATS = ("colmap", "colmap-bin", "nerfstudio", "ply")
EXPORT_KIND = "fullview export"  # marks a folder as a previous export, which --out may update


def export(pipeline: Pipeline, fmt: str, out: Path | None = None, *, sparse_only: bool = False) -> Path:
    """Write the current reconstruction in `fmt`; returns the folder written. `sparse_only`: ``ply`` without the
    dense cloud and mesh (otherwise they must be fresh)."""
    if fmt not in FORMATS:
        raise ConfigError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    ws = pipeline.ws
    status = pipeline.chain_status("triangulation")
    if status.state != "fresh":
        raise RunnerError(f"{ws.root}: the sparse model is {status.state} ({'; '.join(status.reasons)}); "
                          "run the pipeline first")
    out = _checked_out(Path(out)) if out is not None else None
    dense = fmt == "ply" and not sparse_only
    if dense:
        _require_dense(pipeline)
    if out is not None:  # nothing is written in the workspace: reading under the commit lock is enough
        with folder_update(out) as writer:
            _write(pipeline, fmt, writer, dense)
        return out
    with ws.locked(command="fullview export"), ws.transaction(folder_of("export_dir", format=fmt)) as writer:
        _write(pipeline, fmt, writer, dense)
    return ws.path("export_dir", format=fmt)


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


def _write(pipeline: Pipeline, fmt: str, writer: StageWriter, dense: bool) -> None:
    ws = pipeline.ws
    models = sparse_models(pipeline)
    for k, model in enumerate(models):
        _write_model(pipeline, fmt, model, writer, str(k), dense=dense and k == 0)
    writer.commit_manifest({"fingerprint": record_fingerprint({"triangulation": pipeline.fingerprint("triangulation"),
                                                               "format": fmt}),
                            "upstream": {"triangulation": pipeline.fingerprint("triangulation")},
                            "summary": {"kind": EXPORT_KIND, "format": fmt,
                                        "models": [{"images": int(m.registered.sum()), "points": int(len(m.points))}
                                                   for m in models]}})
    log.info("exported %s: %d model(s) of %s registered images to %s", fmt, len(models),
             "+".join(str(int(m.registered.sum())) for m in models), ws.root)


def _write_model(pipeline: Pipeline, fmt: str, model: SparseModel, writer: StageWriter, sub: str,
                 dense: bool) -> None:
    """One model into the subfolder `sub` of the export (the dense cloud too when `dense`)."""
    folder = writer.dir / sub  # the export's files go straight into the transaction's folder
    make_dirs(folder)
    if fmt in ("colmap", "colmap-bin"):
        write_colmap_model(model, folder, binary=fmt == "colmap-bin")
    elif fmt == "nerfstudio":
        final = writer.dir.parent / writer.folder / sub  # where the export lives once committed
        paths = [os.path.relpath(pipeline.dataset.image_path(n).resolve(), final.resolve())
                 for n in model.image_names]
        write_nerfstudio(model, folder, image_paths=paths)
    else:
        normals = sparse_point_normals(model.points, model.centers, track_point3d=model.track_point3d,
                                       track_image=model.track_image)
        write_point_cloud(folder / "sparse.ply", model.points, model.colors, normals)
        cloud = pipeline.ws.load_dense_cloud() if dense else None
        if cloud is not None:
            xyz = np.column_stack([cloud["x"], cloud["y"], cloud["z"]])
            normals = np.column_stack([cloud["nx"], cloud["ny"], cloud["nz"]]) if "nx" in cloud else None
            write_point_cloud(folder / "dense.ply", xyz, np.column_stack([cloud["red"], cloud["green"], cloud["blue"]]),
                              normals)
            mesh = pipeline.ws.load_dense_mesh()
            for name in ("dense_mesh.ply", "dense_mesh.obj") if mesh is not None else ():
                write_mesh(folder / name, mesh["vertices"], mesh["triangles"], mesh["colors"])


def sparse_models(pipeline: Pipeline) -> list[SparseModel]:
    """Every bundle-adjusted sparse model (model 0 first) with every observation's pixel, as the exporters take
    them."""
    ws, dataset = pipeline.ws, pipeline.dataset
    with ws.reading():
        sparse = ws.load_sparse()
        obs = ws.load_observations(dataset)
    whole = SparseModel(
        image_names=list(dataset.image_names), image_sizes=[tuple(int(v) for v in o["image_size"]) for o in obs],
        registered=sparse["model_id"] >= 0, R_cam_from_world=sparse["R_cam_from_world"],
        t_cam_from_world=sparse["t_cam_from_world"], points=sparse["points"], colors=sparse["colors"],
        point_errors_rad=sparse["point_error_rad"], track_point3d=sparse["track_ids"],
        track_image=sparse["image_ids"], track_point2d=sparse["feature_ids"], pixels=[o["pixels"] for o in obs])
    return split_models(whole, sparse["model_id"])
