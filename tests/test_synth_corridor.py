"""The corridor walk scene (synth/corridor.py) and a registration of a short walk with `auto` pairs."""

import numpy as np
import pytest

from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace
from fullview.sfm.pairs import exhaustive
from fullview.synth import write_synthetic_dataset
from fullview.synth.corridor import VIEWS_PER_BAY, layout_corridor
from fullview.synth.render import cast_rays


def _line_of_sight(layout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    c = layout.centers
    i, j = np.triu_indices(len(c), 1)
    d = c[j] - c[i]
    dist = np.linalg.norm(d, axis=1)
    t, _ = cast_rays(c[i], d / dist[:, None], layout.boxes)
    return i, j, t >= dist - 1e-3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_200_view_walk_is_in_order_inside_and_its_view_graph_is_sparse(seed):
    layout = layout_corridor(np.random.default_rng(seed), 200)
    c, boxes = layout.centers, layout.boxes
    assert np.all((c > boxes[0, 0] + 0.3) & (c < boxes[0, 1] - 0.3))  # inside the corridor, off its walls
    inside_slab = np.all((c[:, None] > boxes[None, 1:, 0] - 0.25) & (c[:, None] < boxes[None, 1:, 1] + 0.25), axis=2)
    assert not inside_slab.any()  # >= 0.25 m from every partition
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert np.all(np.diff(c[:, 0]) > 0) and steps.min() > 0.7 and steps.max() < 1.8
    assert np.allclose(layout.R_world_from_cam[:, 1], [0, 1, 0])  # level cameras (yaw only)
    assert np.array_equal(layout.bay_of_view, np.arange(200) // VIEWS_PER_BAY)
    i, j, seen = _line_of_sight(layout)
    assert seen[j - i == 1].all()  # every step of the walk is in sight
    assert (j - i)[seen].max() <= 6 and seen.sum() < 0.05 * len(seen)  # no view down the corridor: sparse graph
    again = layout_corridor(np.random.default_rng(seed), 200)
    assert np.array_equal(again.centers, c) and np.array_equal(again.boxes, boxes)


def test_a_short_walk_registers_with_auto_pairs(tmp_path, make_pipeline):
    """9 views (3 bays) matched by window + retrieval (auto forced below its threshold): every image registered,
    exact to a fraction of a degree, with fewer pairs than exhaustive matching."""
    path = write_synthetic_dataset(tmp_path / "walk", views=9, width=512, seed=0, kind="corridor", hand_points="none")
    # the cameras are level by construction; at 512 px the vanishing-point gravity of these busy textures is too
    # rough for the upright solver (exhaustive pairs then split the walk too), so gravity is the image's down axis
    pipeline = make_pipeline(path, ["matches.auto_exhaustive_below=2", "matches.window=2",
                                    "matches.retrieval_neighbours=2", "filter.upright=level"])
    pipeline.run(until="registration")
    ws = Workspace(tmp_path / "ws", Dataset(path).name)
    pairs = ws.load_matches().pairs
    assert set(pairs) >= {(k, k + 1) for k in range(8)} and len(pairs) < len(exhaustive(9))
    summary = ws.read_manifest("registration")["summary"]
    assert summary["registered"] == 9
