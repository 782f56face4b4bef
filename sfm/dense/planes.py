"""Textureless surfaces: planes through the depths around untextured image regions, checked by the views.

Stereo finds depth where there is texture; on plain walls, floors and ceilings it finds only the edges where they
meet, and those edges bound the plain surface on its plane. So, per panorama (``fill_plane_ranges``):

1. ``image_regions``: connected regions bounded by image edges (Canny) and by the pixels that have a stereo depth,
   joined across the ±180° seam and across the poles.
2. ``fit_region_planes``: a region's evidence is the stereo depths inside it and within a few pixels of its border
   (``RING_OFFSETS``); its plane is fitted to them by RANSAC and refined by least squares in shrinking bands, and
   kept when it explains ``min_share`` of them and they span it (not one line). A region whose edges leak (a wall
   and the ceiling together) has no such plane and is not filled. A plane within ``snap_deg`` of level is made
   exactly level where that still explains ``min_share`` of them (``snap_region_plane``).
3. The region's pixels without depth get the range where their rays meet the plane (in front, not grazing), and
   ``check_against_views`` drops a filled point that a nearby view sees through (a valid range clearly beyond it) or
   sees in another colour more often than in its own.
4. ``confirmed_by_views``: a filled pixel is kept only where another panorama's own result (its stereo depth, else
   its own independent fill) puts the surface at the same range. Planes fitted from two viewpoints agree where they
   are right and seldom where they are wrong: no depth is better than a wrong depth.
Everything runs on a reduced grid (``fill_width``); the stage carries the result to the full map.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fullview.sfm.camera import bearings_to_pixels_f32, camera_center, camera_up, pixel_grid_bearings

RANSAC_HYPOTHESES = 128  # plane hypotheses per region (fit_region_plane)
MIN_SPREAD_RATIO = 0.15  # a region's plane inliers must spread this much across their main direction
REFINE_SHRINK = (1.0, 0.5, 0.25, 0.25)  # inlier bands of the successive least-squares refinements (x fit_tolerance)
MIN_GAIN_POINTS = 200  # shared stereo points exposure_gain needs to measure a gain (else: median colours)
GAIN_SAMPLE = 20_000  # exposure_gain looks at about this many of a view's stereo points
RING_OFFSETS = [(dy, dx) for r in (2, 4, 6) for dy, dx in
                ((r, 0), (-r, 0), (0, r), (0, -r), (r, r), (-r, -r), (r, -r), (-r, r))]  # a region's border band
RING_REACH = max(max(abs(dy), abs(dx)) for dy, dx in RING_OFFSETS)  # the ring's largest offset (pixels)


@dataclass(kw_only=True)
class PlaneOptions:
    fit_tolerance: float = 0.03  # relative range difference within which a depth lies on a plane
    min_evidence: int = 20  # stereo depths a region needs inside or around it
    min_share: float = 0.6  # ... of which its plane(s) must explain this share
    min_region_pixels: int = 200  # smaller regions are not filled (reduced grid)
    min_incidence_deg: float = 8.0  # rays meeting the plane at a grazing angle are not filled
    canny_low: int = 4  # Canny thresholds on the blurred grey panorama (plain walls meet in faint edges)
    canny_high: int = 12
    edge_dilation: int = 3  # edges and stereo pixels are dilated by this square before regions are formed (closes gaps)
    view_tolerance: float = 0.03  # relative range margin of the view check
    max_color_difference: float = 0.12  # relative colour difference that still counts as the same colour
    confirm_tile: int = 32  # confirmed_by_views judges a unit's filled points per tile of this side (reduced grid)
    min_confirmed: int = 10  # points of a tile another view must confirm
    min_agreement: float = 0.5  # ... at least this share of the points another view has a range for
    max_contradicted: float = 0.1  # ... and at most this share of them may be contradicted (seen through)
    snap_deg: float = 0.0  # a region's plane within this angle of level is made exactly level, where that still
    # explains min_share of its depths (snap_region_plane); 0: fitted normals kept


# ------------------------------------------------------------------------------------------------ regions
def _union_labels(labels: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Relabel so that the label pairs in ``pairs`` (K, 2) become one label each (union-find over a few labels)."""
    parent = np.arange(labels.max() + 1)

    def root(a: int) -> int:
        while parent[a] != a:
            a = parent[a]
        return a

    for a, b in pairs:
        ra, rb = root(int(a)), root(int(b))
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([root(a) for a in range(len(parent))])
    return roots[labels]


