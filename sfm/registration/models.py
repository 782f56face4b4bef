"""Every model the verified pairs support: global registration per group, growth by resection, merging.

1. **Global models.** ``register`` (rotation and translation averaging) places the largest group of images joined
   by usable pairs as a model, which then grows (step 2); the next model starts from the largest group of the
   images still outside, until no group of two images or more remains. Each model has its own gauge (its first
   image at R = I, centre 0).
2. **Growth.** A model takes the images outside every model that it can hold: a camera tied by a
   single pair is attached along that pair's baseline (``attach_cameras``); an image that sees enough of the
   model's points is placed by resection (P3P on bearings inside LO-RANSAC, refined on its inliers; see
   ``fullview.sfm.resection``). After each round the model is bundle-adjusted and its points re-triangulated, so the
   next round sees the points the new cameras add; growth stops when no image can be added.
3. **Merging.** Two models whose tracks triangulate in both are merged into the larger one by the similarity those
   points agree on (3-point Umeyama samples in RANSAC; a point agrees when, carried into the larger model, it
   reprojects within the threshold in every camera of that model that observes it), then the merged model grows
   again.

4. **Evidence.** Every placement is recorded (`ModelSet.own`: how each camera was placed in its model;
   `ModelSet.join_records`: each join that carried cameras into another model and what confirmed it; see
   `evidence`). A join nothing confirms (a guessed scale or length) is never made while cameras can still be placed
   by evidence; with `registration.unconfirmed_joins: approximate` such joins are made last, their cameras marked
   approximate (`ModelSet.approximate`), and nothing grows from them.

Models are numbered by size, largest first (ties: lowest image id). Pure geometry: no file access.
"""

from __future__ import annotations

import logging
from functools import partial
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from fullview.sfm.attach import attach_cameras, model_points
from fullview.sfm.heights import (BRIDGE_FLOOR_AGREEMENT, BRIDGE_MIN_FLOOR_POINTS, MAX_NEIGHBOUR_DEVIATION,
                                  MIN_SHARE)
from fullview.sfm.registration.free_blocks import camera_heights, floor_clusters
from fullview.sfm.bundle import bundle_adjust
from fullview.sfm.metrics import umeyama
from fullview.sfm.options import MatchesOptions, RegistrationOptions
from fullview.sfm.registration.driver import register
from fullview.sfm.registration.placement_check import contradicted, join_conflicts
from fullview.sfm.registration.rematch_join import ModelPoints, join_by_rematching
from fullview.sfm.registration.rigid_parts import estimate_join, rigid_parts
from fullview.sfm.registration.view_graph import bridges, component_labels, largest_component
from fullview.sfm.registration.weak_joins import (MAX_ROTATION_DISAGREEMENT_DEG, MIN_AGREEING_PAIRS, MIN_PAIR_INLIERS,
                                                  CrossPair, _place, guessed_scale, join_by_weak_pairs)
from fullview.sfm.resection import ResectionOptions, resect
from fullview.sfm.matching import match_descriptors
from fullview.sfm.rotations import angle_between_deg, rotation_angle_deg
from fullview.sfm.two_view import baseline_given_rotation
from fullview.sfm.tracks import Tracks, add_observations
from fullview.sfm.triangulation import angular_errors, gather_bearings, triangulate_multiview

log = logging.getLogger(__name__)

POINT_ERROR_DEG = 1.0  # model points used for resection and merging: angular error bound before bundle adjustment
MIN_POINT_ANGLE_DEG = 1.0  # ... and smallest triangulation angle
MERGE_POINT_ERROR_DEG = 3.0  # common points of two models: hand points, clicked a few pixels off, must count
MERGE_ITERATIONS = 500  # RANSAC samples of the similarity between two models
MERGE_START_FACTOR = 5.0  # common points agreeing with a candidate similarity: this many resection thresholds
WEAK_PAIR_MAX_OFF_DEG = 5.0  # a weak pair's baseline must lie this close to its model's: on the bare 1024 px homes
# (seeds 0, 1, 3, 4) the true ones lie within 3.2° (a part's guessed scale), the chance fits 4.5-8.6° off
WEAK_PAIR_MAX_SHIFT = 0.25  # ... and its far camera within this many of the model's median used-pair baselines of
# that direction: a guessed scale misplaces a camera by a share of its part's extent, whatever the pair's length, so
# a long pair's few degrees are a shift no guess explains (11 bare homes: the true ones within 0.15, 2.88-4.33
# baselines long; a chance fit between rooms 11.7 baselines apart, 2.43° off, shifted 0.50 and shrank a room 14x)
GROWTH_BA_ITERATIONS = 30  # function evaluations of the bundle adjustment after each growth round


@dataclass(kw_only=True)
class PairLinks:
    """The relative poses of the image pairs, as registration takes them."""

    pairs: np.ndarray  # (P, 2) image indices
    R_j_from_i: np.ndarray  # (P, 3, 3)
    t_j_from_i: np.ndarray  # (P, 3)
    weights: np.ndarray  # (P,) inlier counts, 0 for pairs that must not be used (below registration.min_inliers
    # and not verified by hand points)
    e_i: np.ndarray | None = None  # (P, 3) epipoles in image i (signs aligned with t), optional
    e_j: np.ndarray | None = None  # (P, 3) epipoles in image j, optional


@dataclass(frozen=True)
class JoinRules:
    """How the rigid parts of an averaged layout are joined (from `RegistrationOptions`)."""

    min_tracks: int  # tracks that must agree on a part's scale


@dataclass(kw_only=True)
class ModelSet:
    model_id: np.ndarray  # (N,) model of each image, -1 for none; model 0 is the largest
    R_cam_from_world: np.ndarray  # (N, 3, 3) rotation in its model's frame; identity outside every model
    centers: np.ndarray  # (N, 3) centre in its model's frame; 0 outside every model
    averaged_in: np.ndarray  # (N,) the global model that placed the image by averaging (-1: grown or none)
    averaging_verdict: np.ndarray  # (P,) averaging's own judgement of pairs inside one of its models
    rejected_pairs: np.ndarray  # (P,) pairs averaging rejected (both ends placed) or into a contradicted bridge's side
    epipole_cost: float  # the report's epipole cost summed over the global models
    attached: list[int] = field(default_factory=list)  # images attached along a single pair's baseline
    resected: list[int] = field(default_factory=list)  # images placed by resection
    merges: list[dict] = field(default_factory=list)  # {"images": [...], "points": n}: models merged into another
    joins: list[dict] = field(default_factory=list)  # {"images": [...], "tracks": n, "scale": s}: rigid parts of an
    # averaged layout joined to its largest part by points
    scale_free: list[int] = field(default_factory=list)  # images of rigid parts no points could join (placed again)
    matched: list[int] = field(default_factory=list)  # images placed by 2D-3D matching of their descriptors
    matches_2d3d: list[tuple[int, int, int, int]] = field(default_factory=list)  # (image, feature, image, feature):
    # each feature matched 2D-3D to a model point, with one model observation of that point (a match for the tracks)
    weak_pair_matches: list[tuple[int, int, int, int]] = field(default_factory=list)  # (image, feature, image,
    # feature): the inlier matches of the weak pairs that fit their model (for the final tracks)
    tracks: Tracks | None = None  # the tracks, with the observations 2D-3D matching added
    own: dict[int, dict] = field(default_factory=dict)  # image -> how it was placed in its model ({"how": ..., the
    # evidence}); joins that carried it into another model are in join_records
    join_records: list[dict] = field(default_factory=list)  # {"kind", "images", "confirmed", "scale": "measured" |
    # "guessed", "evidence": {...}}: every join of cameras into a model, in order
    approximate: np.ndarray | None = None  # (N,) cameras placed by an unconfirmed join (unconfirmed_joins:
    # approximate), or grown from one

    @property
    def num_models(self) -> int:
        return int(self.model_id.max(initial=-1)) + 1

    def sizes(self) -> list[int]:
        return np.bincount(self.model_id[self.model_id >= 0], minlength=self.num_models).tolist()

    def sizes_of(self, images: np.ndarray) -> np.ndarray:
        """(len(images),) the size of each image's model."""
        return np.array(self.sizes(), int)[self.model_id[images]] if len(images) else np.zeros(0, int)


