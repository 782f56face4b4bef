"""Stereo on the ground by a sweep of ground-parallel planes (plane-induced warps on the sphere).

Rectified SGBM matches along epipolar rows with square windows and a capped disparity range. Outdoors the ground
defeats it: near the cameras the ground subtends more than the disparity cap of a metres-long baseline, and seen at
a grazing angle it is strongly foreshortened, differently in the two panoramas, so square windows do not match.
Here every pixel of a panorama below the horizon is matched against a partner under hypotheses "the surface is the
plane at height h below the camera" (planes normal to the model's up; h over a log-spaced range around the camera's
height above its ground): each hypothesis warps the partner panorama onto the reference one through the plane
(for a pixel's ray b with depression s = −b·up, the point is c + b h / s), and the warped partner is compared with
the reference by normalised cross-correlation over a window. Where the surface is that plane the warp is exact over
the whole window, so a slanted ground is matched as if fronto-parallel and there is no disparity cap.
Winner-take-all over the hypotheses, sub-step parabola, then: a textured window, a correlation floor, a unique peak
(no second local maximum nearly as good) and a left-right check (the partner's sweep puts the same point within a
tolerance). A tilted ground only shifts the winning height with distance; its windows are still nearly aligned.

Pure geometry: no file access. ``ground_sweep_pair`` gives both panoramas' ranges; ``ground_heights`` the cameras'
heights above the ground from the sparse points; ``indoor_or_outdoor`` the decision that keeps the sweep to scenes
without a ceiling over the cameras (indoors the region and world-plane fills own the floor).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fullview.sfm.camera import bearings_to_pixels_f32, camera_center, pixel_grid_bearings, pixel_latitude
from fullview.sfm.dense.rectify import _pad_equirect

PAD = 4  # source padding of the warps (pixels), as in rectification
KNOT_STEP = 4  # the warp's source pixels are computed exactly every this many hypotheses, interpolated between
CHUNK_ROWS = 48  # reference rows swept at a time (the cost volume of a chunk stays a few tens of MB)
MIN_POINTS = 20  # sparse points a camera's ground height rests on (else the other cameras' median)
GROUND_DEPRESSION_DEG = 30.0  # sparse points this far below a camera's horizon are taken as its ground
SECTORS = 12  # indoor_or_outdoor: azimuth sectors of 30° around each camera (an empty half-circle is 6 of them)
MIN_SECTOR_POINTS = 3  # ... points above the camera a sector needs to count (one stray point does not)
MIN_SECTORS = 3  # ... sectors with points above the camera that can enclose it (three, 120° apart, at the least)
TOP_PERCENTILE = 90  # ... a sector's top: this percentile of its points' heights (robust to a few wrong points)
# ... a ceiling stands at most this many times the camera's height above the floor over the camera: ceilings up to
# 3 m over cameras at least 1 m above the floor, (3 - 1) / 1 = 2. A taller room or a lower camera is judged outdoors,
# which costs the ground sweep's time on a floor it mostly cannot match; a street judged a room loses its ground
# (measured: 360_Flat 0.96-1.10, a rendered home 0.39-0.64; 360_school 7.6-9.3, a rendered street 4.3-4.9)
MAX_CEILING_RATIO = 2.0
COARSE_SPAN = (0.05, 5.0)  # the coarse sweep's heights: these factors of the baseline ...
COARSE_STEP = 0.04  # ... in log steps of this relative size
MIN_COARSE_PIXELS = 100  # accepted near-ground pixels the coarse sweep's height needs


@dataclass(frozen=True, kw_only=True)
class GroundSweepOptions:
    window: int = 9  # NCC window side (pixels of the swept panorama)
    min_height_factor: float = 0.5  # hypotheses span these factors of the camera's ground height ...
    max_height_factor: float = 2.0
    step: float = 0.015  # ... in log steps of this relative size
    min_ncc: float = 0.6  # the winner's correlation must reach this
    max_second_ratio: float = 0.8  # (1 − NCC of the best) / (1 − NCC of any other local maximum) at most this
    min_texture_std: float = 2.0  # grey-level std of the reference window at least this
    lr_tolerance: float = 0.02  # relative range agreement of the two directions
    min_depression_deg: float = 2.0  # rays nearer the horizon than this are not swept (the ground lies too far)
    min_latitude_deg: float = -90.0  # no range below this latitude (nadir cap), in either panorama


def ground_heights(centers: np.ndarray, points: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(N,) each camera's height above its ground: the median height below it of the sparse points it would see
    more than ``GROUND_DEPRESSION_DEG`` below its horizon (near ground, rarely anything else); the other cameras'
    median where fewer than ``MIN_POINTS`` are; NaN if no camera has enough."""
    centers, points = np.asarray(centers, np.float64), np.asarray(points, np.float64).reshape(-1, 3)
    heights = np.full(len(centers), np.nan)
    for k, c in enumerate(centers):  # one vector step per camera (a few cameras)
        d = points - c
        below = -(d @ up)
        ground = below > np.sin(np.radians(GROUND_DEPRESSION_DEG)) * np.linalg.norm(d, axis=1)
        if ground.sum() >= MIN_POINTS:
            heights[k] = float(np.median(below[ground]))
    if np.isfinite(heights).any():
        heights[~np.isfinite(heights)] = np.nanmedian(heights)
    return heights


