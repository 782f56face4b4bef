"""Dense reconstruction from pairs of equirectangular panoramas by spherical rectification.

The report's method, done carefully:

1. **Rectify** (``rectify_pair``): both cameras are rotated into one shared frame whose pole is the baseline
   direction ``e = (c_j − c_i) / |c_j − c_i|``. In that frame every epipolar plane contains the pole, so epipolar
   great circles are meridians. Each panorama is resampled to a rectified equirectangular grid in which the
   meridians are image columns, and the result is transposed so that **rows are epipolar planes** (row ↔ plane
   angle φ ∈ [−π, π)) and **columns are the angle θ from the epipole** (column ↔ θ ∈ [0, π], linear).
   Concretely the rectified frame has its −y axis along ``e``, so it is an ordinary ``fullview.sfm.camera``
   equirectangular camera (of width ``n_phi`` and height ``n_theta``) whose top pole looks at camera j; with
   continuous pixel coordinates (u, v) = (column, row) of the transposed image:
   ``θ = π u / n_theta`` and ``φ = 2π (v / n_phi − 0.5)``.
2. **Disparity** (``compute_disparity``): a scene point P seen at ``θ_i`` from camera i is seen at
   ``θ_j = θ_i + d`` from camera j, where ``d = ∠O_i P O_j ≥ 0`` (triangle angle sum, see
   ``depth_from_disparity``). OpenCV's StereoSGBM expects the match of left-image column x at ``x − d`` in the right
   image, so the rectified images are flipped along columns (θ → π − θ) before matching i (left) against
   j (right); the right-to-left disparity for the consistency check is then SGBM(left = j, right = i) unflipped.
3. **Depth** (``depth_from_disparity``): law of sines, ``|O_i P| = T sin(θ_j) / sin(d)``.
4. **Back to the panorama** (``range_map_to_panorama``) and **fusion** (``fuse_depth_maps``, ``clean_point_cloud``).

Ranges (distances from the camera centre) rather than z-depths are used throughout; invalid ranges are NaN.

Modules: ``rectify`` (step 1), ``disparity`` (2), ``depth`` (3, back to the panorama, ``densify_pair`` and the
per-panorama range maps), ``fusion`` (4), ``pairs`` (which pairs, how deep to search), ``scene`` (sparse-scene scales),
``planes`` (textureless regions: one plane per image region), ``world_planes`` (textureless pixels: the model's planes).
"""

from fullview.sfm.camera import camera_center
from fullview.sfm.dense.depth import (PairDepth, combine_range_estimates, combine_with_conflicts, conflicting_estimates, single_partner, densify_pair, depth_from_disparity,
                                      apply_mask, mask_below_latitude, range_error_per_pixel, range_map_to_panorama,
                                      rectified_range_maps, sample_edge_aware)
from fullview.sfm.dense.disparity import DisparityResult, SgbmParams, compute_disparity, disparity_search_range, pad_theta
from fullview.sfm.dense.fusion import (clean_point_cloud, fuse_depth_maps, fusion_neighbours, resolve_conflicts,
                                       seen_through_single_estimates)
from fullview.sfm.dense.pairs import pair_min_depth_ratio, select_stereo_pairs
from fullview.sfm.dense.rectify import (RectifiedPair, bearings_to_rectified, rectified_grid_bearings, rectify_pair,
                                        rectifying_rotation, theta_of_columns)
from fullview.sfm.dense.scene import SCENE_PERCENTILES, camera_depths, scene_size

__all__ = [
    "DisparityResult", "PairDepth", "RectifiedPair", "SCENE_PERCENTILES", "SgbmParams", "bearings_to_rectified",
    "camera_center", "camera_depths", "clean_point_cloud", "combine_range_estimates", "combine_with_conflicts", "conflicting_estimates", "compute_disparity",
    "densify_pair", "depth_from_disparity", "disparity_search_range", "fuse_depth_maps", "fusion_neighbours",
    "apply_mask", "mask_below_latitude", "pad_theta", "pair_min_depth_ratio", "range_error_per_pixel", "range_map_to_panorama",
    "rectified_grid_bearings", "rectified_range_maps", "rectify_pair", "resolve_conflicts", "rectifying_rotation", "sample_edge_aware",
    "scene_size", "seen_through_single_estimates", "select_stereo_pairs", "single_partner", "theta_of_columns",
]