def build_models(*, links: PairLinks, tracks: Tracks, bearings: Sequence[np.ndarray], options: RegistrationOptions,
                 descriptors: Sequence[np.ndarray] | None = None,
                 pair_matches: dict[tuple[int, int], np.ndarray] | None = None,
                 gravity: np.ndarray | None = None, weak_join_threshold_rad: float | None = None,
                 wall_axes: np.ndarray | None = None) -> ModelSet:
    """Global models, grown by attachment and resection, merged where they overlap (see the module doc).

    ``descriptors`` (per image, (F_i, D) for its first F_i features, L2-normalised), when given, let growth place an
    image no track ties to a model by matching them to the model's points (2D-3D matching). ``pair_matches``
    ((i, j) -> (M, 2) feature indices: every matched pair's raw matches), when given, let the pairs too weak to
    verify alone give their matches that fit a model (`_weak_pair_matches`) to the final tracks; with ``gravity``
    ((N, 3) per image, zero rows unknown) and ``weak_join_threshold_rad`` (the filter's inlier threshold) too, two
    models are joined where several such pairs between them agree (`weak_joins`); ``wall_axes`` ((N, 3) each image's
    Manhattan axis, zero rows unknown) give the one-pair join its seeds from the walls (`rematch_join`)."""
    state = _empty_state(len(bearings), len(links.pairs))
    state.tracks = tracks
    open_pairs = links.weights > 0
    rules = JoinRules(min_tracks=options.min_join_points)
    while (m := _next_global_model(state, open_pairs, links, state.tracks, bearings, options, rules,
                                   descriptors)) is not None:
        if any(j["model"] == m for j in state.joins):
            _adjust_model(state, m, state.tracks, bearings, options)
        # grow before the next model starts, so images a model can hold never start tiny models of their own
        _grow(state, m, links, bearings, options, descriptors)
    merge_points = options.min_merge_points if options.merge_models else None

    def by_evidence() -> None:
        """Merges by shared points and joins along verified pairs, until none is left; then the single images
        verified pairs tie to a model (a leaf past a doorway), joined where the floor measures the length."""
        while (merge_points is not None and _merge_once(state, links, bearings, options, merge_points, descriptors)) \
                or _join_along_verified_pairs(state, links, bearings, options, descriptors, gravity=gravity):
            pass
        _join_single_images(state, links, bearings, options, descriptors, gravity=gravity)

    by_evidence()
    if options.resection and descriptors is not None:
        while _absorb_a_model_by_matching(state, links, bearings, options, descriptors):
            pass
    if (options.join_by_weak_pairs and pair_matches is not None and gravity is not None
            and weak_join_threshold_rad is not None):
        guided, rematch = options.weak_join_guided, options.weak_join_rematch
        one_pair, several = options.weak_join_one_pair and rematch, options.weak_join_several and rematch
        weak = partial(_join_once_by_weak_pairs, state, links, pair_matches, bearings, gravity, weak_join_threshold_rad,
                       options, descriptors, guided, rematch, wall_axes if one_pair else None, one_pair, several,
                       options.join_check)
        while weak():
            by_evidence()  # a weak join may bring verified pairs or shared points between two models
    else:
        weak = None
    if options.unconfirmed_joins == "approximate":
        # last, and nothing grows from them: along verified pairs between two models (an image in none is a model
        # of one here), else by a weak join whose scale is a guess (one rematched pair alone, or pairs touching one
        # camera of a model)
        _join_single_images(state, links, bearings, options, descriptors, gravity=gravity, unconfirmed=True,
                            weak=partial(weak, unconfirmed=True, guess=rematch) if weak is not None else None)
    _renumber(state)
    if pair_matches is not None and options.min_weak_pair_inliers:
        joined = set(state.weak_pair_matches)  # the weak joins' matches, if any: not added twice
        state.weak_pair_matches += [row for row in _weak_pair_matches(state, links, pair_matches, bearings, options)
                                    if row not in joined]
    log.info("models: sizes %s; %d attached, %d resected, %d merge(s)", state.sizes(), len(state.attached),
             len(state.resected), len(state.merges))
    return state


# --------------------------------------------------------------------------------------------- global models
def _empty_state(num_images: int, num_pairs: int) -> ModelSet:
    return ModelSet(model_id=np.full(num_images, -1), R_cam_from_world=np.tile(np.eye(3), (num_images, 1, 1)),
                    centers=np.zeros((num_images, 3)), averaged_in=np.full(num_images, -1),
                    averaging_verdict=np.zeros(num_pairs, bool), rejected_pairs=np.zeros(num_pairs, bool),
                    epipole_cost=0.0, approximate=np.zeros(num_images, bool))


def _next_global_model(state: ModelSet, open_pairs: np.ndarray, links: PairLinks, tracks: Tracks, bearings,
                       options: RegistrationOptions, rules: JoinRules, descriptors=None) -> int | None:
    """Register the largest group of free images joined by open pairs as a new model; its id, or None when no group
    of two images or more can be registered. Spends the group's pairs (`open_pairs` is updated in place), except
    those among images averaging left out, which may still form a model of their own."""
    pairs, w, num_images = links.pairs, links.weights, len(state.model_id)
    while True:
        free = state.model_id < 0
        active = open_pairs & free[pairs].all(axis=1)
        group = largest_component(num_images, pairs, active, w)
        if len(group) < 2:
            return None
        inside = np.zeros(num_images, bool)
        inside[group] = True
        in_group = active & inside[pairs].all(axis=1)
        reg = register(num_images=num_images, pairs=pairs, R_j_from_i=links.R_j_from_i, t_j_from_i=links.t_j_from_i,
                       weights=np.where(in_group, w, 0.0), model=options.model, e_ij=links.e_i, e_ji=links.e_j,
                       min_weight=0.0, max_rotation_residual_deg=options.max_rotation_residual_deg,
                       max_direction_residual_deg=options.max_direction_residual_deg)
        open_pairs &= ~in_group
        m = state.num_models
        if reg.num_registered < 2:
            # Averaging cannot place a group it cannot scale (a chain of single pairs): start from its strongest
            # pair at unit baseline and let growth attach the rest by points.
            _seed_from_pair(state, m, int(np.argmax(np.where(in_group, w, -np.inf))), links)
            return m
        contradicted = _behind_contradicted_bridges(reg, in_group, pairs, num_images)
        # pairs no guess may follow: those averaging placed both ends of and rejected, and those into a side
        # behind a contradicted bridge (it needs points)
        state.rejected_pairs |= in_group & ((reg.registered[pairs].all(axis=1) & ~reg.pair_inlier_mask)
                                            | contradicted[pairs].any(axis=1))
        placed = reg.registered & ~contradicted
        averaged, centers = placed, reg.centers
        if reg.flexible_modes > 0:
            # A bridge leaves the scale behind it free, so the side a contradicted bridge holds is a rigid part of
            # its own: points may still confirm it (they do not fit a wrong bridge's pose), a guess may not.
            averaged, placed, centers = _join_rigid_parts(state, m, reg, reg.registered, pairs, tracks, bearings,
                                                          options, rules, descriptors, needs_points=contradicted)
        open_pairs |= in_group & (inside & ~placed)[pairs].all(axis=1)
        state.model_id[placed] = m
        state.averaged_in[averaged] = m  # joined parts: their pairs to the rest are judged by residuals
        for k in np.flatnonzero(placed):
            state.own[int(k)] = {"how": "averaging"}
        state.R_cam_from_world[placed] = reg.R_cam_from_world[placed]
        state.centers[placed] = centers[placed]
        state.averaging_verdict |= reg.pair_inlier_mask
        state.epipole_cost += reg.epipole_cost
        return m


