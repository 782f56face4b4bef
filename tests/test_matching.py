from dataclasses import replace

import numpy as np
import pytest

from fullview.io.dataset import Dataset

from fullview.sfm.matching import descriptor_basis, match_descriptors, project_descriptors
from fullview.sfm.pairs import pair_list
from fullview.sfm.options import MatchesOptions


def _descriptors(rng, n, d=128):
    x = np.abs(rng.normal(size=(n, d))).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_matches_permuted_noisy_copies_and_rejects_ambiguous():
    rng = np.random.default_rng(0)
    a = _descriptors(rng, 3000)
    perm = rng.permutation(3000)
    b = a[perm] + rng.normal(size=a.shape).astype(np.float32) * 0.01
    m = match_descriptors(a, b, MatchesOptions(), block_rows=512)
    assert len(m) > 2900
    assert np.array_equal(perm[m[:, 1]], m[:, 0])
    # duplicate a descriptor in b: its query becomes ambiguous and fails the ratio test
    b2 = np.vstack([b, b[:1]])
    m2 = match_descriptors(a, b2, MatchesOptions())
    assert perm[0] not in m2[:, 0]


def test_mutual_check_removes_many_to_one():
    rng = np.random.default_rng(1)
    b = _descriptors(rng, 50)
    a = np.vstack([b[:1] + 0.001, b[:1] + 0.002]).astype(np.float32)  # two queries, same nearest neighbour
    assert len(match_descriptors(a, b, MatchesOptions(mutual=True))) == 1
    assert len(match_descriptors(a, b, MatchesOptions(mutual=False))) == 2


def test_empty_inputs():
    assert match_descriptors(np.zeros((0, 128), np.float32), np.zeros((5, 128), np.float32), MatchesOptions()).shape == (0, 2)


def test_unknown_pair_mode():
    with pytest.raises(ValueError, match="unknown pair mode 'random'"):
        pair_list(4, "random")


def test_guided_matching_finds_the_match_the_epipolar_circle_allows():
    """Feature 0 of i has an almost identical twin among j's features far from its epipolar circle: unguided, the
    ratio test drops it; guided, only the candidate on the circle competes and it matches."""
    from fullview.sfm.matching import epipolar_candidates
    rng = np.random.default_rng(0)
    d = rng.random((3, 128)).astype(np.float32)
    desc_i = d[:1]
    desc_j = np.stack([d[0] + 0.01, d[0] + 0.012, d[2]]).astype(np.float32)
    b_i = np.array([[0.0, 0.0, 1.0]])
    t = np.array([1.0, 0.0, 0.0])  # pure translation along x: F = [t]x, circles through the x axis
    F = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    b_j = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.6, 0.0, 0.8]])  # j1 lies off the circle of b_i
    opts = MatchesOptions(ratio=0.8, mutual=False)
    assert len(match_descriptors(np.vstack([desc_i, desc_i]), desc_j, opts)) == 0  # twins: ambiguous
    allowed = epipolar_candidates(np.vstack([b_i, b_i]), b_j, F, np.radians(1.0))
    m = match_descriptors(np.vstack([desc_i, desc_i]), desc_j, opts, allowed=allowed)
    assert m.tolist() == [[0, 0], [1, 0]]


def test_guided_filter_adds_inliers_and_keeps_poses(tiny_dataset, make_pipeline, tmp_path):
    base = make_pipeline(tiny_dataset, workspace=tmp_path / "a")
    base.run(until="epipoles")
    guided = make_pipeline(tiny_dataset, ["filter.guided_matching=true"], workspace=tmp_path / "b")
    guided.run(until="epipoles")
    a, b = base.ws.load_inliers(), guided.ws.load_inliers()
    assert all(len(mb) >= len(ma) for ma, mb in zip(a.matches, b.matches))
    assert guided.ws.read_manifest("filter")["summary"]["guided_matches_added"] > 0
    from fullview.sfm.rotations import rotation_angle_deg
    ea, eb = base.ws.load_epipoles(), guided.ws.load_epipoles()
    assert rotation_angle_deg(ea["R_j_from_i"], eb["R_j_from_i"]).max() < 0.1


@pytest.mark.parametrize("num_images,mode,block", [(7, "exhaustive", 3), (40, "exhaustive", 16), (9, "sequential", 2)])
def test_pair_blocks_cover_every_pair_once_with_few_images(num_images, mode, block):
    from fullview.sfm.matching import pair_blocks
    pairs = pair_list(num_images, mode, window=3)
    blocks = pair_blocks(pairs, block)
    assert sorted(k for b in blocks for k in b) == list(range(len(pairs)))
    assert all(len({i for k in b for i in pairs[k]}) <= 2 * block for b in blocks)


