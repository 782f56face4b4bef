"""Pair selection (sfm/pairs.py): retrieval, sequential with loop closures, auto, GPS and geometry neighbours."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import PIL.Image
import pytest

from fullview.io.dataset import exif_gps
from fullview.sfm import pairs as P
from fullview.sfm.options import MatchesOptions


def _walk_descriptors(places: list[int], *, seed: int = 0, reach: int = 2, per_place: int = 60,
                      noise: float = 0.08) -> list[np.ndarray]:
    """Image k stands at place places[k] of a street of landmarks and sees the landmarks of the places within
    `reach` of it (each image a random subset, with descriptor noise): images at nearby places share landmarks."""
    rng = np.random.default_rng(seed)
    num_places = max(places) + 1 + reach
    landmarks = np.abs(rng.normal(size=(num_places, per_place, 128))).astype(np.float32)
    out = []
    for p in places:
        seen = landmarks[max(p - reach, 0):p + reach + 1].reshape(-1, 128)
        keep = seen[rng.random(len(seen)) < 0.7]
        d = keep + noise * np.abs(rng.normal(size=keep.shape)).astype(np.float32)
        out.append(d / np.linalg.norm(d, axis=1, keepdims=True))
    return out


def test_retrieval_finds_the_true_neighbours_and_is_deterministic():
    desc = _walk_descriptors(list(range(30)))
    g = P.global_descriptors(desc, size=16, seed=0, per_image=200)
    ranking = P.similarity_ranking(g)
    for i in range(30):  # the two most similar images are the ones one place away (one of them at either end)
        expected = {j for j in (i - 1, i + 1) if 0 <= j < 30}
        assert expected <= set(ranking[i, :2]) | ({i + 2} if i == 0 else {i - 2} if i == 29 else set())
    assert P.retrieval(g, 2) == P.retrieval(P.global_descriptors(desc, 16, 0, 200), 2)  # same seed, same pairs
    assert all(abs(i - j) <= 2 for i, j in P.retrieval(g, 2))


def test_vlad_is_normalised_and_zero_without_features():
    words = P.train_vocabulary(_walk_descriptors([0, 1]), size=8, seed=0, per_image=100)
    v = P.vlad(_walk_descriptors([0])[0], words)
    assert v.shape == (8 * 128,) and np.isclose(np.linalg.norm(v), 1.0)
    assert not P.vlad(np.zeros((0, 128), np.float32), words).any()


def test_sequential_with_loop_closure_finds_the_revisit():
    """A walk of 12 places that comes back along them: images 12..23 stand at places 11..0."""
    places = list(range(12)) + list(range(11, -1, -1))
    options = MatchesOptions(pairs="sequential", window=2, retrieval_neighbours=2, vocabulary_size=16,
                             vocabulary_sample=200)
    pairs, summary = P.select_pairs(_walk_descriptors(places), options)
    assert set(P.sequential(24, 2)) <= set(pairs)
    loops = [(i, j) for i, j in pairs if j - i > 2]
    assert summary["loops"] == len(loops) > 0
    # every loop closure joins two images at places at most 2 apart, and most revisited places are closed
    assert all(abs(places[i] - places[j]) <= 2 for i, j in loops)
    closed = {places[i] for i, j in loops if places[i] == places[j]}
    assert len(closed) >= 8


def test_auto_is_exhaustive_below_the_threshold_and_sparse_above():
    options = MatchesOptions(pairs="auto", auto_exhaustive_below=20, window=2, retrieval_neighbours=3,
                             vocabulary_size=16, vocabulary_sample=100)
    below, s_below = P.select_pairs(_walk_descriptors(list(range(19))), options)
    assert below == P.exhaustive(19) and s_below["mode"] == "exhaustive"
    above, s_above = P.select_pairs(_walk_descriptors(list(range(20))), options)
    assert s_above["mode"] == "auto" and set(P.sequential(20, 2)) <= set(above)
    assert len(above) < len(P.exhaustive(20)) / 2 and above == sorted(set(above))
    assert P.select_pairs(_walk_descriptors(list(range(19))), replace(options, pairs="exhaustive"))[0] == below


def test_gps_neighbours():
    # 5 images 10 m apart along a meridian (1 m = 1/111195 degree of latitude), one without GPS
    lat = 48.0 + np.arange(5) * 10.0 / (np.pi / 180 * P.EARTH_RADIUS_M)
    gps = np.column_stack([lat, np.full(5, 11.0), np.full(5, 500.0)])
    gps[2] = np.nan
    local = P.gps_to_local(gps)
    assert np.isnan(local[2]).all()
    assert np.allclose(np.diff(local[[0, 1, 3, 4], 1]), [10, 20, 10], atol=1e-6) and np.allclose(local[[0, 1], 0], 0)
    assert P.position_neighbours(local, 1) == [(0, 1), (3, 4)]
    assert P.position_neighbours(local, 1, radius=20.5) == [(0, 1), (1, 3), (3, 4)]
    options = MatchesOptions(pairs="auto", auto_exhaustive_below=2, window=1, retrieval_neighbours=1,
                             vocabulary_size=4, vocabulary_sample=50, gps_neighbours=1)
    pairs, summary = P.select_pairs(_walk_descriptors([0, 5, 10, 15, 20]), options, gps)
    assert summary["gps"] == 2 and {(0, 1), (3, 4)} <= set(pairs)


def test_exif_gps_is_read(tmp_path: Path):
    image = PIL.Image.new("RGB", (64, 32))
    exif = image.getexif()
    gps = exif.get_ifd(0x8825)
    gps.update({1: "N", 2: (48.0, 30.0, 36.0), 3: "W", 4: (11.0, 0.0, 0.0), 5: 0, 6: 512.5})
    image.save(tmp_path / "a.jpg", exif=exif)
    PIL.Image.new("RGB", (64, 32)).save(tmp_path / "b.jpg")
    lat, lon, alt = exif_gps(tmp_path / "a.jpg")
    assert (lat, lon, alt) == pytest.approx((48.51, -11.0, 512.5))
    assert exif_gps(tmp_path / "b.jpg") is None


def _png_chunks(data: bytes) -> list[bytes]:
    chunks, at = [], 8
    while at < len(data):
        length = int.from_bytes(data[at:at + 4], "big")
        chunks.append(data[at:at + 12 + length])
        at += 12 + length
    return chunks


def test_png_gps_is_read_wherever_its_exif_chunk_is_and_a_png_without_is_not_decoded(tmp_path: Path, monkeypatch):
    image = PIL.Image.new("RGB", (64, 32))
    exif = image.getexif()
    exif.get_ifd(0x8825).update({1: "S", 2: (10.0, 15.0, 0.0), 3: "E", 4: (20.0, 0.0, 0.0), 6: 3.0})
    image.save(tmp_path / "a.png", exif=exif.tobytes())
    chunks = _png_chunks((tmp_path / "a.png").read_bytes())
    assert [c[4:8] for c in chunks].count(b"eXIf") == 1
    # the eXIf chunk after the image data (allowed by the PNG spec): PIL decodes the image to find it
    late = [c for c in chunks if c[4:8] not in (b"eXIf", b"IEND")]
    late += [c for c in chunks if c[4:8] == b"eXIf"] + [chunks[-1]]
    (tmp_path / "late.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"".join(late))
    PIL.Image.new("RGB", (64, 32)).save(tmp_path / "b.png")
    for name in ("a.png", "late.png"):
        assert exif_gps(tmp_path / name) == pytest.approx((-10.25, 20.0, 3.0))
    monkeypatch.setattr(PIL.Image, "open", lambda *a, **k: pytest.fail("a PNG without EXIF chunks was opened"))
    assert exif_gps(tmp_path / "b.png") is None


def test_geometry_pairs_propose_unmatched_neighbours_of_registered_cameras():
    centers = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [0.5, 0, 0]])
    registered = np.array([True, True, True, True, False])
    proposed = P.geometry_pairs(centers, registered, existing=[(0, 1)], neighbours=1)
    assert proposed == [(1, 2), (2, 3)]  # (0, 1) is matched already; 4 is not registered (ties: lower index)
    assert P.geometry_pairs(centers, registered, existing=[], neighbours=2) == [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)]


def test_retrieval_on_threads_in_row_chunks_equals_one_loop(monkeypatch):
    from fullview.stages.protocol import thread_map
    desc = _walk_descriptors(list(range(0, 40, 3)))
    serial = P.global_descriptors(desc, 16, 0, 200)
    monkeypatch.setattr(P, "ASSIGN_ROWS", 97)  # the sample's rows in many chunks, the last one short
    assert np.array_equal(P.global_descriptors(desc, 16, 0, 200, map=thread_map), serial)
    options = MatchesOptions(pairs="auto", auto_exhaustive_below=2, window=2, retrieval_neighbours=4,
                             vocabulary_size=16, vocabulary_sample=200)
    assert P.plan_pairs(desc, options, map=thread_map) == P.plan_pairs(desc, options)