def _weak_pair_matches(state: ModelSet, links: PairLinks, pair_matches: dict[tuple[int, int], np.ndarray], bearings,
                       options: RegistrationOptions) -> list[tuple[int, int, int, int]]:
    """Inlier matches (image, feature, image, feature) of the pairs too weak to use (unverified, or below
    `min_inliers`) that touch an approximate part (its scale guessed: `unconfirmed_joins: approximate`), where their
    raw matches, under the model's rotations, give a baseline on `min_weak_pair_inliers` inliers
    within `WEAK_PAIR_MAX_OFF_DEG` of the model's and whose far camera that direction moves sideways by at most
    `WEAK_PAIR_MAX_SHIFT` of the model's median used-pair baseline (on a long pair a few degrees are a shift no
    guessed scale explains, and its tracks alone may then set a room's scale in the bundle adjustment).

    Across a doorway a pair holds ten true matches among thirty or forty, which no 3- or 5-unknown fit tells from
    chance; once the model's rotations are known the baseline has two unknowns, and the model's own direction (off
    by a few degrees where a part's scale is guessed) rules out the chance fits. Their matches join the final
    tracks, so the bundle adjustment sees the relative yaw and scale of the rooms that nothing else ties. Where
    points placed a part they are not added: there they only add looser matches (measured: bare 2048 px seed 1
    loses 1 point of AUC@5 with them)."""
    R, C, model_id = state.R_cam_from_world, state.centers, state.model_id
    threshold = np.radians(options.resection_threshold_deg)
    guessed = state.approximate
    i_all, j_all = links.pairs[:, 0], links.pairs[:, 1]
    candidates = ((links.weights <= 0) & (guessed[i_all] | guessed[j_all]) & (model_id[i_all] == model_id[j_all])
                  & (model_id[i_all] >= 0))
    step = _model_steps(C, model_id, links.pairs[links.weights > 0])
    rows, added = [], []
    for k in np.flatnonzero(candidates):
        i, j = int(i_all[k]), int(j_all[k])
        m = pair_matches.get((i, j))
        if m is None or len(m) < options.min_weak_pair_inliers:
            continue
        R_ji = R[j] @ R[i].T
        t, inliers = baseline_given_rotation(bearings[i][m[:, 0]], bearings[j][m[:, 1]], R_ji, threshold,
                                             seed=options.seed + int(k))
        off = float(angle_between_deg(t, R[j] @ (C[i] - C[j])))
        shift = np.linalg.norm(C[i] - C[j]) * np.sin(np.radians(off)) / step[model_id[i]]
        if (inliers.sum() < options.min_weak_pair_inliers or off > WEAK_PAIR_MAX_OFF_DEG
                or shift > WEAK_PAIR_MAX_SHIFT):
            continue
        rows += [(i, int(f), j, int(g)) for f, g in m[inliers]]
        added.append((i, j, int(inliers.sum()), len(m), round(off, 2)))
    if added:
        log.info("%d weak pair(s) fit their model's rotations (i, j, inliers, matches, degrees from the model's "
                 "direction): %s", len(added), added)
    return rows


def _model_steps(C: np.ndarray, model_id: np.ndarray, used_pairs: np.ndarray) -> np.ndarray:
    """(M,) the median length of each model's used pairs (NaN for a model without one: nothing is compared to it)."""
    steps = np.full(int(model_id.max(initial=-1)) + 1, np.nan)
    of = model_id[used_pairs]
    inside = used_pairs[(of[:, 0] == of[:, 1]) & (of[:, 0] >= 0)]
    lengths = np.linalg.norm(C[inside[:, 1]] - C[inside[:, 0]], axis=1)
    for m in np.unique(model_id[inside[:, 0]]):
        steps[m] = np.median(lengths[model_id[inside[:, 0]] == m])
    return steps


def _behind_contradicted_bridges(reg, in_group: np.ndarray, pairs: np.ndarray, num_images: int) -> np.ndarray:
    """(N,) images that averaging placed only through a contradicted bridge: the smaller side of a used pair whose
    removal splits the used graph, when other pairs between the two sides exist and averaging rejected them.

    No cycle passes through a bridge, so nothing checks its relative pose; one contradicted by the other pairs
    between the same two groups is likely the wrong one of them (measured: two rooms joined by mutually
    inconsistent pairs were fused through an arbitrary one of them). An uncontradicted bridge (a doorway pair) is
    kept. The images cut off are placed again by points (attachment, resection, merging), which checks them."""
    used = reg.pair_used_mask.copy()
    cut = np.zeros(num_images, bool)
    while True:
        whole = component_labels(num_images, pairs, used)
        for k in np.flatnonzero(bridges(num_images, pairs, used)):
            labels = component_labels(num_images, pairs, used & (np.arange(len(pairs)) != k))
            a, b = labels[pairs[k]]
            side = labels == (a if (labels == a).sum() < (labels == b).sum() else b)
            inside = whole == whole[pairs[k, 0]]  # the bridge's own component, both sides
            between = in_group & inside[pairs].all(axis=1) & (side[pairs[:, 0]] != side[pairs[:, 1]])
            if (between & ~used).any():
                cut |= side
                used &= ~side[pairs].any(axis=1)
                break
        else:
            return cut