def image_regions(gray: np.ndarray, options: PlaneOptions, barrier: np.ndarray | None = None) -> np.ndarray:
    """(H, W) int32 region labels of an equirectangular grey image (0 = edge or ``barrier``), bounded by Canny edges
    and the ``barrier`` pixels (e.g. those with a stereo depth: in plain rooms, the lines where surfaces meet);
    regions meeting across the ±180° seam or at a pole are one region."""
    blurred = cv2.GaussianBlur(gray, (5, 5), 1.5)
    edges = cv2.Canny(blurred, options.canny_low, options.canny_high, L2gradient=True)
    if barrier is not None:
        edges[barrier] = 255
    edges = cv2.dilate(edges, np.ones((options.edge_dilation, options.edge_dilation), np.uint8))
    _, labels = cv2.connectedComponents((edges == 0).astype(np.uint8), connectivity=4)
    seam = np.stack([labels[:, 0], labels[:, -1]], axis=1)
    poles = [np.stack([row[:-1], row[1:]], axis=1) for row in (labels[0], labels[-1])]
    pairs = np.unique(np.vstack([seam, *poles]), axis=0)
    pairs = pairs[(pairs[:, 0] > 0) & (pairs[:, 1] > 0) & (pairs[:, 0] != pairs[:, 1])]
    return _union_labels(labels, pairs).astype(np.int32) if len(pairs) else labels.astype(np.int32)


# ------------------------------------------------------------------------------------------------ views
@dataclass(kw_only=True)
class View:
    R_cam_from_world: np.ndarray  # (3, 3)
    t_cam_from_world: np.ndarray  # (3,)
    range_map: np.ndarray  # (h, w) float32 stereo ranges on the reduced grid, NaN invalid
    observable: np.ndarray  # (h, w) bool: inside the latitude caps and the image mask
    color: np.ndarray  # (h, w, 3) float32 blurred colours on the reduced grid


def _colour_agrees(a: np.ndarray, b: np.ndarray, gain: np.ndarray, max_difference: float) -> np.ndarray:
    """Same colour up to the views' exposure gain (per channel), relative to the brighter of the two."""
    b = b * gain
    return np.max(np.abs(a - b), axis=1) <= max_difference * np.maximum(np.max(np.maximum(a, b), axis=1), 16.0)