@dataclass(frozen=True, kw_only=True)
class SceneKind:
    """Indoors or outdoors (``indoor_or_outdoor``), with the evidence per camera."""

    indoors: bool  # a ceiling over most cameras (the ground sweep stays off under ``no_ceiling``)
    reason: str  # the decision in plain words
    cameras: list[dict]  # per camera: verdict (sky, ceiling, low, unknown), skyline ratio, sectors, enclosed

    def as_dict(self) -> dict:
        return {"kind": "indoors" if self.indoors else "outdoors", "reason": self.reason, "cameras": self.cameras}


def indoor_or_outdoor(centers: np.ndarray, points: np.ndarray, up: np.ndarray, obs_camera: np.ndarray | None = None,
                      obs_point: np.ndarray | None = None) -> SceneKind:
    """Whether the cameras stand under a ceiling (indoors) or under the sky, from the sparse points each camera sees
    (``obs_camera``/``obs_point``: observations by camera row of ``centers``; without them every camera sees every
    point). Per camera, the points above its horizon are split into ``SECTORS`` azimuth sectors, and each sector
    with ``MIN_SECTOR_POINTS`` gets its top (the ``TOP_PERCENTILE`` of their heights above the camera). The camera's
    *skyline ratio* is the median top over its height above the ground (``ground_heights``; where the near ground
    has too few points, the ``TOP_PERCENTILE`` of the depths below it of the points it sees below its horizon).
    Its verdict:

    - ``sky``: the ratio exceeds ``MAX_CEILING_RATIO``: what stands above it is taller than any room (facades,
      roofs, tree tops, however few), so no ceiling is over it;
    - ``ceiling``: the ratio is within a room's and the sectors with points above the camera surround it (no empty
      half-circle of azimuth: walls and a ceiling enclose it);
    - ``low``: the ratio is within a room's, the points above on one side only (plain walls, or a low wall outside);
    - ``unknown``: no points above it (or none below).

    The scene is outdoors when the ``sky`` cameras are at least as many as the ``ceiling`` and ``low`` ones
    together (a tie, or nothing known: outdoors, where the sweep's cost indoors is a few plain-floor pixels it does
    not match, and a street judged a room loses its ground). A street's open sky has no points, but neither has a
    plain ceiling (360_Flat's, the synthetic homes'), so the points at high elevation do not tell them apart; the
    height of the highest points around does."""
    centers = np.asarray(centers, np.float64).reshape(-1, 3)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    up = np.asarray(up, np.float64)
    if obs_camera is None:
        obs_camera = np.repeat(np.arange(len(centers)), len(points))
        obs_point = np.tile(np.arange(len(points)), len(centers))
    obs_camera, obs_point = np.asarray(obs_camera, np.intp), np.asarray(obs_point, np.intp)
    ground = ground_heights(centers, points, up)
    e1 = np.cross(up, np.eye(3)[np.argmin(np.abs(up))])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    d = points[obs_point] - centers[obs_camera]
    height = d @ up
    sector = (np.floor((np.arctan2(d @ e2, d @ e1) + np.pi) / (2 * np.pi / SECTORS)).astype(np.intp)) % SECTORS
    cams = []
    for k in range(len(centers)):  # one vector step per camera
        mine = obs_camera == k
        above, below = mine & (height > 0), mine & (height < 0)
        tops = np.full(SECTORS, np.nan)
        for s in np.flatnonzero(np.bincount(sector[above], minlength=SECTORS) >= MIN_SECTOR_POINTS):  # <= SECTORS
            tops[s] = np.percentile(height[above & (sector == s)], TOP_PERCENTILE)
        filled = np.isfinite(tops)
        floor = ground[k] if np.isfinite(ground[k]) else \
            (float(np.percentile(-height[below], TOP_PERCENTILE)) if below.any() else np.nan)
        ratio = float(np.median(tops[filled]) / floor) if filled.any() and np.isfinite(floor) else None
        enclosed = int(filled.sum()) >= MIN_SECTORS and _largest_gap(filled) < SECTORS // 2
        verdict = "unknown" if ratio is None else "sky" if ratio > MAX_CEILING_RATIO else \
            "ceiling" if enclosed else "low"
        cams.append({"verdict": verdict, "skyline_ratio": None if ratio is None else round(ratio, 3),
                     "sectors_above": int(filled.sum()), "enclosed": enclosed})
    count = {v: [c["verdict"] for c in cams].count(v) for v in ("sky", "ceiling", "low", "unknown")}
    ratios = [c["skyline_ratio"] for c in cams if c["skyline_ratio"] is not None]
    median = f"{np.median(ratios):.2g}" if ratios else "unknown"
    indoors = count["sky"] < count["ceiling"] + count["low"]
    evidence = (f"{count['sky']} of {len(cams)} cameras see things taller than a room above them, "
                f"{count['ceiling'] + count['low']} see nothing above them higher than a room's ceiling "
                f"({count['ceiling']} enclosed all around), {count['unknown']} nothing above them; the highest "
                f"points around stand a median {median} times the camera's height above its floor or ground")
    reason = f"indoors (a ceiling over the cameras): {evidence}" if indoors else f"outdoors (the sky): {evidence}"
    return SceneKind(indoors=indoors, reason=reason, cameras=cams)


