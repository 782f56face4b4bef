"""Synthetic 360° equirectangular scenes with exact ground truth, for tests and benchmarks.

The scene is a textured room (an axis-aligned box seen from inside) with 3-6 furniture-like axis-aligned boxes
standing on its floor; ``render_scene(kind="home")`` instead renders a flat of several rooms with plain walls,
doorways and a few textured objects per room (a hard case for matching; see ``home``). The world frame has y pointing DOWN like the camera frame (floor at ``y = +FLOOR_Y``, eye
height at ``y ≈ 0``), so a level camera has a ``R_world_from_cam`` that is a rotation about y.

Modules:
- ``geometry``: boxes, face indexing, face frames and normals, the textured ``SceneGeometry``;
- ``layout``: the seeded room, furniture, target markers and camera walk;
- ``home``: the seeded multi-room home (shell, wall slabs with doorways, furniture, level camera walk);
- ``textures``: procedural face textures and their mip-mapped atlas (``build_geometry``);
- ``render``: ray casting and shading of one panorama (``render_view``, ``cast_rays``);
- ``scene``: a whole scene (``render_scene``), hand-point tracks, visibility and surface samples;
- ``dataset``: writing a scene as a dataset folder (``write_synthetic_dataset``; the only file access).
"""

from fullview.synth.dataset import write_synthetic_dataset
from fullview.synth.geometry import SceneGeometry
from fullview.synth.layout import CLEARANCE, EYE_HEIGHT_JITTER, FLOOR_Y, MAX_TILT_DEG, MIN_CAMERA_SEPARATION
from fullview.synth.render import cast_rays, render_view
from fullview.synth.scene import SynthScene, SynthView, render_scene, sample_surface_points, visible_observations
from fullview.synth.textures import build_geometry

__all__ = [
    "CLEARANCE", "EYE_HEIGHT_JITTER", "FLOOR_Y", "MAX_TILT_DEG", "MIN_CAMERA_SEPARATION", "SceneGeometry",
    "SynthScene", "SynthView", "build_geometry", "cast_rays", "render_scene", "render_view", "sample_surface_points",
    "visible_observations", "write_synthetic_dataset",
]
