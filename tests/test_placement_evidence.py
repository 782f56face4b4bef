"""Evidence for every placement (docs/trust.md): a home whose doorway nothing measures gives two models or an
approximate part, never one model with a guessed placement; the same home with the doorway measured (8 hand points
across it) stays one model, every camera verified; the verdict rules themselves."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fullview.cli import main
from fullview.io.workspace import Workspace
from fullview.sfm.registration.evidence import placements, verdict_counts, verdict_line, weakest_links
from fullview.synth.dataset import write_synthetic_dataset


@pytest.fixture(scope="module")
def closed_door_home(tmp_path_factory):
    """12 level panoramas in 4 rooms, the door between rooms 1 and 2 closed (a window in it): nothing but the 8 hand
    points of hand_points.yaml (tracks seen from >= 2 panoramas on each side) measures the rooms across it."""
    return write_synthetic_dataset(tmp_path_factory.mktemp("pe") / "home", views=12, width=1024, seed=0,
                                   kind="home", rooms=4, closed_door=1, hand_points="crossing")


def _registration(dataset, ws, capsys, *settings) -> dict:
    args = [a for s in settings for a in ("--set", s)]
    assert main(["run", str(dataset), "-w", str(ws), "--until", "registration", *args]) == 0
    capsys.readouterr()
    return json.loads((ws / dataset.name / "registration" / "registration.json").read_text())


def _no_guess_is_fact(report: dict) -> None:
    """Every camera not marked approximate was placed without a guessed scale, by joins all confirmed."""
    for name, p in report["placements"].items():
        if p["verdict"] != "approximate":
            assert p["scale"] == "measured", name
            assert all(j["confirmed"] for j in p["joins"]), (name, p["joins"])


def test_a_doorway_nothing_measures_splits_the_home_and_hand_points_across_it_join_it(closed_door_home, tmp_path,
                                                                                         capsys):
    ws = tmp_path / "ws"
    report = _registration(closed_door_home, ws, capsys, "filter.use_hand_points=false")
    counts = report["verdicts"]
    assert counts["approximate"] == 0 and counts["verified"] + counts["own_model"] == 12
    assert len(report["models"]) >= 2 and counts["own_model"] >= 1  # never one model through the closed door
    _no_guess_is_fact(report)
    model_of = report["model_of_image"]
    assert {p["verdict"] for n, p in report["placements"].items() if model_of[n] > 0} == {"own_model"}
    assert any("hand points" in w["confirm"] for w in report["weakest_links"])  # what would join them
    assert main(["status", str(closed_door_home), "-w", str(ws), "--set", "filter.use_hand_points=false"]) == 0
    line = f"registration: {counts['verified']} verified, 0 approximate, {counts['own_model']} in own models"
    assert line in capsys.readouterr().out
    assert Workspace(ws, closed_door_home.name).verified_mask().all()

    report = _registration(closed_door_home, ws, capsys, "filter.use_hand_points=true")
    assert report["models"] == [12] and report["verdicts"]["verified"] == 12
    _no_guess_is_fact(report)


def test_asked_to_keep_unconfirmed_joins_they_are_approximate_and_out_of_the_verified_mask(closed_door_home, tmp_path,
                                                                                           capsys):
    ws = tmp_path / "ws"
    report = _registration(closed_door_home, ws, capsys, "filter.use_hand_points=false",
                           "registration.unconfirmed_joins=approximate")
    _no_guess_is_fact(report)
    approximate = sorted(n for n, p in report["placements"].items() if p["verdict"] == "approximate")
    mask = Workspace(ws, closed_door_home.name).verified_mask()
    names = sorted(report["model_of_image"])
    assert [n for n, ok in zip(names, mask) if not ok] == approximate
    if len(report["models"]) == 1:  # attached through the door: as approximate cameras, never as fact
        assert approximate and report["verdicts"]["verified"] + len(approximate) == 12


def _records(join_confirmed: bool, model_of_2: int = 0):
    names = ["a", "b", "c"]
    pairs = np.array([[0, 1], [1, 2]])
    return placements(names=names, model_id=np.array([0, 0, model_of_2]), own={2: {"how": "resection",
                                                                                  "inliers_2d3d": 40}},
                      join_records=[{"kind": "k", "images": [2], "confirmed": join_confirmed,
                                     "scale": "measured" if join_confirmed else "guessed",
                                     "evidence": {"pairs": [[2, 1, 9]]}}],
                      approximate=np.array([False, False, not join_confirmed]), pairs=pairs,
                      weights=np.array([100.0, 0.0]), pair_ok=np.array([True, False]))


def test_a_camera_carried_by_an_unconfirmed_join_is_approximate_and_a_confirmed_one_verified():
    confirmed, guessed, separate = _records(True), _records(False), _records(True, model_of_2=1)
    assert [confirmed[n]["verdict"] for n in "abc"] == ["verified"] * 3
    assert guessed["c"]["verdict"] == "approximate" and guessed["c"]["scale"] == "guessed"
    assert guessed["a"]["verdict"] == "verified" and guessed["a"]["evidence"]["verified_pairs"] == [["b", 100]]
    assert separate["c"]["verdict"] == "own_model"
    assert guessed["c"]["how"] == "resection" and guessed["c"]["evidence"]["inliers_2d3d"] == 40
    counts = verdict_counts(guessed, 4)
    assert counts == {"verified": 2, "approximate": 1, "own_model": 0, "unregistered": 1}
    line = "registration: 2 verified, 1 approximate, 0 in own models, 1 in no model"
    assert verdict_line({"verdicts": counts}) == line
    links = weakest_links(guessed, {})
    assert links[0]["link"] == "c – b" and "hand points on c / b" in links[0]["confirm"]


def _two_rooms_and_a_doorway_pair(floor_at_door: bool):
    """Rooms A (cameras 0-2) and B (3-5), a tripod tour 1.5 above the floor (world y down, floor at y = 1.5); each
    room's cameras see its own walls and floor, and only doorway pair 2-3 sees the doorway's points (two-view
    tracks: they fix the pair's direction, not its length). With `floor_at_door`, those are floor points below both
    of its cameras; else all of them lie above the cameras (the door frame)."""
    from scipy.spatial.transform import Rotation

    from fullview.sfm.camera import normalize
    from fullview.sfm.registration.models import PairLinks
    from fullview.sfm.tracks import build_tracks
    rng = np.random.default_rng(3)
    centres = np.array([[-5.0, 0, -1.0], [-3.5, 0, 1.5], [-1.2, 0, 0.2], [1.4, 0, -0.3], [3.5, 0, 1.2],
                        [5.5, 0, -1.4]])
    R = Rotation.from_euler("y", rng.uniform(-np.pi, np.pi, (6, 1))).as_matrix()
    n = 1500
    walls = np.column_stack([rng.uniform(-8, 8, n), rng.uniform(-1.5, 1.4, n), rng.choice([-4.0, 4.0], n)])
    floor = np.column_stack([rng.uniform(-8, 8, n), np.full(n, 1.5), rng.uniform(-3.5, 3.5, n)])
    door = np.column_stack([rng.uniform(-0.5, 0.5, 60), np.full(60, 1.5) if floor_at_door else
                            rng.uniform(-1.5, -0.2, 60), rng.uniform(-0.8, 0.8, 60)])  # else: the frame, the lintel
    X = np.concatenate([walls, floor, door])
    room = np.r_[np.sign(walls[:, 0]), np.sign(floor[:, 0]), np.zeros(60)]
    keep = (np.abs(X[:, 0]) > 0.6) | (room == 0)
    X, room = X[keep], room[keep]
    side = np.array([-1, -1, -1, 1, 1, 1])
    seen = [(room == side[k]) | ((room == 0) & (k in (2, 3))) for k in range(6)]
    feature_of = [np.flatnonzero(s) for s in seen]
    bearings = [normalize((X[f] - c) @ r.T) for f, c, r in zip(feature_of, centres, R)]
    matches = {}
    for i in range(6):
        for j in range(i + 1, 6):
            if side[i] == side[j] or (i, j) == (2, 3):
                _, a, b = np.intersect1d(feature_of[i], feature_of[j], return_indices=True)
                matches[(i, j)] = np.column_stack([a, b])
    pairs = np.array(list(matches))
    t = -np.einsum("nab,nb->na", R, centres)
    R_rel = R[pairs[:, 1]] @ np.swapaxes(R[pairs[:, 0]], 1, 2)
    t_rel = normalize(t[pairs[:, 1]] - np.einsum("pab,pb->pa", R_rel, t[pairs[:, 0]]))
    links = PairLinks(pairs=pairs, R_j_from_i=R_rel, t_j_from_i=t_rel,
                      weights=np.array([len(matches[tuple(p)]) for p in pairs], float))
    tracks, _ = build_tracks(matches, [len(b) for b in bearings])
    gravity = R @ np.array([0.0, 1.0, 0.0])  # each camera's down, in its frame
    return centres, links, tracks, bearings, gravity


def _similarity_residual(estimated: np.ndarray, truth: np.ndarray) -> float:
    from fullview.sfm.metrics import umeyama
    return float(np.abs(umeyama(estimated, truth).apply(estimated) - truth).max())


@pytest.mark.parametrize("floor_at_door", [True, False])
def test_one_doorway_pair_joins_two_rooms_as_fact_only_where_the_camera_height_measures_it(floor_at_door):
    """A doorway pair fixes the rotation and direction between the rooms, not its length nor room B's scale. The
    camera height does (a tripod keeps it: each room's floor below its cameras, and the doorway's floor below the
    pair's two cameras): then the rooms are one model at the true similarity, the join confirmed by it. Without the
    floor at the door nothing measures the pair's length: two models, never a guessed placement."""
    from fullview.sfm.options import RegistrationOptions
    from fullview.sfm.registration.models import build_models
    centres, links, tracks, bearings, gravity = _two_rooms_and_a_doorway_pair(floor_at_door)
    models = build_models(links=links, tracks=tracks, bearings=bearings, options=RegistrationOptions(),
                          gravity=gravity)
    assert not models.approximate.any() and all(j["confirmed"] for j in models.join_records)
    if floor_at_door:
        assert models.sizes() == [6]
        assert [j["kind"] for j in models.join_records] == ["verified pairs, scale by camera height"]
        assert _similarity_residual(models.centers, centres) < 1e-3
    else:
        assert models.sizes() == [3, 3] and not models.join_records
        for m in (0, 1):
            k = np.flatnonzero(models.model_id == m)
            assert _similarity_residual(models.centers[k], centres[k]) < 1e-6
    without_gravity = build_models(links=links, tracks=tracks, bearings=bearings, options=RegistrationOptions())
    assert without_gravity.sizes() == [3, 3]
