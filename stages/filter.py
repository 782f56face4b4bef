"""Stage 3 — geometric verification: F on the sphere, seeded by hand points where a pair has enough of them.

Pairs with hand points follow the report: F from the hand points, SIFT matches near its epipolar circles kept, F
re-estimated on all inliers. Other pairs use LO-MSAC with angular errors and a non-linear refinement. A pair whose
inliers a pure rotation explains has no baseline and is dropped. The stored inlier matches live in the extended
feature index space (SIFT features, then hand observations; see `Workspace.load_observations`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from functools import lru_cache, partial

import numpy as np
from tqdm import tqdm

from fullview.sfm import manhattan, two_view, upright, wall_check, wide_pairs
from fullview.sfm.baseline import has_no_baseline
from fullview.sfm.matching import epipolar_candidates, match_descriptors
from fullview.sfm.options import FilterOptions, MatchesOptions
from fullview.stages.protocol import StageContext, process_map, thread_map

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("matches",)
INPUTS = ("hand_points", "images")  # images: gravity from vertical lines (filter.upright: vanishing)
FORK_MIN_PAIRS = 64  # fewer pairs are verified on threads: two forked workers cost ~0.06 CPU s more (measured on the
# 6-view room's 15 pairs: filter 0.51 -> 0.57 CPU s), a quarter of what those pairs' verification costs
DESCRIPTOR_CACHE = 16  # images whose descriptors guided matching keeps in memory
GRAVITY_WIDTH = 2048  # images are read at most this wide to find their vertical lines
# Fewer supporting vertical segments: gravity unknown. Measured on the real captures: the true vertical gathers 75-140
# segments; once the segments within 5° of it are set aside, the best other direction gathers 3-11 (360_school 11,
# 360_Flat 9): a vertical needs more than a wrong direction collects.
GRAVITY_MIN_LINES = 12


@dataclass(frozen=True, kw_only=True)
class _PairResult:
    F: np.ndarray  # (3, 3) the pair's fit (zeros when not fitted)
    inliers: np.ndarray  # (M, 2) verified matches (SIFT inliers, guided additions, hand points); empty if rejected
    seeded: bool  # fitted from hand points
    num_hand: int  # hand correspondences of the pair
    no_baseline: bool  # a rotation explains its matches
    weak: bool  # verified with fewer than min_inliers (hand points that fix the pose)
    early_rejected: bool  # too few matches to try
    guided_added: int | None  # matches guided matching added (None: not run)
    wall_fitted: bool = False  # its fit contradicted the images' walls and the pose they allow explained as much
    wide: bool = False  # verified by the wide-baseline test (filter.wide_pairs)


def run(ctx: StageContext) -> dict:
    options: FilterOptions = ctx.options
    obs = ctx.ws.load_observations(ctx.dataset)
    raw = ctx.ws.load_matches()
    # Guided matching reads descriptors per pair, the recent ones cached (pairs arrive grouped by their first image),
    # so they are never all in memory at once.
    descriptors = (lru_cache(maxsize=DESCRIPTOR_CACHE)(lambda k: ctx.ws.load_descriptors(ctx.dataset.image_names[k]))
                   if options.guided_matching else None)
    gravity, gravity_std, frames = _gravity(ctx, options.upright)
    num_sift = [int(o["num_sift"]) for o in obs]
    # Per pair, its leading matches that pass the strict ratio (fewer than all on noisy pairs, `matches.noisy_ratio`;
    # matches stored before the count existed: all of them).
    num_strict = raw.extra.get("num_strict", np.array([len(m) for m in raw.matches], np.int64))
    guided = MatchesOptions(ratio=options.guided_ratio, mutual=True)
    verify = partial(_filter_pair, ctx, options, obs, num_sift, raw, gravity, descriptors, guided,
                     options.min_inliers_upright, num_strict=num_strict,
                     frames=frames if options.wall_check else None)
    # Pairs are independent and their random seeds fixed per pair: forked workers keep both cores busy and the results
    # are the same as in one thread. Not threads: between its numpy calls a pair's estimation holds the GIL, and two
    # threads of it used the two cores only 1.4 times, spending a quarter more CPU time on the handovers.
    fan_out = process_map if len(raw.pairs) >= FORK_MIN_PAIRS else thread_map
    results = list(tqdm(fan_out(verify, range(len(raw.pairs))), total=len(raw.pairs), desc="filter", unit="pair"))
    # upright pairs the fit rejected, tested by their chance of fitting (filter.wide_pairs, sfm/wide_pairs.py)
    load = lambda n: ctx.ws.load_descriptors(ctx.dataset.image_names[n])  # noqa: E731
    for k, (F, good) in wide_pairs.verify_rejected(options, obs, raw, gravity, results, load, frames).items():
        results[k] = replace(results[k], F=F, inliers=good, weak=len(good) < options.min_inliers, wide=True)
    for (i, j), r in zip(raw.pairs, results):
        if r.no_baseline:
            log.warning("pair %s-%s has no baseline (a rotation explains its matches); skipped",
                        ctx.dataset.image_names[i], ctx.dataset.image_names[j])
    ctx.out.save_inliers(raw.pairs, [r.inliers for r in results], F=np.array([r.F for r in results]).reshape(-1, 3, 3),
                         num_raw=np.array([len(m) for m in raw.matches]),
                         seeded=np.array([r.seeded for r in results], bool),
                         num_hand=np.array([r.num_hand for r in results]),
                         no_baseline=np.array([r.no_baseline for r in results], bool),
                         weak_verified=np.array([r.weak for r in results], bool),
                         # Per image, not per pair: the bundle adjustment's gravity prior reads them. Unknown: zero
                         # and an infinite error, not NaN (reruns compare byte-identical arrays, and NaN != NaN).
                         gravity=np.nan_to_num(gravity, nan=0.0),
                         gravity_std_rad=np.nan_to_num(gravity_std, nan=np.inf),
                         # The Manhattan frame from the same lines, for triangulation's heading prior: its axis and
                         # the gravity refitted with it (unknown: zero and an infinite error).
                         manhattan_axis=np.nan_to_num(frames[0], nan=0.0),
                         manhattan_axis_std_rad=np.nan_to_num(frames[1], nan=np.inf),
                         manhattan_gravity=np.nan_to_num(frames[2], nan=0.0),
                         manhattan_gravity_std_rad=np.nan_to_num(frames[3], nan=np.inf))
    counts = np.array([len(r.inliers) for r in results])
    names = ctx.dataset.image_names
    return {"pairs": len(raw.pairs), "verified_pairs": int((counts > 0).sum()),
            "seeded_pairs": int(sum(r.seeded for r in results)),
            "median_inliers": int(np.median(counts)) if len(counts) else 0,
            "no_baseline_pairs": [[names[i], names[j]] for (i, j), r in zip(raw.pairs, results) if r.no_baseline],
            "guided_matches_added": int(sum(r.guided_added or 0 for r in results)),
            "early_rejected_pairs": int(sum(r.early_rejected for r in results)),
            "wall_fitted_pairs": [[names[i], names[j]] for (i, j), r in zip(raw.pairs, results) if r.wall_fitted],
            "upright_images": int(np.isfinite(gravity).all(axis=1).sum()),
            "wide_verified_pairs": [[names[i], names[j]] for (i, j), r in zip(raw.pairs, results) if r.wide]}


def _filter_pair(ctx: StageContext, options: FilterOptions, obs, num_sift, raw, gravity, descriptors,
                 guided: MatchesOptions, min_upright: int, k: int, *, num_strict=None, frames=None) -> _PairResult:
    """Verify pair k of the raw matches: fit, guided additions, the no-baseline and enough-inliers checks (frames:
    the images' Manhattan frames from `_gravity`, for the wall check; None: no check; num_strict: per pair, the leading matches hypotheses are drawn from, None: all)."""
    i, j = raw.pairs[k]
    hand = (ctx.dataset.hand_pair_matches(num_sift, i, j) if options.use_hand_points
            else np.zeros((0, 2), int))
    threshold = np.radians(options.threshold_deg)
    use_seed = len(hand) >= options.min_hand_points
    upright_pair = not use_seed and _upright((gravity[i], gravity[j]))
    minimum = min_upright if upright_pair else options.min_inliers
    early = not use_seed and len(raw.matches[k]) + len(hand) < min(minimum, options.min_inliers)
    if early:
        # Early rejection: even if every match were an inlier the pair could neither verify nor be flagged as
        # without baseline (guided matching only extends pairs that already have min_inliers): no RANSAC.
        F, keep = np.zeros((3, 3)), np.zeros(len(raw.matches[k]), bool)
    else:
        F, keep = _verify_pair(obs[i]["bearings"], obs[j]["bearings"], raw.matches[k], hand if use_seed else None,
                               threshold, options, seed=options.seed + k, gravity=(gravity[i], gravity[j]),
                               # the hand points (fewer than a seed) count towards the pair's inliers
                               needed=max(1, min(minimum, options.min_inliers) - len(hand)),
                               pool=len(raw.matches[k]) if num_strict is None else int(num_strict[k]))
    walled = ""
    if upright_pair and frames is not None and keep.sum() >= min(minimum, options.min_inliers):
        F, keep, walled = _checked_against_walls(obs[i]["bearings"], obs[j]["bearings"], raw.matches[k], F, keep,
                                                 frames, i, j, threshold, options.seed + k, options.min_inliers,
                                                 gravity=gravity)
    good = np.concatenate([raw.matches[k][keep], hand]) if len(hand) else raw.matches[k][keep]
    added = None
    if descriptors is not None and len(good) >= options.min_inliers:
        good, added = _add_guided(good, descriptors(i), descriptors(j), obs[i]["bearings"], obs[j]["bearings"],
                                  F, threshold, guided)
    flat = len(good) >= min(minimum, options.min_inliers) and has_no_baseline(
        obs[i]["bearings"][good[:, 0]], obs[j]["bearings"][good[:, 1]], threshold)
    # A pair the user joined by hand is verified by its hand points alone when they fix the relative pose (not
    # all on one plane): on a doorway pair SIFT may find almost nothing.
    enough = len(good) >= minimum or (use_seed and two_view.points_determine_f(
        obs[i]["bearings"][hand[:, 0]], obs[j]["bearings"][hand[:, 1]]))
    if not enough or flat:
        good = good[:0]
    return _PairResult(F=F, inliers=good, seeded=use_seed, num_hand=len(hand), no_baseline=flat,
                       weak=0 < len(good) < options.min_inliers, early_rejected=early, guided_added=added,
                       wall_fitted=walled == "fitted")


def _checked_against_walls(bear_i, bear_j, matches, F, keep, frames, i: int, j: int, threshold: float, seed: int,
                           strong: int, *, gravity=None):
    """(F, inlier mask, what the walls did: "" or "fitted"): where the upright fit's yaw contradicts the two images'
    walls (modulo 90°, beyond `wall_check.tolerance_deg`), the pose the walls allow replaces the fit when it explains
    nearly as many matches (`wall_check.AMBIGUOUS_SHARE`) or the fit has fewer than `strong` inliers (the pair then
    verifies only if the walls' pose has enough). A strong fit the walls' pose explains far worse stays (walls not at
    right angles, a wrong axis)."""
    axis, axis_std, wall_gravity = frames[0], frames[1], frames[2]
    known = np.isfinite(axis[i]).all(), np.isfinite(axis[j]).all()
    if not any(known) or (not all(known) and gravity is None):
        return F, keep, ""
    b_i, b_j = bear_i[matches[:, 0]], bear_j[matches[:, 1]]
    try:
        pose = two_view.relative_pose_from_f(F, b_i[keep], b_j[keep])
    except ValueError:
        return F, keep, ""
    if not all(known):
        return _checked_against_one_wall(b_i, b_j, F, keep, pose, frames, gravity, i, j, threshold, seed, known[0])
    residual = wall_check.wall_residual_deg(pose.R_j_from_i, axis[i], axis[j], wall_gravity[j])
    if abs(residual) <= wall_check.tolerance_deg(axis_std[i], axis_std[j]):
        return F, keep, ""
    R, t, inliers = wall_check.pose_the_walls_allow(b_i, b_j, pose.R_j_from_i, axis[i], axis[j], wall_gravity[j],
                                                    threshold, seed)
    if inliers.sum() < wall_check.AMBIGUOUS_SHARE * keep.sum() and keep.sum() >= strong:
        return F, keep, ""
    return wall_check.f_of_pose(R, t), inliers, "fitted"


def _checked_against_one_wall(b_i, b_j, F, keep, pose, frames, gravity, i: int, j: int, threshold: float, seed: int,
                              i_known: bool):
    """The wall check of a pair where one image has no wall axis (`_checked_against_walls`' result): when the fit's
    inliers lie on a wall whose normal the fit puts off the other image's walls, the homography's other pose, if it
    puts the wall on them and explains nearly as many matches (`wall_check.pose_the_plane_allows`), replaces the
    fit. Worked in the frame of the image with the axis as j (the pair swapped when it is i)."""
    R, t = pose.R_j_from_i, pose.t_j_from_i
    if i_known:  # swap: i becomes the image with the axis
        b_i, b_j, R, t = b_j, b_i, R.T, -R.T @ t
        known, other = i, j
    else:
        known, other = j, i
    found = wall_check.pose_the_plane_allows(b_i, b_j, keep, R, t, frames[0][known], gravity[other],
                                             frames[2][known], threshold, seed)
    if found is None or found[2].sum() < wall_check.AMBIGUOUS_SHARE * keep.sum():
        return F, keep, ""
    R, t, inliers = found
    if i_known:
        R, t = R.T, -R.T @ t
    return wall_check.f_of_pose(R, t), inliers, "fitted"


def _gravity(ctx: StageContext, mode: str):
    """(N, 3) gravity of every image in its camera frame (NaN where unknown: upright none, or no vertical lines),
    (N,) its standard error in radians from the spread of the vertical lines (NaN: not measured, as with level), and
    each image's Manhattan frame from the same lines (`manhattan.manhattan_frame`: (N, 3) axis, (N,) its standard
    error, (N, 3) the gravity refitted with it, (N,) that gravity's standard error; NaN where no axis is found)."""
    names = ctx.dataset.image_names
    out, std = np.full((len(names), 3), np.nan), np.full(len(names), np.nan)
    frames = (np.full((len(names), 3), np.nan), np.full(len(names), np.nan), np.full((len(names), 3), np.nan),
              np.full(len(names), np.nan))
    if mode == "level":
        out[:] = upright.Y_AXIS
    elif mode == "vanishing":
        # Images are independent and OpenCV's line detector releases the GIL: two at a time use both cores (the
        # same results as one after the other; `test_gravity_in_threads_equals_serial`).
        estimate = partial(_image_gravity, ctx.dataset, ctx.options.seed)
        for k, (name, (found, frame)) in enumerate(tqdm(zip(names, thread_map(estimate, names, threads=2)),
                                                        total=len(names), desc="gravity", unit="image")):
            if found is None:
                log.warning("%s: no vertical lines found; its pairs are verified without the upright prior", name)
                continue
            out[k], std[k] = found[0], found[2]
            log.debug("%s: gravity %s from %d lines", name, np.round(found[0], 4).tolist(), found[1])
            if frame is not None and np.isfinite(frame[2]):
                frames[2][k], frames[0][k], frames[3][k], frames[1][k] = frame
    return out, std, frames


def _image_gravity(dataset, seed: int, name: str):
    """`upright.estimate_gravity_with_std` of one image, read at most GRAVITY_WIDTH wide, and its Manhattan frame
    about that gravity from the same line segments (`manhattan.manhattan_frame`; None without an axis)."""
    full_w = dataset.image_sizes[name][0]
    normals, lengths = upright.detect_line_normals(dataset.load_image(name, width=min(GRAVITY_WIDTH, full_w)))
    found = upright.gravity_with_std_from_normals(normals, lengths, min_lines=GRAVITY_MIN_LINES, seed=seed)
    if found is None:
        return None, None
    axis = manhattan.manhattan_axis(normals, lengths, found[0])
    return found, None if axis is None else manhattan.manhattan_frame(normals, lengths, found[0], axis[0])


def _add_guided(good: np.ndarray, desc_i, desc_j, bear_i, bear_j, F, threshold, guided_options: MatchesOptions):
    """A verified pair's inliers plus the SIFT matches found along the epipolar circles of F (looser ratio test among
    the candidates near each circle, mutual check), kept when their symmetric epipolar error is within the threshold
    and they lie in front of both cameras under the pair's relative pose (the epipolar constraint alone cannot reject
    a match on the wrong side of the baseline). Only verified pairs are extended: a weak pair's F is too uncertain
    to guide: matches found along a wrong F's circles agree with it by construction. Returns (inliers, added)."""
    num_i, num_j = len(desc_i), len(desc_j)
    allowed = epipolar_candidates(bear_i[:num_i], bear_j[:num_j], F, threshold)
    guided = match_descriptors(desc_i, desc_j, guided_options, block_rows=1024, allowed=allowed)
    if not len(guided):
        return good, 0
    errors = two_view.epipolar_angular_errors(F, bear_i[guided[:, 0]], bear_j[guided[:, 1]])
    guided = guided[errors <= threshold]
    try:
        pose = two_view.relative_pose_from_f(F, bear_i[good[:, 0]], bear_j[good[:, 1]])
    except ValueError:
        return good, 0
    depth_i, depth_j = two_view.ray_depths(bear_i[guided[:, 0]], bear_j[guided[:, 1]], pose.R_j_from_i,
                                           pose.t_j_from_i)
    guided = guided[(depth_i > 0) & (depth_j > 0)]
    width = max(int(good[:, 1].max(initial=0)), int(guided[:, 1].max(initial=0))) + 1
    new = guided[~np.isin(guided[:, 0] * width + guided[:, 1], good[:, 0] * width + good[:, 1])]
    return (np.concatenate([good, new]) if len(new) else good), len(new)


def _fit_upright(b_i, b_j, gravity, opts: two_view.RansacOptions) -> two_view.FResult:
    """The upright model: 3-point yaw solver on levelled bearings, yaw-only refinement, never released.

    Why: in a plain-walled room most inliers of a pair can lie on one textured furniture face. 8-point samples from
    one plane fit a wrong F that still gathers most of them (a plane's matches fix a homography, not F), and an
    unconstrained refinement started at the right upright F slides along that near-degenerate valley; the upright
    model has 3 unknowns, which a plane's matches do fix. The price on well-textured real panoramas, whose estimated gravity is a tenth of a degree off: 360_Flat agrees
    with COLMAP to 0.061° at most instead of 0.027°."""
    L_i, L_j = upright.leveling_rotation(gravity[0]), upright.leveling_rotation(gravity[1])
    res = upright.ransac_f_upright(b_i @ L_i.T, b_j @ L_j.T, opts)
    res.F = upright.unlevel_f(res.F, L_i, L_j)  # levelling rotates bearings: angular errors are unchanged
    return res


def _verify_pair(bear_i, bear_j, matches, hand, threshold, options: FilterOptions, seed, gravity, needed=1,
                 pool: int | None = None):
    """F and the inlier mask over `matches` (hand correspondences, when given, seed the estimate; with both
    gravities known, the upright 3-point solver on levelled bearings). `needed`: the inliers the pair must have to
    count at all, which bounds the search on pairs with few matches (`capped_for_verification`). `pool`: hypotheses
    are drawn from the first `pool` matches only (the strict ones; all when None, or when too few to sample from),
    and the search's bound is theirs: the looser matches after them only count."""
    b_i, b_j = bear_i[matches[:, 0]], bear_j[matches[:, 1]]
    sample_size = upright.UPRIGHT_SAMPLE_SIZE if _upright(gravity) else 8
    pool = len(b_i) if pool is None or pool < max(sample_size, 8) else min(pool, len(b_i))
    opts = two_view.RansacOptions(threshold_rad=threshold, max_iterations=options.max_iterations,
                                  confidence=options.confidence, seed=seed,
                                  sample_pool=pool if pool < len(b_i) else 0)
    try:
        if hand is None:
            res = _fit_matches(b_i, b_j, gravity, capped_for_verification(opts, needed, pool, sample_size))
        else:
            h_i, h_j = bear_i[hand[:, 0]], bear_j[hand[:, 1]]
            res = two_view.fit_f_seeded(h_i, h_j, b_i, b_j, threshold)
            if len(matches) >= options.min_inliers and not _explains(res.F, h_i, h_j, threshold):
                # The clicks and the matches did not settle on one F (noisy clicks; the seeded fit fell back to
                # the clicks' own F): the matches' own fit may be the better one.
                res = _better_of_seeded_and_free(res, h_i, h_j, b_i, b_j, gravity, opts)
    except ValueError as e:  # too few correspondences: the pair is simply not verified
        log.debug("pair not verified: %s", e)
        return np.zeros((3, 3)), np.zeros(len(matches), bool)
    return res.F, res.inliers


def capped_for_verification(opts: two_view.RansacOptions, needed: int, n: int, sample_size: int
                            ) -> two_view.RansacOptions:
    """`opts` with the hypotheses a pair of `n` matches needs to find a model of `needed` inliers, if it has one.

    Why: a pair the retrieval proposed but that sees other rooms (most of them on a walk) has a few dozen chance
    matches; with no model to find, RANSAC never stops early and drew `max_iterations` hypotheses. A pair that can
    verify has an inlier ratio of at least needed / n, and that ratio bounds the samples needed (with the options'
    confidence). Only half the samples are uniform (the other half come from the head of the matches,
    `_draw_samples`), so the bound is doubled. Pairs with many matches keep the full cap."""
    bound = two_view.iterations_to_beat(needed - 1, n, opts, sample_size).max_iterations
    return replace(opts, max_iterations=min(opts.max_iterations, max(opts.min_iterations, 2 * bound)))


# Clicked points are a pixel or so off (0.35° at 1024 px, as much as the inlier threshold): a fit explains them when
# they lie within this many thresholds of its epipolar circles.
HAND_CHECK_THRESHOLDS = 3.0


def _fit_matches(b_i, b_j, gravity, opts: two_view.RansacOptions) -> two_view.FResult:
    """F from the matches alone: the upright solver when both gravities are known, else LO-MSAC."""
    if _upright(gravity):
        return _fit_upright(b_i, b_j, gravity, opts)
    return two_view.ransac_f(b_i, b_j, opts)


def _upright(gravity) -> bool:
    return bool(np.isfinite(gravity[0]).all() and np.isfinite(gravity[1]).all())


def _better_of_seeded_and_free(seeded: two_view.FResult, h_i, h_j, b_i, b_j, gravity, opts) -> two_view.FResult:
    """The matches' own fit replaces the hand-seeded one when it has more inliers and still explains the hand points:
    a seed from a few noisy clicks is less precise than hundreds of matches (on the 200-view corridor, seeding every
    pair with its hand points cost AUC@1 90 -> 22). Where the matches alone fit a wrong F (one dominant plane), the
    hand points reject it and the seeded fit stays.

    Cheapest first: the local optimisation started at the clicks' F usually finds the matches' fit. A sampled search
    (upright when both gravities are known, as its yaw-only model is the more precise on plain rooms; else LO-MSAC)
    then runs only as long as it needs to find a fit with more inliers than the best so far: with a wrong gravity
    estimate it used to run to the hypothesis cap on every seeded pair (5x the filter's time on a 24-view room)."""
    tolerance = HAND_CHECK_THRESHOLDS * opts.threshold_rad
    wins = lambda fit, other: (fit.inliers.sum() > other.inliers.sum()  # noqa: E731
                               and _explains(fit.F, h_i, h_j, tolerance))
    try:
        near = two_view.fit_f_from(seeded.F, b_i, b_j, opts.threshold_rad)
    except ValueError:
        return seeded
    best = near if wins(near, seeded) else seeded
    upright_pair = _upright(gravity)
    if best is near and not upright_pair:
        return best
    sample_size = upright.UPRIGHT_SAMPLE_SIZE if upright_pair else 8
    capped = two_view.iterations_to_beat(int(best.inliers.sum()), len(b_i), opts, sample_size)
    try:
        free = _fit_matches(b_i, b_j, gravity, capped)
    except ValueError:
        return best
    if upright_pair:  # preferred to the free near fit unless it loses a share of its inliers (wrong gravity)
        return free if wins(free, seeded) and free.inliers.sum() >= UPRIGHT_MIN_SHARE * best.inliers.sum() else best
    return free if wins(free, best) else best


# An upright fit with fewer than this share of the free fit's inliers has a wrong gravity estimate behind it (a right
# one loses only the few inliers the free model's 2 extra degrees of freedom absorb).
UPRIGHT_MIN_SHARE = 0.9


def _explains(F, h_i, h_j, tolerance_rad: float) -> bool:
    """Whether F puts the share of the hand points a seeded fit must keep within the tolerance of its circles."""
    return bool(np.mean(two_view.epipolar_angular_errors(F, h_i, h_j) < tolerance_rad) >= two_view.HAND_INLIER_SHARE)
