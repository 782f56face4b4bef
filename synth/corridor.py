"""Seeded layout of the "corridor" scene: a long walk with a sparse view graph, for pair selection and scaling.

A straight corridor along world x (box 0, seen from inside, every face textured) is divided into bays by textured
partition walls across it (``BAFFLE_THICKNESS``); each partition leaves one opening (``OPENING_WIDTH``, full
height) on alternating sides, so a camera sees its own bay and, through the openings, parts of the next ones, but
not far down the corridor: the view graph is sparse (a band along the walk), as in a long capture. The cameras
walk the bays in order, ``VIEWS_PER_BAY`` per bay, level (yaw only, like a Theta's zenith-corrected panoramas) at
``EYE`` height with a little jitter, along a slalom whose z passes each partition at its opening's centre.
Same world frame as the room scene (y down, floor at ``y = FLOOR_Y``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fullview.synth.layout import FLOOR_Y, rot_y

VIEWS_PER_BAY = 3  # cameras between two partitions
STEP = 1.1  # mean distance between consecutive cameras along x (m)
STEP_JITTER = 0.15  # camera x is uniform in its slot's centre +- this (m)
SLALOM_JITTER = 0.15  # camera z is uniform in the slalom +- this (m)
CORRIDOR_WIDTH = (3.6, 4.2)  # along z (m)
CORRIDOR_HEIGHT = (2.6, 3.0)  # floor to ceiling (m)
BAFFLE_THICKNESS = 0.15  # partition walls (m)
OPENING_WIDTH = 1.4  # opening of every partition (m), at one side of the corridor
OPENING_SIDE_GAP = 0.3  # wall left between the opening and the corridor side (m)
EYE = 1.5  # camera height above the floor (m)
EYE_JITTER = 0.05  # camera height is uniform in EYE +- this (m)
END_GAP = 1.0  # corridor beyond the first and the last camera (m)


@dataclass(kw_only=True)
class CorridorLayout:
    boxes: np.ndarray  # (K, 2, 3): the corridor (box 0), then the partition slabs
    R_world_from_cam: np.ndarray  # (V, 3, 3) level rotations (about world y)
    centers: np.ndarray  # (V, 3)
    bay_of_view: np.ndarray  # (V,) bay index of every camera


def layout_corridor(rng: np.random.Generator, views: int) -> CorridorLayout:
    """Seeded corridor with ceil(views / VIEWS_PER_BAY) bays and a walk of ``views`` cameras through them."""
    if not isinstance(views, (int, np.integer)) or views < 1:
        raise ValueError(f"views must be a positive integer, got {views!r}")
    bays = -(-views // VIEWS_PER_BAY)
    width, height = rng.uniform(*CORRIDOR_WIDTH), rng.uniform(*CORRIDOR_HEIGHT)
    bay_length = VIEWS_PER_BAY * STEP
    length = bays * bay_length + 2 * END_GAP
    x0, z0, z1 = -length / 2, -width / 2, width / 2
    shell = np.array([[x0, FLOOR_Y - height, z0], [-x0, FLOOR_Y, z1]])
    # partition k stands between bay k and k + 1; its opening alternates sides
    bx = x0 + END_GAP + bay_length * np.arange(1, bays)
    side = np.where(np.arange(bays - 1) % 2 == 0, 1.0, -1.0)
    open_c = side * (width / 2 - OPENING_SIDE_GAP - OPENING_WIDTH / 2)
    slabs = []
    for x, c in zip(bx, open_c):
        lo, hi = c - OPENING_WIDTH / 2, c + OPENING_WIDTH / 2
        xs = (x - BAFFLE_THICKNESS / 2, x + BAFFLE_THICKNESS / 2)
        slabs.append([[xs[0], shell[0, 1], z0], [xs[1], FLOOR_Y, lo]])
        slabs.append([[xs[0], shell[0, 1], hi], [xs[1], FLOOR_Y, z1]])
    # the walk: slot k at the middle of its step, z on the slalom through the openings' centres
    slot_x = x0 + END_GAP + STEP * (np.arange(views) + 0.5)
    cx = slot_x + rng.uniform(-STEP_JITTER, STEP_JITTER, views)
    knots_x = np.concatenate([[x0], bx, [-x0]])
    knots_z = np.concatenate([[0.0], open_c, [0.0]])
    cz = np.interp(cx, knots_x, knots_z) + rng.uniform(-SLALOM_JITTER, SLALOM_JITTER, views)
    cy = FLOOR_Y - EYE + rng.uniform(-EYE_JITTER, EYE_JITTER, views)
    rots = np.stack([rot_y(a) for a in rng.uniform(0.0, 2 * np.pi, views)])
    boxes = np.concatenate([shell[None], np.array(slabs).reshape(-1, 2, 3)])
    return CorridorLayout(boxes=boxes, R_world_from_cam=rots, centers=np.column_stack([cx, cy, cz]),
                          bay_of_view=np.arange(views) // VIEWS_PER_BAY)
