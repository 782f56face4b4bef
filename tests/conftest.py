"""Shared fixtures: a tiny synthetic dataset (rendered once per session) and a pipeline factory."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from fullview.io.config import load_config
from fullview.io.dataset import Dataset
from fullview import synth
from fullview.synth import write_synthetic_dataset
from fullview.io.workspace import Workspace
from fullview.stages.runner import Pipeline

SHARED = Path(__file__).resolve().parents[2] / "shared" / "datasets"

# Settings for 512x256 panoramas: one pixel is 0.7°, so angular bounds scale up accordingly.
TINY_OVERRIDES = [
    "features.working_width=512",
    "filter.threshold_deg=1.0",
    "filter.min_inliers=15",
    "registration.min_inliers=15",
    "triangulation.max_reprojection_error_deg=1.5",
    "triangulation.ba_max_iterations=30",
]


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """3 views at 512x256 with ground truth and hand points (read-only: copy it before modifying)."""
    return write_synthetic_dataset(tmp_path_factory.mktemp("data") / "tiny", views=3, width=512, seed=1)


@pytest.fixture
def make_pipeline(tmp_path):
    """Build a Pipeline over a dataset with the tiny overrides plus extra ones, in a per-test workspace."""
    def make(dataset: Path, extra: list[str] = (), workspace: Path | None = None) -> Pipeline:
        ds = Dataset(dataset)
        config = load_config(None, TINY_OVERRIDES + list(extra))
        return Pipeline(ds, Workspace(workspace or tmp_path / "ws", ds.name), config)
    return make


@pytest.fixture
def dataset_copy(tiny_dataset, tmp_path) -> Path:
    """A private, modifiable copy of the tiny dataset."""
    dst = tmp_path / "tiny"
    shutil.copytree(tiny_dataset, dst)
    return dst


@pytest.fixture(scope="session")
def tiny_set_args() -> list[str]:
    """TINY_OVERRIDES as CLI arguments."""
    return [a for o in TINY_OVERRIDES for a in ("--set", o)]


@pytest.fixture(scope="session")
def small_room() -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Four 256-px panoramas of the synthetic room (seed 2), rendered once: their exact range maps (float64),
    R_cam_from_world and t_cam_from_world. Modules copy the maps before changing them."""
    scene = synth.render_scene(views=4, width=256, seed=2, supersample=1)
    R = np.stack([v.R_world_from_cam.T for v in scene.views])
    t = -np.einsum("nab,nb->na", R, np.stack([v.center for v in scene.views]))
    return [v.depth.astype(np.float64) for v in scene.views], R, t