def _join_rigid_parts(state: ModelSet, m: int, reg, placed: np.ndarray, pairs: np.ndarray, tracks: Tracks, bearings,
                      options: RegistrationOptions, rules: JoinRules, descriptors=None,
                      needs_points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split an averaged layout that the directions do not make rigid into its rigid parts and join the parts to
    the largest one by the points they share (`rigid_parts`). Returns (N,) the largest part, (N,) every camera kept
    (the largest part and the parts joined to it) and (N, 3) the centres with the joined parts re-scaled; cameras of
    parts no points join are left out, to be placed again (growth, a model of their own, merging). Cameras in
    `needs_points` (behind a contradicted bridge) are kept only through a join by points, until one such join
    confirms the side."""
    needs_points = np.zeros(len(placed), bool) if needs_points is None else needs_points.copy()
    used = reg.pair_used_mask & placed[pairs].all(axis=1)
    C, R = reg.centers.copy(), reg.R_cam_from_world
    parts = [_mask(len(placed), p) for p in rigid_parts(C, pairs[used])]
    if len(parts) < 2 or (parts[0] & needs_points).any():
        placed = placed & ~needs_points
        return placed, placed, C
    log.info("averaged layout of %d images is not rigid (%d flexible mode(s)): rigid parts of %s images", placed.sum(),
             reg.flexible_modes, [int(p.sum()) for p in parts])
    directions = np.nan_to_num(C[pairs[:, 1]] - C[pairs[:, 0]])
    main, pending, failed = parts[0].copy(), list(range(1, len(parts))), set()
    point_err, point_angle = np.radians(POINT_ERROR_DEG), np.radians(MIN_POINT_ANGLE_DEG)
    while pending:
        new = None
        for k in [k for k in pending if k not in failed and _touches(parts[k], main, pairs[used])]:
            part = parts[k]
            # Only cameras near the join can see what both sides see: bounding the points and the 2D-3D matching
            # to them keeps each attempt's cost independent of the model's size (a 200-view walk has many parts).
            near_main, near_part = _near_cameras(main, part, pairs[used]), _near_cameras(part, main, pairs[used])
            main_points = model_points(tracks, bearings, R, C, near_main, point_err, point_angle)
            part_points = model_points(tracks, bearings, R, C, near_part, point_err, point_angle)
            extra = None if descriptors is None else _matched_cross_observations(
                tracks, bearings, descriptors, R, C, near_main, near_part, main_points, part_points)
            join = estimate_join(R_cam_from_world=R, centers=C, main=main, part=part, main_points=main_points,
                                 part_points=part_points, tracks=tracks, bearings=bearings, pairs=pairs[used],
                                 directions=directions[used], extra=extra,
                                 kept=_averaged_placement(part, main, C, reg.centers, pairs[used]),
                                 threshold_rad=np.radians(options.resection_threshold_deg),
                                 min_tracks=rules.min_tracks, seed=options.seed)
            if join is None:
                failed.add(k)
                continue
            new = part & ~main
            if (new & needs_points).any():
                log.info("points confirm a contradicted bridge: %d image(s) behind it stay", needs_points.sum())
                needs_points[:] = False
            C[new] = join.scale * C[new] + join.shift
            state.joins.append({"model": m, "images": np.flatnonzero(new).tolist(), "tracks": join.num_tracks,
                                "scale": join.scale, "confirmed": join.confirmed})
            _record_join(state, "rigid part by shared points", np.flatnonzero(new), confirmed=True,
                         tracks=join.num_tracks, observations=join.num_observations)
            log.info("joined a rigid part of %d image(s) to model %d: scale %.3f, %d tracks agree (%d cross "
                     "observations)", new.sum(), m, join.scale, join.num_tracks, join.num_observations)
            break
        if new is None:
            break
        main |= new
        pending = [k for k in pending if (parts[k] & ~main).any()]
        failed = {k for k in failed if k in pending and not _touches(parts[k], new, pairs[used])}
    left = placed & ~main
    if left.any():
        state.scale_free += np.flatnonzero(left).tolist()
        log.warning("%d image(s) in rigid parts whose scale to model %d no shared points fix: placed again by points "
                    "or as a model of their own", left.sum(), m)
    return parts[0] & placed, main & placed, C


def _near_cameras(side: np.ndarray, other: np.ndarray, used_pairs: np.ndarray, hops: int = 2) -> np.ndarray:
    """(N,) the cameras of `side` within `hops` used pairs of a camera of `other` (shared cameras included)."""
    reach = other.copy()
    for _ in range(hops):
        step = reach[used_pairs]
        reach[used_pairs[step[:, 0], 1]] = True
        reach[used_pairs[step[:, 1], 0]] = True
    return side & reach


def _touches(part: np.ndarray, cameras: np.ndarray, used_pairs: np.ndarray) -> bool:
    """Whether a part shares a camera with `cameras` (N,) bool or has a used pair into them."""
    return bool((part & cameras).any() or (part[used_pairs] & cameras[used_pairs][:, ::-1]).any())


def _averaged_placement(part: np.ndarray, main: np.ndarray, C: np.ndarray, averaged: np.ndarray, used_pairs
                        ) -> np.ndarray | None:
    """(scale, shift) keeping averaging's placement of a part relative to the main cameras it touches (shared, or
    at the other end of a used pair), as they stand now; None when it touches none."""
    touching = _main_cameras_touched(part, main, used_pairs)
    if not touching.any():
        return None
    return np.concatenate([[1.0], (C[touching] - averaged[touching]).mean(axis=0)])


def _main_cameras_touched(part: np.ndarray, main: np.ndarray, used_pairs: np.ndarray) -> np.ndarray:
    """(N,) the main cameras a part shares or, sharing none, those at the other end of its used pairs into main."""
    touching = part & main
    if not touching.any():
        across = used_pairs[(main[used_pairs] & part[used_pairs][:, ::-1]).any(axis=1)]
        touching[across[main[across]]] = True
    return touching


def _matched_cross_observations(tracks: Tracks, bearings, descriptors, R, C, main, part, main_points, part_points):
    """Cross observations of a join found by 2D-3D matching (tracks only hold the matches of verified pairs): the
    part's own cameras' descriptors against main's points and main's own cameras' against the part's points. Rows
    as `rigid_parts.estimate_join(extra=)` takes them: (world ray, point, camera centre, moved_point, point id)."""
    chunks = []
    for (X, of_track), side, cams, moved in ((main_points, main, part & ~main, False),
                                             (part_points, part, main & ~part, True)):
        if len(X) < 2:
            continue
        point_descriptors, track_of_point = _point_descriptors(tracks, side, of_track, descriptors)
        if not point_descriptors.any():
            continue
        for b in np.flatnonzero(cams):
            matches = match_descriptors(descriptors[b], point_descriptors, MATCHING)
            if not len(matches):
                continue
            u = bearings[b][matches[:, 0]] @ R[b]  # R_bᵀ z: world rays
            chunks.append((u, X[matches[:, 1]], np.tile(C[b], (len(matches), 1)), np.full(len(matches), moved),
                           track_of_point[matches[:, 1]]))
    if not chunks:
        return None
    return tuple(np.concatenate(c) for c in zip(*chunks))


def _mask(n: int, ids: np.ndarray) -> np.ndarray:
    out = np.zeros(n, bool)
    out[ids] = True
    return out


def _seed_from_pair(state: ModelSet, m: int, k: int, links: PairLinks) -> None:
    """Model m from pair k alone: its first image at R = I, centre 0, the second one unit baseline away."""
    i, j = links.pairs[k]
    R, t = links.R_j_from_i[k], links.t_j_from_i[k] / np.linalg.norm(links.t_j_from_i[k])
    state.model_id[[i, j]] = m
    for a, b in ((i, j), (j, i)):
        state.own[int(a)] = {"how": "seed pair", "pair": [int(b), int(links.weights[k])]}
    state.R_cam_from_world[i], state.centers[i] = np.eye(3), np.zeros(3)
    state.R_cam_from_world[j], state.centers[j] = R, -R.T @ t


def _by_size(state: ModelSet) -> list[int]:
    sizes = state.sizes()
    return sorted(range(len(sizes)), key=lambda m: (-sizes[m], m))


def _renumber(state: ModelSet) -> None:
    """Model ids by size, largest first (ties: lowest image id), without gaps."""
    ids = [m for m in range(state.num_models) if (state.model_id == m).any()]
    first = {m: int(np.flatnonzero(state.model_id == m)[0]) for m in ids}
    order = sorted(ids, key=lambda m: (-int((state.model_id == m).sum()), first[m]))
    lookup = np.full(state.num_models + 1, -1)
    lookup[order] = np.arange(len(order))
    state.model_id = lookup[state.model_id]  # -1 indexes the last entry, which stays -1


# --------------------------------------------------------------------------------------------- growth
def _grow(state: ModelSet, m: int, links: PairLinks, bearings, options: RegistrationOptions, descriptors=None) -> None:
    """Attach, then resect, the free images model m can hold (by their tracks, then by 2D-3D matching);
    bundle-adjust after each round of resection."""
    _grow_by_points(state, m, links, bearings, options, descriptors)


def _grow_by_points(state: ModelSet, m: int, links: PairLinks, bearings, options: RegistrationOptions,
                    descriptors=None) -> None:
    tracks = state.tracks
    att = attach_cameras(R_cam_from_world=state.R_cam_from_world, centers=state.centers,
                         registered=state.model_id == m, allowed=state.model_id < 0, pairs=links.pairs,
                         R_j_from_i=links.R_j_from_i, t_j_from_i=links.t_j_from_i, weights=links.weights,
                         tracks=tracks, bearings_per_image=bearings, max_error_rad=np.radians(POINT_ERROR_DEG),
                         min_angle_rad=np.radians(MIN_POINT_ANGLE_DEG))
    state.R_cam_from_world, state.centers = att.R_cam_from_world, att.centers
    state.model_id[att.attached] = m
    state.attached += att.attached
    for k in att.attached:
        state.own[int(k)] = {"how": "attached along a verified pair, its distance by points"}
    if not options.resection:
        return
    while True:
        added = _resect_round(state, m, state.tracks, bearings, options)
        state.resected += added
        if not added and descriptors is not None:
            added = _match_round(state, m, np.flatnonzero(state.model_id < 0), bearings, descriptors, options)
        if not added:
            return
        _adjust_model(state, m, state.tracks, bearings, options)


def _resect_round(state: ModelSet, m: int, tracks: Tracks, bearings, options: RegistrationOptions) -> list[int]:
    """Every free image seeing >= min_resection_points of model m's points, placed if its resection holds."""
    resect_options = ResectionOptions(threshold_rad=np.radians(options.resection_threshold_deg),
                                      min_inliers=options.min_resection_points, seed=options.seed)
    if not (state.model_id < 0).any():  # nothing to place: the model's points are not needed
        return []
    X, point_of_track = _points_of(state, m, tracks, bearings)
    seen = (state.model_id[tracks.image_ids] < 0) & (point_of_track[tracks.track_ids] >= 0)
    counts = np.bincount(tracks.image_ids[seen], minlength=len(state.model_id))
    added = []
    for b in np.argsort(-counts, kind="stable"):
        if counts[b] < options.min_resection_points:
            break
        sel = seen & (tracks.image_ids == b)
        result = resect(gather_bearings(bearings, tracks.image_ids[sel], tracks.feature_ids[sel]),
                        X[point_of_track[tracks.track_ids[sel]]], resect_options)
        if result is None:
            continue
        state.model_id[b] = m
        state.R_cam_from_world[b] = result.R_cam_from_world
        state.centers[b] = -result.R_cam_from_world.T @ result.t_cam_from_world
        state.own[int(b)] = {"how": "resection", "inliers_2d3d": int(result.num_inliers), "points": int(sel.sum())}
        added.append(int(b))
        log.debug("resected image %d into model %d: %d/%d inliers", b, m, result.num_inliers, int(sel.sum()))
    return added


def _points_of(state: ModelSet, m: int, tracks: Tracks, bearings, max_error_deg: float = POINT_ERROR_DEG
               ) -> tuple[np.ndarray, np.ndarray]:
    return model_points(tracks, bearings, state.R_cam_from_world, state.centers, state.model_id == m,
                        np.radians(max_error_deg), np.radians(MIN_POINT_ANGLE_DEG))


def _adjust_model(state: ModelSet, m: int, tracks: Tracks, bearings, options: RegistrationOptions) -> None:
    """Bundle adjustment of model m's cameras and points (its first camera fixed), so new cameras and the points
    they add settle before the next round."""
    X, point_of_track = _points_of(state, m, tracks, bearings)
    cams = np.flatnonzero(state.model_id == m)
    obs = (state.model_id[tracks.image_ids] == m) & (point_of_track[tracks.track_ids] >= 0)
    if len(X) < 3 or not obs.any():
        return
    local = np.full(len(state.model_id), -1)
    local[cams] = np.arange(len(cams))
    R = state.R_cam_from_world[cams]
    t = -np.einsum("nab,nb->na", R, state.centers[cams])
    result = bundle_adjust(R_cam_from_world=R, t_cam_from_world=t, points=X,
                           obs_camera=local[tracks.image_ids[obs]], obs_point=point_of_track[tracks.track_ids[obs]],
                           obs_bearings=gather_bearings(bearings, tracks.image_ids[obs], tracks.feature_ids[obs]),
                           fixed_cameras=(0,), loss="soft_l1", loss_scale_rad=np.radians(0.2),
                           max_nfev=GROWTH_BA_ITERATIONS)
    state.R_cam_from_world[cams] = result.R_cam_from_world
    state.centers[cams] = -np.einsum("nba,nb->na", result.R_cam_from_world, result.t_cam_from_world)