def _largest_gap(filled: np.ndarray) -> int:
    """The longest circular run of sectors without points above the camera."""
    if filled.all():
        return 0
    run, best = 0, 0
    for value in np.r_[filled, filled]:  # two turns: a run may wrap around (2 * SECTORS steps)
        run = 0 if value else run + 1
        best = max(best, run)
    return min(best, len(filled))


def has_ceiling(centers: np.ndarray, points: np.ndarray, up: np.ndarray, obs_camera: np.ndarray | None = None,
                obs_point: np.ndarray | None = None) -> bool:
    """Whether the scene is a room, a ceiling over the cameras (``indoor_or_outdoor``)."""
    return indoor_or_outdoor(centers, points, up, obs_camera, obs_point).indoors


def swept_ground_heights(grey_i: np.ndarray, grey_j: np.ndarray, R_i: np.ndarray, c_i: np.ndarray,
                         R_j: np.ndarray, c_j: np.ndarray, up: np.ndarray, options: GroundSweepOptions
                         ) -> tuple[float, float]:
    """Both cameras' heights above their ground from a coarse sweep (half width, heights from ``COARSE_SPAN`` times
    the baseline in ``COARSE_STEP`` log steps, the two directions left-right checked): for each, the most frequent
    height among its accepted rays more than ``GROUND_DEPRESSION_DEG`` below the horizon (NaN if fewer than
    ``MIN_COARSE_PIXELS``). Used where the sparse points do not tell: rectified stereo of the near ground is itself
    what fails there."""
    baseline = float(np.linalg.norm(np.asarray(c_j, np.float64) - np.asarray(c_i, np.float64)))
    h, w = grey_i.shape
    small = [cv2.resize(g, (w // 2, h // 2), interpolation=cv2.INTER_AREA) for g in (grey_i, grey_j)]
    coarse = GroundSweepOptions(**{**options.__dict__, "min_height_factor": COARSE_SPAN[0],
                                   "max_height_factor": COARSE_SPAN[1], "step": COARSE_STEP,
                                   "window": max(3, options.window // 2 | 1)})
    range_i = sweep_ranges(small[0], small[1], R_i, c_i, R_j, c_j, up, baseline, coarse)
    range_j = sweep_ranges(small[1], small[0], R_j, c_j, R_i, c_i, up, baseline, coarse)
    tolerance = 2 * COARSE_STEP
    keep_i = _left_right_agree(range_i, range_j, R_i, c_i, R_j, c_j, tolerance)
    keep_j = _left_right_agree(range_j, range_i, R_j, c_j, R_i, c_i, tolerance)
    return (_mode_height(np.where(keep_i, range_i, np.nan), R_i, up, baseline),
            _mode_height(np.where(keep_j, range_j, np.nan), R_j, up, baseline))


def _mode_height(ranges: np.ndarray, R_cam_from_world: np.ndarray, up: np.ndarray, baseline: float) -> float:
    """The most frequent height below the camera (log bins of ``COARSE_STEP``; the median of the mode's bin and its
    neighbours) of the ranges more than ``GROUND_DEPRESSION_DEG`` below its horizon; NaN if too few."""
    h, w = ranges.shape
    depression = -(pixel_grid_bearings(w, h, np.float32) @ np.asarray(R_cam_from_world, np.float32)) @ \
        np.asarray(up, np.float32)
    near = np.isfinite(ranges) & (depression > np.sin(np.radians(GROUND_DEPRESSION_DEG)))
    if near.sum() < MIN_COARSE_PIXELS:
        return np.nan
    heights = np.log(ranges[near] * depression[near] / baseline)
    bins = np.round(heights / np.log1p(COARSE_STEP))
    values, counts = np.unique(bins, return_counts=True)
    mode = values[np.argmax(counts)]
    return float(baseline * np.exp(np.median(heights[np.abs(bins - mode) <= 1])))


def ground_sweep_pair(image_i: np.ndarray, image_j: np.ndarray, R_i: np.ndarray, t_i: np.ndarray, R_j: np.ndarray,
                      t_j: np.ndarray, up: np.ndarray, height_i: float, height_j: float,
                      options: GroundSweepOptions) -> tuple[np.ndarray, np.ndarray]:
    """Ground ranges of both panoramas of a pair (each (H, W) float32 at the images' size, NaN where the sweep
    found none or the two directions disagree). A height that is NaN is found by a coarse sweep first."""
    grey_i, grey_j = _grey(image_i), _grey(image_j)
    c_i, c_j = camera_center(R_i, t_i), camera_center(R_j, t_j)
    if not np.isfinite([height_i, height_j]).all():
        coarse = swept_ground_heights(grey_i, grey_j, R_i, c_i, R_j, c_j, up, options)
        height_i, height_j = (known if np.isfinite(known) else found for known, found in
                              zip((height_i, height_j), coarse))
    range_i = sweep_ranges(grey_i, grey_j, R_i, c_i, R_j, c_j, up, height_i, options)
    range_j = sweep_ranges(grey_j, grey_i, R_j, c_j, R_i, c_i, up, height_j, options)
    keep_i = _left_right_agree(range_i, range_j, R_i, c_i, R_j, c_j, options.lr_tolerance)
    keep_j = _left_right_agree(range_j, range_i, R_j, c_j, R_i, c_i, options.lr_tolerance)
    return np.where(keep_i, range_i, np.nan).astype(np.float32), np.where(keep_j, range_j, np.nan).astype(np.float32)


def height_hypotheses(height: float, options: GroundSweepOptions) -> np.ndarray:
    """(K,) plane heights below the camera, log-spaced by ``options.step`` over the factors' span."""
    lo, hi = np.log(options.min_height_factor), np.log(options.max_height_factor)
    count = int(np.ceil((hi - lo) / np.log1p(options.step))) + 1
    return height * np.exp(np.linspace(lo, hi, count))


def sweep_ranges(ref: np.ndarray, src: np.ndarray, R_ref: np.ndarray, c_ref: np.ndarray, R_src: np.ndarray,
                 c_src: np.ndarray, up: np.ndarray, height: float, options: GroundSweepOptions) -> np.ndarray:
    """(H, W) float32 ranges of the reference panorama (grey float32) from its sweep against the source one; NaN
    where not swept or not accepted (one direction: no left-right check)."""
    h, w = ref.shape
    out = np.full((h, w), np.nan, np.float32)
    if not np.isfinite(height) or height <= 0:
        return out
    rays = pixel_grid_bearings(w, h, np.float32) @ np.asarray(R_ref, np.float32)  # world bearings (row vectors)
    depression = -(rays @ np.asarray(up, np.float32))
    lat = pixel_latitude(np.arange(h) + 0.5, h)
    swept = (depression > np.sin(np.radians(options.min_depression_deg))) \
        & (lat >= np.radians(options.min_latitude_deg))[:, None]
    rows = np.flatnonzero(swept.any(axis=1))
    if not len(rows):
        return out
    hyp = height_hypotheses(height, options).astype(np.float32)
    half = options.window // 2
    padded = _pad_equirect(src, PAD)
    R_src32 = np.asarray(R_src, np.float32)
    offset = R_src32 @ np.asarray(c_ref - c_src, np.float32)  # the reference centre in the source frame
    size = (2 * half + 1, 2 * half + 1)
    knots = np.unique(np.r_[np.arange(0, len(hyp), KNOT_STEP), len(hyp) - 1])
    min_y = (np.pi / 2 - np.radians(options.min_latitude_deg)) * h / np.pi + PAD - 0.5  # the source's nadir cap
    for top in range(rows[0], rows[-1] + 1, CHUNK_ROWS):
        lo, hi = max(top - half, 0), min(top + CHUNK_ROWS + half, h)  # the chunk with its window margin
        below = np.maximum(depression[lo:hi, :, None], np.float32(1e-3))  # rays at or above the horizon: not swept
        step = (rays[lo:hi] @ R_src32.T) / below  # the plane's point per unit height, source frame
        ref_c = ref[lo:hi]
        mean_r = cv2.blur(ref_c, size)
        std_r = np.sqrt(np.maximum(cv2.blur(ref_c * ref_c, size) - mean_r * mean_r, 0.0))
        coords = [bearings_to_pixels_f32(offset + hyp[k] * step, w, h, offset=PAD - 0.5) for k in knots]
        ncc = np.empty((len(hyp),) + ref_c.shape, np.float32)
        for k in range(len(hyp)):
            x, y = _between_knots(knots, coords, k, w)
            warped = cv2.remap(padded, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            mean_w = cv2.blur(warped, size)
            std_w = np.sqrt(np.maximum(cv2.blur(warped * warped, size) - mean_w * mean_w, 0.0))
            cov = cv2.blur(ref_c * warped, size) - mean_r * mean_w
            score = cov / np.maximum(std_r * std_w, 1e-3)
            score[y > min_y] = -1.0
            ncc[k] = score
        inner = slice(top - lo, min(top + CHUNK_ROWS, h) - lo)
        ranges = _winner_ranges(ncc[:, inner], hyp, depression[top:top + CHUNK_ROWS], options)
        ranges[~(std_r[inner] >= options.min_texture_std) | ~swept[top:top + CHUNK_ROWS]] = np.nan
        out[top:top + CHUNK_ROWS] = ranges
    return out


def _between_knots(knots: np.ndarray, coords: list, k: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The warp's source pixels of hypothesis k: exact at the knots, linear in the hypothesis index between them
    (the point moves smoothly along its epipolar curve; a fraction of a pixel off at 1.5% steps), the column
    unwrapped across the panorama's seam."""
    b = int(np.searchsorted(knots, k))
    if knots[b] == k:
        return coords[b]
    a = b - 1
    t = np.float32((k - knots[a]) / (knots[b] - knots[a]))
    (xa, ya), (xb, yb) = coords[a], coords[b]
    dx = xb - xa
    dx = np.where(dx > width / 2, dx - width, np.where(dx < -width / 2, dx + width, dx))
    x = xa + t * dx
    x = np.where(x < PAD - 0.5, x + width, np.where(x >= width + PAD - 0.5, x - width, x))
    return x.astype(np.float32), (ya + t * (yb - ya)).astype(np.float32)


def _winner_ranges(ncc: np.ndarray, hyp: np.ndarray, depression: np.ndarray, options: GroundSweepOptions
                   ) -> np.ndarray:
    """Ranges of the winning hypotheses (sub-step parabola in log height) that pass the correlation floor and the
    uniqueness test; NaN elsewhere. ``ncc`` (K, rows, W)."""
    k_count = len(hyp)
    best = np.argmax(ncc, axis=0)
    top = np.take_along_axis(ncc, best[None], 0)[0]
    inside = (best > 0) & (best < k_count - 1)
    prev = np.take_along_axis(ncc, np.clip(best - 1, 0, k_count - 1)[None], 0)[0]
    nxt = np.take_along_axis(ncc, np.clip(best + 1, 0, k_count - 1)[None], 0)[0]
    curve = prev - 2 * top + nxt
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(curve < 0, 0.5 * (prev - nxt) / curve, 0.0)
    log_h = np.log(hyp[0]) + (best + np.clip(shift, -0.5, 0.5)) * (np.log(hyp[-1] / hyp[0]) / (k_count - 1))
    # the best other local maximum: a second surface (or a repeated texture) nearly as good makes the winner unsure
    peaks = np.zeros(ncc.shape, bool)
    peaks[1:-1] = (ncc[1:-1] >= ncc[:-2]) & (ncc[1:-1] >= ncc[2:])
    peaks[np.clip(best, 0, k_count - 1)[None] == np.arange(k_count)[:, None, None]] = False
    second = np.where(peaks, ncc, -1.0).max(axis=0)
    unique = (1.0 - top) <= options.max_second_ratio * (1.0 - second)
    ok = inside & (top >= options.min_ncc) & unique
    with np.errstate(divide="ignore", invalid="ignore"):
        ranges = np.exp(log_h) / depression
    return np.where(ok, ranges, np.nan).astype(np.float32)


def _left_right_agree(range_a: np.ndarray, range_b: np.ndarray, R_a, c_a, R_b, c_b, tolerance: float) -> np.ndarray:
    """Where panorama a's range puts a point that panorama b's own sweep finds at the same range (nearest pixel,
    ``tolerance`` relative)."""
    h, w = range_a.shape
    finite = np.isfinite(range_a)
    rays = pixel_grid_bearings(w, h, np.float32)[finite] @ np.asarray(R_a, np.float32)
    points = np.asarray(c_a, np.float32) + rays * range_a[finite][:, None]
    in_b = (points - np.asarray(c_b, np.float32)) @ np.asarray(R_b, np.float32).T
    x, y = bearings_to_pixels_f32(in_b, w, h)
    col = np.mod(np.floor(x), w).astype(np.intp)
    row = np.clip(np.floor(y), 0, h - 1).astype(np.intp)
    seen = range_b[row, col]
    dist = np.linalg.norm(in_b, axis=1)
    keep = np.zeros((h, w), bool)
    with np.errstate(invalid="ignore"):
        keep[finite] = np.abs(seen - dist) <= tolerance * seen
    return keep


def _grey(image: np.ndarray) -> np.ndarray:
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    return np.ascontiguousarray(grey, np.float32)