@pytest.mark.parametrize("b_unit", [True, False])
def test_similarity_search_finds_exactly_the_distance_search_matches(b_unit):
    """RootSIFT rows take the similarity path (one pass besides the product); forcing the distance path with an
    all-allowed mask must give the same matches: exact search, not an approximation (recall 1)."""
    rng = np.random.default_rng(3)
    a = _descriptors(rng, 1500)
    b = np.vstack([a[rng.permutation(1500)[:1000]] + rng.normal(size=(1000, 128)).astype(np.float32) * 0.03,
                   _descriptors(rng, 800)])
    if not b_unit:
        b *= rng.uniform(0.8, 1.2, (len(b), 1)).astype(np.float32)
    everything = lambda start, stop: np.ones((stop - start, len(b)), bool)  # noqa: E731
    fast = match_descriptors(a, b, MatchesOptions(), block_rows=256)
    exact = match_descriptors(a, b, MatchesOptions(), block_rows=256, allowed=everything)
    assert len(exact) > 500
    assert set(map(tuple, fast.tolist())) == set(map(tuple, exact.tolist()))


def _low_rank_descriptors(rng, n, rank):
    """Unit descriptors spanning a `rank`-dimensional subspace of the 128 dimensions."""
    basis = np.linalg.qr(rng.normal(size=(128, rank)))[0]
    x = rng.normal(size=(n, rank)) @ basis.T
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def test_projection_is_exact_when_the_descriptors_span_fewer_dimensions():
    rng = np.random.default_rng(3)
    a = _low_rank_descriptors(rng, 1500, 40)
    b = _project_onto_span(a, a[rng.permutation(1500)] + 0.02 * rng.normal(size=a.shape).astype(np.float32))
    basis = descriptor_basis([a, b], 48)
    pa, pb = project_descriptors(a, basis), project_descriptors(b, basis)
    assert pa.shape == (1500, 48)
    np.testing.assert_allclose(np.linalg.norm(pa, axis=1), 1.0, atol=1e-5)  # unit rows stay unit
    full, reduced = match_descriptors(a, b, MatchesOptions()), match_descriptors(pa, pb, MatchesOptions())
    # The same matches; their order (by distance ratio) may differ where float32 rounding ties two ratios.
    assert len(full) > 1000 and set(map(tuple, full)) == set(map(tuple, reduced))


def _project_onto_span(a, b):
    """b moved into the span of a's rows (kept unit), so both sets span the same subspace."""
    q = np.linalg.qr(a.T.astype(np.float64))[0][:, :40]
    b = (b @ q) @ q.T
    return (b / np.linalg.norm(b, axis=1, keepdims=True)).astype(np.float32)


def test_projected_distances_bound_the_full_ones_from_below_and_keep_norms():
    rng = np.random.default_rng(4)
    a, b = _descriptors(rng, 400), _descriptors(rng, 300) * 2.0  # b not unit: norms must still be kept
    basis = descriptor_basis(iter([a, b]), 32)
    pa, pb = project_descriptors(a, basis), project_descriptors(b, basis)
    np.testing.assert_allclose(np.linalg.norm(pb, axis=1), np.linalg.norm(b, axis=1), rtol=1e-5)
    full = ((a[:, None] - b[None]) ** 2).sum(-1)
    reduced = ((pa[:, None] - pb[None]) ** 2).sum(-1)
    assert np.all(reduced <= full + 1e-4)
    assert reduced.mean() > 0.5 * full.mean()  # the leading components hold most of the spread
    assert descriptor_basis([a], 0) is None and descriptor_basis([a], 128) is None


def test_projected_search_keeps_the_mutual_matches_the_projected_column_maxima_reject():
    """At few projected dimensions the column maxima of projected similarities reject true mutual matches (another
    feature looks nearer in projection only); searching back from the chosen columns with full-distance re-ranking
    keeps them. The old projected mutual check kept 97.7% of these matches."""
    rng = np.random.default_rng(0)
    base = rng.gamma(0.5, 1.0, (1500, 128))
    root = lambda x: np.sqrt(x / x.sum(axis=1, keepdims=True)).astype(np.float32)  # noqa: E731
    a = root(base)
    b = np.concatenate([root(np.abs(base + rng.normal(0, 0.15, base.shape)))[rng.permutation(1500)],
                        root(rng.gamma(0.5, 1.0, (500, 128)))])
    exact = {tuple(m) for m in match_descriptors(a, b, MatchesOptions(descriptor_dims=0)).tolist()}
    basis = descriptor_basis([a, b], 16)
    found = {tuple(m) for m in match_descriptors(project_descriptors(a, basis), project_descriptors(b, basis),
                                                 MatchesOptions(int8_search=False), full=(a, b)).tolist()}
    assert len(exact) > 1400
    assert len(found & exact) >= 0.99 * len(exact) and not found - exact


def _rootsift_pair(seed: int, n: int = 1500):
    """RootSIFT-like unit rows a and b: b holds noisy copies of a's rows (shuffled) and 500 unrelated rows."""
    rng = np.random.default_rng(seed)
    base = rng.gamma(0.5, 1.0, (n, 128))
    root = lambda x: np.sqrt(x / x.sum(axis=1, keepdims=True)).astype(np.float32)  # noqa: E731
    return root(base), np.concatenate([root(np.abs(base + rng.normal(0, 0.15, base.shape)))[rng.permutation(n)],
                                       root(rng.gamma(0.5, 1.0, (500, 128)))])