# --------------------------------------------------------------------------------------------- 2D-3D matching
def _match_round(state: ModelSet, m: int, candidates: np.ndarray, bearings, descriptors, options: RegistrationOptions,
                 commit: bool = True) -> list[int]:
    """Images of `candidates` placed into model m by 2D-3D matching, as COLMAP registers its next image: each image's
    descriptors are matched to one descriptor per model point (the mean of its observations'), ratio test and
    mutual check, then resection (P3P LO-RANSAC) on the matches. An image whose tracks reach too few model points
    (one verified pair into the model, whose other end sees little of the rest) is placed this way. With `commit`,
    the placed images join model m and their inlier matches join the tracks."""
    if not len(candidates):  # nothing to place: the model's points and their descriptors are not needed
        return []
    X, point_of_track = _points_of(state, m, state.tracks, bearings)
    if len(X) < options.min_resection_points:
        return []
    point_descriptors, track_of_point = _point_descriptors(state.tracks, state.model_id == m, point_of_track,
                                                           descriptors)
    resect_options = ResectionOptions(threshold_rad=np.radians(options.resection_threshold_deg),
                                      min_inliers=options.min_resection_points, seed=options.seed)
    added = []
    for b in candidates:
        matches = match_descriptors(descriptors[b], point_descriptors, MATCHING)
        if len(matches) < options.min_resection_points:
            continue
        result = resect(bearings[b][matches[:, 0]], X[matches[:, 1]], resect_options)
        if result is None:
            continue
        added.append(int(b))
        state.R_cam_from_world[b] = result.R_cam_from_world
        state.centers[b] = -result.R_cam_from_world.T @ result.t_cam_from_world
        log.info("image %d placed into model %d by 2D-3D matching: %d/%d inliers", b, m, result.num_inliers,
                 len(matches))
        if commit:
            state.model_id[b] = m
            state.own[int(b)] = {"how": "2D-3D matching", "inliers_2d3d": int(result.num_inliers),
                                 "matches": int(len(matches))}
            _add_matches(state, m, b, matches[result.inliers, 0], track_of_point[matches[result.inliers, 1]])
    if commit:
        state.matched += added
    return added


MATCHING = MatchesOptions(ratio=0.8, mutual=True)  # 2D-3D matching: Lowe's ratio and the mutual check


def _point_descriptors(tracks: Tracks, cameras: np.ndarray, point_of_track: np.ndarray, descriptors):
    """(P, D) one L2-normalised descriptor per point (the mean of its SIFT observations' in the (N,) bool
    `cameras`) and (P,) its track."""
    num_sift = np.array(getattr(descriptors, "counts", None) or [len(d) for d in descriptors])
    sel = (cameras[tracks.image_ids] & (point_of_track[tracks.track_ids] >= 0)
           & (tracks.feature_ids < num_sift[tracks.image_ids]))
    rows = point_of_track[tracks.track_ids[sel]]
    width = descriptors[int(np.flatnonzero(num_sift)[0])].shape[1] if num_sift.any() else 128
    sums = np.zeros((len(point_of_track[point_of_track >= 0]), width))
    image_ids, feature_ids = tracks.image_ids[sel], tracks.feature_ids[sel]
    for b in np.unique(image_ids):  # one gather per image
        here = image_ids == b
        target = rows[here]
        if len(np.unique(target)) == len(target):
            # A point meets an image once (the usual case): a buffered add, each row summed in the same order as
            # np.add.at would (image by image), so bitwise the same sums, ~10x faster.
            sums[target] += descriptors[b][feature_ids[here]]
        else:
            np.add.at(sums, target, descriptors[b][feature_ids[here]])
    norms = np.linalg.norm(sums, axis=1, keepdims=True)
    track_of_point = np.empty(len(sums), np.int64)
    track_of_point[point_of_track[point_of_track >= 0]] = np.flatnonzero(point_of_track >= 0)
    return (sums / np.maximum(norms, 1e-12)).astype(np.float32), track_of_point


def _add_matches(state: ModelSet, m: int, b: int, features: np.ndarray, tracks_matched: np.ndarray) -> None:
    """Image b's inlier 2D-3D matches join the tracks (and are recorded with one model observation each)."""
    tracks = state.tracks
    first = {}
    in_model = state.model_id[tracks.image_ids] == m
    for k in np.flatnonzero(in_model & np.isin(tracks.track_ids, tracks_matched)):
        first.setdefault(int(tracks.track_ids[k]), (int(tracks.image_ids[k]), int(tracks.feature_ids[k])))
    state.tracks, taken = add_observations(tracks, tracks_matched, np.full(len(features), b), features)
    state.matches_2d3d += [(int(b), int(f), *first[int(t)]) for f, t, ok in zip(features, tracks_matched, taken) if ok]


def _absorb_a_model_by_matching(state: ModelSet, links: PairLinks, bearings, options: RegistrationOptions,
                                descriptors) -> bool:
    """Move a smaller model into a larger one when 2D-3D matching places its images there (models whose images share
    no track: merging by common points cannot see them): every image of it, or at least two whose poses agree on
    one similarity, which then carries the rest. True if one was moved."""
    order = _by_size(state)
    for a_rank, a in enumerate(order):
        for b in order[a_rank + 1:]:
            images = np.flatnonzero(state.model_id == b)
            if len(images) == 0:
                continue
            saved = (state.R_cam_from_world.copy(), state.centers.copy())
            placed = _match_round(state, a, images, bearings, descriptors, options, commit=False)
            sim = None
            if 2 <= len(placed) < len(images):
                sim = _similarity_of_poses(saved[0][placed], saved[1][placed], state.R_cam_from_world[placed],
                                           state.centers[placed])
            if len(placed) < len(images) and sim is None:
                state.R_cam_from_world, state.centers = saved
                continue
            if sim is not None:
                M, scale, shift = sim
                state.R_cam_from_world[images] = saved[0][images] @ M.T
                state.centers[images] = scale * saved[1][images] @ M.T + shift
            state.model_id[images] = a
            _match_round(state, a, np.array(placed), bearings, descriptors, options)
            state.merges.append({"images": images.tolist(), "points": 0})
            _record_join(state, "2D-3D matching of its images", images, confirmed=True, resected=len(placed))
            log.info("model %d (%d images) moved into model %d by 2D-3D matching of %d of its images", b,
                     len(images), a, len(placed))
            _adjust_model(state, a, state.tracks, bearings, options)
            _grow(state, a, links, bearings, options, descriptors)
            return True
    return False


def _similarity_of_poses(R_b, C_b, R_a, C_a, max_rotation_deg: float = 1.0, max_centre_error: float = 0.05):
    """(M, scale, shift) with x_a = scale M x_b + shift taking camera poses (R_b, C_b) of one frame onto (R_a, C_a)
    of another (two or more cameras), or None when the cameras disagree on it (rotations beyond `max_rotation_deg`,
    centres beyond `max_centre_error` of their spread)."""
    per_camera = np.einsum("kba,kbc->kac", R_a, R_b)  # M = R_aᵀ R_b for each camera
    U, _, Vt = np.linalg.svd(per_camera.sum(axis=0))
    M = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    if rotation_angle_deg(per_camera, np.broadcast_to(M, per_camera.shape)).max() > max_rotation_deg:
        return None
    src = (C_b - C_b.mean(0)) @ M.T
    dst = C_a - C_a.mean(0)
    spread = np.linalg.norm(dst, axis=1).mean()
    if not spread > 0 or not (src * src).sum() > 0:
        return None
    scale = float((src * dst).sum() / (src * src).sum())
    shift = C_a.mean(0) - scale * C_b.mean(0) @ M.T
    if scale <= 0 or np.linalg.norm(scale * C_b @ M.T + shift - C_a, axis=1).max() > max_centre_error * spread:
        return None
    return M, scale, shift


