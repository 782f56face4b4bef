"""Every setting of the pipeline, in one place: one kw-only dataclass per stage, one field per `pipeline.yaml` key.

Each field carries its default, its bounds and a one-line meaning (`setting(...)`). The config loader, its validation,
the README's key table and the stage fingerprints all derive from these classes, and `sfm/` consumes them directly,
so a default or a bound is written exactly once.

Bounds: `ge`/`gt`/`le`/`lt` as in pydantic; `choices` for strings; `odd` for window sides; `zero_means` documents a
0 that switches a feature off or to "automatic" (0 is then accepted beside the bounds). Floats must be finite.
Cross-key rules live in each class's `RULES`: (description, predicate) pairs checked after loading.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, field, fields
from typing import Any, Callable, ClassVar


def setting(default: Any, doc: str, *, ge: float | None = None, gt: float | None = None, le: float | None = None,
            lt: float | None = None, choices: tuple[str, ...] | None = None, odd: bool = False,
            zero_means: str | None = None):
    """A dataclass field with its meaning and bounds as metadata."""
    return field(default=default, metadata={"doc": doc, "ge": ge, "gt": gt, "le": le, "lt": lt, "choices": choices,
                                            "odd": odd, "zero_means": zero_means})


Rule = tuple[str, Callable[[Any], bool]]


@dataclass(frozen=True, kw_only=True)
class FeaturesOptions:
    # le: never above the native width, whose memory the dataset's pixel budget bounds (io/limits.py)
    working_width: int = setting(2048, "panoramas are resized to this width before detection (never upsampled)",
                                 ge=128, le=65536, zero_means="native width")
    # le: the native face of the widest panorama PIL's pixel limit admits (13,377 px: 3,716 at margin 5); 4096² x 290
    # bytes (measured) x 2 images at once = 9 GiB; a machine with less memory allows less (io/limits.max_face_size)
    face_size: int = setting(0, "cube face side in pixels", ge=32, le=4096,
                             zero_means="as many pixels per degree as the working panorama")
    margin_deg: float = setting(5.0, "extra field of view on each side of a face's 90°, keeps features at seams",
                                ge=0.0, le=30.0)
    max_features_per_face: int = setting(1500, "SIFT nfeatures per face", ge=1, le=1_000_000, zero_means="unlimited")
    contrast_threshold: float = setting(0.02, "SIFT contrast threshold (OpenCV's default is 0.04)", gt=0.0, le=1.0)
    min_features_per_face: int = setting(300, "a face with fewer keypoints is detected again with half the contrast "
                                         "threshold (plain walls)", ge=0, le=1_000_000, zero_means="never")
    min_contrast_threshold: float = setting(0.0025, "... but never below this contrast threshold", gt=0.0, le=1.0)
    denoise_min_noise: float = setting(0.0, "panoramas with more sensor noise than this (grey levels, estimated) are "
                                       "denoised (non-local means) before detection (loses true matches: README)",
                                       ge=0.0, le=255.0, zero_means="never")
    min_latitude_deg: float = setting(-65.0, "drop features below this latitude (nadir cap: tripod, hand)",
                                      ge=-90.0, le=90.0)
    max_latitude_deg: float = setting(90.0, "drop features above this latitude (zenith cap)", ge=-90.0, le=90.0)
    root_sift: bool = setting(True, "Hellinger-normalised descriptors (RootSIFT)")
    RULES: ClassVar[list[Rule]] = [
        ("min_latitude_deg < max_latitude_deg", lambda o: o.min_latitude_deg < o.max_latitude_deg),
        ("min_contrast_threshold <= contrast_threshold", lambda o: o.min_contrast_threshold <= o.contrast_threshold)]


@dataclass(frozen=True, kw_only=True)
class MatchesOptions:
    pairs: str = setting("auto", "which pairs are matched. sequential: the window plus loop closures by retrieval; "
                         "retrieval: top neighbours by VLAD; auto: exhaustive below auto_exhaustive_below images, "
                         "else window + retrieval (+ GPS)", choices=("auto", "exhaustive", "sequential", "retrieval"))
    window: int = setting(3, "sequential / auto: partners after each image in capture order", ge=1, le=100_000)
    auto_exhaustive_below: int = setting(40, "auto: match every pair below this many images (<= 780 pairs)",
                                         ge=2, le=100_000)
    retrieval_neighbours: int = setting(10, "retrieval / auto / sequential loop closures: most similar images "
                                        "matched with each image", ge=1, le=100_000, zero_means="no retrieval")
    vocabulary_size: int = setting(64, "retrieval: k-means words of the VLAD vocabulary (trained per dataset)",
                                   ge=2, le=4096)
    vocabulary_sample: int = setting(1000, "retrieval: descriptors per image that train the vocabulary", ge=10,
                                     le=1_000_000)
    vocabulary_seed: int = setting(0, "retrieval: seed of the vocabulary's sample and k-means start", ge=0, le=2**31)
    gps_neighbours: int = setting(8, "auto: nearest images by EXIF GPS position matched with each image (those "
                                  "with GPS)", ge=1, le=100_000, zero_means="no GPS pairs")
    gps_radius_m: float = setting(0.0, "auto: also match every image within this GPS distance (m)", ge=0.0,
                                  le=100_000.0, zero_means="off")
    loop_patience: int = setting(2, "auto / sequential: retrieval pairs more than 2 x window capture steps apart (loop "
                                 "candidates) are matched in each image's similarity order, and an image stops after "
                                 "this many of its candidates in a row find too few matches (loop_min_share)",
                                 ge=0, le=100_000, zero_means="every loop candidate matched")
    loop_min_share: float = setting(0.1, "auto / sequential: a loop candidate finds enough matches with this share of "
                                    "the median raw matches of its two images' window pairs (the lower)",
                                    ge=0.0, le=1.0)
    ratio: float = setting(0.8, "Lowe's ratio test on descriptor distances", gt=0.0, le=1.0)
    mutual: bool = setting(True, "keep only mutual nearest neighbours")
    noisy_ratio: float = setting(0.85, "the ratio test of a pair whose noisier image measures more sensor noise than "
                                 "noisy_min_noise (noise blurs the nearest and second nearest distances alike); the "
                                 "filter draws its hypotheses from the matches that pass `ratio` and only counts the "
                                 "others", ge=0.0, le=1.0, zero_means="ratio, whatever the noise")
    noisy_min_noise: float = setting(0.3, "sensor noise (grey levels, `features.noise_sigma` of the working image) "
                                     "above which an image counts as noisy (plain clean renders ~0.1, Theta S "
                                     "~0.55; fine texture reads as noise too: textured rooms 0.7-0.9)",
                                     ge=0.0, le=255.0)
    descriptor_dims: int = setting(32, "nearest neighbours are searched on the descriptors' first principal "
                                   "components (per dataset; a quarter of the matrix product), the 3 nearest "
                                   "(4 with int8_search) re-ranked by full distances, the mutual check searched "
                                   "back the same way",
                                   ge=8, le=128, zero_means="all 128 dimensions")
    int8_search: bool = setting(True, "descriptor_dims > 0: the search multiplies the projections rounded to 8 "
                                "bits (integer kernels, a third of float32's time), its 4 nearest re-ranked by full "
                                "distances (4: rounding adds near-ties)")
    RULES: ClassVar[list[Rule]] = [
        ("retrieval_neighbours > 0 when pairs is retrieval", lambda o: o.pairs != "retrieval" or o.retrieval_neighbours > 0)]


@dataclass(frozen=True, kw_only=True)
class FilterOptions:
    use_hand_points: bool = setting(True, "seed F with hand points where a pair has >= min_hand_points")
    min_hand_points: int = setting(8, "hand correspondences needed to seed a pair (the 8-point algorithm)", ge=8,
                                   le=1_000_000)
    threshold_deg: float = setting(0.35, "angular distance to the epipolar great circle of an inlier", gt=0.0, le=90.0)
    max_iterations: int = setting(5000, "RANSAC hypotheses cap (lower on a pair with few matches: what finding the "
                                   "min_inliers it needs takes)", ge=1, le=10_000_000)
    confidence: float = setting(0.9999, "RANSAC adaptive stopping confidence", gt=0.0, lt=1.0)
    min_inliers: int = setting(30, "pairs with fewer inliers are dropped", ge=8, le=1_000_000)
    min_inliers_upright: int = setting(15, "pairs fitted by the upright model (3 unknowns, not 5) are kept from this "
                                       "many inliers", ge=8, le=1_000_000)
    seed: int = setting(0, "RANSAC random seed (pair k uses seed + k)", ge=0, le=2**31)
    wall_check: bool = setting(True, "upright pairs whose yaw contradicts both images' wall directions (modulo 90 "
                               "degrees, upright: vanishing) are fitted again under the yaws the walls allow; that "
                               "pose replaces the fit when it explains 90% as many matches")
    guided_matching: bool = setting(False, "rematch a pair's features along the epipolar circles of its F estimate "
                                    "(more inliers on weak pairs)")
    guided_ratio: float = setting(0.9, "ratio test of guided matching, among the candidates near the circle",
                                  gt=0.0, le=1.0)
    upright: str = setting("vanishing", "levelled panoramas: yaw-only relative rotations, 3-point solver. level: gravity is "
                           "each image's down axis; vanishing: gravity from vertical lines (none where none found)",
                           choices=("none", "level", "vanishing"))
    wide_pairs: bool = setting(False, "upright pairs the fit rejected are tested again by the chance of a wrong pair "
                               "fitting as well: an a-contrario test with guided rematching (docs/wide-baselines.md)")
    wide_false_alarms: float = setting(1e-3, "wrong pairs the wide test may accept by chance, expected over a "
                                       "dataset (its bound on the number of false alarms)", gt=0.0, lt=1.0)
    wide_height_spread_m: float = setting(0.1, "the cameras of a tour are at one height to within this (m): with "
                                          "wide_min_baseline_m it bounds the baseline's elevation", ge=0.0, le=10.0)
    wide_min_baseline_m: float = setting(2.0, "the shortest baseline the wide test serves (m): closer pairs share "
                                         "enough matches for the normal fit", gt=0.0, le=1000.0)
    wide_guided_band: float = setting(3.0, "the wide test rematches features within this many thresholds of a "
                                      "hypothesis' epipolar circles", gt=1.0, le=100.0)
    RULES: ClassVar[list[Rule]] = []


@dataclass(frozen=True, kw_only=True)
class EpipolesOptions:
    min_cheiral_ratio: float = setting(0.9, "share of inliers in front of both cameras for a valid pose",
                                       ge=0.0, le=1.0)
    RULES: ClassVar[list[Rule]] = []


@dataclass(frozen=True, kw_only=True)
class RegistrationOptions:
    model: str = setting("general", "general: rotation + translation averaging; planar: the report's Newton method",
                         choices=("general", "planar"))
    min_inliers: int = setting(30, "pairs with fewer inliers are not used", ge=8, le=1_000_000)
    max_rotation_residual_deg: float = setting(5.0, "pairs whose relative rotation disagrees more are rejected",
                                               gt=0.0, le=180.0)
    max_direction_residual_deg: float = setting(10.0, "pairs whose baseline direction disagrees more are rejected",
                                                gt=0.0, le=180.0)
    resection: bool = setting(True, "grow every model by absolute pose (P3P on bearings) of the images left out")
    min_resection_points: int = setting(15, "model points an image must see (inliers) to be added by resection",
                                        ge=6, le=1_000_000)
    resection_threshold_deg: float = setting(1.0, "angular error of a resection inlier", gt=0.0, le=90.0)
    merge_models: bool = setting(True, "merge two models by a similarity when they share enough points")
    min_merge_points: int = setting(6, "points triangulated in both models that must agree on the similarity (3 fix its 7 "
                                    "unknowns; the rest check it) to merge them",
                                    ge=4, le=1_000_000)
    min_join_points: int = setting(6, "tracks that must agree on the scale joining a part of an averaged layout whose "
                                   "scale the pair directions leave free", ge=2, le=1_000_000)
    min_weak_pair_inliers: int = setting(6, "a pair too weak to be used (below min_inliers) touching a part whose "
                                         "scale averaging guessed gives its matches to the final tracks when this "
                                         "many fit a baseline near the model's under its rotations (2 unknowns)",
                                         ge=2, le=1_000_000, zero_means="never")
    join_by_weak_pairs: bool = setting(True, "join two models where three or more raw-matched pairs between them, "
                                       "each too weak to verify (6+ upright inliers), agree on one rotation and "
                                       "placement (a doorway seen from both rooms)")
    weak_join_guided: bool = setting(True, "where no three weak pairs agree, each one's rotation guides 2-unknown "
                                     "baseline fits of the other pairs between the models, and three of them that "
                                     "place the models consistently join them")
    weak_join_rematch: bool = setting(True, "where the weak joins find nothing, each weak pair's fit is a pose under "
                                      "which its descriptors are matched again along the epipolar circles (ratio "
                                      "test among the circle's features); two or more pairs so confirmed (20+ "
                                      "matches, twice those under the pose turned by 90, 180 or 270 degrees) that "
                                      "place the models consistently join them")
    weak_join_one_pair: bool = setting(True, "where the rematch confirms one pair but no second one (a single doorway "
                                       "pair), the pair joins the models when points of both models agree on one "
                                       "placement of its second camera (5+ and 3/4 of each model's points "
                                       "among its matches, b's scale within 2x of the baselines' ratio); seeds "
                                       "also from the four rotations the images' walls allow between the models")
    weak_join_several: bool = setting(True, "where nothing above joins two models, a rematched pair with more "
                                      "matches than under each of its quarter turns, and one more such pair sharing "
                                      "one of its cameras, that place the models consistently join them (a doorway "
                                      "in a box room, whose quarter turns rematch nearly as well)")
    join_check: bool = setting(True, "a weak join is undone when it puts 10+ and over 5% of the points one model "
                               "has on the other's observed rays in front of what those cameras saw (10%+ "
                               "closer): a chance pair places a model inside the other's rooms")
    unconfirmed_joins: str = setting("separate", "a join that nothing confirms (a guessed scale or length, one "
                                     "rematched pair alone): separate: never made, the part stays a model of its "
                                     "own; approximate: made last, its cameras marked approximate (kept out of "
                                     "densify and the exports, nothing grows from them)",
                                     choices=("separate", "approximate"))
    seed: int = setting(0, "random seed of resection and merging (RANSAC)", ge=0, le=2**31)
    RULES: ClassVar[list[Rule]] = []


@dataclass(frozen=True, kw_only=True)
class TriangulationOptions:
    max_reprojection_error_deg: float = setting(0.5, "angular reprojection error of a kept observation",
                                                gt=0.0, le=90.0)
    min_triangulation_angle_deg: float = setting(1.5, "tracks seen under a smaller angle are dropped", ge=0.0, lt=90.0)
    bundle_adjust: bool = setting(True, "refine poses and points jointly")
    ba_loss_scale_deg: float = setting(0.2, "soft-L1 loss scale of bundle adjustment residuals", gt=0.0, le=90.0)
    ba_max_iterations: int = setting(100, "function evaluations of bundle adjustment", ge=1, le=100_000)
    geometry_neighbours: int = setting(5, "before the final pass, each registered camera is also matched with this "
                                       "many nearest registered cameras never matched before", ge=0, le=1000,
                                       zero_means="no geometry pairs")
    geometry_min_inliers: int = setting(30, "matches a geometry pair needs within max_reprojection_error_deg of "
                                        "its known epipolar circles", ge=8, le=1_000_000)
    gravity_prior: bool = setting(True, "bundle adjustment holds each image's tilt to its gravity from vertical "
                                  "lines (filter.upright: vanishing), weighted by its precision")
    manhattan_prior: bool = setting(True, "bundle adjustment holds each image's heading, modulo 90°, to its "
                                    "model's wall directions measured from its horizontal lines (needs a measured "
                                    "gravity; a model whose images do not agree on one pair of directions gets none)")
    height_prior: bool = setting(True, "bundle adjustment holds every camera's height above its floor points to its "
                                 "model's common height (a tripod tour; needs a measured gravity; cameras whose floor "
                                 "disagrees with their room's and models without enough floors get none)")
    height_prior_sigma: float = setting(0.033, "relative standard error of one camera's height above the floor: a "
                                        "person or a tripod keeps its height within about 5 cm over a walk, 0.05 m "
                                        "/ 1.5 m (measured robust spread: 360_Flat 0.017-0.020, 360_school 0.006)",
                                        gt=0.0, le=1.0)
    height_prior_max_spread: float = setting(0.067, "after the pose round, a model whose heights above the floor still "
                                             "spread more than this (relative, robust) gets no height prior in the "
                                             "final adjustment: twice height_prior_sigma, 10 cm at 1.5 m (not one "
                                             "height: a split level, a camera lifted off its tripod)",
                                             gt=0.0, le=10.0)
    bridge_floor: bool = setting(True, "with the height prior, a bridge (two cameras only two-view tracks join) "
                                 "whose own points show the floor below both cameras gets the length that puts it "
                                 "at the model's camera height, instead of registration's")
    free_block_min_pairs: int = setting(3, "after the final adjustment, blocks of cameras that share no track with "
                                        "the rest (meeting at one camera) and hold this many verified pairs are scaled "
                                        "to the block with the most pairs (free_block_scale)", ge=0, le=1_000_000,
                                        zero_means="keep registration's scales")
    free_block_scale: str = setting("camera_height", "what such a block's scale is set by: its cameras' median "
                                    "height above the floor equal to the root block's (a tripod keeps it; the "
                                    "baseline where either block's floor is not seen), or the median pair baseline",
                                    choices=("camera_height", "baseline"))
    RULES: ClassVar[list[Rule]] = []


@dataclass(frozen=True, kw_only=True)
class DensifyOptions:
    neighbours: int = setting(2, "stereo partners per camera (best by inlier count, short baselines discounted)",
                              ge=1, le=64)
    min_epipole_separation_deg: float = setting(
        30.0, "a camera's partners lie in baseline directions at least this far apart (their epipoles differ)",
        ge=0.0, le=90.0)
    min_triangulation_angle_deg: float = setting(
        5.0, "partner baselines must subtend at least this at the scene's median depth", gt=0.0, lt=90.0)
    max_triangulation_angle_deg: float = setting(60.0, "... and at most this", gt=0.0, le=180.0)
    min_pair_inliers: int = setting(50, "epipolar inliers a stereo pair needs", ge=8, le=1_000_000)
    # le: never above the native width. The pixel budget bounds one panorama, but densify holds all of them (about
    # 36 bytes per pixel each, run peaks of a 6-view scene at 512 and 1024 px): 0 on many huge panoramas may not fit
    working_width: int = setting(2048, "panoramas are resized to this width; range maps have this size "
                                 "(never upsampled)", ge=128, le=65536, zero_means="native width")
    # le: never above the panoramas' height at the working width (stages/densify.py), which the pixel budget bounds
    rect_height: int = setting(1024, "rectified grid height (angle from the epipole); width = 2x", ge=16, le=16384)
    min_depth_percentile: float = setting(1.0, "nearest plausible depth: this percentile of a camera's sparse-point "
                                          "distances", ge=0.0, le=100.0)
    min_depth_factor: float = setting(0.5, "... times this factor; bounds the disparity search", gt=0.0, le=10.0)
    max_disparity_deg: float = setting(45.0, "cap of the disparity search (wide baselines lose their nearest points)",
                                       gt=0.0, le=90.0)
    epipole_margin_deg: float = setting(8.0, "pixels closer than this to an epipole are masked", ge=0.0, lt=90.0)
    max_range_error_per_px: float = setting(0.05, "drop ranges whose relative error per pixel of disparity error "
                                            "exceeds this", gt=0.0, le=1000.0)
    block_size: int = setting(5, "SGBM matching window side", ge=1, le=31, odd=True)
    min_texture_std: float = setting(2.0, "grey-level std below which a pixel counts as untextured (not matched)",
                                     ge=0.0, le=255.0)
    min_latitude_deg: float = setting(-65.0, "range maps are invalid below this latitude (nadir cap: tripod, hand)",
                                      ge=-90.0, le=90.0)
    max_latitude_deg: float = setting(90.0, "range maps are invalid above this latitude (zenith cap)", ge=-90.0,
                                      le=90.0)
    combine_tolerance: float = setting(0.02, "relative agreement of a panorama's pair estimates (conflicting ones "
                                       "are dropped)", gt=0.0, le=1.0)
    stereo_check: bool = setting(True, "drop a stereo range resting on one pair that a neighbouring panorama's stereo "
                                 "sees clearly beyond while none confirms it (fusion_views nearest, "
                                 "consistency_tolerance); the textureless fills still see it")
    resolve_conflicts: bool = setting(True, "where a panorama's pair estimates conflict, take the one its "
                                      "neighbouring panoramas' stereo confirms (fusion_views nearest; with "
                                      "stereo_check), instead of none")
    min_consistent: int = setting(1, "other depth maps that must agree for a fused point", ge=0, le=64)
    consistency_tolerance: float = setting(0.02, "relative range tolerance for agreement", gt=0.0, le=1.0)
    fusion_views: int = setting(4, "nearest other panoramas checking each panorama's points", ge=1, le=64)
    fusion_stride: int = setting(2, "fuse every n-th pixel of the range maps in both directions", ge=1, le=64)
    voxel_size: float = setting(0.0, "voxel size of the fused cloud (model units)", ge=0.0,
                                zero_means="0.2% of the scene's size")
    outlier_neighbours: int = setting(20, "statistical outlier removal: neighbours", ge=1, le=1000)
    outlier_std_ratio: float = setting(2.0, "statistical outlier removal: std ratio", gt=0.0, le=1000.0)
    preview: bool = setting(True, "render densify/dense_preview.png")
    fill_planes: bool = setting(True, "fill textureless regions with the planes through their border depths, kept "
                                "where another view's own result agrees (sfm/dense/planes.py)")
    # le: never above the range maps' width (densify.working_width)
    fill_width: int = setting(1024, "textureless filling works at this width (at most the range maps')", ge=64,
                              le=65536)
    plane_tolerance: float = setting(0.03, "relative range difference within which a border depth lies on a plane",
                                     gt=0.0, le=0.5)
    region_plane_snap_deg: float = setting(6.0, "textureless filling: a region's plane within this angle of level "
                                           "is made exactly level where that still explains its share of the border "
                                           "depths (their bias along the lines where surfaces meet tilts a ceiling's "
                                           "fit by a degree or more; walls keep their fit)", ge=0.0, le=45.0,
                                           zero_means="region planes keep their fitted normals")
    region_planes_from_world: bool = setting(True, "with world_planes, a textureless region whose filled pixels (at "
                                             "least 90%) lie within the view tolerance of a kept world plane takes "
                                             "that plane (fitted on every panorama's points, not one view's)")
    world_planes: bool = setting(True, "fill what is still empty with the dominant planes of the whole model, each "
                                 "within the extent its points support (sfm/dense/world_planes.py)")
    world_plane_distance: float = setting(0.015, "a point supports a world plane within this share of its range "
                                          "(from the camera that measured it)", gt=0.0, le=0.2)
    world_plane_extent: str = setting("gravity", "a world plane's extent: gravity = floor/ceiling span their "
                                      "support's bounding rectangle, walls each column between their lowest and "
                                      "highest support; support = closed support, enclosed holes filled; both minus "
                                      "what the views see through", choices=("gravity", "support"))
    world_plane_snap_deg: float = setting(6.0, "world planes: level ones are made exactly level (gravity), upright "
                                          "ones within this angle of the model's dominant wall direction (or its "
                                          "perpendicular) are turned onto it", ge=0.0, le=45.0,
                                          zero_means="planes keep their fitted normals")
    sweep_walls: bool = setting(True, "with world_plane_snap_deg > 0, also the walls along the dominant wall "
                                "directions that RANSAC missed (a plain wall's floor and ceiling lines are explained "
                                "by the floor and the ceiling first)")
    free_ceiling: bool = setting(True, "a level world plane above a camera (its ceiling) may fill any of its image "
                                 "regions, without their stereo support (with world_plane_snap_deg > 0)")
    ceiling_over_camera: bool = setting(True, "with free_ceiling, a level plane above a camera is its ceiling only "
                                        "where its extent spans over the camera (outdoors a ledge or a roof beside "
                                        "the camera is no ceiling, and the sky stays empty)")
    room_window_cells: int = setting(2, "world planes: a level plane spans over (under) a camera, its ceiling (floor) "
                                     "for free_ceiling, free_floor and free_walls, where at least half the extent "
                                     "cells within this many of the camera's foot point are its (one carved cell under "
                                     "a tripod switched a panorama's free floor and walls)", ge=0, le=50,
                                     zero_means="the cell of the foot point alone")
    free_floor: bool = setting(True, "a pixel no other rule fills may take the level world plane below its camera "
                               "(its floor, spanning under it) where that is the first plane its ray meets, in a room "
                               "(a ceiling spans over the camera too), without its region's stereo support")
    free_walls: bool = setting(True, "a pixel no other rule fills (not even free_floor) may take the first world plane "
                               "its ray meets where that is a wall (upright), in a room, without its region's stereo "
                               "support; the view checks still apply")
    ground_max_tilt_deg: float = setting(10.0, "world planes: the ground (best supported level plane below the "
                                         "cameras) is refitted with a tilt up to this where that explains 1.5x its "
                                         "points (outdoor ground slopes)", ge=0.0, le=30.0, zero_means="always level")
    ground_sweep: str = setting("no_ceiling", "stereo on the ground by a sweep of ground-parallel planes (sfm/dense/"
                                "ground_sweep.py), where a pair's SGBM has no range below the horizon or one it "
                                "disagrees with: never, always, or no_ceiling = outdoors (the highest points around "
                                "most cameras stand more than twice the camera's height above it: "
                                "ground_sweep.indoor_or_outdoor)",
                                choices=("never", "no_ceiling", "always"))  # "never", not "off" (YAML 1.1 read a bool)
    # le: never above the range maps' width (densify.working_width)
    ground_sweep_width: int = setting(1280, "the ground sweep works at this width (at most the range maps'; its "
                                      "ranges are resized to them)", ge=64, le=65536)
    ground_sweep_window: int = setting(9, "ground sweep: NCC window side (pixels at its width)", ge=3, le=31, odd=True)
    ground_sweep_min_ncc: float = setting(0.6, "ground sweep: the winning plane's NCC must reach this", ge=-1.0,
                                          le=1.0)
    free_space_confirmed: bool = setting(True, "the free-space check of the world planes counts only the stereo "
                                         "ranges another panorama confirms (one view's errors at the lines where "
                                         "surfaces meet see through true floors and ceilings)")
    seed: int = setting(0, "seed of the plane RANSAC of textureless filling", ge=0, le=2**31 - 1)
    mesh: bool = setting(True, "write densify/dense_mesh.ply: a Poisson mesh of the fused cloud, trimmed to what the "
                         "views support")
    mesh_depth: int = setting(0, "Poisson octree depth of the mesh", ge=5, le=12,
                              zero_means="cells about mesh_cell_voxels voxels wide (at most 11)")
    mesh_cell_voxels: float = setting(4.0, "with mesh_depth 0: Poisson's octree cells about this many voxels of the "
                                      "fused cloud wide (2: a finer mesh, 4 to 5 times the Poisson time)",
                                      ge=1.0, le=64.0)
    mesh_density_quantile: float = setting(0.02, "mesh vertices below this quantile of Poisson density are dropped",
                                           ge=0.0, lt=1.0)
    mesh_max_distance_voxels: float = setting(3.0, "mesh triangles with a vertex farther than this many voxels from "
                                              "a dense point are dropped", gt=0.0, le=1000.0)
    mesh_support_tolerance: float = setting(0.03, "relative range tolerance of a view observing (or seeing through) "
                                            "a mesh triangle", gt=0.0, le=1.0)
    mesh_window_px: int = setting(3, "pixel window of the mesh's visibility tests in the range maps", ge=1, le=31,
                                  odd=True)
    mesh_min_component_triangles: int = setting(50, "connected mesh pieces with fewer triangles are dropped", ge=0,
                                                le=1_000_000_000)
    occlusion_aware_vote: bool = setting(True, "the world fill's view check of floor and ceiling pixels: another "
                                         "colour seen by a panorama whose world planes put a surface in front of "
                                         "the point (a floor next to a cupboard) is no vote against it")
    occlusion_aware_wall_vote: bool = setting(True, "with occlusion_aware_vote, the same for wall pixels: with whole "
                                              "walls and free_walls the model's nearest plane is mostly the wall "
                                              "seen, and the colour of a surface it puts in front is no vote")
    one_level_plane_per_band: bool = setting(True, "world planes: the level planes seen from one side within 3 median "
                                             "tolerances of each other (one ceiling found in pieces a few cm apart) "
                                             "become one, at the mode of their points' heights, judged invented only "
                                             "where the views see 2 view tolerances beyond it (with "
                                             "world_plane_snap_deg > 0)")
    one_wall_plane_per_offset: bool = setting(True, "world planes: the wall pieces snapped to the dominant "
                                              "direction and seen from one side that reach one mode of their "
                                              "points' offsets (searched within 3 median tolerances; one wall found "
                                              "in pieces a few cm apart) become one plane there, the wall direction "
                                              "fitted on all walls' points, judged invented as a merged level plane "
                                              "(with world_plane_snap_deg > 0)")
    walls_floor_to_ceiling: bool = setting(True, "world planes: every column of a wall's extent runs from the floor "
                                           "to the ceiling plane (what the views see through is cut, and a pixel "
                                           "takes the wall only where its region or its brackets support it)")
    wall_extent_by_votes: bool = setting(True, "world planes: a wall is judged invented on its support's own extent, "
                                         "and each column its generous extent adds (floor to ceiling) by the free-"
                                         "space votes of the columns around it; false: the whole generous extent "
                                         "against max_seen_through, else the support's extent alone")
    wall_brackets: bool = setting(True, "world fill: a wall may also take a pixel whose nearest ranges above and "
                                  "below it in its image column, or left and right in its row, lie on the wall "
                                  "(its floor and ceiling lines, its corners), whatever its image region's evidence")
    RULES: ClassVar[list[Rule]] = [
        ("min_triangulation_angle_deg < max_triangulation_angle_deg",
         lambda o: o.min_triangulation_angle_deg < o.max_triangulation_angle_deg),
        ("fusion_views >= min_consistent", lambda o: o.fusion_views >= o.min_consistent),
        ("min_latitude_deg < max_latitude_deg", lambda o: o.min_latitude_deg < o.max_latitude_deg)]


# pipeline.yaml's sections; the stage order itself is declared once, in fullview.stages.PIPELINE.
OPTIONS_BY_SECTION: dict[str, type] = {
    "features": FeaturesOptions, "matches": MatchesOptions, "filter": FilterOptions, "epipoles": EpipolesOptions,
    "registration": RegistrationOptions, "triangulation": TriangulationOptions, "densify": DensifyOptions,
}


def option_fields(cls: type) -> list:
    """The settings of an options class (its dataclass fields), in declaration order."""
    return [f for f in fields(cls) if f.default is not MISSING]