def test_int8_products_are_the_exact_integer_products_with_and_without_onnxruntime(monkeypatch):
    """onnxruntime's MatMulInteger and the float32 fallback give the exact integer products, so the same
    neighbours (ties to the lower index); 127-valued rows reach the largest sums."""
    from fullview.sfm import matching

    rng = np.random.default_rng(1)
    a = rng.integers(-127, 128, (300, 32)).astype(np.int8)
    b = rng.integers(-127, 128, (500, 32)).astype(np.int8)
    a[0], b[0] = 127, 127
    b[7] = b[3]  # a tie: the lower index comes first
    exact = a.astype(np.int64) @ b.astype(np.int64).T
    best = np.argsort(-exact, axis=1, kind="stable")[:, :4]
    assert matching._int8_session() is not None  # onnxruntime is a dependency: the fast path is what runs
    assert np.array_equal(matching._nearest_on_int8(a, b, 64, 4), best)
    monkeypatch.setattr(matching, "_int8_session", lambda: None)
    assert np.array_equal(matching._nearest_on_int8(a, b, 64, 4), best)


def test_int8_search_matches_the_same_without_onnxruntime_and_keeps_the_full_search_matches(monkeypatch):
    """At 32 dimensions the int8 search keeps the full 128-dimensional search's matches on RootSIFT-like rows, and
    finds the same ones on the float32 fallback."""
    from fullview.sfm import matching

    a, b = _rootsift_pair(0)
    exact = {tuple(m) for m in match_descriptors(a, b, MatchesOptions(descriptor_dims=0)).tolist()}
    basis = descriptor_basis([a, b], 32)
    pa, pb = project_descriptors(a, basis), project_descriptors(b, basis)
    fast = match_descriptors(pa, pb, MatchesOptions(), full=(a, b))
    found = {tuple(m) for m in fast.tolist()}
    assert len(exact) > 1400 and len(found & exact) >= 0.999 * len(exact) and not found - exact
    monkeypatch.setattr(matching, "_int8_session", lambda: None)
    assert np.array_equal(match_descriptors(pa, pb, MatchesOptions(), full=(a, b)), fast)


def test_the_stored_int8_graph_is_the_one_onnx_builds():
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    from fullview.sfm.matching import _MATMUL_INTEGER_ONNX

    info = helper.make_tensor_value_info
    graph = helper.make_graph([helper.make_node("MatMulInteger", ["A", "B", "azp"], ["Y"])], "mm",
                              [info("A", TensorProto.UINT8, ["n", "k"]), info("B", TensorProto.INT8, ["k", "m"])],
                              [info("Y", TensorProto.INT32, ["n", "m"])],
                              initializer=[helper.make_tensor("azp", TensorProto.UINT8, [], [128])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    assert model.SerializeToString() == _MATMUL_INTEGER_ONNX


def test_noisy_ratio_applies_to_a_pair_with_one_noisy_image_only():
    from fullview.sfm.matching import ratio_for_pair
    options = MatchesOptions(ratio=0.8, noisy_ratio=0.85, noisy_min_noise=0.3)
    assert ratio_for_pair(options, 0.08, 0.1) == 0.8  # clean renders: the test as configured
    assert ratio_for_pair(options, 0.08, 0.55) == 0.85  # a Theta S image on either side
    assert ratio_for_pair(options, 0.55, 0.5) == 0.85
    assert ratio_for_pair(replace(options, noisy_ratio=0.0), 0.55, 0.55) == 0.8  # 0: the ratio whatever the noise
    assert ratio_for_pair(replace(options, ratio=0.9), 0.55, 0.55) == 0.9  # it never tightens the test


def test_matches_stage_takes_each_pairs_ratio_from_its_images_noise(tiny_dataset, make_pipeline, tmp_path):
    """The features stage stores each panorama's noise estimate; the matches stage matches a pair at noisy_ratio
    exactly when its noisier image measures above noisy_min_noise."""
    runs = {}
    for tag, extra in {"base": ["matches.noisy_ratio=0"], "looser": ["matches.ratio=0.9"],
                       "clean": ["matches.noisy_ratio=0.9", "matches.noisy_min_noise=5"],
                       "all noisy": ["matches.noisy_ratio=0.9", "matches.noisy_min_noise=0"]}.items():
        pipe = make_pipeline(tiny_dataset, extra, workspace=tmp_path / tag.replace(" ", "_"))
        pipe.run(until="matches")
        runs[tag] = pipe.ws
    names = Dataset(tiny_dataset).image_names
    noise = [float(runs["base"].load_features(n, ("noise_sigma",))["noise_sigma"]) for n in names]
    assert all(0.0 < s < 5 for s in noise)
    matches = {tag: ws.load_matches().matches for tag, ws in runs.items()}
    same = lambda a, b: all(np.array_equal(x, y) for x, y in zip(matches[a], matches[b]))  # noqa: E731
    assert same("clean", "base") and same("all noisy", "looser") and not same("looser", "base")
