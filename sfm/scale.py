"""A metric scale for a model: from the camera height the user states, or from a known distance between two points.

Nothing in the images fixes the size of the scene; a model's unit is whatever registration chose. A statement of
the user's turns it into metres:

- camera height H (metres from the floor to the lens): each camera's height above its floor in model units,
  h_i (`heights.floor_rows`: the farthest-down cluster of the points it sees steeply below the horizon, the rule
  the triangulation's height prior uses, along the floor's own normal, `floor_down`), gives one measurement
  H / h_i of the metres per unit; the scale is their median (robust to the few cameras that took a furniture top
  for the floor; `heights.consistent_cameras` is not used: it drops the cameras of a hand-held walk whose heights
  really differ, and the median of the rest then rests on whichever cameras happen to agree). Its relative standard
  error is that of a median, 1.2533 σ / √n, with σ the robust spread (1.4826 · median absolute deviation) of
  log h_i: real height changes of a hand-held camera and the floor estimate's own noise both show in it. Where
  the triangulation's height prior held the heights to one value (`triangulation.height_prior`), σ is at least
  that prior's per-camera error (`height_prior_sigma`): the adjusted heights agree by construction (360_Flat:
  0.4% after it, 2% before the final adjustment).
- known distance D between two named points (hand points, triangulated in the model): D / |A − B|. Its relative
  standard error is σ_d / |A − B|, σ_d from the two points' triangulation covariances along A − B
  (`point_covariance`: each observation a bearing with an angular noise, the larger of the model's
  (`angular_sigma`) and the hand points' own residuals' (`residual_sigma`, pooled over the model's hand
  points): a click is noisier than SIFT).

The stated value itself is taken as exact (a 2 cm error on a 1.6 m camera height is a further 1.3 %).
Pure geometry: no file access (`commands.export.metric_scales` reads the model and the statement).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fullview.sfm import heights

MEDIAN_EFFICIENCY = 1.2533  # standard error of a median = this · σ / √n (normal samples)
MAD_TO_SIGMA = 1.4826  # σ of a normal sample = this · median absolute deviation
RAYLEIGH_MEDIAN = 1.1774  # median of a 2-D isotropic normal error's length, in units of its per-axis σ


class ScaleError(ValueError):
    """The stated scale cannot be measured on this model (no floor seen, a named point not triangulated)."""


@dataclass(frozen=True, kw_only=True)
class Scale:
    """Metres per model unit of one model, with its relative standard error and what it rests on."""

    metres_per_unit: float  # multiply model coordinates by this to get metres
    rel_std: float  # relative standard error of metres_per_unit (nan: one measurement, no spread to tell)
    method: str  # "camera_height" or "known_distance"
    stated: str  # the user's statement, as said ("camera height 1.6 m", "pt_a-pt_b 2.5 m")
    measurements: int  # cameras measuring their height (camera_height), 1 (known_distance)
    spread: float  # camera_height: relative spread of the per-camera heights (σ of log h_i); known_distance: nan

    def describe(self) -> str:
        """"1 model unit = 2.31 m ± 1.2% (camera height 1.6 m, 11 cameras)"."""
        pm = "± ?" if not np.isfinite(self.rel_std) else f"± {100 * self.rel_std:.1f}%"
        what = (f"{self.measurements} camera{'s' if self.measurements != 1 else ''}, per-camera spread "
                f"{100 * self.spread:.1f}%" if self.method == "camera_height" else "triangulated hand points")
        return f"1 model unit = {self.metres_per_unit:.4g} m {pm} ({self.stated}, {what})"

    def as_dict(self) -> dict:
        return {"unit": "metre", "metres_per_unit": self.metres_per_unit,
                "rel_std": None if not np.isfinite(self.rel_std) else self.rel_std, "method": self.method,
                "stated": self.stated, "measurements": self.measurements,
                "spread": None if not np.isfinite(self.spread) else self.spread}


# The floor's normal is the down direction the heights are measured along: a gravity measured on few images (or
# the mean camera axis of panoramas levelled to a few degrees) is off by 1-3° (rendered room, 8 views: 3.1° and
# 1.0°), and a floor point r away then moves by r·sin(error), 5-15 cm at 2-3 m: the farthest-down cluster of
# `floor_rows` picks the strip tilted away, heights 10-15% long. So the down is refined first on the floor
# itself: the points each camera sees in its nadir cone, deeper than FLOOR_DEPTH of its height (table tops and
# beds are higher), fitted by one plane normal (each camera's points about their own mean: floors at several
# levels share the normal) with Tukey weights, a few rounds.
NADIR_ELEVATION_DEG = 30.0  # a floor point lies at least this far below a camera's horizon (h·cot 30° = 1.7 h out)
FLOOR_DEPTH = 0.8  # ... and deeper than this share of the camera's first height estimate
MIN_PLANE_POINTS = 20  # fewer floor points: the down is kept as given
DOWN_ROUNDS = 4
TUKEY_C = 4.685  # Tukey's biweight constant (95% efficiency for normal residuals), in robust σ


def floor_down(centers: np.ndarray, down: np.ndarray, points: np.ndarray, track_ids: np.ndarray,
               image_ids: np.ndarray) -> np.ndarray:
    """`down` (N, 3) refined to the normal of the floor the cameras see below them (see above); rows of `down` that
    are nan stay nan, and the input is returned as it is when the floor offers too few points."""
    valid = np.isfinite(down).all(axis=1)
    if not valid.any():
        return down
    d = down[valid][0]
    slope = np.tan(np.radians(NADIR_ELEVATION_DEG))
    for _ in range(DOWN_ROUNDS):
        _, _, h = heights.floor_rows(centers, np.where(valid[:, None], d, np.nan), points, track_ids, image_ids)
        v = points[track_ids] - centers[image_ids]
        depth = v @ d
        lateral = np.linalg.norm(v - depth[:, None] * d, axis=1)
        cam_h = h[image_ids]
        keep = valid[image_ids] & np.isfinite(cam_h) & (depth > slope * lateral) & (depth > FLOOR_DEPTH * cam_h)
        if keep.sum() < MIN_PLANE_POINTS:
            break
        cams, x = image_ids[keep], points[track_ids[keep]]
        _, index = np.unique(cams, return_inverse=True)
        counts = np.bincount(index)
        mean = np.stack([np.bincount(index, x[:, a]) for a in range(3)], axis=1) / counts[:, None]
        r = x - mean[index]
        w = np.ones(len(r))
        for _ in range(3):  # Tukey-weighted normal: the smallest principal axis of the weighted scatter
            _, vecs = np.linalg.eigh((r * w[:, None]).T @ r)
            n = vecs[:, 0] * np.sign(vecs[:, 0] @ d)
            res = r @ n
            sigma = MAD_TO_SIGMA * float(np.median(np.abs(res))) + 1e-12
            u = res / (TUKEY_C * sigma)
            w = np.where(np.abs(u) < 1, (1 - u ** 2) ** 2, 0.0)
        if np.degrees(np.arccos(np.clip(n @ d, -1.0, 1.0))) > 15.0:
            break  # not the floor (a wall, a slope): keep the given down
        d = n
    out = np.full_like(down, np.nan)
    out[valid] = d
    return out


def camera_height_scale(height_m: float, centers: np.ndarray, down: np.ndarray, points: np.ndarray,
                        track_ids: np.ndarray, image_ids: np.ndarray, min_spread: float = 0.0) -> Scale:
    """The scale that puts the model's cameras `height_m` above their floor. `centers` (N, 3) and `down` (N, 3,
    unit, nan where unknown: one direction for the model, refined on its floor by `floor_down`) of its cameras;
    `min_spread`: the least per-camera relative error the uncertainty assumes (the adjustment's height prior
    pulled the heights together, so their spread after it understates their independent errors); `points` (P, 3)
    and the observations (`track_ids` → point, `image_ids` → camera) of the model. ScaleError when no camera sees
    its floor."""
    if not (np.isfinite(height_m) and height_m > 0):
        raise ScaleError(f"camera height {height_m} m: expected a positive length in metres")
    down = floor_down(centers, down, points, track_ids, image_ids)
    _, _, h = heights.floor_rows(centers, down, points, track_ids, image_ids)
    h = h[np.isfinite(h) & (h > 0)]
    if not len(h):
        raise ScaleError("no camera sees the floor below it (too few points steeply below the horizon); state a "
                         "known distance between two hand points instead (--known-distance NAME_A NAME_B METRES)")
    logs = np.log(h)
    spread = MAD_TO_SIGMA * float(np.median(np.abs(logs - np.median(logs)))) if len(h) >= 2 else float("nan")
    # the median of H / h_i, in log space (an even count: the geometric mean of the two middle values)
    scale = height_m / float(np.exp(np.median(logs)))
    rel = MEDIAN_EFFICIENCY * max(spread, min_spread) / np.sqrt(len(h)) if len(h) >= 2 else float("nan")
    return Scale(metres_per_unit=scale, rel_std=float(rel), method="camera_height",
                 stated=f"camera height {height_m:g} m", measurements=int(len(h)), spread=float(spread))


def point_covariance(point: np.ndarray, centers: np.ndarray, sigma_rad: float) -> np.ndarray:
    """(3, 3) covariance of a point triangulated from bearings at `centers` (K, 3), each with an isotropic angular
    error of `sigma_rad` per axis: the inverse of Σ_k (I − b_k b_kᵀ) / (r_k² σ²) (a ray constrains the point across
    itself, to r_k σ). A point seen from a single direction has an infinite variance along it."""
    v = np.asarray(point, np.float64) - np.asarray(centers, np.float64).reshape(-1, 3)
    r2 = np.einsum("ka,ka->k", v, v)
    b = v / np.sqrt(r2)[:, None]
    info = np.einsum("k,kab->ab", 1.0 / (r2 * sigma_rad ** 2), np.eye(3)[None] - b[:, :, None] * b[:, None, :])
    try:
        return np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return np.full((3, 3), np.inf)


def residual_sigma(tracks: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> float:
    """Per-axis angular noise of the observations of some points, pooled from their own residual angles: each
    (point, centers (K, 3), unit world bearings (K, 3)) contributes Σ angle² over 2K − 3 degrees of freedom (2K
    angles measured, 3 coordinates fitted); pooled, since one point of two views has one. nan without any."""
    total, dof = 0.0, 0
    for point, centers, bearings in tracks:
        v = np.asarray(point, np.float64) - np.asarray(centers, np.float64).reshape(-1, 3)
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        cos = np.clip(np.einsum("ka,ka->k", v, np.asarray(bearings, np.float64).reshape(-1, 3)), -1.0, 1.0)
        if len(v) >= 2:
            total, dof = total + float(np.sum(np.arccos(cos) ** 2)), dof + 2 * len(v) - 3
    return float(np.sqrt(total / dof)) if dof else float("nan")


def known_distance_scale(distance_m: float, a: np.ndarray, b: np.ndarray, cov_a: np.ndarray, cov_b: np.ndarray,
                         stated: str) -> Scale:
    """The scale that puts points `a` and `b` (model coordinates, with covariances) `distance_m` apart."""
    if not (np.isfinite(distance_m) and distance_m > 0):
        raise ScaleError(f"known distance {distance_m} m: expected a positive length in metres")
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    length = float(np.linalg.norm(d))
    if not length > 0:
        raise ScaleError(f"{stated}: the two points coincide in the model")
    u = d / length
    var = float(u @ (np.asarray(cov_a) + np.asarray(cov_b)) @ u)
    rel = np.sqrt(var) / length if np.isfinite(var) and var >= 0 else float("inf")
    return Scale(metres_per_unit=distance_m / length, rel_std=float(rel), method="known_distance", stated=stated,
                 measurements=1, spread=float("nan"))


def angular_sigma(obs_error_rad: np.ndarray) -> float:
    """Per-axis angular noise of the observations from their error lengths: median / RAYLEIGH_MEDIAN."""
    err = np.asarray(obs_error_rad, np.float64)
    return float(np.median(err)) / RAYLEIGH_MEDIAN if len(err) else float("nan")
