"""Traits of a real hand-made capture that the clean synthetic renders lack (all off by default).

A real tour differs from a clean render in ways that matter to matching and registration, not to the scene:

- ``tilt_deg``: the camera's zenith correction is not exact; each panorama is turned about a random horizontal
  axis by an angle uniform in [0, tilt_deg] (the ground truth holds the tilted pose). The upright prior takes
  gravity from each image's vertical lines, so a tilted image tests that estimate, not an assumed level.
- ``exposure_stops``: auto exposure differs from image to image (a bright room, a dark hall); each image's
  intensities are scaled by 2 ** u, u uniform in [-exposure_stops, exposure_stops], and clipped to 0-255.
- ``noise``: sensor noise, Gaussian with this standard deviation in 8-bit levels, added after the exposure (it
  gives plain walls features of their own, which match nothing).
- ``shuffle``: the image names do not follow the walk (files sorted by another key, or a tour re-ordered by hand);
  view k of the walk is written as ``pano_<perm[k]>``.

Every trait draws from its own generator seeded by the scene seed, so switching one on changes nothing else and the
default (all off) gives the renders bit for bit as before.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# child keys of the scene seed, one generator per trait (fixed, so each trait's draws do not depend on the others)
_TILT_KEY, _EXPOSURE_KEY, _NOISE_KEY, _ORDER_KEY = 101, 102, 103, 104


@dataclass(frozen=True, kw_only=True)
class CaptureTraits:
    tilt_deg: float = 0.0  # each panorama tilted by up to this angle (deg) about a random horizontal axis
    exposure_stops: float = 0.0  # each image's gain 2 ** u, u uniform in +- this (stops)
    noise: float = 0.0  # Gaussian sensor noise, standard deviation in 8-bit levels
    shuffle: bool = False  # image names in a random order, not the walk's

    def __post_init__(self) -> None:
        for key, hi in (("tilt_deg", 10.0), ("exposure_stops", 3.0), ("noise", 50.0)):
            value = getattr(self, key)
            if not (isinstance(value, (int, float)) and 0.0 <= value <= hi):
                raise ValueError(f"{key} must be a number in [0, {hi:g}], got {value!r}")
        if not isinstance(self.shuffle, bool):
            raise ValueError(f"shuffle must be bool, got {self.shuffle!r}")

    @property
    def any(self) -> bool:
        return bool(self.tilt_deg or self.exposure_stops or self.noise or self.shuffle)


def _rng(seed: int, key: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), key]))


def tilted(rots: np.ndarray, max_deg: float, seed: int) -> np.ndarray:
    """(V, 3, 3) ``R_world_from_cam`` turned about a random horizontal world axis by up to ``max_deg`` each (world y
    is the vertical); the same input when ``max_deg`` is 0."""
    rots = np.asarray(rots, dtype=np.float64)
    if max_deg <= 0:
        return rots
    rng = _rng(seed, _TILT_KEY)
    azimuth = rng.uniform(0.0, 2 * np.pi, len(rots))
    angle = np.deg2rad(rng.uniform(0.0, max_deg, len(rots)))
    axes = np.column_stack([np.cos(azimuth), np.zeros(len(rots)), np.sin(azimuth)])
    return np.einsum("vij,vjk->vik", _axis_angle(axes, angle), rots)


def _axis_angle(axes: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(V, 3, 3) rotations about unit ``axes`` (V, 3) by ``angle`` (V,) (Rodrigues)."""
    k = np.zeros((len(axes), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
    k -= k.transpose(0, 2, 1)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def gains(views: int, stops: float, seed: int) -> np.ndarray:
    """(V,) exposure gain of each image (all 1 when ``stops`` is 0)."""
    if stops <= 0:
        return np.ones(views)
    return 2.0 ** _rng(seed, _EXPOSURE_KEY).uniform(-stops, stops, views)


def exposed(images: list[np.ndarray], gain: np.ndarray, noise: float, seed: int) -> list[np.ndarray]:
    """The uint8 images with their gains and sensor noise applied (the same arrays when there is neither)."""
    if np.all(gain == 1.0) and noise <= 0:
        return images
    rng = _rng(seed, _NOISE_KEY)
    out = []
    for image, g in zip(images, gain):
        value = image.astype(np.float32) * np.float32(g)
        if noise > 0:
            value += rng.normal(0.0, noise, image.shape).astype(np.float32)
        out.append(np.clip(np.rint(value), 0, 255).astype(np.uint8))
    return out


def name_order(views: int, shuffle: bool, seed: int) -> np.ndarray:
    """(V,) the file number of walk view k: k itself, or a seeded permutation with ``shuffle``."""
    if not shuffle:
        return np.arange(views)
    return _rng(seed, _ORDER_KEY).permutation(views)
