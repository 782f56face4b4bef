"""Loop candidates (sfm/pairs.py: plan_pairs, loop_rounds; stages/matches.py): a walk's retrieval pairs far apart in
capture order are matched in rounds, each image in its similarity order until `loop_patience` of its candidates in
a row find too few matches; every other pair is matched at once, and the artifact is deterministic."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fullview.io.config import load_config
from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace
from fullview.sfm import pairs as P
from fullview.sfm.matching import basis_from_moments, match_descriptors, project_descriptors, second_moment
from fullview.sfm.options import MatchesOptions
from fullview.stages.runner import Pipeline
from fullview.synth import write_synthetic_dataset

from tests.test_pairs import _walk_descriptors


def _prefixes(candidates, patience, found) -> set:
    """What the rounds must match, stated without rounds: each image's candidates up to and including the
    `patience`-th miss in a row (a pair's outcome is its own, whoever proposes it)."""
    out = set()
    for mine in candidates:
        misses = 0
        for pair in mine:
            out.add(pair)
            misses = 0 if found[pair] else misses + 1
            if misses >= patience:
                break
    return out


class _Matcher:
    def __init__(self, found):
        self.found, self.calls = found, []

    def __call__(self, pairs):
        assert pairs == sorted(pairs) and not set(pairs) & {p for c in self.calls for p in c}  # each pair once
        self.calls.append(pairs)
        return {p: self.found[p] for p in pairs}


def test_an_image_stops_after_patience_misses_in_a_row_and_a_hit_keeps_it_looking():
    candidates = [[(0, 5), (0, 6), (0, 7), (0, 8)],  # miss, miss: stops before (0, 7)
                  [(1, 5), (1, 6), (1, 7), (1, 8)],  # miss, hit, miss, miss: all four
                  [(2, 8), (0, 6), (2, 9)],  # (0, 6) was image 0's miss: counted, not matched again
                  []]
    found = {(0, 5): False, (0, 6): False, (0, 7): True, (0, 8): True, (1, 5): False, (1, 6): True,
             (1, 7): False, (1, 8): False, (2, 8): False, (2, 9): True}
    matcher = _Matcher(found)
    matched, rounds = P.loop_rounds(candidates, 2, matcher)
    assert set(matched) == {(0, 5), (0, 6), (1, 5), (1, 6), (1, 7), (1, 8), (2, 8)}
    assert matched == sorted(matched) and rounds == len(matcher.calls) == 2
    assert set(P.loop_rounds(candidates, 3, _Matcher(found))[0]) == set(found)  # 3 misses in a row never happen
    every, one_round = P.loop_rounds(candidates, 0, _Matcher(found))
    assert every == sorted(found) and one_round == 1


@pytest.mark.parametrize("seed", range(20))
def test_rounds_match_exactly_the_prefixes_up_to_the_patience_th_miss(seed):
    rng = np.random.default_rng(seed)
    n, patience = 30, int(rng.integers(1, 4))
    candidates = [[(min(i, int(j)), max(i, int(j))) for j in rng.permutation(n)[:8] if abs(i - int(j)) > 2]
                  for i in range(n)]
    every = {p for c in candidates for p in c}
    found = {p: bool(rng.random() < 0.3) for p in sorted(every)}
    matched, _ = P.loop_rounds(candidates, patience, _Matcher(found))
    assert set(matched) == _prefixes(candidates, patience, found)
    # the first proposals matched beforehand (as the stage does, with the other pairs): the same pairs, each once
    first = P.first_loop_proposals(candidates, patience)
    assert set(first) <= set(matched)
    later = _Matcher(found)
    again, _ = P.loop_rounds(candidates, patience, later, found={p: found[p] for p in first})
    assert again == matched and not set(first) & {p for c in later.calls for p in c}
    # all hits (a room): every candidate is matched
    assert P.loop_rounds(candidates, patience, _Matcher(dict.fromkeys(every, True)))[0] == sorted(every)


def test_the_plan_splits_the_same_pairs_into_direct_ones_and_ranked_loop_candidates():
    places = list(range(12)) + list(range(11, -1, -1))  # a walk that comes back along its path
    desc = _walk_descriptors(places)
    options = MatchesOptions(pairs="auto", auto_exhaustive_below=10, window=2, retrieval_neighbours=4,
                             vocabulary_size=16, vocabulary_sample=200)
    plan = P.plan_pairs(desc, options)
    off = P.plan_pairs(desc, replace(options, loop_patience=0))
    assert plan.all_pairs == off.pairs == P.select_pairs(desc, options)[0]  # the same pairs, split differently
    assert not any(off.loop_candidates) and any(plan.loop_candidates)
    assert all(j - i <= 4 for i, j in plan.pairs) and not set(plan.pairs) & {p for c in plan.loop_candidates for p in c}
    ranking = P.similarity_ranking(P.global_descriptors(desc, 16, 0, 200))
    for i, mine in enumerate(plan.loop_candidates):  # each image's far retrieval pairs, most similar first
        partners = [j for j in ranking[i, :4] if abs(i - j) > 4]
        assert mine == [(min(i, j), max(i, j)) for j in partners]
    assert plan.summary["loop_candidates"] == len(plan.all_pairs) - len(plan.pairs)
    exhaustive = P.plan_pairs(desc[:9], options)
    assert exhaustive.pairs == P.exhaustive(9) and not any(exhaustive.loop_candidates)


# ------------------------------------------------------------------------------------------------ the stage
WALK_SETTINGS = ["features.working_width=512", "matches.auto_exhaustive_below=2", "matches.window=1",
                 "matches.retrieval_neighbours=5", "matches.vocabulary_sample=300", "matches.loop_patience=1",
                 "matches.loop_min_share=0.5"]


@pytest.fixture(scope="module")
def walk(tmp_path_factory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("walk") / "walk", views=14, width=512, seed=0,
                                   kind="corridor", hand_points="none")


def _matches_stage(dataset: Path, ws_root: Path, extra=()) -> tuple[Workspace, dict]:
    config = load_config(None, WALK_SETTINGS + list(extra))
    ds = Dataset(dataset)
    ws = Workspace(ws_root, ds.name)
    pipeline = Pipeline(ds, ws, config)
    pipeline.run(until="matches")
    return ws, ws.read_manifest("matches")


def test_a_loop_candidate_is_matched_iff_no_patience_misses_in_a_row_come_before_it(walk, tmp_path):
    ws, manifest = _matches_stage(walk, tmp_path / "ws")
    options = load_config(None, WALK_SETTINGS)["matches"]
    names = Dataset(walk).image_names
    desc = [ws.load_descriptors(n) for n in names]
    plan = P.plan_pairs(desc, options)
    assert any(plan.loop_candidates)
    # every candidate's own matches (as the stage finds them), and its images' window medians
    basis = basis_from_moments([second_moment(d) for d in desc], options.descriptor_dims)
    proj = [project_descriptors(d, basis) for d in desc]
    count = lambda p: len(match_descriptors(proj[p[0]], proj[p[1]], options, full=(desc[p[0]], desc[p[1]])))  # noqa
    window = {p: count(p) for p in plan.pairs if p[1] - p[0] <= options.window}
    median = [np.median([c for p, c in window.items() if k in p]) for k in range(len(names))]
    found = {p: count(p) >= options.loop_min_share * min(median[p[0]], median[p[1]])
             for c in plan.loop_candidates for p in c}
    expected = set(plan.pairs) | _prefixes(plan.loop_candidates, options.loop_patience, found)
    stored = ws.load_matches()
    assert set(stored.pairs) == expected and stored.pairs == sorted(expected)
    assert len(expected) < len(plan.all_pairs)  # some candidates were not matched (the old code matched them all)
    sources = manifest["summary"]["pair_sources"]
    assert sources["loop_matched"] == len(expected) - len(plan.pairs)
    assert sources["loop_candidates"] == len(plan.all_pairs) - len(plan.pairs)


def test_the_matches_artifact_is_byte_identical_on_a_rerun_and_complete_without_patience(walk, tmp_path):
    ws, _ = _matches_stage(walk, tmp_path / "a")
    first = (ws.folder("matches") / "matches.npz").read_bytes()
    Pipeline(Dataset(walk), ws, load_config(None, WALK_SETTINGS)).run(start="matches", until="matches")
    assert (ws.folder("matches") / "matches.npz").read_bytes() == first
    every, _ = _matches_stage(walk, tmp_path / "b", ["matches.loop_patience=0"])
    desc = [ws.load_descriptors(n) for n in Dataset(walk).image_names]
    assert every.load_matches().pairs == P.select_pairs(desc, load_config(None, WALK_SETTINGS)["matches"])[0]


def test_a_walk_that_comes_back_still_closes_its_loops():
    """The walk of 12 places that returns along them (as in test_pairs): its revisits find as many matches as the
    window's pairs, so the images keep looking, and every revisited place is still closed."""
    places = list(range(12)) + list(range(11, -1, -1))
    desc = _walk_descriptors(places)
    options = MatchesOptions(pairs="sequential", window=2, retrieval_neighbours=4, vocabulary_size=16,
                             vocabulary_sample=200, descriptor_dims=0)
    plan = P.plan_pairs(desc, options)
    count = {p: len(match_descriptors(desc[p[0]], desc[p[1]], options)) for p in plan.all_pairs}
    median = [np.median([c for p, c in count.items() if k in p and p[1] - p[0] <= 2]) for k in range(len(desc))]
    enough = lambda p: count[p] >= options.loop_min_share * min(median[p[0]], median[p[1]])  # noqa: E731
    matched, _ = P.loop_rounds(plan.loop_candidates, options.loop_patience, lambda ps: {p: enough(p) for p in ps})
    every = {p for c in plan.loop_candidates for p in c}
    closed = lambda pairs: {places[i] for i, j in pairs if places[i] == places[j]}  # noqa: E731
    assert len(closed(every)) >= 6 and closed(matched) == closed(every)
    assert all(enough(p) for p in every) and matched == sorted(every)  # revisits all: nobody stops looking