# --------------------------------------------------------------------------------------------- weak joins
def _join_once_by_weak_pairs(state: ModelSet, links: PairLinks, pair_matches: dict[tuple[int, int], np.ndarray],
                             bearings, gravity: np.ndarray, threshold_rad: float, options: RegistrationOptions,
                             descriptors=None, guided: bool = False, rematch: bool = False,
                             wall_axes: np.ndarray | None = None, one_pair: bool = False,
                             several: bool = False, check: bool = False, *, unconfirmed: bool = False,
                             guess: bool = False) -> bool:
    """Join the first pair of models (largest first) that several weak pairs between them agree on
    (`weak_joins.join_by_weak_pairs`; with ``guided``, single fits' rotations guide the other pairs; with
    ``rematch``, pairs rematched along their epipolar circles, `rematch_join`): the smaller
    one moves into the larger by the join's similarity, the agreeing pairs' inlier matches join the final tracks (as
    weak pairs' do), and the model grows again. True if joined.

    A join whose scale is a guess (its pairs touch one camera of a model, or one rematched pair alone: ``guess``) is
    unconfirmed: refused unless ``unconfirmed`` (`unconfirmed_joins: approximate`, after every confirmed join),
    where the moved cameras are marked approximate, their matches stay out of the tracks and nothing grows."""
    order = _by_size(state)
    steps = _model_steps(state.centers, state.model_id, links.pairs[links.weights > 0])
    for a_rank, a in enumerate(order):
        for b in order[a_rank + 1:]:
            cross = _cross_pairs(state.model_id, a, b, pair_matches, bearings)
            if len(cross) < MIN_AGREEING_PAIRS:
                continue
            cams_a, cams_b = np.flatnonzero(state.model_id == a), np.flatnonzero(state.model_id == b)
            step_a, step_b = steps[a], steps[b] if np.isfinite(steps[b]) else steps[a]
            frames = dict(R_a={int(k): state.R_cam_from_world[k] for k in cams_a},
                          C_a={int(k): state.centers[k] for k in cams_a},
                          R_b={int(k): state.R_cam_from_world[k] for k in cams_b},
                          C_b={int(k): state.centers[k] for k in cams_b}, gravity=gravity,
                          threshold_rad=threshold_rad, step_a=float(step_a), step_b=float(step_b), seed=options.seed)
            points = _model_points_pair(state, (a, b), bearings) if one_pair or check else None
            check_placement = (partial(_placement_agrees, points=points, bearings=bearings,
                                       tolerance_rad=2 * threshold_rad,
                                       **{key: frames[key] for key in ("R_a", "C_a", "R_b", "C_b")})
                               if check else (lambda M, placed: True))

            def accept(M, placed, check_placement=check_placement):  # placed: (scale, shift, scale guessed)
                return (unconfirmed or not placed[2]) and check_placement(M, placed)

            rematching = (partial(join_by_rematching, cross=cross, bearings=bearings, descriptors=descriptors,
                                  points=points if one_pair else None, wall_axes=wall_axes if one_pair else None,
                                  several=several, guess=guess, accept=accept,
                                  min_points=options.min_merge_points, **frames)
                          if rematch and descriptors is not None else None)
            join = join_by_weak_pairs(cross=cross, guided=guided, rematch=rematching, accept=accept, **frames)
            if join is None:
                continue
            state.R_cam_from_world[cams_b] = state.R_cam_from_world[cams_b] @ join.M.T
            state.centers[cams_b] = join.scale * state.centers[cams_b] @ join.M.T + join.shift
            state.model_id[cams_b] = a
            state.merges.append({"images": cams_b.tolist(), "points": 0})
            _record_join(state, join.kind, cams_b, confirmed=not join.scale_guessed,
                         pairs=[list(map(int, f)) for f in join.pairs])
            log.info("model %d (%d images) joined to model %d by %d weak pairs (%s; k, l, inliers): %s%s", b,
                     len(cams_b), a, len(join.pairs), join.kind, join.pairs,
                     "; its scale is a guess: approximate" if join.scale_guessed else "")
            if join.scale_guessed:
                state.approximate[cams_b] = True
                return True
            state.weak_pair_matches += join.inlier_matches
            _adjust_model(state, a, state.tracks, bearings, options)
            _grow(state, a, links, bearings, options, descriptors)
            return True
    return False


def _record_join(state: ModelSet, kind: str, images, *, confirmed: bool, **evidence) -> None:
    """A join of `images` into a model: its kind, whether something confirmed it, and its evidence."""
    state.join_records.append({"kind": kind, "images": [int(k) for k in images], "confirmed": bool(confirmed),
                               "scale": "measured" if confirmed else "guessed", "evidence": evidence})


def _join_single_images(state: ModelSet, links: PairLinks, bearings, options: RegistrationOptions, descriptors=None,
                        *, gravity=None, unconfirmed: bool = False, weak=None) -> None:
    """Images in no model that verified pairs tie to one, each a model of one image while
    `_join_along_verified_pairs` (then `weak`, when given) joins what it can (every model, with ``unconfirmed``);
    those still alone are in no model again."""
    alone = _free_images_as_models(state, links)
    if not len(alone) and weak is None and not unconfirmed:
        return
    while _join_along_verified_pairs(state, links, bearings, options, descriptors, unconfirmed=unconfirmed,
                                     gravity=gravity) or (weak is not None and weak()):
        pass
    for k in alone[state.sizes_of(alone) == 1]:  # nothing joined it: in no model again
        state.model_id[k] = -1
        state.own.pop(int(k), None)


def _free_images_as_models(state: ModelSet, links: PairLinks) -> np.ndarray:
    """Each image in no model that a verified pair ties to one becomes a model of one image (identity pose), so
    that `_join_along_verified_pairs` may attach it; their ids."""
    pairs, free = links.pairs, state.model_id < 0
    tied = (links.weights > 0) & ~state.rejected_pairs & (free[pairs[:, 0]] != free[pairs[:, 1]])
    alone = np.unique(pairs[tied][free[pairs[tied]]]).astype(int)
    for k in alone:
        state.model_id[k] = state.num_models
        state.R_cam_from_world[k], state.centers[k] = np.eye(3), np.zeros(3)
        state.own[int(k)] = {"how": "one verified pair"}
    return alone


def _join_along_verified_pairs(state: ModelSet, links: PairLinks, bearings, options: RegistrationOptions,
                               descriptors=None, *, unconfirmed: bool = False, gravity: np.ndarray | None = None
                               ) -> bool:
    """Two models that verified pairs join (never pairs averaging rejected): the smaller moves into the larger by
    the rotation of the strongest pair between them and the placement its cross pairs' baseline rays give
    (`weak_joins._place`, every pair within its 2 degrees). Rays from two or more cameras of each model fix the scale,
    and MIN_AGREEING_PAIRS of them or more check it (two rays are exactly the 4 unknowns): the join is confirmed, the
    model is adjusted and grows again. Rays from one camera of either fix the shape, not
    the size: with ``gravity`` ((N, 3) per image, zero rows unknown) the camera height measures it where both models'
    cameras agree on their height above the floor (a tripod keeps it: `_placement_by_camera_height`), and the floor
    below one pair's two cameras measures that pair's length (`_length_by_floor`); the join is then confirmed.
    Otherwise model a's median baseline sets b's scale (`weak_joins.guessed_scale`), a guess, taken only when
    ``unconfirmed`` (`unconfirmed_joins: approximate`), its cameras marked approximate and nothing grown from them.
    True if a model was moved."""
    pairs, model_id = links.pairs, state.model_id
    i, j = pairs[:, 0], pairs[:, 1]
    across = (links.weights > 0) & ~state.rejected_pairs & (model_id[i] >= 0) & (model_id[j] >= 0) & (
        model_id[i] != model_id[j])
    if not across.any():
        return False
    steps = _model_steps(state.centers, model_id, pairs[links.weights > 0])
    order = _by_size(state)
    R, C = state.R_cam_from_world, state.centers
    for a_rank, a in enumerate(order):
        for b in order[a_rank + 1:]:
            between = np.flatnonzero(across & (np.isin(model_id[i], (a, b)) & np.isin(model_id[j], (a, b))))
            if not len(between):
                continue
            fits = []
            for k in between[np.argsort(-links.weights[between], kind="stable")]:
                Rk, t = links.R_j_from_i[k], links.t_j_from_i[k] / np.linalg.norm(links.t_j_from_i[k])
                b_first = model_id[i[k]] == b  # x_l = R_lk x_kb + s t_lk: t_lk points from C_l to C_kb
                kb, l = (int(i[k]), int(j[k])) if b_first else (int(j[k]), int(i[k]))
                R_lk, t_lk = (Rk, t) if b_first else (Rk.T, -Rk.T @ t)
                pair = CrossPair(k=kb, l=l, b_k=np.zeros((0, 3)), b_l=np.zeros((0, 3)), matches=np.zeros((0, 2), int))
                fits.append((pair, R[l].T @ R_lk @ R[kb], R[l].T @ t_lk, int(links.weights[k])))
            M = fits[0][1]
            agree = [f for f in fits if rotation_angle_deg(f[1], M) <= MAX_ROTATION_DISAGREEMENT_DEG]
            frames = dict(C_a={int(k): C[k] for k in np.flatnonzero(model_id == a)},
                          C_b={int(k): C[k] for k in np.flatnonzero(model_id == b)})
            step_a = float(steps[a])
            step_b = float(steps[b]) if np.isfinite(steps[b]) else step_a
            one_ray = len({f[0].k for f in agree}) < 2 and len({f[0].l for f in agree}) < 2
            placed = None if one_ray else _place(M, agree, frames["C_a"], frames["C_b"], step_a, step_b)
            if placed is not None and len(agree) < MIN_AGREEING_PAIRS:
                placed = placed[0], placed[1], True  # determined, not checked: no better than a guess
            if placed is None:  # one ray fixes no length along it either: model a's median baseline
                agree = fits[:1]
                pair, _, u, _ = agree[0]
                scale = guessed_scale(step_a, step_b)
                placed = scale, C[pair.l] + step_a * u - scale * M @ C[pair.k], True
            heights = None
            if placed[2] and gravity is not None:
                heights = _placement_by_camera_height(state, a, b, agree, M, bearings, gravity)
                if heights is not None:
                    placed, heights = heights
            if placed[2] and not unconfirmed:
                continue
            scale, shift, guessed = placed
            cams_b = np.flatnonzero(model_id == b)
            state.R_cam_from_world[cams_b] = R[cams_b] @ M.T
            state.centers[cams_b] = scale * C[cams_b] @ M.T + shift
            state.model_id[cams_b] = a
            evidence = [[f[0].k, f[0].l, f[3]] for f in agree]
            kind = ("verified pairs, guessed scale" if guessed else "verified pairs, scale by camera height"
                    if heights is not None else "verified pairs")
            _record_join(state, kind, cams_b, confirmed=not guessed, pairs=evidence,
                         **({"camera_height": heights} if heights is not None else {}))
            if guessed:
                state.approximate[cams_b] = True
                log.warning("model %d (%d images) attached to model %d along verified pairs %s at a guessed scale: "
                            "approximate", b, len(cams_b), a, evidence)
                return True
            log.info("model %d (%d images) joined to model %d by verified pairs %s placing both", b, len(cams_b), a,
                     evidence)
            _adjust_model(state, a, state.tracks, bearings, options)
            _grow(state, a, links, bearings, options, descriptors)
            return True
    return False


