"""Stage 6 — tracks, multi-view triangulation, filtering and bundle adjustment; npz, PLY and COLMAP text models.

Two rounds: triangulate with the registration's poses and keep tracks under a loose error bound, bundle-adjust
the poses on each image's longest of them, then re-triangulate every track with the refined poses, apply the
configured bounds and bundle-adjust again. Both adjustments hold each image's tilt to its gravity and, where its
lines show one dominant pair of horizontal directions, its heading modulo 90° to its model's wall axis
(`triangulation.gravity_prior`, `manhattan_prior`; `sfm/manhattan.py`), and every camera's height above the floor
points below it to its model's common height, where the models' cameras see their floors and, after the pose
round, agree on one height (a tripod tour; `triangulation.height_prior`; `sfm/heights.py`). Blocks of cameras that no track joins to
the rest (rooms meeting at one doorway camera) are then put at the root block's camera height above the floor, or
one median pair baseline where a floor is not seen (`triangulation.free_block_min_pairs`, `free_block_scale`): the
adjustment's cost is the same for any scale of such a block, so it kept registration's guesses.
Every model of the registration is adjusted in its own frame (one problem, its first camera fixed per model: tracks
never span two models, since only pairs inside one model are consistent) and written as ``models/<k>/``.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from fullview.io.errors import NothingLeftError
from fullview.io.exports import SparseModel, colmap_text_safe, split_models, write_colmap_model
from fullview.sfm import heights, manhattan
from fullview.sfm.bundle import bundle_adjust, gravity_error_factor, gravity_prior_for_models, with_gravity_error
from fullview.sfm.registration.free_blocks import camera_heights, camera_links, free_block_similarities
from fullview.sfm.tracks import Tracks, build_tracks
from fullview.sfm.options import TriangulationOptions
from fullview.sfm.triangulation import (filter_tracks, gather_bearings, longest_tracks_per_image,
                                        triangulate_multiview)
from fullview.stages.geometry_pairs import geometry_matches
from fullview.stages.protocol import StageContext
from fullview.stages.registration import track_matches

log = logging.getLogger(__name__)

VERSION = 2
UPSTREAM = ("registration",)
INPUTS: tuple[str, ...] = ()
LOOSE_FACTOR = 4.0  # first round keeps tracks up to this multiple of the final error bound
# The first round only refines the poses (every track is re-triangulated after it): each image's longest tracks
# suffice. On the 24-view room 1,500 per image (17% of the points) give the rotations of the full adjustment within
# 0.002° (median) for a third of its time.
POSE_ROUND_TRACKS_PER_IMAGE = 1500
# The first round's poses only decide which tracks pass the final error bound (and start the final adjustment, which
# refines them again): it stops once a reweighting round moves no camera's bearings by more than this share of the
# bound, instead of running to the cost tolerance.
POSE_ROUND_TOLERANCE = 0.01


def run(ctx: StageContext) -> dict:
    config: TriangulationOptions = ctx.options
    obs = ctx.ws.load_observations(ctx.dataset)
    reg = ctx.ws.load_registration()
    placed_in = reg["model_id"]
    # Approximate cameras (placed by a join nothing confirms, docs/trust.md) are adjusted as a group of their own:
    # no track ties them to their model's verified cameras, so nothing they hold moves those.
    model_id = np.where(ctx.ws.verified_mask() | (placed_in < 0), placed_in, placed_in.max(initial=0) + 1 + placed_in)
    verified = ctx.ws.load_inliers()
    # 2D-3D matches and the weak pairs' inliers join the verified pairs' (workspaces older than either lack them)
    extra_rows = [rows for rows in (reg.get("matches_2d3d"), reg.get("weak_pair_matches")) if rows is not None]
    matches = track_matches(ctx.dataset, verified, obs, reg["pair_inlier_mask"],
                            np.concatenate(extra_rows) if extra_rows else None)
    bearings = [o["bearings"] for o in obs]
    R, t = reg["R_cam_from_world"], reg["t_cam_from_world"]
    max_err = np.radians(config.max_reprojection_error_deg)
    extra = geometry_matches(ctx, verified.pairs, model_id, R, t, bearings, neighbours=config.geometry_neighbours,
                             threshold_rad=max_err, min_inliers=config.geometry_min_inliers)
    tracks, _ = build_tracks({p: m for p, m in {**matches, **extra}.items() if model_id[p[0]] == model_id[p[1]] >= 0},
                             [len(o["bearings"]) for o in obs])
    min_angle = np.radians(config.min_triangulation_angle_deg)

    # The filter's gravity per image (absent from workspaces it wrote before it stored them: no prior).
    measured = (verified.extra.get("gravity"), verified.extra.get("gravity_std_rad"))
    measured = measured if measured[0] is not None and measured[1] is not None else None
    headings = (_manhattan_axes(verified.extra, measured, model_id) if config.manhattan_prior and measured is not None
                else None)
    # Where an image's Manhattan frame is found, its gravity is the frame's, fitted on the horizontal lines too.
    refined = measured if headings is None else (headings[2], headings[3])
    gravity = refined if config.gravity_prior else None
    keep = _triangulate_and_filter(tracks, bearings, R, t, LOOSE_FACTOR * max_err, min_angle)
    tracks_kept, points = tracks.subset(keep[0]), keep[1]
    if config.bundle_adjust and tracks_kept.num_tracks:
        pose_tracks = longest_tracks_per_image(tracks_kept, POSE_ROUND_TRACKS_PER_IMAGE)
        pose_set = tracks_kept.subset(pose_tracks)
        floor = _height_prior(pose_set, R, t, points[pose_tracks], model_id, measured, config)
        R, t, _, _ = _bundle(pose_set, bearings, R, t, points[pose_tracks], model_id, config,
                             gravity, pose_tolerance_rad=POSE_ROUND_TOLERANCE * max_err, headings=headings,
                             height=floor)
    mask, points = _triangulate_and_filter(tracks, bearings, R, t, max_err, min_angle)
    final = tracks.subset(mask)
    if tracks.num_tracks and not final.num_tracks:  # no model to write; densify and the exports need points
        raise NothingLeftError(f"triangulation: no point survives triangulation.min_triangulation_angle_deg="
                               f"{config.min_triangulation_angle_deg:g} and max_reprojection_error_deg="
                               f"{config.max_reprojection_error_deg:g} (of {tracks.num_tracks} tracks)")
    if config.bundle_adjust and final.num_tracks:
        floor = _height_prior(final, R, t, points, model_id, measured, config, check=tracks_kept.num_tracks > 0)
        R, t, points, errors = _bundle(final, bearings, R, t, points, model_id, config, gravity,
                                       gravity_error=tracks_kept.num_tracks > 0, headings=headings, height=floor)
        # The last adjustment moved the points: drop the few tracks it left beyond the bound, so the stored
        # errors describe the stored points.
        worst = np.full(final.num_tracks, 0.0)
        np.maximum.at(worst, final.track_ids, errors)
        good = worst <= max_err
        final, points, errors = final.subset(good), points[good], errors[good[final.track_ids]]
        if config.free_block_min_pairs:
            pairs = np.asarray(verified.pairs, np.int64).reshape(-1, 2)[reg["pair_inlier_mask"]]
            down = _model_down(R, model_id, measured) if config.free_block_scale == "camera_height" else None
            R, t, points = _rescale_free_blocks(final, R, t, points, pairs, config.free_block_min_pairs, down)
    else:  # the errors of the points just triangulated (with an adjustment, its own errors replace them)
        errors = triangulate_multiview(final, bearings, R, t).obs_error_rad
    return _write(ctx, obs, placed_in, R, t, final, points, errors, geometry_pairs=len(extra))


def _manhattan_axes(filtered: dict, gravity, model_id):
    """Each registered image's Manhattan frame, as the filter found it from the lines that gave its gravity: its axis
    (`manhattan.manhattan_axis` about its measured gravity), the axis's standard error (NaN where none: no gravity,
    too few lines, no dominant pair of directions), and its gravity and the gravity's standard error, refined with
    the axis on the vertical and horizontal lines (`manhattan.manhattan_frame`; the measured ones where no axis is
    found). None when no image has an axis (or the filter's artifact predates the frames)."""
    if filtered.get("manhattan_axis_std_rad") is None:
        return None
    g, std = np.array(gravity[0], np.float64), np.array(gravity[1], np.float64)
    measured = (model_id >= 0) & np.isfinite(std) & (np.linalg.norm(g, axis=1) > 0)
    found = measured & np.isfinite(filtered["manhattan_axis_std_rad"])
    axis, sigma = np.full(g.shape, np.nan), np.full(len(g), np.nan)
    axis[found], sigma[found] = filtered["manhattan_axis"][found], filtered["manhattan_axis_std_rad"][found]
    g[found], std[found] = filtered["manhattan_gravity"][found], filtered["manhattan_gravity_std_rad"][found]
    log.info("manhattan: %d of %d images measure a heading from their horizontal lines", found.sum(), measured.sum())
    return (axis, sigma, g, std) if found.any() else None


def _height_prior(tracks: Tracks, R, t, points, model_id, gravity, config, check: bool = False):
    """The camera-height prior of the adjustment's tracks (`heights.height_prior`, the models' down from the
    measured gravities), or None (`triangulation.height_prior` off, no gravity, no model measures its floor). With
    `check` (the poses were adjusted with it once), None too where the adjusted heights still disagree by more than
    `height_prior_max_spread` (not a tripod tour: the prior would bend the model, not straighten it)."""
    sigma, limit = config.height_prior_sigma, config.height_prior_max_spread
    if not config.height_prior or gravity is None or not tracks.num_tracks:
        return None
    down = _model_down(R, model_id, gravity)
    centers = -np.einsum("nba,nb->na", R, t)
    prior = heights.height_prior(centers, down, points, tracks.track_ids, tracks.image_ids, model_id, sigma)
    if prior is None:
        log.info("height prior: no model measures its floor from enough cameras")
        return None
    spread = heights.height_spread(centers, points, prior)
    log.info("height prior: %d cameras measure their height above the floor (%d floor points), spread %.3f",
             len(np.unique(prior.camera)), len(prior.camera), spread)
    if check and spread > limit:
        log.info("height prior: the adjusted heights disagree (spread %.3f > %.3f): none in the final adjustment",
                 spread, limit)
        return None
    return prior


def _model_down(R, model_id, gravity) -> np.ndarray | None:
    """(N, 3) each camera's model's down direction in world coordinates: the mean of its images' measured gravity
    carried to the world (None without gravity; nan rows for a model with none)."""
    if gravity is None:
        return None
    g, std = gravity
    measured = np.isfinite(std) & (np.linalg.norm(g, axis=1) > 0) & (model_id >= 0)
    world = np.einsum("nji,nj->ni", R, g)
    down = np.full((len(R), 3), np.nan)
    for k in np.unique(model_id[measured]):
        mean = world[measured & (model_id == k)].sum(axis=0)
        down[model_id == k] = mean / np.linalg.norm(mean)
    return down


def _rescale_free_blocks(tracks: Tracks, R, t, points, pairs, min_pairs: int, down=None):
    """Blocks of cameras that no track joins put at the root block's median camera height above the floor, or
    where a floor is not seen (or `down` is None) its median verified-pair baseline (`free_blocks`): the adjustment's
    cost is the same for any scale of such a block about its junction camera, so it kept the parts' guesses."""
    centers = -np.einsum("nba,nb->na", R, t)
    heights = None if down is None else camera_heights(centers, down, points, tracks.track_ids, tracks.image_ids)
    scale, shift, depth = free_block_similarities(centers, camera_links(tracks.track_ids, tracks.image_ids), pairs,
                                                  min_pairs, heights)
    if np.all(scale == 1.0):
        return R, t, points
    moved = centers * scale[:, None] + shift
    log.info("blocks no track joins re-scaled to one camera height (%d cameras measure one) or median baseline: "
             "cameras %s, scales %s", 0 if heights is None else int(np.isfinite(heights).sum()),
             np.flatnonzero(scale != 1.0).tolist(), np.round(np.unique(scale[scale != 1.0]), 3).tolist())
    # each track's points move with its deepest camera (the block it lies in)
    order = np.lexsort((depth[tracks.image_ids], tracks.track_ids))
    last = np.r_[tracks.track_ids[order][1:] != tracks.track_ids[order][:-1], True]
    owner = tracks.image_ids[order][last]  # (num_tracks,) in track order
    points = points * scale[owner, None] + shift[owner]
    return R, -np.einsum("nab,nb->na", R, moved), points


def _triangulate_and_filter(tracks: Tracks, bearings, R, t, max_err, min_angle):
    tri = triangulate_multiview(tracks, bearings, R, t)
    mask = filter_tracks(tri, max_error_rad=max_err, min_angle_rad=min_angle)
    return mask, tri.points[mask]


def _bundle(tracks: Tracks, bearings, R, t, points, model_id, config, gravity=None, pose_tolerance_rad=0.0,
            gravity_error=False, headings=None, height=None):
    """Bundle adjustment over the cameras of every model (reindexed), the first camera of each model fixed; with
    `gravity` ((N, 3) gravity per image in its frame, (N,) its standard error), each image's tilt is held to it.
    With `gravity_error` (R already adjusted once: the pose round), the standard errors are first widened by how far
    the gravities lie from that model's up (`bundle.gravity_error_factor`): the stated ones are a lower bound, 1.85×
    too small on 360_Flat (segments of one edge are not independent).

    Returns refined (R, t) of every camera, the points and the final angular error of every observation."""
    cams = np.flatnonzero(model_id >= 0)
    local = np.full(len(model_id), -1)
    local[cams] = np.arange(len(cams))
    prior = None if gravity is None else gravity_prior_for_models(R[cams], gravity[0][cams], gravity[1][cams],
                                                                  model_id[cams])
    if prior is not None and gravity_error:
        factor = gravity_error_factor(R[cams], prior)
        log.info("gravity: measured %.2f stated standard errors (per component) from the adjusted up%s", factor,
                 ", standard errors widened" if factor > 1.0 else "")
        prior = with_gravity_error(prior, factor)
    heading = None if headings is None else manhattan.heading_prior_for_models(
        R[cams], headings[0][cams], headings[2][cams], headings[1][cams], model_id[cams])
    if heading is not None and gravity_error:
        factor = manhattan.heading_error_factor(R[cams], heading)
        log.info("manhattan: headings measured %.2f stated standard errors from the adjusted axes", factor)
        heading = manhattan.with_heading_error(heading, factor)
    # Each model's first camera is held, preferably one with a measured gravity: the prior then decides its tilt.
    held = np.zeros(len(cams), bool) if prior is None else np.isin(np.arange(len(cams)), prior.camera)
    _, first = np.unique(np.stack([model_id[cams], ~held]).T, axis=0, return_index=True)
    _, first_of_model = np.unique(model_id[cams][first], return_index=True)
    first = first[first_of_model]
    obs_camera = local[tracks.image_ids]
    # With a height prior the heights fix each block's scale; the scale gauge is then held on the camera that shares
    # the most tracks with the fixed one. The default, the camera farthest from it, lies blocks away on a walk and
    # ties the gauge to the free length of a doorway that only two-view tracks cross (registration's guess, which
    # nothing else measures), which then takes up every change of the blocks' scales (the held length is then wrong
    # by however much the heights moved the blocks).
    scale_camera = (_best_linked(obs_camera, tracks.track_ids, len(cams), int(first[0]))
                    if height is not None and len(first) == 1 else None)
    local_height = None if height is None else _local_height(height, local)
    bridge_floor = config.bridge_floor  # the bridges' lengths from their floor points (with the height prior)
    result = bundle_adjust(
        R_cam_from_world=R[cams], t_cam_from_world=t[cams], points=points,
        obs_camera=obs_camera, obs_point=tracks.track_ids, scale_camera=scale_camera,
        obs_bearings=gather_bearings(bearings, tracks.image_ids, tracks.feature_ids),
        fixed_cameras=tuple(first.tolist()), loss="soft_l1", loss_scale_rad=np.radians(config.ba_loss_scale_deg),
        max_nfev=config.ba_max_iterations, gravity_prior=prior, pose_tolerance_rad=pose_tolerance_rad,
        heading_prior=heading, height_prior=local_height)
    log.info("bundle adjustment: %d cameras (%d with a gravity prior, %d with a heading prior), %d points, cost "
             "%.4g -> %.4g, median error %.4f deg", len(cams), 0 if prior is None else len(prior.camera),
             0 if heading is None else len(heading.camera), len(points), result.initial_cost,
             result.final_cost, np.degrees(np.median(result.obs_error_rad)))
    R, t = R.copy(), t.copy()
    points = result.points
    if height is not None:  # the bridges: lengths from their floor points, or back where they were (`restore_bridges`)
        before = -np.einsum("nba,nb->na", R[cams], t[cams])
        centers = -np.einsum("nba,nb->na", result.R_cam_from_world, result.t_cam_from_world)
        level, down = (heights.model_levels(centers, points, local_height, model_id[cams]) if bridge_floor
                       else (None, None))
        centers, points, bridges, measured = heights.restore_bridges(
            before, centers, points, tracks.track_ids, obs_camera, first,  # the held cameras stay where they are
            level=level, down=down)
        if bridges:
            log.info("height prior: %d bridges (two cameras only two-view tracks join): %d set by their floor points, "
                     "the rest kept at their lengths", bridges, measured)
        result = dataclasses.replace(result, t_cam_from_world=-np.einsum("nab,nb->na", result.R_cam_from_world,
                                                                        centers))
    R[cams], t[cams] = result.R_cam_from_world, result.t_cam_from_world
    return R, t, points, result.obs_error_rad


def _best_linked(obs_camera, track_ids, num_cameras: int, camera: int) -> int | None:
    """The camera sharing the most tracks with `camera` (None if it shares none)."""
    shared = heights.shared_tracks(track_ids, obs_camera, num_cameras)[camera]
    shared[camera] = 0
    return int(np.argmax(shared)) if shared.max() > 0 else None


def _local_height(prior: heights.HeightPrior, local: np.ndarray) -> heights.HeightPrior:
    """The prior with its cameras renumbered as the adjustment's (registered cameras only)."""
    return dataclasses.replace(prior, camera=local[prior.camera])


def _write(ctx: StageContext, obs, model_id, R, t, tracks: Tracks, points, errors, geometry_pairs: int) -> dict:
    colors = _mean_colors(tracks, obs)
    point_error = np.zeros(len(points))
    np.maximum.at(point_error, tracks.track_ids, errors)
    point_model = model_id[tracks.image_ids[tracks.offsets[:-1]]] if len(points) else np.zeros(0, np.int64)
    names = ctx.dataset.image_names
    lengths = np.diff(tracks.offsets)
    sizes = np.bincount(model_id[model_id >= 0], minlength=int(model_id.max(initial=-1)) + 1)
    summary = {"points": int((point_model == 0).sum()), "registered": int((model_id == 0).sum()), "images": len(names),
               "models": [{"images": int(n), "points": int((point_model == k).sum())} for k, n in enumerate(sizes)],
               "mean_track_length": float(lengths.mean()) if len(lengths) else 0.0,
               "median_error_deg": float(np.degrees(np.median(errors))) if len(errors) else 0.0,
               "geometry_pairs": geometry_pairs}
    ctx.out.save_sparse(points=points, colors=colors, summary=summary, image_names=names, registered=model_id == 0,
                        model_id=model_id, point_model=point_model, R_cam_from_world=R, t_cam_from_world=t,
                        point_error_rad=point_error, track_ids=tracks.track_ids, image_ids=tracks.image_ids,
                        feature_ids=tracks.feature_ids, obs_error_rad=errors)
    whole = SparseModel(image_names=list(names), image_sizes=[tuple(int(v) for v in o["image_size"]) for o in obs],
                        registered=model_id >= 0, R_cam_from_world=R, t_cam_from_world=t, points=points,
                        colors=colors, point_errors_rad=point_error, track_point3d=tracks.track_ids,
                        track_image=tracks.image_ids, track_point2d=tracks.feature_ids,
                        pixels=[o["pixels"] for o in obs])
    # approximate cameras (placed by a join nothing confirms, docs/trust.md) stay out of the COLMAP models; text,
    # COLMAP's readable form, unless a name would not read back from it (then binary: the exact names)
    for k, model in enumerate(split_models(whole, np.where(ctx.ws.verified_mask(), model_id, -1))):
        write_colmap_model(model, ctx.out.path("sparse_model", model=k), binary=not colmap_text_safe(model))
    return summary


def _mean_colors(tracks: Tracks, obs) -> np.ndarray:
    rgb = np.concatenate([o["colors"] for o in obs]).astype(np.float64)
    offsets = np.cumsum([0] + [len(o["colors"]) for o in obs])
    sums = np.zeros((tracks.num_tracks, 3))
    np.add.at(sums, tracks.track_ids, rgb[offsets[tracks.image_ids] + tracks.feature_ids])
    return np.round(sums / np.maximum(np.diff(tracks.offsets), 1)[:, None]).astype(np.uint8)
