import numpy as np
import pytest

from fullview.sfm.matching import match_descriptors, pair_list
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
