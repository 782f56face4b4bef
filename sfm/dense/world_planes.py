"""Plain surfaces as planes of the world, shared by all panoramas, rather than one plane per image region.

An indoor scene is mostly a few large planes, and stereo finds their borders (the lines where walls, floor and
ceiling meet) from several viewpoints. A region of one panorama whose edges leak (a wall and the ceiling together)
has no single plane, but every pixel of it still lies on one of the world's planes. So:

1. ``detect_world_planes``: sequential RANSAC on the stereo points of all panoramas (and the sparse points), level
   or upright planes only (``max_tilt_deg``). A hypothesis scores the points no accepted plane explains yet, but a
   point on the line where two surfaces meet still supports the extent of both. A plane's **extent** is a grid in
   its own coordinates: the cells holding its supporting points, closed over small gaps (``extent_closing_cells``)
   and with the holes they enclose filled (a plain wall is supported only along its border). An opening that
   reaches the border (a doorway) is not enclosed and stays outside the extent. With gravity, the pieces of one
   wall become one plane and the four wall directions are fitted together on all the walls' points
   (``_one_wall_plane_per_offset``).
2. ``carve_extents``: every extent cell is looked at from every panorama; a cell that panoramas' stereo sees
   through more often than on it (a window, a doorway bridged by the closing) is removed, and a plane seen through
   on more than half of the cells some view has a range for was invented (e.g. through two parallel lines across a
   room) and is dropped. A wall is judged invented on its support's own extent, and each column its generous
   extent adds keeps its cells no view judged only where the columns around it hold votes on the wall and not
   mostly votes through it (``_carve_locally``): no whole-wall switch on one threshold.
   With gravity, a wall's columns are carried to the floor and ceiling planes where these do not go on behind it
   (``_walls_floor_to_ceiling``: a plain wall's stereo often holds only one of its two horizontal lines).
3. ``region_candidates`` and ``label_pixels``: each empty pixel gets the nearest plane its ray meets inside that
   plane's extent (from inside a room that is the surface it sees), among the planes that explain at least a
   quarter of the stereo depths around its image region (Canny edges and stereo pixels bound the regions, as in
   ``planes``; a region may leak, it then holds several planes' evidence); a pixel no such plane takes may take
   the nearest wall that the ranges next to it in its image column or row lie on (``_wall_brackets``); in a room, a
   pixel still empty may take the first plane its ray meets where that is the floor (``_free_floor``) or a wall
   (``_free_walls``); small islands of one label are dropped.
Before 3, ``adopt_world_planes`` moves a region fill's unit (``planes.fill_plane_ranges``) onto the kept level world
plane of its surface (a floor, a ceiling), where one lies within the view tolerance of (nearly) all its pixels.
4. ``fill_from_world_planes`` keeps a filled point where ``planes.check_against_views`` does (no nearby view sees
   through it; its colour is seen by another view); the stage then confirms it per tile by the other panoramas'
   results (``planes.confirmed_by_views``), as for the region fill.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial
from typing import Callable, Iterable

import cv2
import numpy as np
from scipy import ndimage, sparse

from fullview.sfm.camera import camera_up
from fullview.sfm.dense.planes import (PlaneOptions, View, check_against_views, exposure_gain, image_regions,
                                       pixel_points, project_into, reduced_bearings_world, region_evidence_pixels)

RANSAC_HYPOTHESES = 256  # plane hypotheses per accepted plane
REFINE_SHRINK = (1.0, 0.5, 0.25, 0.25)  # inlier bands of the successive least-squares refinements (x distance)
SCORE_SAMPLE = 8_000  # hypotheses are scored on at most this many unexplained points
MANHATTAN_WINDOW_DEG = 3.0  # walls within this azimuth of each other count for one dominant direction
LEVEL_TRIM_PERCENTILE = 1.0  # a level plane's gravity rectangle spans these percentiles of its support (each axis)
SNAP_SHRINK = (1.0, 0.5)  # bands of the offset refinement of a snapped plane (x distance)
# _one_level_plane_per_band: level planes of one side within this many median tolerances are one surface: two pieces
# fitted to one surface's points, each within a tolerance of them, lie up to 2 tolerances apart, plus one for the band
LEVEL_MERGE_BANDS = 3
LEVEL_MODE_WINDOWS = (2.0, 1.0, 0.5)  # _merge_level_pieces: half-widths (x median tolerance) of the mode's windows
LEVEL_MODE_ROUNDS = 10  # ... medians per window at most (until the height stays)
# A band's level plane is invented where the views see this many view tolerances beyond it: a plain surface's own
# stereo lies up to one tolerance beyond it (the matching window takes the corner's disparity), a view through it more
LEVEL_DROP_TOLERANCES = 2
WALL_MERGE_BANDS = 3  # _one_wall_plane_per_offset: snapped walls facing one way within this many median tolerances
# (as LEVEL_MERGE_BANDS)
WALL_AZIMUTH_BANDS = (3.0, 2.0) + (1.0,) * 8  # ... rounds of the common wall direction's fit, inlier band (x
# tolerance); the rounds in the last band stop when the direction's step moves no point by more than
WALL_AZIMUTH_STAYS = 0.01  # ... this share of the median tolerance (the step times the points' horizontal span)
INDEX_AFTER_SLABS = 3  # _WallSide: a side asked for more slabs than this indexes its points by offset bucket ...
OFFSET_BUCKETS = 1 << 16  # ... into this many (16-bit keys: a radix sort)
SWEEP_SUPPORT_FACTOR = 2  # a swept wall needs this many times min_support points (its lines, seen from its side)
BEHIND_CELLS = 2  # _walls_floor_to_ceiling: floor (ceiling) points this many cells behind a wall's face ...
BEHIND_POINTS = 3  # ... at least this many in a column: the floor (ceiling) goes on behind the wall there
GROUND_TILT_GAIN = 1.5  # tilt_ground: the tilted ground must explain this many times the level one's points
EVIDENCE_BLOCK = 16_384  # region_candidates judges this many stereo pixels against all planes at a time
ADOPT_SHARE = 0.9  # adopt_world_planes: a region fill's unit takes a world plane within view_tolerance of this share
# of its pixels


@dataclass(kw_only=True)
class WorldPlaneOptions:
    distance: float  # a point within this share of its range (from the camera that saw it) of a plane supports it
    cell: float  # side of an extent cell (model units)
    min_support: int = 150  # points (not yet explained) a plane needs
    max_planes: int = 60
    extent_closing_cells: int = 3  # gaps in a plane's support up to about this many cells are closed
    extent_hull: bool = False  # extent: convex hull of each piece of support (else its enclosed holes filled)
    min_front_share: float = 0.8  # with observers: this share of a plane's points must be seen from one side
    extent: str = "gravity"  # "support": closed support, enclosed holes filled; "gravity": see _gravity_extent
    max_tilt_deg: float = 5.0  # planes are level or upright within this angle (90: any orientation)
    min_evidence_cells: int = 20  # a plane is judged by the free-space check only with this many cells seen
    view_tolerance: float = 0.03  # relative range margin of "sees through" and of "occluded"
    max_seen_through: float = 0.5  # a plane whose extent is seen through more than this share is dropped
    local_extent: bool = True  # a plane with a generous extent: judged on its support's extent, each added cell by
    # the votes around it (_carve_locally); else the whole generous extent or, seen through, the support's alone
    extent_evidence_cells: int = 8  # _evidenced: half-side of the window of votes an added cell is judged by
    min_incidence_deg: float = 8.0  # rays meeting a plane at a grazing angle are not filled
    min_region_support: int = 10  # stereo depths around an image region a plane must explain to be taken there
    min_region_share: float = 0.25  # ... and this share of them
    min_island_pixels: int = 50  # smaller connected pieces of one label are not filled (reduced grid)
    sweep_walls: bool = True  # with up and observers: add the walls along the dominant directions RANSAC missed
    free_ceiling: bool = True  # a level plane above the camera may fill any image region (region_candidates)
    ceiling_over_camera: bool = True  # ... only if its extent spans over the camera (outdoors: no ceiling at all)
    free_floor: bool = True  # label_pixels: a pixel nothing else takes may take the floor under the camera where it is
    # the first plane its ray meets, in a room (a ceiling spans over the camera too): _free_floor
    free_walls: bool = True  # label_pixels: a pixel nothing else takes (not even the free floor) may take the first
    # plane its ray meets where that is a wall (upright), in a room: _free_walls
    occluders_on_walls: bool = True  # fill_from_world_planes: the occluders void votes against wall pixels too (else
    # against floor and ceiling pixels only)
    snap_deg: float = 6.0  # with up known: level planes exactly level, upright ones within this angle of the dominant
    # wall direction (or its perpendicular) turned onto it (_snap_to_gravity); 0: fitted normals kept
    one_level_per_band: bool = True  # with snap_deg > 0: the level planes of one side within LEVEL_MERGE_BANDS
    # median tolerances of each other become one, at the mode of their points' heights (_one_level_plane_per_band)
    one_wall_per_offset: bool = True  # with snap_deg > 0 and observers: the snapped wall pieces facing one way that
    # reach one mode of their points' offsets become one wall, the wall direction fitted on all walls' points
    # (_one_wall_plane_per_offset)
    wall_brackets: bool = True  # label_pixels: a pixel no plane of its image region takes may take the nearest
    # wall that brackets it in its image column or row (_wall_brackets)
    ground_band: float = 0.5  # tilt_ground: its candidates lie within this share of the camera height of the ground
    ground_max_tilt_deg: float = 10.0  # tilt_ground: the ground may be refitted this far from level (0: never)
    walls_floor_to_ceiling: bool = True  # with snap_deg > 0 and observers: a wall's columns run from the floor to
    # the ceiling plane (_walls_floor_to_ceiling); the free-space check and the views then cut what is not wall
    room_window_cells: int = 2  # a level plane spans over (under) a camera where half the cells within this many of
    # the camera's foot point lie in its extent (WorldPlane.spans_over; 0: the foot's cell alone)
    adopt_in_regions: bool = True  # the stage moves a region fill's unit onto the level world plane that matches it
    # (adopt_world_planes) before the world fill


@dataclass(kw_only=True)
class WorldPlane:
    normal: np.ndarray  # (3,) unit
    offset: float  # normal · x = offset on the plane
    origin: np.ndarray  # (3,) world point of extent cell (0, 0)'s corner
    axes: np.ndarray  # (2, 3) in-plane unit axes (cell columns, cell rows)
    cell: float
    extent: np.ndarray  # (rows, cols) bool
    support: int  # supporting points
    front: int = 0  # side (sign of normal · x − offset) its points were seen from; 0: unknown
    fallback: np.ndarray | None = None  # (rows, cols) bool: the support's own extent (closed, holes filled), used
    # when the views see through most of a generous ``extent``
    level: bool = False  # made exactly level, gravity known (_snap_to_gravity)
    drop_tolerance: float = 0.0  # > 0: relative range margin beyond which the views see through it when _carve
    # judges whether it was invented (else view_tolerance); a level plane of a band (_merge_level_pieces)

    def is_ceiling_of(self, center: np.ndarray, up: np.ndarray) -> bool:
        """Whether this is a level plane above ``center`` (``up``: the vertical, either sign of it)."""
        cos = float(self.normal @ up)
        return self.level and abs(cos) > 0.5 and (self.offset - self.normal @ center) / cos > 0

    def spans_over(self, center: np.ndarray, reach: int = 0) -> bool:
        """Whether the point of this plane straight above (or below) ``center`` lies inside its extent: a room's
        ceiling spans over every camera in the room; a level plane beside the camera (a porch roof, a ledge or a
        cloud seen from a street) does not. With ``reach`` > 0: whether at least half the cells within ``reach``
        cells of that point (a square window; cells off the grid count as outside) lie inside the extent.

        Why the window: the floor under a camera lies in its tripod cap, and the free-space check carves single cells
        there (a glossy floor's reflections look through it). On 360_Flat the one cell under R0010215 was carved in
        one run and not in another with the poses 1e-4° apart, and with it the camera's free floor and free walls
        (0.08 of the panorama) came and went; 17 of the 25 cells around it were in the extent in both."""
        foot = np.asarray(center, np.float64) - (self.normal @ center - self.offset) * self.normal
        if reach <= 0:
            return bool(self.contains(foot[None])[0])
        col, row = np.floor((foot - self.origin) @ self.axes.T / self.cell).astype(np.int64)
        window = self.extent[max(row - reach, 0):max(row + reach + 1, 0), max(col - reach, 0):max(col + reach + 1, 0)]
        return bool(window.sum() >= 0.5 * (2 * reach + 1) ** 2)

    def cells_of(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside the grid) of world points (assumed on the plane)."""
        uv = (points - self.origin) @ self.axes.T / self.cell
        col, row = np.floor(uv[:, 0]).astype(np.intp), np.floor(uv[:, 1]).astype(np.intp)
        inside = (row >= 0) & (row < self.extent.shape[0]) & (col >= 0) & (col < self.extent.shape[1])
        return np.where(inside, row, 0), np.where(inside, col, 0), inside

    def contains(self, points: np.ndarray) -> np.ndarray:
        row, col, inside = self.cells_of(points)
        return inside & self.extent[row, col]

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) of the extent cells and their (N, 3) world centres."""
        rows, cols = np.nonzero(self.extent)
        uv = np.stack([cols + 0.5, rows + 0.5], axis=1) * self.cell
        return (rows, cols), self.origin + uv @ self.axes


# ------------------------------------------------------------------------------------------------ detection
def _plane_basis(normal: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """(2, 3) two unit axes spanning the plane of ``normal``; for a plane containing ``up`` (upright), the second
    axis is ``up`` projected on the plane (grid columns are vertical lines of the wall)."""
    if up is not None and abs(normal @ up) < 0.5:
        b = up - (up @ normal) * normal
        b /= np.linalg.norm(b)
        return np.stack([np.cross(b, normal), b])
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    a = np.cross(normal, helper)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(normal, a)])


def _gravity_extent(grid: np.ndarray, upright: bool) -> np.ndarray:
    """Indoors, with gravity known: a level plane (floor, ceiling) spans the bounding rectangle of its support, and
    an upright plane (wall) spans, in each vertical column of its grid, the cells between its lowest and highest
    support. A plain wall is supported along its floor and ceiling lines, so it is filled between them; a doorway's
    columns hold support only at the lintel (its floor line is missing), so the opening stays outside. What the
    views see through is removed afterwards (``carve_extents``): the free space bounds the extent, not its
    outline."""
    if not grid.any():
        return grid
    if not upright:
        return np.ones_like(grid)
    above = np.maximum.accumulate(grid, axis=0)
    below = np.maximum.accumulate(grid[::-1], axis=0)[::-1]
    return above & below


def _fit(points: np.ndarray) -> tuple[np.ndarray, float]:
    centroid = points.mean(axis=0)
    normal = np.linalg.svd(points - centroid, full_matrices=False)[2][2]
    return normal, float(normal @ centroid)


def _extent(support: np.ndarray, normal: np.ndarray, offset: float, cell: float, closing: int, hull: bool,
            mode: str = "support", up: np.ndarray | None = None, axes: np.ndarray | None = None):
    """(origin, axes, extent grid) of a plane from its supporting points (``WorldPlaneOptions.extent``); ``axes``
    (2, 3): the grid's in-plane axes, if not the default ones (``_plane_basis``)."""
    axes = _plane_basis(normal, up if mode == "gravity" else None) if axes is None else axes
    uv = support @ axes.T
    lo = uv.min(axis=0) - cell
    idx = np.floor((uv - lo) / cell).astype(np.intp)
    shape = idx.max(axis=0)[::-1] + 2
    grid = np.zeros(shape, np.uint8)
    grid[idx[:, 1], idx[:, 0]] = 1
    size = 2 * closing + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    grid = cv2.morphologyEx(np.pad(grid, size), cv2.MORPH_CLOSE, kernel)[size:-size, size:-size]
    if hull:
        contours, _ = cv2.findContours(grid, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.fillPoly(grid, [cv2.convexHull(c) for c in contours], 1)
    closed = ndimage.binary_fill_holes(grid > 0)
    extent = _gravity_extent(grid > 0, upright=abs(normal @ up) < 0.5) if mode == "gravity" and up is not None \
        else closed
    if mode == "gravity" and up is not None and abs(normal @ up) >= 0.5 and LEVEL_TRIM_PERCENTILE > 0:
        # the rectangle between low and high percentiles of the support: stereo a few per cent too far at the
        # lines where the ceiling meets the outer walls supports the ceiling plane beyond those walls
        first, last = np.percentile(idx, [LEVEL_TRIM_PERCENTILE, 100 - LEVEL_TRIM_PERCENTILE], axis=0)
        rows, cols = np.arange(shape[0])[:, None], np.arange(shape[1])[None]
        extent = extent & (cols >= np.floor(first[0])) & (cols <= np.ceil(last[0])) \
            & (rows >= np.floor(first[1])) & (rows <= np.ceil(last[1]))
    origin = normal * offset + lo @ axes
    return origin, axes, extent, (closed if extent is not closed else None)


def _tilt_ok(normals: np.ndarray, up: np.ndarray | None, max_tilt_deg: float) -> np.ndarray:
    """Whether each normal (K, 3) is within ``max_tilt_deg`` of ``up`` or of the horizontal (level or upright
    planes); all True without ``up``."""
    if up is None or max_tilt_deg >= 90:
        return np.ones(len(normals), bool)
    sin_up = np.abs(normals @ up)
    return (sin_up >= np.cos(np.radians(max_tilt_deg))) | (sin_up <= np.sin(np.radians(max_tilt_deg)))


def detect_world_planes(points: np.ndarray, ranges: np.ndarray, rng: np.random.Generator,
                        options: WorldPlaneOptions, up: np.ndarray | None = None,
                        observers: np.ndarray | None = None) -> list[WorldPlane]:
    """The dominant planes of a point cloud (N, 3) by sequential RANSAC, each with its supported extent. A point
    supports a plane within ``distance`` times its range (N,) from the camera that measured it: stereo errors grow
    with the range. ``observers`` (N, 3): the centre of the camera that measured each point. A surface is seen from
    one side: a plane whose points were seen from both sides (less than ``min_front_share`` from one) runs through
    both faces of a thin wall and is not kept; the side of the others is their ``front``."""
    points = np.asarray(points, np.float64)
    tolerance = options.distance * np.asarray(ranges, np.float64)
    explained = np.zeros(len(points), bool)
    planes: list[WorldPlane] = []
    for _ in range(2 * options.max_planes):  # a tilted best plane costs a round
        if len(planes) >= options.max_planes:
            break
        free = np.flatnonzero(~explained)
        if len(free) < max(options.min_support, 3):
            break
        idx = free[rng.choice(len(free), min(SCORE_SAMPLE, len(free)), replace=False)]
        sample, sample_tol = points[idx].astype(np.float32), tolerance[idx].astype(np.float32)
        triples = free[rng.integers(0, len(free), size=(RANSAC_HYPOTHESES, 3))]
        a, b, c = points[triples[:, 0]], points[triples[:, 1]], points[triples[:, 2]]
        normals = np.cross(b - a, c - a)
        norm = np.linalg.norm(normals, axis=1)
        ok = norm > 1e-12
        ok[ok] = _tilt_ok(normals[ok] / norm[ok, None], up, options.max_tilt_deg)
        if not ok.any():
            continue
        normals = normals[ok] / norm[ok, None]
        offsets = np.einsum("ij,ij->i", normals, a[ok])
        # score: the points no accepted plane explains yet
        score = np.count_nonzero(np.abs(sample @ normals.T.astype(np.float32) - offsets.astype(np.float32))
                                 <= sample_tol[:, None], axis=0)
        best = int(np.argmax(score))
        normal, offset = normals[best], offsets[best]
        # least squares in shrinking bands: points of a neighbouring surface next to the shared edge pass the
        # RANSAC band and would tilt the plane
        for shrink in REFINE_SHRINK:
            inliers = np.abs(points @ normal - offset) <= shrink * tolerance
            if inliers.sum() < 3:
                break
            normal, offset = _fit(points[inliers])
        inliers = np.abs(points @ normal - offset) <= tolerance
        if not _tilt_ok(normal[None], up, options.max_tilt_deg)[0]:
            continue
        new = inliers & ~explained
        if new.sum() < options.min_support:
            # this plane does not hold enough unexplained points; the best hypothesis will not get better
            break
        explained |= inliers
        front = 0
        if observers is not None:
            side = np.sign(observers[inliers] @ normal - offset)
            if max(np.mean(side > 0), np.mean(side < 0)) < options.min_front_share:
                continue
            front = 1 if side.sum() > 0 else -1
        support = points[inliers]
        origin, axes, extent, fallback = _extent(support, normal, offset, options.cell, options.extent_closing_cells,
                                       options.extent_hull, options.extent, up)
        planes.append(WorldPlane(normal=normal, offset=offset, origin=origin, axes=axes, cell=options.cell,
                                 extent=extent, support=int(inliers.sum()), fallback=fallback, front=front))
    if up is not None and options.snap_deg > 0:
        planes = _snap_to_gravity(planes, points, tolerance, np.asarray(up, np.float64), options)
        if options.one_level_per_band:
            planes = _one_level_plane_per_band(planes, points, tolerance, np.asarray(up, np.float64) /
                                               np.linalg.norm(up), observers, options)
        merge_walls = options.one_wall_per_offset and observers is not None
        if merge_walls:  # the sweep then runs along the direction fitted on all the walls' points
            planes = _one_wall_plane_per_offset(planes, points, tolerance, np.asarray(up, np.float64) /
                                                np.linalg.norm(up), observers, options)
        if options.sweep_walls and observers is not None:
            planes = planes + _sweep_walls(planes, points, tolerance, np.asarray(up, np.float64), observers, options)
            if merge_walls:  # a swept wall a few bands off a wall's mode: a line of its stereo, too far
                planes = _one_wall_plane_per_offset(planes, points, tolerance, np.asarray(up, np.float64) /
                                                    np.linalg.norm(up), observers, options)
        if options.walls_floor_to_ceiling and observers is not None:
            _walls_floor_to_ceiling(planes, np.asarray(up, np.float64), observers, points, tolerance)
    return planes


# ------------------------------------------------------------------------------------------------ gravity
def _floor_and_ceiling_heights(planes: list[WorldPlane], up: np.ndarray, eye: float) -> tuple[float, float] | None:
    """Heights (along ``up``) of the best-supported level plane below ``eye`` (the floor) and above it (the
    ceiling); None unless both exist."""
    below, above = None, None
    for p in sorted((p for p in planes if p.level), key=lambda p: -p.support):
        height = p.offset * float(np.sign(p.normal @ up))
        if height < eye and below is None:
            below = height
        elif height > eye and above is None:
            above = height
    return (below, above) if below is not None and above is not None else None


def _walls_floor_to_ceiling(planes: list[WorldPlane], up: np.ndarray, observers: np.ndarray, points: np.ndarray,
                            tolerance: np.ndarray) -> None:
    """Carry the columns of each one-sided upright plane's extent that hold a cell down to the floor plane and up to
    the ceiling plane (in place), except where that floor or ceiling goes on behind the wall.

    Why: a plain wall's stereo is its floor line, its ceiling line and its corners, and often only one of the two
    horizontal lines lies within the point tolerance (a long wall parallel to the walk can have its ceiling
    line in no stereo: matching along a line parallel to the baseline has nothing to lock on): its columns then held
    only that line. Where the floor's own points go on behind the wall (more than ``BEHIND_CELLS`` cells behind its
    face, at least ``BEHIND_POINTS`` of them in a column), the wall is not what bounds the room there: a doorway (the
    floor goes on into the next room) or an interior wall, whose own lines stay its extent; the same for the ceiling
    (a wall that stops below it). What the views see through is removed later (``carve_extents``), and a pixel takes
    a wall only where its image region or its brackets support it (``label_pixels``)."""
    up = up / np.linalg.norm(up)
    heights = _floor_and_ceiling_heights(planes, up, float(np.median(observers @ up)))
    if heights is None:
        return
    levels = {}
    for name, height in zip(("floor", "ceiling"), heights):
        on = np.abs(points @ up - height) <= tolerance
        levels[name] = (height, points[on])
    for plane in planes:
        if plane.level or not plane.front or abs(plane.normal @ up) > 1e-6 \
                or abs(plane.axes[1] @ up) < 1 - 1e-6 or not plane.extent.any():
            continue
        for name, (height, level_points) in levels.items():
            base = float(plane.origin @ plane.axes[1])  # height of row 0's lower edge
            target = int(np.floor((height - base) / plane.cell))
            pad = (max(0, -target), 0) if name == "floor" else (0, max(0, target - plane.extent.shape[0] + 1))
            if any(pad):
                plane.extent = np.pad(plane.extent, (pad, (0, 0)))
                if plane.fallback is not None:
                    plane.fallback = np.pad(plane.fallback, (pad, (0, 0)))
                plane.origin = plane.origin - pad[0] * plane.cell * plane.axes[1]
                target += pad[0]
            rows, cols = plane.extent.shape
            behind = plane.front * (level_points @ plane.normal - plane.offset) < -BEHIND_CELLS * plane.cell
            col = np.floor((level_points[behind] - plane.origin) @ plane.axes[0] / plane.cell).astype(np.intp)
            goes_on = np.bincount(col[(col >= 0) & (col < cols)], minlength=cols) >= BEHIND_POINTS
            columns = plane.extent.any(axis=0) & ~goes_on
            row = np.arange(rows)[:, None]
            if name == "floor":
                lowest = np.argmax(plane.extent, axis=0)[None]
                plane.extent |= columns[None] & (row >= target) & (row < lowest)
            else:
                highest = rows - 1 - np.argmax(plane.extent[::-1], axis=0)[None]
                plane.extent |= columns[None] & (row > highest) & (row <= target)


def tilt_ground(planes: list[WorldPlane], points: np.ndarray, ranges: np.ndarray, centers: np.ndarray,
                up: np.ndarray, rng: np.random.Generator, options: WorldPlaneOptions) -> list[WorldPlane]:
    """The ground refitted with a free tilt (at most ``ground_max_tilt_deg``) where that explains clearly more of the
    points near it than the level plane does (``GROUND_TILT_GAIN`` times as many).

    Indoors a floor is level, and snapping it to gravity removes the noise of its fit. Outdoors the ground slopes
    (drainage, a street's camber, a hill) and the panoramas' gravity is known to a degree or two: on the school
    courtyard the level ground explains 19% of the low stereo points within 3% of the camera height, a plane tilted
    2.7° explains 40%, and a quadric no more than that plane. A ray meets the ground at a grazing angle, so
    the range errs by the height error over the camera's height: the level plane put the ground 8% too near or too
    far, which the other views rightly rejected.

    The ground: the best supported level plane below the cameras (their mean centre). Its candidates: the points
    below the cameras within ``ground_band`` of the camera height of it. The refitted plane keeps the level flag
    (it is the floor for the ceiling and wall rules), gets its own extent (the bounding rectangle of its support,
    gravity mode), and the level planes below the cameras that it explains (most of their support lies on it: pieces
    of a sloping ground) are dropped."""
    up = np.asarray(up, np.float64)
    center = np.asarray(centers, np.float64).mean(axis=0)
    below = [k for k, p in enumerate(planes) if p.level and not p.is_ceiling_of(center, up)]
    if not below or options.ground_max_tilt_deg <= 0:
        return planes
    ground = planes[max(below, key=lambda k: planes[k].support)]
    height = float(ground.normal @ center - ground.offset)  # signed: the camera's side of the normal
    tolerance = options.distance * np.asarray(ranges, np.float64)
    side = np.sign(height)
    off_ground = side * (points @ ground.normal - ground.offset)  # height above the ground plane
    candidates = np.flatnonzero((np.abs(off_ground) <= options.ground_band * abs(height))
                                & (off_ground < abs(height)))
    if len(candidates) < max(options.min_support, 3):
        return planes
    level_count = int(np.count_nonzero(np.abs(off_ground[candidates]) <= tolerance[candidates]))
    triples = candidates[rng.integers(0, len(candidates), size=(RANSAC_HYPOTHESES, 3))]
    a, b, c = points[triples[:, 0]], points[triples[:, 1]], points[triples[:, 2]]
    normals = np.cross(b - a, c - a)
    norm = np.linalg.norm(normals, axis=1)
    keep = norm > 1e-12
    normals = normals[keep] / norm[keep, None]
    a = a[keep]
    keep = np.abs(normals @ up) >= np.cos(np.radians(options.ground_max_tilt_deg))
    if not keep.any():
        return planes
    normals, a = normals[keep], a[keep]
    offsets = np.einsum("ij,ij->i", normals, a)
    cand, cand_tol = points[candidates], tolerance[candidates]
    scored = rng.choice(len(cand), min(SCORE_SAMPLE, len(cand)), replace=False)  # bounded memory, as detection
    score = np.count_nonzero(np.abs(cand[scored].astype(np.float32) @ normals.T.astype(np.float32)
                                    - offsets.astype(np.float32)) <= cand_tol[scored, None].astype(np.float32),
                             axis=0)
    best = int(np.argmax(score))
    normal, offset = normals[best], float(offsets[best])
    for shrink in REFINE_SHRINK:
        inliers = np.abs(cand @ normal - offset) <= shrink * cand_tol
        if inliers.sum() < 3:
            return planes
        normal, offset = _fit(cand[inliers])
    inliers = np.abs(cand @ normal - offset) <= cand_tol
    if abs(normal @ up) < np.cos(np.radians(options.ground_max_tilt_deg)) \
            or inliers.sum() < GROUND_TILT_GAIN * max(level_count, 1):
        return planes
    if normal @ ground.normal < 0:
        normal, offset = -normal, -offset
    support = cand[inliers]
    origin, axes, extent, fallback = _extent(support, normal, offset, ground.cell, options.extent_closing_cells,
                                             options.extent_hull, options.extent, up)
    tilted = replace(ground, normal=normal, offset=offset, origin=origin, axes=axes, extent=extent,
                     fallback=fallback, support=int(inliers.sum()))
    on_tilted = np.abs(points @ normal - offset) <= tolerance

    def explained(plane: WorldPlane) -> bool:  # most of a level plane's points lie on the tilted ground
        mine = (np.abs(points @ plane.normal - plane.offset) <= tolerance) & plane.contains(points)
        return bool(mine.any()) and np.mean(on_tilted[mine]) >= 0.5

    return [tilted if p is ground else p for k, p in enumerate(planes)
            if p is ground or k not in below or not explained(p)]


def _one_level_plane_per_band(planes: list[WorldPlane], points: np.ndarray, tolerance: np.ndarray, up: np.ndarray,
                              observers: np.ndarray | None, options: WorldPlaneOptions) -> list[WorldPlane]:
    """The planes with each band of level pieces replaced by one level plane. The level planes seen from one side
    (from above: a floor, a table top; from below: a ceiling) whose heights follow each other within
    ``LEVEL_MERGE_BANDS`` median tolerances are one surface found in pieces (``_merge_level_pieces``).

    Why: a floor or a ceiling is one level surface, but RANSAC finds it in pieces, each piece's height the median of
    its own inliers (a band a tolerance wide), their supports nearly equal: which piece is the best supported then
    flips with the smallest change of the sparse model, and with it the height the free-space check judges. The
    pieces' two signs of the normal would count as two sides, so two floors and two ceilings would be kept and the
    nearer of each would win every ray."""
    band = float(np.median(tolerance))
    groups: dict[int, list[tuple[float, int]]] = {}
    for i, plane in enumerate(planes):
        if plane.level:
            sign = 1 if plane.normal @ up > 0 else -1
            facing = sign * plane.front if plane.front else sign  # +1: seen from above
            groups.setdefault(facing, []).append((plane.offset * sign, i))
    replaced: dict[int, WorldPlane | None] = {}
    for facing, members in groups.items():
        members.sort()
        start = 0
        for end in range(1, len(members) + 1):
            if end < len(members) and members[end][0] - members[end - 1][0] < LEVEL_MERGE_BANDS * band:
                continue
            chain = [i for _, i in members[start:end]]
            best = max(chain, key=lambda i: planes[i].support)
            merged = _merge_level_pieces(planes[best], members[start][0], members[end - 1][0], facing, points,
                                         tolerance, up, observers, options, band)
            for i in chain:
                replaced[i] = merged if i == best else None
            start = end
    return [replaced.get(i, p) for i, p in enumerate(planes) if replaced.get(i, p) is not None]


def _merge_level_pieces(best: WorldPlane, low: float, high: float, facing: int, points: np.ndarray,
                        tolerance: np.ndarray, up: np.ndarray, observers: np.ndarray | None,
                        options: WorldPlaneOptions, band: float) -> WorldPlane:
    """One level plane for the pieces at heights ``low``..``high`` seen from the side ``facing`` (+1: above), the
    best supported of them ``best`` (its normal's sign, front and grid axes are kept): at the
    mode of the heights of the points in that slab (one band wider each way) seen from that side, found by medians
    in shrinking windows from the slab's median; its support and extent are those of the points within tolerance
    of it (as ``_snap_to_gravity``'s). The views judge whether it was invented (``_carve``) by the stereo more than
    ``LEVEL_DROP_TOLERANCES`` view tolerances beyond it.

    Why the wider margin: a plain ceiling's stereo is a few per cent too far (the matching window takes the corner's
    disparity), so at one view tolerance the views see "through" a true plain ceiling on about half of the judged
    cells (the drop is above 50%: a knife edge), at two on a third; an invented level plane (a furniture top spanning
    the flat, a plane at eye height) is seen through on nearly all of its cells either way.

    Why the mode: the pieces' own heights are medians of differently drawn inlier sets (a point supports a piece
    within 1.5% of its range, so a far floor point supports a piece several cm above the floor, and the bottom
    strips of the walls do too); the points' heights peak at the surface and trail off towards the walls' strips."""
    heights = points @ up
    slab = (heights >= low - band) & (heights <= high + band)
    if observers is not None:
        slab &= facing * (observers @ up - heights) > 0
    values = heights[slab]
    if len(values) < 3:
        return best
    height = _mode_of(values, band)
    sign = 1.0 if best.normal @ up > 0 else -1.0
    normal, offset = sign * up, sign * height
    inliers = np.abs(points @ normal - offset) <= tolerance
    origin, axes, extent, fallback = _extent(points[inliers], normal, offset, options.cell,
                                             options.extent_closing_cells, options.extent_hull, options.extent, up,
                                             best.axes)
    return WorldPlane(normal=normal, offset=offset, origin=origin, axes=axes, cell=options.cell, extent=extent,
                      support=int(inliers.sum()), fallback=fallback, front=best.front, level=True,
                      drop_tolerance=LEVEL_DROP_TOLERANCES * options.view_tolerance)


def _one_wall_plane_per_offset(planes: list[WorldPlane], points: np.ndarray, tolerance: np.ndarray, up: np.ndarray,
                               observers: np.ndarray, options: WorldPlaneOptions) -> list[WorldPlane]:
    """The planes with the walls snapped to the dominant direction (``_snap_to_gravity``) replaced by one plane per
    wall: each snapped wall piece climbs to the mode of the offsets of the points seen from its side within
    ``WALL_MERGE_BANDS`` median tolerances of it, and the pieces that reach one mode are one wall. The four wall
    directions are turned together to the direction that fits all the walls' points best (``_fit_wall_azimuth``);
    each wall then lies at the mode of its points' offsets (``_mode_of``), with the support and extent of the
    points within tolerance of it, seen from its side, judged invented by the views as a band's level plane is
    (``LEVEL_DROP_TOLERANCES``). Walls of their own direction (not snapped) are kept as they are.

    Why: a long wall comes out as many pieces whose offsets spread over about a tolerance, and the dominant direction
    taken as the mode of the pieces' fitted normals is off by a fraction of a degree: a 15 m wall turned 0.5° is 7 cm
    off at its ends (half a tolerance of 1% of the scene), so each piece fits its own stretch of the wall, and the
    nearest piece along a ray, a few cm in front of the wall, takes the pixels the wall should have. The mode of the
    pieces' normals also moves with the pieces; one direction fitted to all the walls' points does not."""
    upright = [p for p in planes if abs(p.normal @ up) < 1e-9]
    azimuth = dominant_wall_azimuth(np.array([p.normal for p in upright]).reshape(-1, 3),
                                    np.array([p.support for p in upright], np.float64), up)
    if azimuth is None:
        return planes
    e1, e2 = _horizontal_basis(up)
    band = float(np.median(tolerance))
    pieces: dict[int, list[tuple[float, int]]] = {}  # quarter of the side they are seen from: (offset, index)
    for i, plane in enumerate(planes):
        if plane.level or not plane.front or abs(plane.normal @ up) > 1e-9:
            continue
        outward = plane.front * plane.normal
        turn = (np.arctan2(outward @ e2, outward @ e1) - azimuth) / (np.pi / 2)
        if abs(turn - np.round(turn)) > 1e-6:
            continue  # a wall of its own direction
        pieces.setdefault(int(np.round(turn)) % 4, []).append((plane.front * plane.offset, i))
    flat = np.column_stack([points @ e1, points @ e2])
    seen_from = np.column_stack([observers @ e1, observers @ e2])
    walls: list[tuple[int, float, list[int]]] = []  # (quarter, offset, piece indices)
    for quarter, members in sorted(pieces.items()):
        # each piece climbs to the mode of the offsets near it; the pieces that reach one mode are one wall (not a
        # chain of pieces: a chain of many pieces a band apart reaches from a wall to a cupboard in front of it)
        side = _WallSide(flat, seen_from, tolerance, azimuth + quarter * np.pi / 2)
        starts = np.array([o for o, _ in members])
        modes = sorted(zip(side.offsets(starts - WALL_MERGE_BANDS * band, starts + WALL_MERGE_BANDS * band,
                                        band).tolist(), [i for _, i in members]))
        start = 0
        for end in range(1, len(modes) + 1):
            if end < len(modes) and modes[end][0] - modes[end - 1][0] < band:
                continue
            walls.append((quarter, float(np.median([m for m, _ in modes[start:end]])),
                          [i for _, i in modes[start:end]]))
            start = end
    if not walls:
        return planes
    azimuth, offsets = _fit_wall_azimuth(flat, seen_from, tolerance, azimuth, [w[0] for w in walls],
                                         [w[1] for w in walls], band)
    joined: dict[tuple[int, float], list[int]] = {}  # walls that the fit brought within a band: one
    for (quarter, _, members), offset in sorted(zip(walls, offsets), key=lambda w: (w[0][0], w[1])):
        last = next(reversed(joined), None)
        if last is not None and last[0] == quarter and offset - last[1] < band:
            joined[last] += members
        else:
            joined[(quarter, offset)] = list(members)
    merged: dict[int, WorldPlane | None] = {}
    sides = {q: _WallSide(flat, seen_from, tolerance, azimuth + q * np.pi / 2) for q in {q for q, _ in joined}}
    for (quarter, offset), members in joined.items():
        a = azimuth + quarter * np.pi / 2
        normal = np.cos(a) * e1 + np.sin(a) * e2
        inliers = sides[quarter].near(offset, 1.0)
        if len(inliers) < 3:
            continue
        origin, axes, extent, fallback = _extent(points[inliers], normal, offset, options.cell,
                                                 options.extent_closing_cells, options.extent_hull, options.extent, up)
        wall = WorldPlane(normal=normal, offset=offset, origin=origin, axes=axes, cell=options.cell, extent=extent,
                          support=len(inliers), fallback=fallback, front=1,
                          drop_tolerance=LEVEL_DROP_TOLERANCES * options.view_tolerance)
        first = max(members, key=lambda i: planes[i].support)
        for i in members:
            merged[i] = wall if i == first else None
    return [merged.get(i, p) for i, p in enumerate(planes) if merged.get(i, p) is not None]


class _WallSide:
    """The points seen from the side of one horizontal wall normal (``azimuth``) and their offsets along it
    (``flat`` (N, 2): the points' horizontal coordinates, ``seen_from``: their observers'): a wall's points are a
    slab of them. The wall fit builds a side per direction in each of its rounds, so a side asked for a few slabs
    (at most ``INDEX_AFTER_SLABS``) does not sort its points: each slab is a pass over all of them, and only the
    points it keeps are sorted, giving the same points in the same order (by offset, ties in row order) as a slice
    of all of them sorted by a stable sort. A side asked for more (a textured room's walls: ~180 per round), or
    for the modes of many slabs at once (``offsets``), sorts its points once: a radix sort of 16-bit offset buckets
    (``OFFSET_BUCKETS``, rows ascending within a bucket), then a stable sort of the offsets in that order, which
    is nearly sorted already (timsort: 9 ms for 240,000 points where a stable sort from scratch takes 27 ms); each
    slab is then a slice of them."""

    def __init__(self, flat: np.ndarray, seen_from: np.ndarray, tolerance: np.ndarray, azimuth: float):
        normal = np.array([np.cos(azimuth), np.sin(azimuth)])
        d = flat @ normal
        front = seen_from @ normal > d
        self.rows, self.d, self.tolerance = np.flatnonzero(front), d[front], tolerance[front]  # rows ascending
        self.widest = float(self.tolerance.max()) if len(self.rows) else 0.0
        self._reach: dict[float, np.ndarray] = {}  # shrink: shrink x tolerance
        self._slabs = 0  # slabs asked for so far
        self._index: tuple | None = None  # (rows, d, tolerance) by offset, ties in row order

    def _sorted(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, offsets, tolerances) of the side's points sorted by offset, ties in row order (built once)."""
        if self._index is None:
            order = np.arange(len(self.d))
            if len(self.d):
                lowest, highest = float(self.d.min()), float(self.d.max())
                scale = (OFFSET_BUCKETS - 1) / (highest - lowest) if highest > lowest else 0.0
                keys = np.clip((self.d - lowest) * scale, 0, OFFSET_BUCKETS - 1).astype(np.uint16)
                order = np.argsort(keys, kind="stable")  # equal offsets share a bucket: rows ascending
                order = order[np.argsort(self.d[order], kind="stable")]
            self._index = (self.rows[order], self.d[order], self.tolerance[order])
        return self._index

    def _slab(self, low: float, high: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows, offsets and tolerances of the points with ``low <= offset <= high`` by offset, ties in row order
        (every point, unsorted, while the side has no index)."""
        self._slabs += 1
        if self._index is None and (self._slabs <= INDEX_AFTER_SLABS or not len(self.d)):
            return self.rows, self.d, self.tolerance
        rows, d, tolerance = self._sorted()
        slab = slice(np.searchsorted(d, low, "left"), np.searchsorted(d, high, "right"))
        return rows[slab], d[slab], tolerance[slab]

    def offset(self, low: float, high: float, band: float) -> float:
        """The mode of the offsets in ``low``..``high`` (``_mode_of``); the middle if fewer than three lie there."""
        d = self._slab(low, high)[1]
        values = np.sort(d[(d >= low) & (d <= high)])
        return _mode_of(values, band, presorted=True) if len(values) >= 3 else 0.5 * (low + high)

    def offsets(self, lows: np.ndarray, highs: np.ndarray, band: float) -> np.ndarray:
        """``offset`` of each slab ``lows[k]``..``highs[k]``, all at once (``_modes_of_runs``): the same numbers."""
        d = self._sorted()[1]
        lows, highs = np.asarray(lows, np.float64), np.asarray(highs, np.float64)
        starts, stops = np.searchsorted(d, lows, "left"), np.searchsorted(d, highs, "right")
        many = stops - starts >= 3
        out = 0.5 * (lows + highs)
        out[many] = _modes_of_runs(d, starts[many], stops[many], band)
        return out

    def near(self, offset: float, shrink: float) -> np.ndarray:
        """Rows of the points within ``shrink`` times their tolerance of the plane at ``offset``, by offset (ties
        in row order): those within ``shrink`` times the widest tolerance of it (the slab a sorted search would
        read) and within their own."""
        low, high = offset - shrink * self.widest, offset + shrink * self.widest
        rows, d, tolerance = self._slab(low, high)
        if rows is not self.rows:  # a slice of the sorted points
            return rows[np.abs(d - offset) <= shrink * tolerance]
        if shrink not in self._reach:  # no index: every point, with its reach kept for the side's next slabs
            self._reach[shrink] = shrink * self.tolerance
        at = np.flatnonzero(np.abs(d - offset) <= self._reach[shrink])
        kept = d[at]
        keep = (kept >= low) & (kept <= high)
        return rows[at[keep][np.argsort(kept[keep], kind="stable")]]


def _side_offsets(sides: dict[int, _WallSide], quarters: list[int], offsets: list[float], reach: float,
                  band: float) -> list[float]:
    """Each wall's mode (``_WallSide.offsets``) within ``reach`` of its offset, its side's walls at once."""
    quarters, out = np.asarray(quarters), np.asarray(offsets, np.float64).copy()
    for q, side in sides.items():
        mine = np.flatnonzero(quarters == q)
        if len(mine):
            out[mine] = side.offsets(out[mine] - reach, out[mine] + reach, band)
    return out.tolist()


def _fit_wall_azimuth(flat: np.ndarray, seen_from: np.ndarray, tolerance: np.ndarray, azimuth: float,
                      quarters: list[int], offsets: list[float], band: float) -> tuple[float, list[float]]:
    """The wall direction (radians, modulo 90°) that fits the points of all the walls (``quarters``, ``offsets``)
    best, and the walls' offsets along it: least squares over every wall's points within a band of it (each wall
    its own offset, all at right angles), i.e. the smallest eigenvector of the sum of their horizontal scatter
    matrices, each turned back by its wall's right angles (``WALL_AZIMUTH_BANDS``: the rounds' inlier bands; the
    offsets are the modes again after each round). One long wall fixes the direction better than the mode of
    short pieces' fitted normals, and its fit moves continuously with the points."""
    def normal_of(azimuth: float, quarter: int) -> np.ndarray:
        return np.array([np.cos(azimuth + quarter * np.pi / 2), np.sin(azimuth + quarter * np.pi / 2)])

    def sides_at(azimuth: float) -> dict[int, _WallSide]:
        return {q: _WallSide(flat, seen_from, tolerance, azimuth + q * np.pi / 2) for q in set(quarters)}

    sides = sides_at(azimuth)
    span = float(np.max(np.ptp(flat, axis=0))) if len(flat) else 0.0
    for shrink in WALL_AZIMUTH_BANDS:
        scatter, centroids = np.zeros((2, 2)), []
        for quarter, offset in zip(quarters, offsets):
            near = flat[sides[quarter].near(offset, shrink)]
            centroids.append(near.mean(axis=0) if len(near) >= 3 else None)
            if len(near) < 3:
                continue
            c, s = np.cos(-quarter * np.pi / 2), np.sin(-quarter * np.pi / 2)
            turned = near @ np.array([[c, -s], [s, c]]).T  # this wall's normal turned onto the first
            turned -= turned.mean(axis=0)
            scatter += turned.T @ turned
        if not scatter.any():
            break
        normal = np.linalg.eigh(scatter)[1][:, 0]
        fitted = np.arctan2(normal[1], normal[0])
        turned_to = azimuth + (fitted - azimuth + np.pi / 2) % np.pi - np.pi / 2  # the same line, nearest turn
        # each wall turns about its points' centroid (not the model's origin), then takes the mode near there
        offsets = [o if m is None else o + m @ (normal_of(turned_to, q) - normal_of(azimuth, q))
                   for q, o, m in zip(quarters, offsets, centroids)]
        step, azimuth = abs(turned_to - azimuth), turned_to
        sides = sides_at(azimuth)
        offsets = _side_offsets(sides, quarters, offsets, shrink * band, band)
        if shrink == WALL_AZIMUTH_BANDS[-1] and step * span <= WALL_AZIMUTH_STAYS * band:
            break
    return azimuth, offsets


def _mode_of(values: np.ndarray, band: float, presorted: bool = False) -> float:
    """The mode of ``values`` (at least one; ``presorted``: in ascending order): medians in shrinking windows
    (``LEVEL_MODE_WINDOWS`` x ``band``) from their median, each until it stays (at most ``LEVEL_MODE_ROUNDS``).
    The values are sorted once; each window is then a run of them (``_run_within``) and its median is read off:
    the same numbers as ``np.median`` of the values a mask of the window keeps."""
    values = values if presorted else np.sort(values)
    mode = _median_of_sorted(values)
    for window in LEVEL_MODE_WINDOWS:
        for _ in range(LEVEL_MODE_ROUNDS):
            lo, hi = _run_within(values, mode, window * band)
            if hi - lo < 3:
                break
            previous, mode = mode, _median_of_sorted(values[lo:hi])
            if previous == mode:
                break
    return mode


def _run_within(values: np.ndarray, centre: float, reach: float) -> tuple[int, int]:
    """The run ``lo:hi`` of ``values`` (ascending) where ``abs(value - centre) <= reach`` as numpy computes it (the
    values a mask ``np.abs(values - centre) <= reach`` keeps are one run: ``value - centre`` rounded keeps their
    order). Bisection for ``centre ± reach`` finds it up to rounding; the bounds are then moved by the test itself
    (a step or none)."""
    def within(i: int) -> bool:
        return bool(abs(values[i] - centre) <= reach)

    lo = int(np.searchsorted(values, centre - reach, "left"))
    hi = int(np.searchsorted(values, centre + reach, "right"))
    while lo > 0 and within(lo - 1):
        lo -= 1
    while lo < hi and not within(lo):
        lo += 1
    while hi < len(values) and within(hi):
        hi += 1
    while hi > lo and not within(hi - 1):
        hi -= 1
    return lo, hi


def _modes_of_runs(values: np.ndarray, starts: np.ndarray, stops: np.ndarray, band: float) -> np.ndarray:
    """``_mode_of`` of each run ``values[starts[k]:stops[k]]`` (ascending values, runs of at least three), all runs
    at once: the same steps on each, so the same numbers (a run leaves a window's rounds where ``_mode_of``
    breaks)."""
    starts, stops = np.asarray(starts, np.intp), np.asarray(stops, np.intp)
    mode = _medians_of_runs(values, starts, stops)
    for window in LEVEL_MODE_WINDOWS:
        reach = window * band
        active = np.arange(len(starts))
        for _ in range(LEVEL_MODE_ROUNDS):
            if not len(active):
                break
            lo, hi = _runs_within(values, starts[active], stops[active], mode[active], reach)
            moved = hi - lo >= 3
            previous = mode[active]
            first = starts[active]  # a run too small to move is read at its start (any index inside will do)
            median = np.where(moved, _medians_of_runs(values, np.where(moved, lo, first), np.where(moved, hi, first + 1)),
                              previous)
            mode[active] = median
            active = active[moved & (median != previous)]
    return mode


def _medians_of_runs(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``_median_of_sorted`` of each run ``values[lo[k]:hi[k]]`` (non-empty)."""
    half = lo + (hi - lo) // 2
    odd = (hi - lo) % 2 == 1
    return np.where(odd, values[half], (values[np.maximum(half - 1, lo)] + values[half]) / 2)


def _runs_within(values: np.ndarray, starts: np.ndarray, stops: np.ndarray, centres: np.ndarray, reach: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``_run_within`` on each run ``values[starts[k]:stops[k]]`` about ``centres[k]``, as absolute indices."""
    def within(i: np.ndarray, at: np.ndarray) -> np.ndarray:
        return np.abs(values[i] - centres[at]) <= reach

    lo = np.clip(np.searchsorted(values, centres - reach, "left"), starts, stops)
    hi = np.clip(np.searchsorted(values, centres + reach, "right"), starts, stops)
    for step in range(4):  # the four corrections of _run_within, each until no bound moves
        while True:
            if step == 0:
                at = np.flatnonzero(lo > starts)
                at = at[within(lo[at] - 1, at)]
                lo[at] -= 1
            elif step == 1:
                at = np.flatnonzero(lo < hi)
                at = at[~within(lo[at], at)]
                lo[at] += 1
            elif step == 2:
                at = np.flatnonzero(hi < stops)
                at = at[within(hi[at], at)]
                hi[at] += 1
            else:
                at = np.flatnonzero(hi > lo)
                at = at[~within(hi[at] - 1, at)]
                hi[at] -= 1
            if not len(at):
                break
    return lo, hi


def _median_of_sorted(values: np.ndarray) -> float:
    """``np.median`` of values in ascending order (the middle one, or the mean of the middle two)."""
    half = len(values) // 2
    return float(values[half]) if len(values) % 2 else float((values[half - 1] + values[half]) / 2)


def _horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to ``up``."""
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def dominant_wall_azimuth(normals: np.ndarray, weights: np.ndarray, up: np.ndarray) -> float | None:
    """The azimuth (radians, about ``up``) of the model's dominant wall direction modulo 90°: the weighted mode of
    the upright normals' azimuths (walls of a building meet at right angles), refined by the weighted circular
    mean within ``MANHATTAN_WINDOW_DEG`` of it; None without upright normals."""
    if not len(normals):
        return None
    e1, e2 = _horizontal_basis(up)
    quad = np.exp(4j * np.arctan2(normals @ e2, normals @ e1))  # period 90°
    grid = np.exp(4j * np.radians(np.arange(0.0, 90.0, 0.25)))
    window = np.cos(np.radians(4 * MANHATTAN_WINDOW_DEG))
    score = ((np.real(quad[None] * np.conj(grid[:, None])) >= window) * weights[None]).sum(axis=1)
    mode = grid[int(np.argmax(score))]
    near = np.real(quad * np.conj(mode)) >= window
    return float(np.angle(mode * np.exp(1j * np.angle(np.sum(weights[near] * quad[near] * np.conj(mode))))) / 4)


def _sweep_walls(planes: list[WorldPlane], points: np.ndarray, tolerance: np.ndarray, up: np.ndarray,
                 observers: np.ndarray, options: WorldPlaneOptions) -> list[WorldPlane]:
    """The walls along the dominant wall directions that sequential RANSAC missed, one-sided: for each of the four
    horizontal normals, the offsets (normal · x) of the points seen from the normal's side, peaks of at least
    ``min_support`` points in bands of the median tolerance, away from the planes already found.

    Why: a plain wall's stereo is its floor, ceiling and corner lines; RANSAC scores only the points no accepted plane
    explains yet, and the floor and the ceiling explain most of those lines first, so the wall falls below
    ``min_support``. What the views see through is removed later (``carve_extents``), as for every plane."""
    up = up / np.linalg.norm(up)
    upright = [p for p in planes if abs(p.normal @ up) < 1e-9]
    azimuth = dominant_wall_azimuth(np.array([p.normal for p in upright]).reshape(-1, 3),
                                    np.array([p.support for p in upright], np.float64), up)
    if azimuth is None or not len(points):
        return []
    e1, e2 = _horizontal_basis(up)
    band = float(np.median(tolerance))
    found: list[WorldPlane] = []
    for quarter in range(4):
        a = azimuth + quarter * np.pi / 2
        normal = np.cos(a) * e1 + np.sin(a) * e2
        offsets = points @ normal
        front = observers @ normal > offsets  # seen from the side the normal points to
        values = offsets[front]
        need = SWEEP_SUPPORT_FACTOR * options.min_support
        if len(values) < need:
            continue
        taken = [(p.offset if p.normal @ normal > 0 else -p.offset) for p in planes + found
                 if abs(p.normal @ normal) > 0.999 and (p.front == 0 or p.front * np.sign(p.normal @ normal) > 0)]
        edges = np.arange(values.min(), values.max() + 2 * band, band)
        counts = np.histogram(values, edges)[0]
        pairs = counts[:-1] + counts[1:]  # about ± one band around each inner edge
        # the side's points sorted by offset (ties in row order): each candidate reads a run of them, not all
        order = np.argsort(values, kind="stable")
        ranked, rows, reach = values[order], np.flatnonzero(front)[order], tolerance[front][order]
        widest = 2 * float(reach.max())  # twice: a slab wider than any point's own test, rounding included
        for i in np.argsort(-pairs, kind="stable"):
            if pairs[i] < need:
                break
            offset = float(edges[i + 1])
            if any(abs(offset - o) < 2 * band for o in taken):
                continue
            for shrink in SNAP_SHRINK:  # the median of the values within the band (np.median of the mask's)
                lo, hi = _run_within(ranked, offset, shrink * 2 * band)
                offset = _median_of_sorted(ranked[lo:hi]) if hi > lo else float("nan")
            if offset != offset:  # no value within the band: np.median's NaN supports nothing
                continue
            slab = slice(np.searchsorted(ranked, offset - widest, "left"),
                         np.searchsorted(ranked, offset + widest, "right"))
            inliers = np.sort(rows[slab][np.abs(ranked[slab] - offset) <= reach[slab]])  # as a mask's rows
            if len(inliers) < need:
                continue
            taken.append(offset)
            origin, axes, extent, fallback = _extent(points[inliers], normal, offset, options.cell,
                                                     options.extent_closing_cells, options.extent_hull,
                                                     options.extent, up)
            found.append(WorldPlane(normal=normal, offset=offset, origin=origin, axes=axes, cell=options.cell,
                                    extent=extent, support=len(inliers), fallback=fallback, front=1))
    return found


def _snap_to_gravity(planes: list[WorldPlane], points: np.ndarray, tolerance: np.ndarray, up: np.ndarray,
                     options: WorldPlaneOptions) -> list[WorldPlane]:
    """Planes with gravity imposed: a level plane's normal becomes ``up`` exactly and an upright plane within
    ``snap_deg`` of the dominant wall direction (or its perpendicular) takes that direction; each then gets the
    offset of its points (median, in shrinking bands) and the extent of its new support.

    Why: least squares on stereo points tilts a plane by 1-4° (the points along the lines where surfaces meet are
    biased, a few per cent too far), and one floor can come out as several tilted pieces; a tilted floor is
    seen through on half of its rectangle and loses its extent, a tilted wall is wrong a metre from its support."""
    up = up / np.linalg.norm(up)
    upright = [p for p in planes if abs(p.normal @ up) < 0.5]
    azimuth = dominant_wall_azimuth(np.array([p.normal for p in upright]).reshape(-1, 3),
                                    np.array([p.support for p in upright], np.float64), up)
    e1, e2 = _horizontal_basis(up)
    out = []
    for plane in planes:
        axes = None
        if abs(plane.normal @ up) >= 0.5:
            normal = up * np.sign(plane.normal @ up)
            if azimuth is not None:
                # the grid along the walls: a floor's or ceiling's rectangle is then the building's footprint, not
                # the larger rectangle around it in arbitrary axes, whose corners outside the walls no view sees
                # through and rays past a plain wall (no plane of its own) met
                along = np.cos(azimuth) * e1 + np.sin(azimuth) * e2
                axes = np.stack([along, np.cross(normal, along)])
        else:
            a = np.arctan2(plane.normal @ e2, plane.normal @ e1)
            quarter = np.round((a - azimuth) / (np.pi / 2))
            if abs(a - azimuth - quarter * np.pi / 2) > np.radians(options.snap_deg):
                out.append(plane)  # a wall of its own direction keeps its fit
                continue
            a = azimuth + quarter * np.pi / 2
            normal = np.cos(a) * e1 + np.sin(a) * e2
        inliers = np.abs(points @ plane.normal - plane.offset) <= tolerance
        offset = float(np.median(points[inliers] @ normal))
        for shrink in SNAP_SHRINK:
            band = np.abs(points @ normal - offset) <= shrink * tolerance
            if band.sum() < 3:
                break
            offset = float(np.median(points[band] @ normal))
        inliers = np.abs(points @ normal - offset) <= tolerance
        if inliers.sum() < 3:
            continue
        origin, axes, extent, fallback = _extent(points[inliers], normal, offset, options.cell,
                                                 options.extent_closing_cells, options.extent_hull, options.extent, up,
                                                 axes)
        out.append(WorldPlane(normal=normal, offset=offset, origin=origin, axes=axes, cell=options.cell,
                              extent=extent, support=int(inliers.sum()), fallback=fallback, front=plane.front,
                              level=abs(normal @ up) > 0.5))
    return out


# ------------------------------------------------------------------------------------------------ free space
def confirmed_views(views: list[View], neighbours: list[list[int]], tolerance: float) -> list[View]:
    """The views with only the stereo ranges that another view's stereo confirms: the point lands within
    ``tolerance`` (relative) of a neighbour's own range (``neighbours[a]``: the views checking view a). Stereo
    along the lines where two plain surfaces meet is often a few per cent too far (the matching window takes the
    corner's disparity); such ranges look through the true floor or ceiling, and they can be nearly all of
    the votes that carve those planes away. The errors of one view seldom land on another view's range."""
    out = []
    for a, view in enumerate(views):
        rows, cols = np.nonzero(np.isfinite(view.range_map))
        points = pixel_points(view, view.range_map, rows, cols)
        confirmed = np.zeros(len(rows), bool)
        for b in neighbours[a]:
            row, col, r_pred = project_into(views[b], points, views[b].range_map.shape)
            with np.errstate(invalid="ignore"):
                confirmed |= np.abs(views[b].range_map[row, col] - r_pred) <= tolerance * r_pred
        ranges = np.full(view.range_map.shape, np.nan, np.float32)
        ranges[rows[confirmed], cols[confirmed]] = view.range_map[rows[confirmed], cols[confirmed]]
        out.append(View(R_cam_from_world=view.R_cam_from_world, t_cam_from_world=view.t_cam_from_world,
                        range_map=ranges, observable=view.observable, color=view.color))
    return out


def carve_extents(planes: list[WorldPlane], views: list[View], options: WorldPlaneOptions,
                  map: Callable[..., Iterable[bool]] = map) -> list[WorldPlane]:
    """Remove the extent cells that a view's stereo sees through; drop planes seen through on most of the cells
    some view has a range for (invented planes). A wall with a generous extent is judged cell by cell
    (``_carve_locally``, with ``local_extent``). Returns the planes kept (extents modified in place). Each plane is
    judged on its own: ``map`` may judge them on threads (the kept ones come back in order)."""
    return [plane for plane, keep in zip(planes, map(partial(_carve_plane, views=views, options=options), planes))
            if keep]


def _carve_plane(plane: WorldPlane, views: list[View], options: WorldPlaneOptions) -> bool:
    """``carve_extents`` for one plane: whether it is kept (its extent carved in place)."""
    if plane.fallback is not None and options.local_extent and not plane.level:
        return _carve_locally(plane, views, options)
    if _carve(plane, views, options):
        return True
    if plane.fallback is not None:
        # the views see through most of the generous extent (a slightly tilted floor far from its support, a
        # wall's columns through a window): the plane keeps the extent of its own support, judged the same way
        plane.extent, plane.fallback = plane.fallback, None
        return _carve(plane, views, options)
    return False


def _carve(plane: WorldPlane, views: list[View], options: WorldPlaneOptions) -> bool:
    """Remove the cells of the plane's extent that the views see through; False if it is seen through on more than
    ``max_seen_through`` of the cells judged (extent unchanged then)."""
    (rows, cols), centers = plane.cell_centers()
    if not len(rows):
        return False
    through, on, invented = _cell_votes(plane, centers, views, options)
    carved = through > on
    judged = (through + on) > 0
    if judged.sum() >= options.min_evidence_cells and invented.sum() > options.max_seen_through * judged.sum():
        return False
    plane.extent[rows[carved], cols[carved]] = False
    return True


def _cell_votes(plane: WorldPlane, centers: np.ndarray, views: list[View], options: WorldPlaneOptions
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per cell centre (N, 3) of the plane: (views seeing through it, views seeing a range on it, whether it counts
    as seen through when judging if the plane was invented: beyond ``drop_tolerance`` if the plane has one)."""
    through = np.zeros(len(centers), np.int32)
    on = np.zeros(len(centers), np.int32)
    beyond = np.zeros(len(centers), np.int32)  # seen through by more than the plane's drop_tolerance
    for view in views:
        row, col, r_pred = project_into(view, centers, view.range_map.shape)
        r_obs = view.range_map[row, col]
        seen = view.observable[row, col]
        with np.errstate(invalid="ignore"):
            through += seen & (r_obs > (1 + options.view_tolerance) * r_pred)
            on += seen & (np.abs(r_obs - r_pred) <= options.view_tolerance * r_pred)
            if plane.drop_tolerance > 0:
                beyond += seen & (r_obs > (1 + plane.drop_tolerance) * r_pred)
    invented = (beyond > on) if plane.drop_tolerance > 0 else through > on  # the cells are carved as for every plane
    return through, on, invented


def _carve_locally(plane: WorldPlane, views: list[View], options: WorldPlaneOptions) -> bool:
    """Judge a plane that has a generous extent and its support's own extent (``fallback``) cell by cell: whether it
    was invented on the support's extent (what its points hold), and each cell the generous extent adds by the
    evidence around it (``_evidenced``). False if invented (extents unchanged then); else the extent becomes the
    support's extent and the evidenced added cells, less every cell the views see through.

    Why: the old rule judged the whole generous extent against ``max_seen_through`` and, above it, fell back to the
    support's extent: one threshold decided a whole wall's added cells. On 360_Flat the wall with the arched opening
    into the corridor, judged 0.477 seen through in one run and 0.552 in another with the poses 1e-4° apart, filled
    the opening (the corridor beyond, 10% of a panorama, at the range of the wall) in the one and not in the other.
    Here a cell of the opening goes with the views' votes around it, wherever the plane's total lands."""
    union = plane.extent | plane.fallback
    rows, cols = np.nonzero(union)
    uv = np.stack([cols + 0.5, rows + 0.5], axis=1) * plane.cell
    through, on, invented = _cell_votes(plane, plane.origin + uv @ plane.axes, views, options)
    support = plane.fallback[rows, cols]
    judged = (through + on) > 0
    if judged[support].sum() >= options.min_evidence_cells \
            and invented[support].sum() > options.max_seen_through * judged[support].sum():
        return False
    carved = np.zeros(union.shape, bool)
    carved[rows, cols] = through > on
    seen_on = np.zeros(union.shape, bool)
    seen_on[rows, cols] = judged & (through <= on)
    plane.extent = (plane.fallback | (plane.extent & (seen_on | _evidenced(seen_on, carved, options)))) & ~carved
    plane.fallback = None
    return True


def _evidenced(seen_on: np.ndarray, carved: np.ndarray, options: WorldPlaneOptions) -> np.ndarray:
    """(rows, cols) bool: the cells of a wall's grid (rows along the vertical) whose columns, with the
    ``extent_evidence_cells`` columns each side, hold cells the views see on the wall, and no more than
    ``max_seen_through`` of the judged cells there seen through. A wall's generous extent is carried column by
    column (``_gravity_extent``, ``_walls_floor_to_ceiling``), and a plain wall's votes lie on its floor and ceiling
    lines: a column is judged with its neighbours as one. A cell no view has judged needs votes on the wall next to
    it; one more vote moves only the columns whose window holds it."""
    k, cols = options.extent_evidence_cells, seen_on.shape[1]
    window = np.ones(2 * k + 1)  # the full convolution's centred part: "same" gives the window's length if longer
    on = np.convolve(seen_on.sum(axis=0), window)[k:k + cols]
    through = np.convolve(carved.sum(axis=0), window)[k:k + cols]
    return np.broadcast_to((on > 0) & (through <= options.max_seen_through * (on + through)), seen_on.shape)


# ------------------------------------------------------------------------------------------------ per pixel
def region_candidates(ref: View, planes: list[WorldPlane], regions: np.ndarray, options: WorldPlaneOptions,
                      wanted: np.ndarray | None = None) -> np.ndarray:
    """(regions, planes) bool: the world planes a panorama's image region may take, those that explain at least
    ``min_region_support`` of the stereo depths inside or around it (``planes._region_evidence``). A plane crossing
    the room without being a surface there has no such support in the region's own view. ``wanted`` (bool per
    region): only these regions are judged (the others' rows are False, bar ``free_ceiling``'s), and only the stereo
    pixels of their evidence looked at: each pixel's numbers are those of the whole (``_rows_times``)."""
    allowed = np.zeros((int(regions.max()) + 1, len(planes)), bool)
    region, pixel, rows, cols = region_evidence_pixels(regions, ref.range_map, wanted)
    if not len(region) or not planes:
        return allowed
    if wanted is not None:  # the pixels of the kept pairs (pixel ascending: the blocks below see them in order)
        used, pixel = np.unique(pixel, return_inverse=True)
        rows, cols = rows[used], cols[used]
    h, w = ref.range_map.shape
    bearings = reduced_bearings_world(ref.R_cam_from_world, w, h)[rows, cols].astype(np.float64)
    center = -ref.R_cam_from_world.T @ ref.t_cam_from_world
    observed = ref.range_map[rows, cols].astype(np.float64)
    normals = np.array([p.normal for p in planes])
    offsets = np.array([p.offset for p in planes])
    # whether a plane explains a pixel's depth depends on the pixel alone: computed once per pixel (not once per
    # region around it), a block of pixels at a time, and summed per region through the (region, pixel) incidence
    by_pixel = np.argsort(pixel, kind="stable")
    counts = np.zeros(allowed.shape, np.int64)
    for start in range(0, len(rows), EVIDENCE_BLOCK):
        block = slice(start, start + EVIDENCE_BLOCK)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (offsets - normals @ center)[None] / _rows_times(bearings[block], normals.T)
            on = np.abs(r - observed[block, None]) <= options.view_tolerance * observed[block, None]
        first, last = np.searchsorted(pixel[by_pixel], [start, start + len(on)])
        pairs = by_pixel[first:last]
        incidence = sparse.csr_matrix((np.ones(len(pairs), np.int32), (region[pairs], pixel[pairs] - start)),
                                      shape=(len(allowed), len(on)))
        counts += incidence @ on.astype(np.int32)
    total = np.bincount(region, minlength=len(allowed))[:, None]
    allowed = (counts >= options.min_region_support) & (counts >= options.min_region_share * total)
    if options.free_ceiling:
        # nothing but the ceiling is level and above the camera in a room: its plane needs no support from the
        # region (a plain ceiling's region leaks into the walls, and the region rule drops most of its pixels)
        up = camera_up(ref.R_cam_from_world[None])
        allowed[1:, [k for k, p in enumerate(planes) if p.is_ceiling_of(center, up)
                     and (not options.ceiling_over_camera or p.spans_over(center, options.room_window_cells))]] = True
    return allowed


def _rows_times(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for a block of rows of a larger (N, 3) array, bit for bit what the whole product gives those rows:
    numpy takes a one-row product as a vector product (another BLAS routine, other roundings), so a lone row is
    computed with a copy of itself."""
    return a @ b if len(a) != 1 else (np.repeat(a, 2, axis=0) @ b)[:1]


def label_pixels(ref: View, planes: list[WorldPlane], fillable: np.ndarray, options: WorldPlaneOptions,
                 regions: np.ndarray | None = None, allowed: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """((h, w) float32 range, (h, w) int32 label: plane index + 1, 0 none) of the ``fillable`` pixels of ``ref``:
    the nearest plane each ray meets inside its extent (in front, not grazing), among the planes ``allowed``
    (regions, planes) in the pixel's image region (``regions``), if given. With ``options.wall_brackets`` a pixel
    no such plane takes gets the nearest wall (upright plane) that brackets it (``_wall_brackets``)."""
    h, w = ref.range_map.shape
    label = np.zeros(h * w, np.int32)
    pix = np.flatnonzero(fillable.ravel())
    if not len(pix) or not planes:
        return np.full((h, w), np.nan, np.float32), label.reshape(h, w)
    best = np.full(h * w, np.inf, np.float32)
    nearest = np.full(len(pix), np.inf, np.float32)  # per fillable pixel: best range so far, and its label
    taken = np.zeros(len(pix), np.int32)
    bearings = reduced_bearings_world(ref.R_cam_from_world, w, h).reshape(-1, 3)[pix].astype(np.float64)
    center = -ref.R_cam_from_world.T @ ref.t_cam_from_world
    pix_regions = regions.ravel()[pix] if regions is not None else None
    for k, plane in enumerate(planes):
        if regions is not None and not allowed[:, k].any():
            continue  # no region of this view may take it
        # only the pixels whose region may take the plane are looked at (per pixel: the same numbers; BLAS gives a
        # row of bearings the same product in any subset)
        sel = np.flatnonzero(allowed[:, k][pix_regions]) if regions is not None else np.arange(len(pix))
        _take_nearest(plane, k, sel, bearings, center, nearest, taken, options)
    if regions is not None and options.wall_brackets:
        # the pixels no plane of their region takes: the nearest wall that brackets them
        free = np.flatnonzero(taken == 0)
        bits = _wall_brackets(ref, planes, pix[free], options.view_tolerance)
        for k, plane in enumerate(planes):
            if not plane.level:
                sel = free[((bits[:, k // 8] >> (7 - k % 8)) & 1).astype(bool)]
                _take_nearest(plane, k, sel, bearings, center, nearest, taken, options)
    if regions is not None and options.free_floor:
        _free_floor(planes, np.flatnonzero(taken == 0), bearings, center, camera_up(ref.R_cam_from_world[None]),
                    nearest, taken, options)
    if regions is not None and options.free_walls:
        _free_walls(planes, np.flatnonzero(taken == 0), bearings, center, camera_up(ref.R_cam_from_world[None]),
                    nearest, taken, options)
    best[pix], label[pix] = nearest, taken
    label = _drop_islands(label.reshape(h, w), options.min_island_pixels)
    out = np.where(label > 0, best.reshape(h, w), np.nan).astype(np.float32)
    return out, label


def _take_nearest(plane: WorldPlane, k: int, sel: np.ndarray, bearings: np.ndarray, center: np.ndarray,
                  nearest: np.ndarray, taken: np.ndarray, options: WorldPlaneOptions) -> None:
    """Label ``k + 1`` (in place) the pixels ``sel`` whose ray meets the plane inside its extent, in front, not
    grazing, and nearer than their current ``nearest``; nothing for a camera behind a one-sided plane (it would see
    the back of a wall's other face)."""
    if not len(sel) or (plane.front and np.sign(plane.normal @ center - plane.offset) != plane.front):
        return
    cos = bearings[sel] @ plane.normal
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (plane.offset - plane.normal @ center) / cos
    hit = (r > 0) & (np.abs(cos) >= np.sin(np.radians(options.min_incidence_deg))) & (r < nearest[sel])
    if not hit.any():
        return
    sel, r = sel[hit], r[hit]
    inside = plane.contains(center + bearings[sel] * r[:, None])
    nearest[sel[inside]] = r[inside]
    taken[sel[inside]] = k + 1


def _floor_in_room(planes: list[WorldPlane], center: np.ndarray, up: np.ndarray, reach: int = 0) -> list[int]:
    """Indices of the level planes below ``center`` spanning under it (its floor), if a level plane above spans over
    it too (a room: outdoors the ground keeps the region rule); else []. ``reach``: ``WorldPlane.spans_over``'s."""
    level = [k for k, p in enumerate(planes)
             if p.level and abs(float(p.normal @ up)) > 0.5 and p.spans_over(center, reach)]
    below = [k for k in level if (planes[k].offset - planes[k].normal @ center) / float(planes[k].normal @ up) < 0]
    return below if len(below) < len(level) else []


def _free_walls(planes: list[WorldPlane], free: np.ndarray, bearings: np.ndarray, center: np.ndarray, up: np.ndarray,
                nearest: np.ndarray, taken: np.ndarray, options: WorldPlaneOptions) -> None:
    """Label (in place) the pixels ``free`` (indices into ``bearings``, ``nearest``, ``taken``) with the first of all
    the planes their ray meets inside its extent where that plane is a wall (upright), only in a room (as
    ``_free_floor``). A plain wall's image region often holds no stereo on the wall at all (its stereo lies on the
    ceiling and floor lines of a leaking region, or a few per cent off the wall), so neither the region rule nor the
    brackets take it; from inside a room the first plane met is the surface seen. A cupboard that is a plane of the
    model is met first and its face is taken; the view checks then judge every filled pixel as the others'."""
    if not len(free) or not _floor_in_room(planes, center, up, options.room_window_cells):
        return
    first, which = np.full(len(free), np.inf, np.float32), np.zeros(len(free), np.int32)
    sel = np.arange(len(free))
    for k, plane in enumerate(planes):
        _take_nearest(plane, k, sel, bearings[free], center, first, which, options)
    wall = np.array([False] + [not p.level for p in planes])[which]
    nearest[free[wall]], taken[free[wall]] = first[wall], which[wall]


def _free_floor(planes: list[WorldPlane], free: np.ndarray, bearings: np.ndarray, center: np.ndarray, up: np.ndarray,
                nearest: np.ndarray, taken: np.ndarray, options: WorldPlaneOptions) -> None:
    """Label (in place) the pixels ``free`` (indices into ``bearings``, ``nearest``, ``taken``) whose ray meets the
    camera's floor, a level plane below it spanning under it, where the floor is the first of all the planes the ray
    meets inside their extents; only in a room, where a level plane above spans over the camera too (outdoors the
    ground keeps the region rule). The floor's own stereo is often missing or wrong (plain, seen at a grazing angle),
    and one plain region runs from the floor up the walls, so the region rule can refuse most of a room's floor. A cupboard whose plain face is no plane of its region would be filled with the
    floor behind it: where the cupboard is a plane of the model, the ray meets it first and the pixel stays empty."""
    below = _floor_in_room(planes, center, up, options.room_window_cells)
    if not len(free) or not below:
        return
    sel = np.arange(len(free))
    first, which = np.full(len(free), np.inf, np.float32), np.zeros(len(free), np.int32)
    for k in below:
        _take_nearest(planes[k], k, sel, bearings[free], center, first, which, options)
    on = np.flatnonzero(which > 0)
    if not len(on):
        return
    blocked, other = first[on].copy(), which[on].copy()  # any other plane met nearer inside its extent blocks it
    for k, plane in enumerate(planes):
        if k not in below:
            _take_nearest(plane, k, np.arange(len(on)), bearings[free[on]], center, blocked, other, options)
    ok = on[other == which[on]]
    nearest[free[ok]], taken[free[ok]] = first[ok], which[ok]


def _wall_brackets(ref: View, planes: list[WorldPlane], pix: np.ndarray, tolerance: float) -> np.ndarray:
    """(len(pix), ceil(planes / 8)) uint8, bit k (``np.packbits`` order) set where wall k brackets pixel ``pix``
    (flat indices of ``ref``): it explains (within ``tolerance`` of the range) both the nearest range above and the
    nearest range below the pixel in its image column, or both the nearest ranges left and right of it in its row
    with neither column range beyond it. A column of a level panorama is a vertical half-plane through the camera:
    on a wall it is a vertical line between the wall's floor and ceiling lines; a row runs along the wall between
    its corners. A plane in front of the wall (a cupboard's face carried up to the ceiling) explains neither the
    ceiling line nor the wall's corners; across a doorway the two jambs lie on the wall, but the floor beyond the
    opening, below the pixel in its column, lies beyond it. Level planes get no bits."""
    h, w = ref.range_map.shape
    rows, cols = np.nonzero(np.isfinite(ref.range_map))
    index = np.full((h, w), len(rows), np.intp)  # the last row of the bits below: "no range there"
    index[rows, cols] = np.arange(len(rows))
    finite = index < len(rows)
    row, col = np.divmod(pix, w)
    grid = np.broadcast_to(np.arange(h)[:, None], (h, w))
    above = np.maximum.accumulate(np.where(finite, grid, -1), axis=0)  # nearest range at or above
    below = np.minimum.accumulate(np.where(finite, grid, h)[::-1], axis=0)[::-1]  # ... at or below
    up = above[np.maximum(row - 1, 0), col]
    down = below[np.minimum(row + 1, h - 1), col]
    twice = np.concatenate([finite, finite], axis=1)  # a row twice: the nearest range left / right wraps the seam
    grid = np.broadcast_to(np.arange(2 * w)[None], (h, 2 * w))
    left = np.maximum.accumulate(np.where(twice, grid, -1), axis=1)[row, col + w - 1]
    right = np.minimum.accumulate(np.where(twice, grid, 2 * w)[:, ::-1], axis=1)[:, ::-1][row, col + 1]

    def at(r, c, ok):
        return np.where(ok, index[np.clip(r, 0, h - 1), np.clip(c, 0, 2 * w - 1) % w], len(rows))

    u, d = at(up, col, (row > 0) & (up >= 0)), at(down, col, (row < h - 1) & (down < h))
    lt, rt = at(row, left, left > col), at(row, right, right < col + w)  # within one turn, not the pixel itself
    # only the ranges next to the pixels are judged (a few percent of them): each range's numbers are those of
    # all of them (``_rows_times``); the last row of the bits stays "no range there"
    ranged, slot = np.unique(np.concatenate([u, d, lt, rt]), return_inverse=True)
    u, d, lt, rt = np.split(slot, 4)
    ranged = ranged[ranged < len(rows)]  # "no range there" (the largest) is then the row after them
    bearings = reduced_bearings_world(ref.R_cam_from_world, w, h)[rows[ranged], cols[ranged]].astype(np.float64)
    observed = ref.range_map[rows[ranged], cols[ranged]].astype(np.float64)
    center = -ref.R_cam_from_world.T @ ref.t_cam_from_world
    upright = np.array([not p.level for p in planes])
    normals = np.array([p.normal for p in planes])
    distances = np.array([p.offset for p in planes]) - normals @ center
    width = (len(planes) + 7) // 8
    on, beyond = [np.zeros((0, width), np.uint8)], [np.zeros((0, width), np.uint8)]
    for start in range(0, len(ranged), EVIDENCE_BLOCK):  # per range: on each wall, clearly beyond it
        block = slice(start, start + EVIDENCE_BLOCK)
        with np.errstate(divide="ignore", invalid="ignore"):
            predicted = distances[None] / _rows_times(bearings[block], normals.T)
            o = observed[block, None]
            on.append(np.packbits((np.abs(predicted - o) <= tolerance * o) & upright, axis=1))
            beyond.append(np.packbits((o > (1 + tolerance) * predicted) & upright, axis=1))
    none = np.zeros((1, width), np.uint8)
    on, beyond = np.concatenate(on + [none]), np.concatenate(beyond + [none])
    return (on[u] & on[d]) | (on[lt] & on[rt] & ~beyond[u] & ~beyond[d])


def _drop_islands(label: np.ndarray, min_pixels: int) -> np.ndarray:
    """Labels with the connected pieces (per label, 4-connected) smaller than ``min_pixels`` set to 0. Each label
    is looked at inside its bounding box only (its pieces lie there)."""
    if min_pixels <= 1 or not label.any():
        return label
    out = label.copy()
    for k, box in enumerate(ndimage.find_objects(label), start=1):
        if box is None:
            continue
        n, comp, stats, _ = cv2.connectedComponentsWithStats((label[box] == k).astype(np.uint8), connectivity=4)
        small = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] < min_pixels)
        small = small[small > 0]
        if len(small):
            out[box][np.isin(comp, small)] = 0
    return out


def nearest_plane_ranges(view: View, planes: list[WorldPlane], options: WorldPlaneOptions, step: int = 4
                         ) -> np.ndarray:
    """(h / step, w / step) float32: the range of the nearest plane each ray of ``view`` meets inside its extent
    (every ``step``-th pixel; NaN: none), what the model predicts the view sees. Used as occluders by the view check:
    a floor point next to a cupboard is hidden from a view behind the cupboard whose own stereo is empty there, and
    that view's colour (the cupboard's) is no vote against it."""
    h, w = view.range_map.shape
    coarse = View(R_cam_from_world=view.R_cam_from_world, t_cam_from_world=view.t_cam_from_world,
                  range_map=np.full((h // step, w // step), np.nan, np.float32),
                  observable=np.ones((h // step, w // step), bool), color=view.color)
    return label_pixels(coarse, planes, coarse.observable, replace(options, min_island_pixels=0))[0]


def adopt_world_planes(ref: View, fill: np.ndarray, units: np.ndarray, planes: list[WorldPlane],
                       options: WorldPlaneOptions) -> np.ndarray:
    """(h, w) float32: a region fill's ranges (``fill``, NaN: none; ``units``: its region labels) with each unit's
    pixels moved onto the kept level world plane (a floor or a ceiling) that lies within ``view_tolerance`` of at
    least ``ADOPT_SHARE`` of them (the one nearest on average, if several; the camera on its front side); a pixel whose
    ray does not meet that plane (behind, grazing) is left empty. Units no such plane matches keep their ranges.

    Why: a region's plane is fitted on one panorama's stereo around the region, a world plane on every panorama's
    points of that surface. Both are the same surface here, but one view's evidence carries its stereo's bias: on
    360_Flat R0010212 filled its ceiling (a quarter of the panorama) level but 1.9% too low, 0.035 below the ceiling
    every other panorama filled from the world planes, and disagreed with them across the room. Level planes only: a
    level world plane is exactly level at the mode of every view's heights, while a wall is turned onto the dominant
    wall direction, which a real wall may miss by a few degrees (its region's own plane keeps its azimuth)."""
    out = fill.copy()
    rows, cols = np.nonzero(np.isfinite(fill))
    if not len(rows) or not planes:
        return out
    h, w = fill.shape
    bearings = reduced_bearings_world(ref.R_cam_from_world, w, h)[rows, cols].astype(np.float64)
    center = -ref.R_cam_from_world.T @ ref.t_cam_from_world
    own = fill[rows, cols].astype(np.float64)
    unit = np.unique(units[rows, cols], return_inverse=True)[1]
    best = np.full(unit.max() + 1, -1)
    best_error = np.full(unit.max() + 1, np.inf)
    size = np.bincount(unit)
    for k, plane in enumerate(planes):
        if not plane.level or (plane.front and np.sign(plane.normal @ center - plane.offset) != plane.front):
            continue  # only floors and ceilings; the camera sees the back of a one-sided plane
        cos = bearings @ plane.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            error = np.abs((plane.offset - plane.normal @ center) / cos - own) / own
        on = error <= options.view_tolerance
        share = np.bincount(unit, weights=on, minlength=len(size)) / size
        mean = np.bincount(unit, weights=np.where(on, error, 0.0), minlength=len(size)) / np.maximum(
            np.bincount(unit, weights=on, minlength=len(size)), 1)
        better = (share >= ADOPT_SHARE) & (mean < best_error)
        best[better], best_error[better] = k, mean[better]
    for u in np.flatnonzero(best >= 0):
        plane, sel = planes[best[u]], np.flatnonzero(unit == u)
        cos = bearings[sel] @ plane.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (plane.offset - plane.normal @ center) / cos
        ok = (r > 0) & (np.abs(cos) >= np.sin(np.radians(options.min_incidence_deg)))
        out[rows[sel], cols[sel]] = np.where(ok, r, np.nan)
    return out


def fill_from_world_planes(ref: View, planes: list[WorldPlane], others: list[View], options: WorldPlaneOptions,
                           view_options: PlaneOptions, occluders: list[np.ndarray] | None = None
                           ) -> tuple[np.ndarray, np.ndarray]:
    """((h, w) float32 ranges, (h, w) int32 plane labels) for the pixels of ``ref`` without a stereo range: the
    world plane its ray meets (``label_pixels``), kept where no other view sees through it and its colour is seen
    (``planes.check_against_views``)."""
    fillable = ~np.isfinite(ref.range_map) & ref.observable
    gray = cv2.cvtColor(np.clip(ref.color, 0, 255).astype(np.uint8), cv2.COLOR_BGR2GRAY)
    regions = image_regions(gray, view_options, np.isfinite(ref.range_map))
    wanted = np.zeros(int(regions.max()) + 1, bool)  # the regions of pixels to fill: no other region's planes matter
    wanted[regions[fillable]] = True
    allowed = region_candidates(ref, planes, regions, options, wanted)
    fill, label = label_pixels(ref, planes, fillable, options, regions, allowed)
    rows, cols = np.nonzero(label)
    if not len(rows):
        return fill, label
    points = pixel_points(ref, fill, rows, cols)
    gains = [exposure_gain(ref, o) for o in others]
    colors = ref.color[rows, cols]
    # the occluders for the floor and the ceiling (level planes), and with ``occluders_on_walls`` for the walls: with
    # walls as pieces they let through the pixels labelled with a wall behind the right one; with whole walls and free
    # walls the views' votes against right wall pixels that the model says are hidden are most of what the check
    # drops (the model's occlusion is coarser than a wall's extent)
    occludable = np.array([False] + [p.level or options.occluders_on_walls for p in planes])[label[rows, cols]] \
        if occluders is not None else np.zeros(len(rows), bool)
    keep = np.zeros(len(rows), bool)
    keep[~occludable] = check_against_views(points[~occludable], colors[~occludable], others, gains, view_options)
    keep[occludable] = check_against_views(points[occludable], colors[occludable], others, gains, view_options,
                                           occluders)
    fill[rows[~keep], cols[~keep]] = np.nan
    label[rows[~keep], cols[~keep]] = 0
    return fill, label
