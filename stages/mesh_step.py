"""The densify stage's mesh step: a trimmed, coloured Poisson mesh of the fused cloud (``dense_mesh.ply``), its
preview and summary figures. Called once at the end of `fullview.stages.densify.run`; the geometry lives in
`fullview.sfm.dense.mesh`."""

from __future__ import annotations

import logging
import resource
import time

import numpy as np

from fullview.io.render import render_mesh
from fullview.sfm.camera import camera_center, camera_up
from fullview.sfm.dense.mesh import MeshParams, mesh_from_dense, nearest_observing_cameras
from fullview.sfm.options import DensifyOptions
from fullview.stages.protocol import StageContext, cpu_seconds, forked

log = logging.getLogger(__name__)


def mesh_params(config: DensifyOptions) -> MeshParams:
    return MeshParams(depth=config.mesh_depth, cell_voxels=config.mesh_cell_voxels, density_quantile=config.mesh_density_quantile,
                      max_distance_voxels=config.mesh_max_distance_voxels,
                      support_tolerance=config.mesh_support_tolerance, window_px=config.mesh_window_px,
                      min_component_triangles=config.mesh_min_component_triangles)


def _mesh_maps(range_maps: dict) -> list[np.ndarray]:
    """The range maps (``{camera index: (range, valid)}``) as the mesh reads them, in camera order: NaN where
    invalid."""
    return [np.where(range_maps[k][1], range_maps[k][0], np.nan) for k in sorted(range_maps)]


def observing_cameras(ctx: StageContext, points: np.ndarray, R_cam_from_world: np.ndarray,
                      t_cam_from_world: np.ndarray, range_maps: dict) -> np.ndarray | None:
    """Each point's nearest observing camera (``sfm.dense.mesh.nearest_observing_cameras``, positions in camera
    order), which turns the mesh's normals, found before the normals are (None: no mesh is made)."""
    config: DensifyOptions = ctx.options
    if not config.mesh or len(points) < 16:
        return None
    cams = sorted(range_maps)
    return nearest_observing_cameras(np.asarray(points, np.float64), R_cam_from_world[cams],
                                     t_cam_from_world[cams], _mesh_maps(range_maps),
                                     tolerance=config.mesh_support_tolerance, window_px=config.mesh_window_px)


def write_dense_mesh(ctx: StageContext, points: np.ndarray, colors: np.ndarray, normals: np.ndarray,
                     R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray, range_maps: dict,
                     voxel_size: float, observers: np.ndarray | None = None) -> dict | None:
    """Mesh the fused cloud, trim it by the range maps (``{camera index: (range, valid)}``), save it through the
    stage writer and return its summary figures (None when ``densify.mesh`` is off or the cloud is too small; the
    reason when meshing fails). ``observers``: each point's ``observing_cameras``, when already found."""
    config: DensifyOptions = ctx.options
    if not config.mesh:
        return None
    if len(points) < 16:
        log.warning("densify: no mesh, the fused cloud has %d points", len(points))
        return None
    t0, cpu0 = time.perf_counter(), cpu_seconds()
    cams = sorted(range_maps)
    maps = _mesh_maps(range_maps)
    try:
        # Poisson in a child process: open3d holds the GIL for its 1-2 s, and the stage's side thread has the
        # cloud's preview and the maps to write meanwhile (and this thread the trims' nearest-point tree)
        mesh = mesh_from_dense(points, colors, normals, R_cam_from_world[cams], t_cam_from_world[cams], maps,
                               voxel_size=voxel_size, params=mesh_params(config), poisson=forked,
                               observers=observers)
    except ValueError as e:  # a degenerate cloud: the cloud and range maps stand without a mesh
        log.warning("densify: no mesh: %s", e)
        return {"error": str(e)}
    ctx.out.save_dense_mesh(vertices=mesh.vertices, triangles=mesh.triangles, colors=mesh.vertex_colors)
    if config.preview and len(mesh.triangles) >= 3:
        centers = camera_center(R_cam_from_world[cams], t_cam_from_world[cams])
        render_mesh(ctx.out.path("dense_mesh_preview"), mesh.vertices, mesh.triangles, mesh.vertex_colors,
                    up=camera_up(R_cam_from_world[cams]), cameras=centers,
                    title=f"{ctx.dataset.name}: mesh, {len(mesh.triangles)} triangles")
    summary = {**mesh.stats, "time_s": round(time.perf_counter() - t0, 2),
               "cpu_time_s": round(cpu_seconds() - cpu0, 2),  # the wall time depends on the machine's load
               "process_peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}
    log.info("densify: mesh of %d vertices, %d triangles (%.0f%% of Poisson's trimmed) in %.1f s",
             mesh.stats["vertices"], mesh.stats["triangles"], 100 * mesh.stats["trimmed_share"], summary["time_s"])
    return summary
