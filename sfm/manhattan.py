"""Manhattan heading of a levelled panorama from its horizontal lines, and the heading prior's residual.

Most homes' walls meet at right angles, and a levelled panorama sees their horizontal edges (wall-floor and
wall-ceiling junctions, door and window frames, furniture). A horizontal scene line along the world direction a lies
on a great circle through ±a; with the camera's gravity g (``upright``), the circle's unit normal n is orthogonal to
a, and a is orthogonal to g: every horizontal line gives one heading of a about g. In a Manhattan scene these
headings cluster at one angle modulo 90° (``manhattan_axis``): the image's own heading, measured independently of
every other image.

With the axis found, the gravity and the axis are refined together on the vertical and the horizontal lines
(``manhattan_frame``): horizontal lines constrain the tilt too, and this gravity replaces the vertical lines' one in
the bundle adjustment's gravity prior.

The bundle adjustment uses the axis as a soft prior (``bundle.HeadingPrior``): a model's cameras share one world
Manhattan axis u (one per model, horizontal), and each camera sees it at the heading its lines measured. Why: on a
chain of rooms joined through doorways the bearings leave each room's heading free to drift slowly (a random walk of the
per-doorway heading errors), like its tilt, which the gravity prior holds; each image's heading is ~0.05° off and
independent of its neighbours' (stated 0.048-0.074° on 360_Flat and 360_school).

Residual. With v = R u (the world axis in the camera frame), d the measured axis and b = g × d (unit), the
heading error is Δ = atan2(b·v, d·v) and the residual ``r = w · sin(4Δ) / 4``: Δ for small errors, periodic in
90° (the measured axis is known modulo 90°), smooth everywhere.

References:
- J. M. Coughlan, A. L. Yuille, "Manhattan World: compass direction from a single image by Bayesian inference",
  ICCV 1999.
- J.-C. Bazin, Y. Seo, C. Demonceaux, P. Vasseur, K. Ikeuchi, I. Kweon, M. Pollefeys, "Globally optimal line
  clustering and vanishing point estimation in Manhattan world", CVPR 2012.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from fullview.sfm.camera import normalize

# A line whose great circle passes within this of the vertical direction may be vertical: no heading.
VERTICAL_MARGIN_DEG = 3.0
MANHATTAN_REFIT_ROUNDS = 20  # at most this many least-squares re-fits of the heading
# A standard error below this is not believed: a tenth of a pixel at the width lines are found (0.1 × 360° / 2048,
# `filter.GRAVITY_WIDTH`), what a sub-pixel edge fit reaches; segments of one edge are not independent. The real
# captures state 0.048-0.074° per image (360_Flat, 360_school), so this binds only on clean renders.
MIN_HEADING_SIGMA_RAD = np.radians(0.1 * 360.0 / 2048)


def horizontal_basis(gravity_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two orthonormal vectors (3,) spanning the plane orthogonal to the unit gravity g, e2 = g × e1."""
    g = normalize(np.asarray(gravity_cam, np.float64)[None])[0]
    helper = np.array([1.0, 0.0, 0.0]) if abs(g[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    e1 = normalize(np.cross(helper, g)[None])[0]
    return e1, np.cross(g, e1)


def _wrap90(angle: np.ndarray) -> np.ndarray:
    """Angles (radians) modulo 90°, in [−45°, 45°)."""
    quarter = np.pi / 2
    return (np.asarray(angle) + quarter / 2) % quarter - quarter / 2


def manhattan_axis(normals: np.ndarray, weights: np.ndarray, gravity_cam: np.ndarray, *, inlier_deg: float = 1.0,
                   min_lines: int = 8, min_share: float = 0.25) -> tuple[np.ndarray, float, int] | None:
    """The horizontal direction d (camera frame, orthogonal to gravity) that the most horizontal lines run along
    or across, its standard error (radians) and the number of supporting lines; None with fewer than min_lines or
    less than min_share of the horizontal lines' information (a scene without one dominant pair of wall directions).

    normals: (M, 3) great-circle normals of line segments (`upright.detect_line_normals`), weights (M,) their lengths.
    Each non-vertical line's heading ψ = heading of n × g; its information about the heading is a² (a = n·d⊥,
    small for lines near the horizon, whose circles barely constrain it). The mode of ψ modulo 90° (the candidate
    with the most information within inlier_deg) is refined by weighted least squares of n·d(ψ) = 0 (each line on its nearer
    axis), re-selecting the inliers until they no longer change.
    """
    n = normalize(np.asarray(normals, np.float64).reshape(-1, 3))
    w = np.asarray(weights, np.float64).reshape(-1)
    g = normalize(np.asarray(gravity_cam, np.float64)[None])[0]
    e1, e2 = horizontal_basis(g)
    horizontal = np.abs(n @ g) > np.sin(np.radians(VERTICAL_MARGIN_DEG))
    n, w = n[horizontal], w[horizontal]
    if len(n) < min_lines:
        return None
    along = np.cross(n, g)  # each line's direction, if it is horizontal (length: |a|)
    psi = np.arctan2(along @ e2, along @ e1)
    info = w * np.einsum("ij,ij->i", along, along)  # w·a²
    tolerance = np.radians(inlier_deg)
    close = np.abs(_wrap90(psi[:, None] - psi[None, :])) < tolerance
    heading = psi[np.argmax(close @ info)]
    inliers = np.abs(_wrap90(psi - heading)) < tolerance
    for _ in range(MANHATTAN_REFIT_ROUNDS):
        if inliers.sum() < 2:
            return None
        heading = _refine_heading(n[inliers], w[inliers], e1, e2, heading)
        previous, inliers = inliers, np.abs(_wrap90(psi - heading)) < tolerance
        if np.array_equal(previous, inliers):
            break
    if inliers.sum() < min_lines or info[inliers].sum() < min_share * info.sum():
        return None
    d = np.cos(heading) * e1 + np.sin(heading) * e2
    return d, heading_std(n[inliers], w[inliers], e1, e2, heading), int(inliers.sum())


def _axes(e1, e2, heading: float) -> tuple[np.ndarray, np.ndarray]:
    """The Manhattan axis at this heading and the one 90° on."""
    c, s = np.cos(heading), np.sin(heading)
    return c * e1 + s * e2, -s * e1 + c * e2


def _line_residuals(n: np.ndarray, e1, e2, heading: float) -> tuple[np.ndarray, np.ndarray]:
    """n·d of each line against its nearer axis (d or d⊥) and the derivative by the heading."""
    d, d_perp = _axes(e1, e2, heading)
    on_d = np.abs(n @ d) <= np.abs(n @ d_perp)
    residual = np.where(on_d, n @ d, n @ d_perp)
    derivative = np.where(on_d, n @ d_perp, -(n @ d))
    return residual, derivative


def _refine_heading(n: np.ndarray, w: np.ndarray, e1, e2, heading: float, steps: int = 3) -> float:
    """Gauss-Newton on Σ w (n·d(ψ))² (a few steps: the start is within a degree)."""
    for _ in range(steps):
        r, a = _line_residuals(n, e1, e2, heading)
        heading -= float((w * a) @ r) / max(float((w * a) @ a), 1e-300)
    return heading


def heading_std(n: np.ndarray, w: np.ndarray, e1, e2, heading: float) -> float:
    """Standard error (radians) of the least-squares heading: the residual spread s² = Σ w r² / (m − 1) (weights
    scaled to mean 1) over the information Σ w a², bounded below by MIN_HEADING_SIGMA_RAD. Segments of one edge are
    not independent: a lower bound, widened by the bundle adjustment from the spread of the adjusted headings."""
    if len(n) < 2:
        return float("inf")
    w = np.asarray(w, np.float64) / np.mean(w)
    r, a = _line_residuals(n, e1, e2, heading)
    s2 = float(w @ r**2) / (len(n) - 1)
    return max(float(np.sqrt(s2 / max(float(w @ a**2), 1e-300))), MIN_HEADING_SIGMA_RAD)


def manhattan_frame(normals: np.ndarray, weights: np.ndarray, gravity_cam: np.ndarray, axis_cam: np.ndarray, *,
                    inlier_deg: float = 1.0, rounds: int = 5) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The gravity and axis refined together on the vertical and the horizontal lines: (gravity (3,), axis (3,),
    the gravity's standard error along its worst direction, the heading's standard error), radians.

    The frame (d, g, d × g) turns by the least-squares rotation δ of the lines' residuals n·m (m each line's nearest
    axis, within inlier_deg): r + δ·(m × n) = 0. Horizontal lines constrain the tilt too (a line along d the tilt
    about d × g), so the gravity uses more lines than the vertical ones alone (`upright.estimate_gravity`).
    """
    n = normalize(np.asarray(normals, np.float64).reshape(-1, 3))
    w = np.asarray(weights, np.float64).reshape(-1)
    w = w / np.mean(w)
    g = normalize(np.asarray(gravity_cam, np.float64)[None])[0]
    d = normalize(np.asarray(axis_cam, np.float64)[None])[0]
    frame = np.stack([d, g, np.cross(d, g)])
    sin_inlier = np.sin(np.radians(inlier_deg))
    for _ in range(rounds):
        residuals = n @ frame.T
        nearest = np.argmin(np.abs(residuals), axis=1)
        r = residuals[np.arange(len(n)), nearest]
        inliers = np.abs(r) < sin_inlier
        A = np.cross(frame[nearest[inliers]], n[inliers])
        info = (A * w[inliers, None]).T @ A
        if inliers.sum() < 4 or np.linalg.cond(info) > 1e12:
            return g, d, float("inf"), float("inf")
        delta = -np.linalg.solve(info, (A * w[inliers, None]).T @ r[inliers])
        frame = frame @ _rotation(delta).T
    residuals = n @ frame.T
    nearest = np.argmin(np.abs(residuals), axis=1)
    r = residuals[np.arange(len(n)), nearest]
    inliers = np.abs(r) < sin_inlier
    A = np.cross(frame[nearest[inliers]], n[inliers])
    s2 = float(w[inliers] @ r[inliers] ** 2) / max(int(inliers.sum()) - 3, 1)
    covariance = s2 * np.linalg.inv((A * w[inliers, None]).T @ A)
    g, d = frame[1], frame[0]
    tilt = np.stack([d, frame[2]])  # rotations about d and d × g tilt the gravity
    sigma_g = float(np.sqrt(np.linalg.eigvalsh(tilt @ covariance @ tilt.T).max()))
    return g, d, sigma_g, max(float(np.sqrt(g @ covariance @ g)), MIN_HEADING_SIGMA_RAD)


def _rotation(omega: np.ndarray) -> np.ndarray:
    """exp([ω]×) of one rotation vector."""
    theta = float(np.linalg.norm(omega))
    if theta < 1e-15:
        return np.eye(3)
    k = omega / theta
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def heading_error(v: np.ndarray, axis_cam: np.ndarray, gravity_cam: np.ndarray) -> np.ndarray:
    """(M,) heading Δ (radians, modulo 90° in [−45°, 45°)) of the directions v (M, 3) from the measured axes d,
    about the measured gravities g (camera frame)."""
    d, b = axis_cam, normalize(np.cross(gravity_cam, axis_cam))
    return _wrap90(np.arctan2(np.einsum("mi,mi->m", b, v), np.einsum("mi,mi->m", d, v)))


def heading_residuals(v: np.ndarray, axis_cam: np.ndarray, gravity_cam: np.ndarray,
                      sqrt_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M,) residuals w·sin(4Δ)/4 of the world axis seen in each camera, v (M, 3), against the measured axes
    (module docstring), and their derivatives (M, 3) by v."""
    d, b = axis_cam, normalize(np.cross(gravity_cam, axis_cam))
    x, y = np.einsum("mi,mi->m", d, v), np.einsum("mi,mi->m", b, v)
    delta = np.arctan2(y, x)
    r = sqrt_w * np.sin(4.0 * delta) / 4.0
    d_delta = (x[:, None] * b - y[:, None] * d) / np.maximum(x**2 + y**2, 1e-300)[:, None]
    return r, (sqrt_w * np.cos(4.0 * delta))[:, None] * d_delta


def world_heading(axis_world: np.ndarray, up_world: np.ndarray) -> np.ndarray:
    """(M,) heading of world directions (M, 3) about the world up (3,), in a fixed basis of its horizontal plane."""
    e1, e2 = horizontal_basis(up_world)
    return np.arctan2(axis_world @ e2, axis_world @ e1)


def mean_axis(headings: np.ndarray, weights: np.ndarray, up_world: np.ndarray) -> np.ndarray:
    """The world axis (3,) at the weighted circular mean of headings modulo 90° (the mean of 4ψ on the circle)."""
    z = np.sum(weights * np.exp(4j * np.asarray(headings)))
    e1, e2 = horizontal_basis(up_world)
    return _axes(e1, e2, float(np.angle(z)) / 4.0)[0]


@dataclass(frozen=True, kw_only=True)
class HeadingPrior:
    """Measured Manhattan axes of some cameras, pulling their headings towards their model's world axis."""

    camera: np.ndarray  # (M,) camera index
    axis_cam: np.ndarray  # (M, 3) measured unit axis in the camera frame (modulo 90° about gravity_cam)
    gravity_cam: np.ndarray  # (M, 3) the camera's measured unit gravity, its axis's plane normal
    down_world: np.ndarray  # (M, 3) the group's down direction in the world (the headings are taken about it)
    axis_world: np.ndarray  # (M, 3) the group's world axis (a start: bundle_adjust re-estimates it per group)
    group: np.ndarray  # (M,) cameras of one group (one model) share one world axis
    sigma_rad: np.ndarray  # (M,) standard error of the measured heading, radians


# A measured heading farther than this many standard errors (a 6-sigma test: the real headings lie 2.66 stated
# errors away, root mean square, 360_Flat) and than MIN_HEADING_OUTLIER_RAD (twice the largest wall residual of a correct pair
# on 360_Flat, 0.52°) from its model's axis (modulo 90°) is an outlier (a room built at another angle, furniture taken for walls) and gets no prior.
HEADING_OUTLIER_SIGMAS = 6.0
MIN_HEADING_OUTLIER_RAD = np.radians(1.0)


def heading_prior_for_models(R_cam_from_world: np.ndarray, axis_cam: np.ndarray, gravity_cam: np.ndarray,
                             sigma_rad: np.ndarray, model_id: np.ndarray, *,
                             min_share: float = 0.5) -> HeadingPrior | None:
    """The heading prior of the cameras whose measured axis agrees with their model's: each model's world axis is
    the precision-weighted circular mean (modulo 90°) of its cameras' axes carried to the world, computed again
    without the outliers. A model where fewer than min_share of its measured cameras (or fewer than 3) agree is not
    a Manhattan scene and gets no prior. None when no camera qualifies."""
    R = np.asarray(R_cam_from_world, np.float64)
    d, g = np.asarray(axis_cam, np.float64), np.asarray(gravity_cam, np.float64)
    sigma = np.maximum(np.asarray(sigma_rad, np.float64), MIN_HEADING_SIGMA_RAD)
    model_id = np.asarray(model_id)
    measured = np.isfinite(d).all(1) & np.isfinite(g).all(1) & np.isfinite(sigma) & (model_id >= 0)
    d, g = np.where(measured[:, None], d, 0.0), np.where(measured[:, None], g, 0.0)
    axis_world, down_world = np.einsum("nji,nj->ni", R, d), np.einsum("nji,nj->ni", R, g)
    tolerance = np.maximum(HEADING_OUTLIER_SIGMAS * sigma, MIN_HEADING_OUTLIER_RAD)
    keep = np.zeros(len(R), bool)
    axis_of, down_of = np.zeros((len(R), 3)), np.zeros((len(R), 3))
    for model in np.unique(model_id[measured]):
        members = np.flatnonzero(measured & (model_id == model))
        down = normalize(down_world[members].sum(0)[None])[0]
        psi = world_heading(axis_world[members], down)
        # The camera whose heading most others agree with starts the mean (a wrong one cannot).
        agree = np.abs(_wrap90(psi[:, None] - psi[None, :])) <= tolerance[members][None, :]
        inliers = agree[np.argmax(agree.sum(1))]
        for _ in range(2):  # the weighted mean, then again over the cameras that agree with it
            mean = mean_axis(psi[inliers], 1.0 / sigma[members[inliers]] ** 2, down)
            inliers = np.abs(_wrap90(psi - world_heading(mean[None], down)[0])) <= tolerance[members]
        if inliers.sum() < max(3, min_share * len(members)):
            continue
        keep[members[inliers]] = True
        axis_of[members], down_of[members] = mean, down
    camera = np.flatnonzero(keep)
    if not len(camera):
        return None
    return HeadingPrior(camera=camera, axis_cam=normalize(d[camera]), gravity_cam=normalize(g[camera]),
                        down_world=down_of[camera], axis_world=axis_of[camera], group=model_id[camera],
                        sigma_rad=sigma[camera])


def group_axes(R: np.ndarray, prior: HeadingPrior, weights: np.ndarray) -> np.ndarray:
    """(M, 3) each group's world axis, the weighted circular mean of its cameras' measured axes carried to the world
    by the rotations R (M, 3, 3) of the prior's cameras."""
    axis_world = np.einsum("mji,mj->mi", R, prior.axis_cam)
    out = np.zeros_like(axis_world)
    for group in np.unique(prior.group):
        rows = np.flatnonzero(prior.group == group)
        down = prior.down_world[rows[0]]
        out[rows] = mean_axis(world_heading(axis_world[rows], down), weights[rows], down)
    return out


def heading_error_factor(R_cam_from_world: np.ndarray, prior: HeadingPrior) -> float:
    """How many times its stated standard error each measured heading lies from its group's axis (rotations of the
    prior's cameras taken from R_cam_from_world (N, 3, 3)): √(Σ (Δ_i / σ_i)² / (M − G)), each group's axis taking
    one degree of freedom. 1 when there is no redundancy."""
    dof = len(prior.camera) - len(np.unique(prior.group))
    if dof <= 0:
        return 1.0
    R = np.asarray(R_cam_from_world, np.float64)[prior.camera]
    sigma = np.asarray(prior.sigma_rad, np.float64)
    axis = group_axes(R, prior, 1.0 / sigma**2)
    delta = heading_error(np.einsum("mij,mj->mi", R, axis), prior.axis_cam, prior.gravity_cam)
    return float(np.sqrt(np.sum((delta / sigma) ** 2) / dof))


def with_heading_error(prior: HeadingPrior, factor: float) -> HeadingPrior:
    """The prior with its standard errors scaled by `factor` where that is above 1 (never narrowed)."""
    return dataclasses.replace(prior, sigma_rad=np.asarray(prior.sigma_rad, np.float64) * max(float(factor), 1.0))