def _placement_by_camera_height(state: ModelSet, a: int, b: int, agree: list, M: np.ndarray, bearings,
                                gravity: np.ndarray):
    """((scale, shift, False), heights) placing model b by verified pairs' rays (`agree`: (pair, M, u, inliers) with
    the rotation M of b into a) whose scale the camera height measures: a tripod tour keeps one height, and each
    model's cameras see the floor below them in its own units (`free_blocks.camera_heights`), so b's scale is the
    ratio of the models' common heights (`_common_height`). A model of one camera has no size; the pair's length
    along one ray is measured by the floor below its two cameras (`_length_by_floor`). None where a height is not
    measured."""
    H_a = _common_height(state, a, bearings, gravity)
    cams_b = np.flatnonzero(state.model_id == b)
    H_b = _common_height(state, b, bearings, gravity) if len(cams_b) > 1 else None
    if H_a is None or (len(cams_b) > 1 and H_b is None):
        return None
    scale = H_a / H_b if H_b is not None else 1.0
    C = state.centers
    C_a = {int(k): C[k] for k in np.flatnonzero(state.model_id == a)}
    C_b = {int(k): C[k] for k in cams_b}
    if len({f[0].k for f in agree}) > 1 or len({f[0].l for f in agree}) > 1:
        placed = _place(M, agree, C_a, C_b, scale, 1.0)  # the rays fix the shift under the measured scale
        if placed is None:
            return None
        shift = placed[1]
    else:
        pair, _, u, _ = agree[0]
        length = _length_by_floor(state, pair.l, pair.k, M, u, H_a, bearings, _model_down(state, a, gravity))
        if length is None:
            return None
        shift = C[pair.l] + length * u - scale * M @ C[pair.k]
    heights = {"model": round(float(H_a), 4), "joined": None if H_b is None else round(float(H_b), 4)}
    log.info("model %d joined to model %d at the scale its camera height measures (%.4f against %s)", b, a, H_a,
             "one camera" if H_b is None else f"{H_b:.4f}")
    return (float(scale), shift, False), heights


def _model_down(state: ModelSet, m: int, gravity: np.ndarray) -> np.ndarray | None:
    """Model m's down direction (world), the mean of its cameras' measured gravity carried to the world."""
    cams = np.flatnonzero((state.model_id == m) & (np.linalg.norm(gravity, axis=1) > 0))
    if not len(cams):
        return None
    mean = np.einsum("nji,nj->i", state.R_cam_from_world[cams], gravity[cams])
    return mean / np.linalg.norm(mean)


def _common_height(state: ModelSet, m: int, bearings, gravity: np.ndarray) -> float | None:
    """Model m's cameras' common height above their floor points (its units): the median of the cameras that
    measure one and agree with it within `heights.MAX_NEIGHBOUR_DEVIATION` (furniture tops sit 20-50% higher),
    two cameras or more and `heights.MIN_SHARE` of those that measure; None otherwise."""
    down = _model_down(state, m, gravity)
    if down is None:
        return None
    X, point_of_track = _points_of(state, m, state.tracks, bearings)
    tracks = state.tracks
    sel = (state.model_id[tracks.image_ids] == m) & (point_of_track[tracks.track_ids] >= 0)
    if not sel.any():
        return None
    h = camera_heights(state.centers, np.broadcast_to(down, state.centers.shape), X,
                       point_of_track[tracks.track_ids[sel]], tracks.image_ids[sel])
    h = h[(state.model_id == m) & np.isfinite(h) & (h > 0)]
    if len(h) < 2:
        return None
    level = float(np.median(h))
    agreeing = np.abs(np.log(h / level)) <= MAX_NEIGHBOUR_DEVIATION
    if agreeing.sum() < max(2, MIN_SHARE * len(h)):
        return None
    return float(np.median(h[agreeing]))


def _length_by_floor(state: ModelSet, l: int, k: int, M: np.ndarray, u: np.ndarray, level: float, bearings,
                     down: np.ndarray | None) -> float | None:
    """The length of the verified pair from camera l (model a) to camera k (model b, rotated by M) along u that puts
    the floor its own tracks show below both cameras at model a's camera height `level` (the triangulation's bridge
    rule, `heights.bridge_floor_scale`): the pair's tracks triangulated at unit length, their farthest-down cluster
    below each camera (BRIDGE_MIN_FLOOR_POINTS), both depths agreeing within BRIDGE_FLOOR_AGREEMENT. None without."""
    if down is None:
        return None
    tracks = state.tracks
    on_l, on_k = tracks.image_ids == l, tracks.image_ids == k
    common, at_l, at_k = np.intersect1d(tracks.track_ids[on_l], tracks.track_ids[on_k], return_indices=True)
    if len(common) < BRIDGE_MIN_FLOOR_POINTS:
        return None
    z_l = bearings[l][tracks.feature_ids[on_l][at_l]] @ state.R_cam_from_world[l]  # world rays
    z_k = bearings[k][tracks.feature_ids[on_k][at_k]] @ (state.R_cam_from_world[k] @ M.T)
    C_l, C_k = state.centers[l], state.centers[l] + u
    # closest points of the two rays: C_l + s z_l = C_k + t z_k (least squares in s, t)
    w = C_k - C_l
    A11, A12, A22 = (z_l * z_l).sum(1), -(z_l * z_k).sum(1), (z_k * z_k).sum(1)
    r1, r2 = z_l @ w, -(z_k @ w)
    det = A11 * A22 - A12 * A12
    ok = np.abs(det) > 1e-9
    s_l = np.where(ok, (r1 * A22 - A12 * r2) / np.where(ok, det, 1.0), -1.0)
    t_k = np.where(ok, (A11 * r2 - A12 * r1) / np.where(ok, det, 1.0), -1.0)
    front = (s_l > 0) & (t_k > 0)
    if front.sum() < BRIDGE_MIN_FLOOR_POINTS:
        return None
    X = 0.5 * (C_l + s_l[front, None] * z_l[front] + C_k + t_k[front, None] * z_k[front])
    n = len(X)
    _, _, h = floor_clusters(np.stack([C_l, C_k]), np.stack([down, down]), X, np.r_[np.arange(n), np.arange(n)],
                             np.repeat([0, 1], n), min_points=BRIDGE_MIN_FLOOR_POINTS)
    if not (np.isfinite(h).all() and (h > 0).all() and abs(np.log(h[0] / h[1])) <= BRIDGE_FLOOR_AGREEMENT):
        return None
    return float(level / np.mean(h))


