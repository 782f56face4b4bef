"""Feature tracks from pairwise inlier matches (vectorised union-find).

A node of the match graph is one ``(image, feature)`` pair; every pairwise inlier match is an edge.
A track is a connected component of that graph. Components are found all at once with
``scipy.sparse.csgraph.connected_components`` (equivalent to union-find, without a Python loop).

A track is *inconsistent* when it holds two different features of the same image (the matches
chain through a wrong correspondence somewhere); such tracks are dropped, as are tracks with fewer
than ``min_length`` observations.

Tracks are stored flat, CSR-like: observation ``k`` is feature ``feature_ids[k]`` of image
``image_ids[k]`` and belongs to track ``track_ids[k]``; observations are sorted by track, then
image, and track ``t`` owns observations ``offsets[t]:offsets[t + 1]``.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class Tracks:
    """Feature tracks as flat arrays sorted by track (then image)."""

    track_ids: np.ndarray  # (K,) int64 track index of each observation, non-decreasing, 0..T-1
    image_ids: np.ndarray  # (K,) int64 image index of each observation
    feature_ids: np.ndarray  # (K,) int64 feature index (within its image) of each observation
    offsets: np.ndarray  # (T+1,) int64 track t owns observations offsets[t]:offsets[t+1]
    num_images: int  # number of images the image indices refer to

    @property
    def num_tracks(self) -> int:
        """Number of tracks T."""
        return len(self.offsets) - 1

    @property
    def num_observations(self) -> int:
        """Number of observations K (sum of the track lengths)."""
        return len(self.track_ids)

    @property
    def lengths(self) -> np.ndarray:
        """(T,) number of observations of each track."""
        return np.diff(self.offsets)

    def observations(self, track: int) -> tuple[np.ndarray, np.ndarray]:
        """(image_ids, feature_ids) of one track."""
        if not 0 <= track < self.num_tracks:
            raise ValueError(f"track={track} out of range [0, {self.num_tracks})")
        sl = slice(self.offsets[track], self.offsets[track + 1])
        return self.image_ids[sl], self.feature_ids[sl]

    def subset(self, keep: np.ndarray) -> Tracks:
        """Tracks where the (T,) bool mask ``keep`` is true, renumbered 0..T'-1 in the same order."""
        keep = np.asarray(keep, dtype=bool)
        if keep.shape != (self.num_tracks,):
            raise ValueError(f"keep has shape {keep.shape}, expected ({self.num_tracks},)")
        return _from_sorted(self.track_ids, self.image_ids, self.feature_ids, keep[self.track_ids], self.num_images)

    def feature_to_track(self, image: int, num_features: int) -> np.ndarray:
        """(num_features,) track index of every feature of ``image``, -1 where it is in no track."""
        out = np.full(num_features, -1, dtype=np.int64)
        sel = self.image_ids == image
        out[self.feature_ids[sel]] = self.track_ids[sel]
        return out


@dataclass(frozen=True, kw_only=True)
class TrackStats:
    """Counts from building tracks."""

    num_matches: int  # pairwise matches (graph edges) read, duplicates included
    num_components: int  # connected components of matched (image, feature) nodes
    num_inconsistent: int  # components dropped: two different features of one image
    num_short: int  # consistent components dropped for having < min_length observations
    num_tracks: int  # tracks kept


def _from_sorted(track_ids, image_ids, feature_ids, keep_obs, num_images) -> Tracks:
    """Build Tracks from observations sorted by track, keeping ``keep_obs`` and renumbering tracks."""
    track_ids, image_ids, feature_ids = track_ids[keep_obs], image_ids[keep_obs], feature_ids[keep_obs]
    first = np.ones(len(track_ids), dtype=bool)  # first observation of each track
    first[1:] = track_ids[1:] != track_ids[:-1]
    new_ids = np.cumsum(first) - 1
    offsets = np.r_[np.flatnonzero(first), len(track_ids)].astype(np.int64)
    return Tracks(
        track_ids=new_ids,
        image_ids=image_ids.astype(np.int64),
        feature_ids=feature_ids.astype(np.int64),
        offsets=offsets,
        num_images=int(num_images),
    )


def _edges(pair_matches: Mapping[tuple[int, int], np.ndarray], feature_offsets: np.ndarray) -> np.ndarray:
    """(E, 2) global node ids of all matches, after validating every pair."""
    num_images = len(feature_offsets) - 1
    counts = np.diff(feature_offsets)
    chunks = [np.zeros((0, 2), dtype=np.int64)]
    for (i, j), m in pair_matches.items():
        if not (0 <= i < num_images and 0 <= j < num_images) or i == j:
            raise ValueError(f"pair_matches key {(i, j)} invalid for {num_images} images (need i != j in range)")
        m = np.asarray(m)
        if m.size == 0:
            continue
        if m.ndim != 2 or m.shape[1] != 2 or not np.issubdtype(m.dtype, np.integer):
            raise ValueError(f"pair_matches[{(i, j)}] must be an (M, 2) int array, got {m.dtype} {m.shape}")
        if m.min() < 0 or m[:, 0].max() >= counts[i] or m[:, 1].max() >= counts[j]:
            raise ValueError(
                f"pair_matches[{(i, j)}] has feature indices out of range "
                f"(num_features[{i}]={counts[i]}, num_features[{j}]={counts[j]})"
            )
        chunks.append(m.astype(np.int64) + feature_offsets[[i, j]])
    return np.concatenate(chunks)