def pixel_points(view: View, ranges: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(N, 3) world points of ``view``'s reduced-grid pixels (rows, cols) at the ranges of ``ranges`` (h, w)."""
    h, w = ranges.shape
    center = camera_center(view.R_cam_from_world, view.t_cam_from_world)
    return center + reduced_bearings_world(view.R_cam_from_world, w, h)[rows, cols] * ranges[rows, cols, None]


def stereo_points(views: list[View], step: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every ``step``-th pixel (both directions) with a range of each view's reduced grid as world points: (points
    (N, 3), range (N,) from the camera that measured each, that camera's centre (N, 3))."""
    points, ranges, observers = [], [], []
    for view in views:
        h, w = view.range_map.shape
        rng = view.range_map[::step, ::step]
        ok = np.isfinite(rng)
        center = camera_center(view.R_cam_from_world, view.t_cam_from_world)
        points.append(center + reduced_bearings_world(view.R_cam_from_world, w, h)[::step, ::step][ok]
                      * rng[ok][:, None])
        ranges.append(rng[ok])
        observers.append(np.broadcast_to(center, (int(ok.sum()), 3)))
    return np.concatenate(points), np.concatenate(ranges), np.concatenate(observers)


def project_into(view: View, points: np.ndarray, shape: tuple[int, int]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row, col, range) of world points in ``view``'s reduced grid of ``shape`` (h, w): the nearest pixel
    (clipped to the grid) and the distance from the view's centre."""
    x_cam = (points @ view.R_cam_from_world.T + view.t_cam_from_world).astype(np.float32)
    r_pred = np.linalg.norm(x_cam, axis=1)
    h, w = shape
    u, v = bearings_to_pixels_f32(x_cam / np.maximum(r_pred, 1e-12)[:, None], w, h)
    return np.clip(v.astype(np.intp), 0, h - 1), np.clip(u.astype(np.intp), 0, w - 1), r_pred


def check_against_views(points: np.ndarray, colors: np.ndarray, views: list[View], gains: list[np.ndarray],
                        options: PlaneOptions, occluders: list[np.ndarray] | None = None) -> np.ndarray:
    """Keep mask (N,) of candidate world points: no view sees a valid range clearly beyond one (it would look
    through the surface), at least one view sees its colour there, and no more views see another colour than see
    its own. Views see a point only inside their observable area and unless their range there is clearly nearer
    (occluded). ``occluders`` (one (h', w') range map per view, any size, NaN: nothing): where a view's own stereo
    is empty, the surfaces the model predicts in front of it (``world_planes.nearest_plane_ranges``) explain another
    colour there: that view's vote against the point does not count (its vote for it still does)."""
    contradicted = np.zeros(len(points), bool)
    same = np.zeros(len(points), np.int32)
    other = np.zeros(len(points), np.int32)
    tol = options.view_tolerance
    for v, (view, gain) in enumerate(zip(views, gains)):
        row, col, r_pred = project_into(view, points, view.range_map.shape)
        seen = view.observable[row, col]
        r_obs = view.range_map[row, col]
        with np.errstate(invalid="ignore"):
            beyond = r_obs > (1 + tol) * r_pred
            occluded = r_obs < (1 - tol) * r_pred
            hidden = occluded.copy()
            if occluders is not None:
                o_row, o_col, _ = project_into(view, points, occluders[v].shape)
                hidden |= occluders[v][o_row, o_col] < (1 - tol) * r_pred
        contradicted |= seen & beyond
        looks = seen & ~occluded
        agree = _colour_agrees(colors, view.color[row, col], gain, options.max_color_difference)
        same += looks & agree
        other += looks & ~agree & ~hidden
    return ~contradicted & (same >= 1) & (same >= other)


def confirmed_by_views(ref: View, fill: np.ndarray, units: np.ndarray, others: list[View],
                       other_fills: list[np.ndarray], options: PlaneOptions) -> np.ndarray:
    """(h, w) the filled pixels of ``ref`` (finite in ``fill``) whose region another view confirms.

    A filled point is confirmed where another view's own result (its stereo depth, else its own fill) puts the
    surface at the same range, and contradicted where that result lies clearly beyond it (the view sees through
    it). The points of a unit (``fill_plane_ranges``) are judged together per tile (``confirm_tile``): kept when at
    least ``min_confirmed`` of them and ``min_agreement`` of those another view has a range for are confirmed, and
    at most ``max_contradicted`` of those are contradicted. Planes fitted
    independently from two viewpoints agree where they are right and seldom where they are wrong."""
    rows, cols = np.nonzero(np.isfinite(fill))
    out = np.zeros(fill.shape, bool)
    if not len(rows):
        return out
    h, w = fill.shape
    points = pixel_points(ref, fill, rows, cols)
    agree = np.zeros(len(rows), bool)
    beyond = np.zeros(len(rows), bool)
    checked = np.zeros(len(rows), bool)
    for view, other_fill in zip(others, other_fills):
        row, col, r_pred = project_into(view, points, other_fill.shape)
        r_obs = np.where(np.isfinite(view.range_map[row, col]), view.range_map[row, col], other_fill[row, col])
        with np.errstate(invalid="ignore"):
            agree |= np.abs(r_obs - r_pred) <= options.view_tolerance * r_pred
            beyond |= r_obs > (1 + options.view_tolerance) * r_pred
        checked |= np.isfinite(r_obs)
    # a unit is judged per tile: a plane right on most of a region can be wrong in a corner of it
    tile = (rows // options.confirm_tile) * (w // options.confirm_tile + 1) + cols // options.confirm_tile
    region = units[rows, cols].astype(np.int64) * ((h // options.confirm_tile + 1) * (w // options.confirm_tile + 1)) \
        + tile
    region = np.unique(region, return_inverse=True)[1]
    n_labels = int(region.max()) + 1
    confirmed = np.bincount(region, weights=agree, minlength=n_labels)
    contradicted = np.bincount(region, weights=beyond & ~agree, minlength=n_labels)
    seen = np.bincount(region, weights=checked, minlength=n_labels)
    ok = ((confirmed >= options.min_confirmed) & (confirmed >= options.min_agreement * seen)
          & (contradicted <= options.max_contradicted * seen))
    keep = ok[region]
    out[rows[keep], cols[keep]] = True
    return out


def reduced_bearings_world(R_cam_from_world: np.ndarray, width: int, height: int) -> np.ndarray:
    """(h, w, 3) float32 world bearings of a camera's equirectangular pixel centres."""
    return pixel_grid_bearings(width, height, np.float32) @ np.asarray(R_cam_from_world, np.float32)


def reduced(values: np.ndarray, width: int, interpolation: int = cv2.INTER_NEAREST) -> np.ndarray:
    """An equirectangular map resized to ``width`` x ``width / 2`` (never enlarged)."""
    if values.shape[1] <= width:
        return values
    out = cv2.resize(values.astype(np.float32) if values.dtype == bool else values, (width, width // 2),
                     interpolation=interpolation)
    return out > 0.5 if values.dtype == bool else out


def view_of(R_cam_from_world, t_cam_from_world, range_map, observable, image_bgr, width: int) -> View:
    """A panorama on the reduced grid, for the view check: stereo ranges, observable area, blurred colours."""
    color = cv2.GaussianBlur(reduced(image_bgr, width, cv2.INTER_AREA).astype(np.float32), (5, 5), 1.0)
    return View(R_cam_from_world=np.asarray(R_cam_from_world, np.float64),
                t_cam_from_world=np.asarray(t_cam_from_world, np.float64),
                range_map=reduced(range_map, width), observable=reduced(observable, width), color=color)


def exposure_gain(a: View, b: View, tolerance: float = 0.03) -> np.ndarray:
    """Per-channel gain bringing b's colours to a's: the median colour ratio of the surface points both views
    measured (a's stereo points that b's stereo puts at the same range, within ``tolerance``). The median
    colours of the whole panoramas differ by what each view sees (by 10-20% with no exposure difference at all
    where one view sees more of a bright wall), which turned correct plain-surface points into "another colour"; with fewer than
    ``MIN_GAIN_POINTS`` shared points, that ratio is still the fallback."""
    rows, cols = np.nonzero(np.isfinite(a.range_map))
    step = max(1, len(rows) // GAIN_SAMPLE)  # a median needs no more (this runs for every pair of neighbours)
    rows, cols = rows[::step], cols[::step]
    row, col, r_pred = project_into(b, pixel_points(a, a.range_map, rows, cols), b.range_map.shape)
    with np.errstate(invalid="ignore"):
        shared = np.abs(b.range_map[row, col] - r_pred) <= tolerance * r_pred
    if shared.sum() >= MIN_GAIN_POINTS:
        seen_a, seen_b = a.color[rows[shared], cols[shared]], b.color[row[shared], col[shared]]
        return np.median(np.maximum(seen_a, 1.0) / np.maximum(seen_b, 1.0), axis=0).astype(np.float32)
    ma, mb = np.median(a.color.reshape(-1, 3), axis=0), np.median(b.color.reshape(-1, 3), axis=0)
    return (np.maximum(ma, 1.0) / np.maximum(mb, 1.0)).astype(np.float32)


# ------------------------------------------------------------------------------------------------ planes
def _region_evidence(labels: np.ndarray, range_map: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(region, row, col) of every valid pixel inside or within ``RING_OFFSETS`` of each region, sorted by region."""
    region, pixel, rows, cols = region_evidence_pixels(labels, range_map)
    return region, rows[pixel], cols[pixel]


def region_evidence_pixels(labels: np.ndarray, range_map: np.ndarray, wanted: np.ndarray | None = None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``_region_evidence`` as (region, pixel) pairs, sorted by region, with pixel an index into the (rows, cols) of
    the valid pixels (also returned): what depends on the pixel alone is then computed once per pixel. ``wanted``
    (bool per label): only the pairs of these regions (the same pairs as the others' dropped afterwards)."""
    rows, cols = np.nonzero(np.isfinite(range_map))
    width = labels.shape[1]
    wanted = np.ones(int(labels.max(initial=0)) + 1, bool) if wanted is None else wanted.copy()
    wanted[0] = False  # label 0: no region
    # the labels with the ring's reach added: the edge rows repeated (rows clipped), the columns wrapped around the
    # seam; each offset's labels are then one flat take (3x faster than clipping and wrapping the indices per offset)
    reach = RING_REACH
    padded = np.pad(np.pad(labels, ((reach, reach), (0, 0)), mode="edge"), ((0, 0), (reach, reach)), mode="wrap")
    stride = width + 2 * reach
    at = (rows + reach) * stride + (cols + reach)
    pixel, region = [], []
    for dy, dx in [(0, 0)] + RING_OFFSETS:  # the pixels' labels, each offset's kept before the next is looked up
        near = padded.ravel().take(at + (dy * stride + dx))
        keep = np.flatnonzero(wanted.take(near))
        pixel.append(keep)
        region.append(near.take(keep))
    pair = np.unique(np.concatenate(region).astype(np.int64) * max(len(rows), 1) + np.concatenate(pixel))  # sorted
    return pair // max(len(rows), 1), pair % max(len(rows), 1), rows, cols


def fit_region_planes(points: np.ndarray, bearings: np.ndarray, center: np.ndarray, ranges: np.ndarray,
                      rng: np.random.Generator, options: PlaneOptions, up: np.ndarray | None = None
                      ) -> tuple[list[tuple[np.ndarray, float]], np.ndarray]:
    """The plane through a region's border points, as a list of at most one (normal, offset), and the plane of each
    point (0, or −1: none); no plane unless it explains ``min_share`` of them. With ``up`` (gravity) and
    ``snap_deg``, a nearly level plane is made exactly level where that still explains ``min_share`` of them
    (``snap_region_plane``; a ramp keeps its fit).

    One plane per region: a region whose edges leak (a wall and the ceiling together) is left empty. Up to three
    planes per region were tried: a ceiling then got a wall's plane (nearest in the image) or a slightly wrong plane
    from the leftovers (nearest along the ray), and the views confirmed it, since every view made the same choice
    (agreement between views is no check of a choice they all make)."""
    found = fit_region_plane(points, bearings, center, ranges, rng, options)
    if found is not None and up is not None and options.snap_deg > 0:
        snapped = snap_region_plane(*found, points, bearings, center, ranges, up, options)
        if snapped is not None and snapped[2].mean() >= options.min_share:
            found = snapped
    if found is None or found[2].mean() < options.min_share:
        return [], np.full(len(points), -1)
    return [found[:2]], np.where(found[2], 0, -1)


def snap_region_plane(normal: np.ndarray, offset: float, inliers: np.ndarray, points: np.ndarray,
                      bearings: np.ndarray, center: np.ndarray, ranges: np.ndarray, up: np.ndarray,
                      options: PlaneOptions) -> tuple[np.ndarray, float, np.ndarray] | None:
    """A region's plane (normal, offset, inliers) made exactly level (normal ``up``) when its normal is within
    ``snap_deg`` of that, at the median offset of its points in shrinking bands, with its inliers; None when it is
    not.

    Why: the border depths of a plain ceiling lie along the lines where it meets the walls, and stereo puts those a
    few per cent too far on some sides, so least squares tilts the plane by a degree or more (as the world planes',
    ``world_planes._snap_to_gravity``). On 360_Flat two neighbouring panoramas filled a quarter of their pixels with
    their ceilings 1.2-1.3 degrees tilted, too near by more than 2% across the room from them, and confirmed each
    other (their stereo comes from the same pairs)."""
    up = up / np.linalg.norm(up)
    cos = float(normal @ up)
    if abs(cos) < np.cos(np.radians(options.snap_deg)):
        return None  # walls keep their fit: a real wall may be off vertical (made upright, 360_Flat's R0010215 lost agreement)
    snapped = up * np.sign(cos)
    offset = float(np.median(points[inliers] @ snapped))
    for shrink in REFINE_SHRINK:
        band = _plane_inliers(snapped[None], np.array([offset]), points, bearings, center, ranges,
                              options.fit_tolerance * shrink)[0]
        if band.sum() < 3:
            return None
        offset = float(np.median(points[band] @ snapped))
    mask = _plane_inliers(snapped[None], np.array([offset]), points, bearings, center, ranges,
                          options.fit_tolerance)[0]
    return snapped, offset, mask


def fit_region_plane(points: np.ndarray, bearings: np.ndarray, center: np.ndarray, ranges: np.ndarray,
                     rng: np.random.Generator, options: PlaneOptions
                     ) -> tuple[np.ndarray, float, np.ndarray] | None:
    """The plane (normal, offset, inlier mask) through most of the points (RANSAC on triples, least squares on the
    inliers), if its inliers span it (not one line); else None. A point is an inlier when its ray meets the plane
    within ``fit_tolerance`` of its range."""
    n = len(points)
    triples = rng.integers(0, n, size=(RANSAC_HYPOTHESES, 3))
    a, b, c = points[triples[:, 0]], points[triples[:, 1]], points[triples[:, 2]]
    normals = np.cross(b - a, c - a)
    norm = np.linalg.norm(normals, axis=1)
    good = norm > 1e-12
    if not good.any():
        return None
    normals = normals[good] / norm[good, None]
    offsets = np.einsum("ij,ij->i", normals, a[good])
    inliers = _plane_inliers(normals, offsets, points, bearings, center, ranges, options.fit_tolerance)
    best = int(np.argmax(inliers.sum(axis=1)))
    mask = inliers[best]
    # least squares on the inliers, then on their inliers within a tighter band: points of a neighbouring surface
    # next to the shared edge pass the RANSAC band and would tilt the plane
    for shrink in REFINE_SHRINK:
        if mask.sum() < 3:
            return None
        centroid = points[mask].mean(axis=0)
        _, sv, vt = np.linalg.svd(points[mask] - centroid, full_matrices=False)
        normal, offset = vt[2], float(vt[2] @ centroid)
        mask = _plane_inliers(normal[None], np.array([offset]), points, bearings, center, ranges,
                              options.fit_tolerance * shrink)[0]
    mask = _plane_inliers(normal[None], np.array([offset]), points, bearings, center, ranges,
                          options.fit_tolerance)[0]
    if mask.sum() < 3 or sv[1] < MIN_SPREAD_RATIO * sv[0]:
        return None
    return normal, offset, mask


def _plane_inliers(normals, offsets, points, bearings, center, ranges, tolerance) -> np.ndarray:
    """(H, N) whether each point's ray meets each plane within ``tolerance`` (relative) of its range."""
    cos = normals @ bearings.T
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (offsets - normals @ center)[:, None] / cos
    return np.abs(r - ranges[None]) <= tolerance * ranges[None]


def _ray_plane_ranges(normal: np.ndarray, offset: float, bearings: np.ndarray, center: np.ndarray,
                      options: PlaneOptions) -> np.ndarray:
    """Per ray (N, 3) from ``center``: the range where it meets the plane, NaN behind or at a grazing angle."""
    cos = bearings @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (offset - normal @ center) / cos
    return np.where((r > 0) & (np.abs(cos) >= np.sin(np.radians(options.min_incidence_deg))), r, np.nan)


def fill_plane_ranges(ref: View, others: list[View], options: PlaneOptions, seed: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """((h, w) float32 ranges, (h, w) int32 units) that textureless filling gives the reduced-grid pixels of ``ref``
    without a stereo range (NaN elsewhere). Each edge-bounded region whose border depths lie on one plane gets that
    plane where its rays meet it, kept where the views agree (``check_against_views``); a unit is the region label
    of a filled pixel (0: none), what ``confirmed_by_views`` confirms."""
    h, w = ref.range_map.shape
    out = np.full((h, w), np.nan, np.float32)
    units = np.zeros((h, w), np.int32)
    gray = cv2.cvtColor(np.clip(ref.color, 0, 255).astype(np.uint8), cv2.COLOR_BGR2GRAY)
    labels = image_regions(gray, options, np.isfinite(ref.range_map))
    sizes = np.bincount(labels.ravel())
    bearings = reduced_bearings_world(ref.R_cam_from_world, w, h).astype(np.float64)
    center = -ref.R_cam_from_world.T @ ref.t_cam_from_world
    up = camera_up(ref.R_cam_from_world[None]) if options.snap_deg > 0 else None  # a levelled panorama's up: gravity
    region, rows, cols = _region_evidence(labels, ref.range_map)
    starts = np.searchsorted(region, np.arange(len(sizes) + 1))
    fillable = (~np.isfinite(ref.range_map) & ref.observable).ravel()
    order = np.argsort(labels.ravel(), kind="stable")  # pixels by region
    pixel_starts = np.searchsorted(labels.ravel()[order], np.arange(len(sizes) + 1))
    rng = np.random.default_rng(seed)
    fill_pix, fill_ranges = [], []
    for lab in np.flatnonzero((sizes >= options.min_region_pixels) & (np.diff(starts) >= options.min_evidence)):
        if lab == 0:
            continue
        sel = slice(starts[lab], starts[lab + 1])
        b, r = bearings[rows[sel], cols[sel]], ref.range_map[rows[sel], cols[sel]].astype(np.float64)
        planes, _ = fit_region_planes(center + b * r[:, None], b, center, r, rng, options, up)
        if not planes:
            continue
        pix = order[pixel_starts[lab]:pixel_starts[lab + 1]]
        pix = pix[fillable[pix]]
        rr = _ray_plane_ranges(*planes[0], bearings.reshape(-1, 3)[pix], center, options)
        ok = np.isfinite(rr)
        fill_pix.append(pix[ok]), fill_ranges.append(rr[ok])
    if not fill_pix:
        return out, units
    pix, rr = np.concatenate(fill_pix), np.concatenate(fill_ranges)
    keep = check_against_views(center + bearings.reshape(-1, 3)[pix] * rr[:, None], ref.color.reshape(-1, 3)[pix],
                               others, [exposure_gain(ref, o) for o in others], options)
    out.ravel()[pix[keep]] = rr[keep]
    units.ravel()[pix[keep]] = labels.ravel()[pix[keep]]
    return out, units