def _placement_agrees(M: np.ndarray, placed: tuple, *, points: tuple[ModelPoints, ModelPoints], bearings,
                      tolerance_rad: float, **frames) -> bool:
    """False when the join (M, (scale, shift, guessed)) puts one model's points in front of what the other's
    cameras saw (`placement_check`)."""
    found, overlaps = join_conflicts(*points, bearings=bearings, M=M, scale=placed[0], shift=placed[1],
                                     tolerance_rad=tolerance_rad, **frames)
    rejected = contradicted(found, overlaps)
    log.info("join check: %d of %d points on the other model's observed rays are in front of what they saw%s",
             found, overlaps, ": the join is undone" if rejected else "")
    return not rejected


def _model_points_pair(state: ModelSet, models: tuple[int, int], bearings) -> tuple[ModelPoints, ModelPoints]:
    """Models' points in their frames, with the row of each feature of their images (`rematch_join.ModelPoints`)."""
    tracks, out = state.tracks, []
    for m in models:
        X, point_of_track = _points_of(state, m, tracks, bearings)
        rows = point_of_track[tracks.track_ids]
        seen = (state.model_id[tracks.image_ids] == m) & (rows >= 0)
        of_feature = {}
        for k in np.flatnonzero(state.model_id == m):
            here = seen & (tracks.image_ids == k)
            of_feature[int(k)] = np.full(len(bearings[k]), -1)
            of_feature[int(k)][tracks.feature_ids[here]] = rows[here]
        out.append(ModelPoints(X=X, point_of_feature=of_feature))
    return out[0], out[1]


def _cross_pairs(model_id: np.ndarray, a: int, b: int, pair_matches: dict[tuple[int, int], np.ndarray],
                 bearings) -> list[CrossPair]:
    """The raw-matched pairs between a camera k of model b and a camera l of model a, as (k, l) pairs."""
    out = []
    for (i, j), m in pair_matches.items():
        if len(m) < MIN_PAIR_INLIERS or {model_id[i], model_id[j]} != {a, b}:
            continue
        k, l, mk = (i, j, m) if model_id[i] == b else (j, i, m[:, ::-1])
        out.append(CrossPair(k=int(k), l=int(l), b_k=bearings[k][mk[:, 0]], b_l=bearings[l][mk[:, 1]], matches=mk))
    return out


# --------------------------------------------------------------------------------------------- merging
def _merge_once(state: ModelSet, links: PairLinks, bearings, options: RegistrationOptions, min_points: int,
                descriptors=None) -> bool:
    """Merge the first pair of models (largest first) whose common points agree on a similarity; True if merged.

    Common points are triangulated in each model on its own, so far points (seen through a doorway) carry large
    depth errors: the similarity from them is only a start. The merge is kept when, after bundle adjustment of the
    merged model, at least `min_points` common tracks fit the rays of both sides together (see
    `_common_tracks_fitting`); otherwise it is undone."""
    tracks = state.tracks
    order = _by_size(state)
    points = {m: _points_of(state, m, tracks, bearings, MERGE_POINT_ERROR_DEG) for m in order}
    for a_rank, a in enumerate(order):
        for b in order[a_rank + 1:]:
            common = np.flatnonzero((points[a][1] >= 0) & (points[b][1] >= 0))
            if len(common) < min_points:
                continue
            X_a, X_b = points[a][0][points[a][1][common]], points[b][0][points[b][1][common]]
            sim, agree = _ransac_similarity(state, a, X_b, X_a, common, tracks, bearings, options)
            if agree < 3:
                continue
            saved = (state.model_id.copy(), state.R_cam_from_world.copy(), state.centers.copy())
            moved = np.flatnonzero(state.model_id == b)
            state.centers[moved] = sim.apply(state.centers[moved])
            state.R_cam_from_world[moved] = state.R_cam_from_world[moved] @ sim.R.T
            state.model_id[moved] = a
            _adjust_model(state, a, tracks, bearings, options)
            joined = _common_tracks_fitting(state, a, moved, common, tracks, bearings)
            if joined < min_points:
                state.model_id, state.R_cam_from_world, state.centers = saved
                log.info("models %d and %d share %d points but only %d fit both after adjustment: not merged",
                         a, b, len(common), joined)
                continue
            state.merges.append({"images": moved.tolist(), "points": joined})
            _record_join(state, "merge by shared points", moved, confirmed=True, points=joined)
            log.info("merged model %d (%d images) into model %d: %d/%d common points fit both", b, len(moved), a,
                     joined, len(common))
            _grow(state, a, links, bearings, options, descriptors)
            return True
    return False


def _common_tracks_fitting(state: ModelSet, a: int, moved: np.ndarray, common: np.ndarray, tracks: Tracks,
                           bearings) -> int:
    """How many common tracks, triangulated from all their observations in the merged model a, reproject within
    MERGE_POINT_ERROR_DEG in at least two images of each side (one badly clicked hand observation must not
    discard a point that the other views agree on)."""
    sel = np.isin(tracks.track_ids, common) & (state.model_id[tracks.image_ids] == a)
    ids, row = np.unique(tracks.track_ids[sel], return_inverse=True)
    counts = np.bincount(row, minlength=len(ids))
    sub = Tracks(track_ids=row, image_ids=tracks.image_ids[sel], feature_ids=tracks.feature_ids[sel],
                 offsets=np.concatenate([[0], np.cumsum(counts)]), num_images=tracks.num_images)
    t = -np.einsum("nab,nb->na", state.R_cam_from_world, state.centers)
    fits = triangulate_multiview(sub, bearings, state.R_cam_from_world, t).obs_error_rad <= np.radians(
        MERGE_POINT_ERROR_DEG)
    other_side = np.isin(sub.image_ids, moved)
    per_side = [np.bincount(row[fits & side], minlength=len(ids)) for side in (other_side, ~other_side)]
    return int(((per_side[0] >= 2) & (per_side[1] >= 2)).sum())


def _ransac_similarity(state: ModelSet, a: int, X_b: np.ndarray, X_a: np.ndarray, common: np.ndarray,
                       tracks: Tracks, bearings, options: RegistrationOptions):
    """Similarity taking model b's points onto model a's, and how many common points roughly agree with it (within
    MERGE_START_FACTOR times the resection threshold: their depths are uncertain until both sides' rays meet)."""
    rng = np.random.default_rng(options.seed)
    check = _agreement_check(state, a, common, tracks, bearings,
                             np.radians(MERGE_START_FACTOR * options.resection_threshold_deg))
    best, best_agree = None, np.zeros(len(common), bool)
    for _ in range(MERGE_ITERATIONS):
        sample = rng.choice(len(common), 3, replace=False)
        try:
            sim = umeyama(X_b[sample], X_a[sample])
        except (ValueError, np.linalg.LinAlgError):
            continue
        if not np.isfinite(sim.scale) or sim.scale <= 0:
            continue
        agree = check(sim.apply(X_b))
        if agree.sum() > best_agree.sum():
            best, best_agree = sim, agree
    if best is None or best_agree.sum() < 3:
        return None, 0
    refined = umeyama(X_b[best_agree], X_a[best_agree])
    agree = check(refined.apply(X_b))
    return (refined, int(agree.sum())) if agree.sum() >= best_agree.sum() else (best, int(best_agree.sum()))


def _agreement_check(state: ModelSet, a: int, common: np.ndarray, tracks: Tracks, bearings, max_error_rad: float):
    """A function: candidate positions (C, 3) of the common points in model a -> (C,) whether each reprojects
    within ``max_error_rad`` in every camera of model a that observes it."""
    row = np.full(tracks.num_tracks, -1)
    row[common] = np.arange(len(common))
    obs = (state.model_id[tracks.image_ids] == a) & (row[tracks.track_ids] >= 0)
    images, which = tracks.image_ids[obs], row[tracks.track_ids[obs]]
    z = gather_bearings(bearings, images, tracks.feature_ids[obs])
    R, C = state.R_cam_from_world[images], state.centers[images]

    def check(Y: np.ndarray) -> np.ndarray:
        err = angular_errors(z, np.einsum("kab,kb->ka", R, Y[which] - C))
        worst = np.zeros(len(common))
        np.maximum.at(worst, which, err)
        return worst <= max_error_rad

    return check
