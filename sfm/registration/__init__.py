"""Global registration: absolute camera poses from pairwise relative poses (see ``driver`` for the method).

Modules:
- ``driver``: ``register`` and its result ``Registration`` (input checks, epipoles, gauge and residuals);
- ``view_graph``: components, pruning, one edge per image pair, triangle support;
- ``rotation_averaging``: spanning tree, consensus repair, robust IRLS on SO(3) (the ``"general"`` rotations);
- ``translation_averaging``: LUD, chordal refinement, parallel-rigidity check;
- ``planar``: the report's level-camera model (yaw averaging, Newton on the epipole cost);
- ``poses``: relative from absolute poses, rotations about the vertical.
"""

from fullview.sfm.registration.driver import MODELS, Registration, register
from fullview.sfm.registration.planar import planar_epipole_cost, planar_epipole_cost_derivatives, planar_newton
from fullview.sfm.registration.poses import relative_from_absolute, rotation_yaw, yaw_rotation
from fullview.sfm.registration.rotation_averaging import (consensus_sweeps, rotation_averaging_irls,
                                                          spanning_tree_rotations)
from fullview.sfm.registration.translation_averaging import flexible_modes, translation_averaging
from fullview.sfm.registration.view_graph import triangle_support

__all__ = [
    "MODELS", "Registration", "consensus_sweeps", "flexible_modes", "planar_epipole_cost",
    "planar_epipole_cost_derivatives", "planar_newton", "register", "relative_from_absolute", "rotation_averaging_irls",
    "rotation_yaw", "spanning_tree_rotations", "translation_averaging", "triangle_support", "yaw_rotation",
]
