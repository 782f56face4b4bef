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
    assert verdict_line({"verdicts": counts}) == "registration: 2 verified, 1 approximate, 0 in own models, 1 in no model"
    links = weakest_links(guessed, {})
    assert links[0]["link"] == "c – b" and "hand points on c / b" in links[0]["confirm"]