def build_tracks(
    pair_matches: Mapping[tuple[int, int], np.ndarray],
    num_features: Sequence[int],
    *,
    min_length: int = 2,
) -> tuple[Tracks, TrackStats]:
    """Tracks = connected components of the (image, feature) match graph.

    ``pair_matches[(i, j)]`` is an (M, 2) int array of inlier matches (feature in image i, feature
    in image j); ``num_features[i]`` is the number of features of image i. Components with two
    different features of one image are dropped (inconsistent), as are components with fewer than
    ``min_length`` observations.
    """
    num_features = np.asarray(num_features, dtype=np.int64)
    if num_features.ndim != 1 or (num_features < 0).any():
        raise ValueError(f"num_features must be a 1-D sequence of counts >= 0, got {num_features}")
    feature_offsets = np.r_[0, np.cumsum(num_features)]
    edges = _edges(pair_matches, feature_offsets)
    nodes, inverse = np.unique(edges, return_inverse=True)  # only matched nodes enter the graph
    inverse = inverse.reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges), dtype=np.int8), (inverse[:, 0], inverse[:, 1])), shape=(len(nodes),) * 2)
    num_components, labels = connected_components(graph, directed=False)

    image_ids = np.searchsorted(feature_offsets, nodes, side="right") - 1
    feature_ids = nodes - feature_offsets[image_ids]
    order = np.lexsort((image_ids, labels))
    labels, image_ids, feature_ids = labels[order], image_ids[order], feature_ids[order]

    same_image = (labels[1:] == labels[:-1]) & (image_ids[1:] == image_ids[:-1])
    inconsistent = np.zeros(num_components, dtype=bool)
    inconsistent[labels[1:][same_image]] = True
    short = np.bincount(labels, minlength=num_components) < min_length
    keep = ~inconsistent & ~short
    tracks = _from_sorted(labels, image_ids, feature_ids, keep[labels], len(num_features))
    stats = TrackStats(
        num_matches=len(edges),
        num_components=int(num_components),
        num_inconsistent=int(inconsistent.sum()),
        num_short=int((short & ~inconsistent).sum()),
        num_tracks=tracks.num_tracks,
    )
    log.info(
        "tracks: %d kept of %d components (%d inconsistent, %d short dropped) from %d matches",
        stats.num_tracks, stats.num_components, stats.num_inconsistent, stats.num_short, stats.num_matches,
    )
    return tracks, stats


def add_observations(tracks: Tracks, track_ids: np.ndarray, image_ids: np.ndarray, feature_ids: np.ndarray
                     ) -> tuple[Tracks, np.ndarray]:
    """Tracks with feature ``feature_ids[k]`` of image ``image_ids[k]`` added to track ``track_ids[k]`` (2D-3D
    matches). A feature already in another track brings that whole track along (the two are one point), unless
    they share an image; a feature already in the track is left alone; a match that would put a second feature of
    one image into a track is skipped. Returns the new tracks (renumbered) and (K,) which matches were taken."""
    track_ids, image_ids, feature_ids = (np.asarray(a, np.int64) for a in (track_ids, image_ids, feature_ids))
    label = tracks.track_ids.copy()  # the new track of every existing observation
    owner: dict[int, set[int]] = {}  # track -> images, for the tracks touched here

    def images(t: int) -> set[int]:
        if t not in owner:
            owner[t] = set(tracks.image_ids[label == t].tolist())
        return owner[t]

    where = {(int(i), int(f)): k for k, (i, f) in enumerate(zip(tracks.image_ids.tolist(),
                                                              tracks.feature_ids.tolist()))}
    new_obs, taken = [], np.zeros(len(track_ids), bool)
    for k, (t, i, f) in enumerate(zip(track_ids.tolist(), image_ids.tolist(), feature_ids.tolist())):
        obs = where.get((i, f))
        if obs is not None:
            other = int(label[obs])
            if other == t:
                continue
            if images(other) & images(t):
                continue
            label[label == other] = t
            owner[t] = images(t) | owner.pop(other)
            taken[k] = True
        elif i not in images(t):
            new_obs.append((t, i, f))
            owner[t].add(i)
            taken[k] = True
    extra = np.array(new_obs, np.int64).reshape(-1, 3)
    all_tracks = np.concatenate([label, extra[:, 0]])
    all_images = np.concatenate([tracks.image_ids, extra[:, 1]])
    all_features = np.concatenate([tracks.feature_ids, extra[:, 2]])
    order = np.lexsort((all_images, all_tracks))
    return _from_sorted(all_tracks[order], all_images[order], all_features[order], np.ones(len(order), bool),
                        tracks.num_images), taken
