"""Boxes and their faces: the shared vocabulary of the synthetic scene.

The scene is axis-aligned boxes: box 0 is the room (seen from inside), the others are furniture standing on its
floor. Face ``6 * k + 2 * axis + side`` is the face of box k whose normal is along ``axis``; side 0 is the plane
``x[axis] = box_min[axis]``, side 1 the max plane. ``SceneGeometry`` adds the textures (see ``textures``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


# Per normal axis: the world axes used as texture (u, v) coordinates of that face.
FACE_UV_AXES = np.array([[2, 1], [0, 2], [0, 1]])


@dataclass(kw_only=True)
class SceneGeometry:
    boxes: np.ndarray  # (K, 2, 3) axis-aligned boxes (min, max corner); box 0 = room, seen from inside
    texel: float  # texture sample spacing (m) at mip level 0
    atlas: np.ndarray  # (A_h, A_w, 3) uint8 BGR atlas of every face texture at every mip level (shaded)
    tile_offset: np.ndarray  # (L, F, 2) float32 atlas (x, y) of texel (0, 0) of face f at mip level l
    markers: np.ndarray  # (M, 3) world centres of the target markers drawn on the room faces
    marker_names: list[str]  # (M,) names of the markers, e.g. "room_face3_marker1"


def face_frame(boxes: np.ndarray, face: int) -> tuple[int, int, int, float, np.ndarray, np.ndarray]:
    """(axis, u axis, v axis, plane coordinate, (u, v) min, (u, v) size) of a face."""
    k, axis, side = face // 6, (face % 6) // 2, face % 2
    uax, vax = FACE_UV_AXES[axis]
    lo, hi = boxes[k]
    plane = hi[axis] if side else lo[axis]
    return axis, int(uax), int(vax), float(plane), lo[[uax, vax]], (hi - lo)[[uax, vax]]


def face_normal(face: int, room: bool) -> np.ndarray:
    """Unit normal of a face pointing into free space (inwards for the room)."""
    axis, side = (face % 6) // 2, face % 2
    n = np.zeros(3)
    n[axis] = (1.0 if side else -1.0) * (-1.0 if room else 1.0)
    return n


def face_uv_origins(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F,) float32 world u and v coordinates of texel (0, 0) of every face."""
    faces = np.arange(6 * len(boxes))
    axis = (faces % 6) // 2
    lo = boxes[faces // 6, 0]
    return (lo[faces, FACE_UV_AXES[axis, 0]].astype(np.float32),
            lo[faces, FACE_UV_AXES[axis, 1]].astype(np.float32))
