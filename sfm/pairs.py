"""Which image pairs are matched: exhaustive, sequential (window + loop closures), retrieval, GPS, and `auto`.

Pure functions, no file access. Every list is sorted, of pairs (i, j) with i < j, so that the matches artifact and
everything downstream are deterministic.

Retrieval describes each image by one global vector, VLAD (Jégou et al. 2010) over its own (Root)SIFT descriptors:
a small k-means vocabulary trained on the dataset itself with the config's seed, residuals to the nearest word summed
per word, power-normalised (signed square root), intra-normalised per word (Arandjelović & Zisserman 2013, so
that bursty words such as repeated furniture texture do not dominate) and L2-normalised; images are neighbours
by cosine similarity. No shipped vocabulary: trained per dataset it costs seconds and fits the scene's textures.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np
import scipy.sparse

from fullview.sfm.options import MatchesOptions

log = logging.getLogger(__name__)

Pairs = list[tuple[int, int]]
# map(fn, items) -> results in the order of items: builtin map, or a stage's fan-out (threads) for per-image work
Mapper = Callable[[Callable, Iterable], Iterator]
EARTH_RADIUS_M = 6_371_008.8  # mean Earth radius (IUGG)
KMEANS_ITERATIONS = 15  # Lloyd iterations of the vocabulary (converged well enough for retrieval by then)
ASSIGN_ROWS = 8192  # sample rows assigned to words per task: the same chunks whatever runs them, so the same words
SAMPLE_AHEAD = 8  # images whose descriptors the vocabulary's sample reads at a time (on `map`): bounded memory


def _sorted_pairs(pairs) -> Pairs:
    return sorted({(int(min(i, j)), int(max(i, j))) for i, j in pairs if i != j})


def exhaustive(num_images: int) -> Pairs:
    return list(combinations(range(num_images), 2))


def sequential(num_images: int, window: int) -> Pairs:
    """Each image with its next `window` images in capture order."""
    return [(i, j) for i in range(num_images) for j in range(i + 1, min(num_images, i + 1 + window))]


def pair_list(num_images: int, mode: str = "exhaustive", window: int = MatchesOptions.window) -> Pairs:
    """The pair modes that need no image content: 'exhaustive' or 'sequential' (window only)."""
    if mode == "exhaustive":
        return exhaustive(num_images)
    if mode == "sequential":
        return sequential(num_images, window)
    raise ValueError(f"unknown pair mode {mode!r} (expected 'exhaustive' or 'sequential')")


# ------------------------------------------------------------------------------------------------ retrieval
def _sample_descriptors(descriptors: Sequence[np.ndarray], per_image: int, rng: np.random.Generator,
                        map: Mapper = map) -> np.ndarray:
    """Up to `per_image` descriptors of every image, drawn in image order (`descriptors[k]` read `SAMPLE_AHEAD`
    images at a time on `map`)."""
    parts = []
    for start in range(0, len(descriptors), SAMPLE_AHEAD):
        block = range(start, min(start + SAMPLE_AHEAD, len(descriptors)))
        for d in list(map(descriptors.__getitem__, block)):
            take = rng.choice(len(d), size=min(per_image, len(d)), replace=False) if len(d) else np.zeros(0, int)
            parts.append(np.asarray(d, np.float32)[np.sort(take)])
    return np.concatenate(parts) if parts else np.zeros((0, 128), np.float32)


def _nearest_word(x: np.ndarray, words: np.ndarray) -> np.ndarray:
    # argmin |x - w|² = argmax (x·w - |w|²/2), one matrix product
    return np.argmax(x @ words.T - 0.5 * np.einsum("ij,ij->i", words, words)[None, :], axis=1)


def _nearest_words(x: np.ndarray, words: np.ndarray, map: Mapper = map) -> np.ndarray:
    """`_nearest_word` of every row of x, `ASSIGN_ROWS` rows per task on `map`: the k-means iterations' products are
    most of the vocabulary's cost, and the chunks do not depend on who runs them."""
    starts = range(0, len(x), ASSIGN_ROWS)
    return np.concatenate(list(map(lambda s: _nearest_word(x[s:s + ASSIGN_ROWS], words), starts)))


def train_vocabulary(descriptors: Sequence[np.ndarray], size: int, seed: int, per_image: int,
                     map: Mapper = map) -> np.ndarray:
    """(size, D) k-means words from up to `per_image` descriptors of every image (seeded sample and start)."""
    rng = np.random.default_rng(seed)
    sample = _sample_descriptors(descriptors, per_image, rng, map)
    if len(sample) == 0:
        return np.zeros((0, descriptors[0].shape[1] if len(descriptors) else 128), np.float32)
    size = min(size, len(sample))
    words = sample[np.sort(rng.choice(len(sample), size=size, replace=False))].copy()
    for _ in range(KMEANS_ITERATIONS):
        assign = _nearest_words(sample, words, map)
        counts = np.bincount(assign, minlength=size).astype(np.float32)
        sums = _word_sums(sample, assign, size)
        filled = counts > 0  # an empty word keeps its place (rare with a sample this much larger)
        words[filled] = sums[filled] / counts[filled, None]
    return words


def _word_sums(x: np.ndarray, assign: np.ndarray, size: int) -> np.ndarray:
    onehot = scipy.sparse.csr_matrix((np.ones(len(x), np.float32), (assign, np.arange(len(x)))), shape=(size, len(x)))
    return np.asarray(onehot @ x, np.float32)


def vlad(descriptors: np.ndarray, words: np.ndarray) -> np.ndarray:
    """The image's (size * D,) VLAD vector: power-, intra- and L2-normalised; zeros for an image without features."""
    size, dim = words.shape
    if len(descriptors) == 0 or size == 0:
        return np.zeros(size * dim, np.float32)
    x = np.asarray(descriptors, np.float32)
    assign = _nearest_word(x, words)
    residuals = _word_sums(x, assign, size) - np.bincount(assign, minlength=size)[:, None] * words
    residuals = np.sign(residuals) * np.sqrt(np.abs(residuals))
    residuals /= np.maximum(np.linalg.norm(residuals, axis=1, keepdims=True), 1e-12)
    v = residuals.ravel()
    return (v / max(float(np.linalg.norm(v)), 1e-12)).astype(np.float32)


def global_descriptors(descriptors: Sequence[np.ndarray], size: int, seed: int, per_image: int,
                       map: Mapper = map) -> np.ndarray:
    """(N, size * D) VLAD vectors of all images with a vocabulary trained on them; the per-image vectors (and the
    reads of `descriptors[k]`, which may load from disk) and the vocabulary's assignments on `map`."""
    words = train_vocabulary(descriptors, size, seed, per_image, map)
    vectors = list(map(lambda k: vlad(descriptors[k], words), range(len(descriptors))))
    return np.stack(vectors) if vectors else np.zeros((0, 0), np.float32)


def similarity_ranking(global_desc: np.ndarray) -> np.ndarray:
    """(N, N - 1) every image's other images, most similar first (ties by index, so deterministic)."""
    n = len(global_desc)
    sim = np.asarray(global_desc, np.float64) @ np.asarray(global_desc, np.float64).T
    np.fill_diagonal(sim, -np.inf)
    order = np.argsort(-sim, axis=1, kind="stable")
    return order[:, :max(n - 1, 0)]


def retrieval(global_desc: np.ndarray, neighbours: int) -> Pairs:
    """Each image with its `neighbours` most similar images (symmetrised: a pair either side proposes)."""
    order = similarity_ranking(global_desc)[:, :neighbours]
    return _sorted_pairs((i, j) for i in range(len(order)) for j in order[i])


def loop_closures(global_desc: np.ndarray, window: int, neighbours: int) -> Pairs:
    """Retrieval pairs outside the sequential window: a walk that returns to a place it saw before."""
    return [(i, j) for i, j in retrieval(global_desc, neighbours) if j - i > window]


# ------------------------------------------------------------------------------------------------------ GPS
def gps_to_local(lat_lon_alt: np.ndarray) -> np.ndarray:
    """(N, 3) degrees, degrees, metres → (N, 3) east, north, up in metres about the mean position (local tangent
    plane; exact enough over the few kilometres of a capture). NaN rows stay NaN."""
    lla = np.asarray(lat_lon_alt, np.float64).reshape(-1, 3)
    ok = np.isfinite(lla).all(axis=1)
    out = np.full_like(lla, np.nan)
    if not ok.any():
        return out
    lat0, lon0 = np.deg2rad(lla[ok, :2].mean(axis=0))
    lat, lon = np.deg2rad(lla[ok, 0]), np.deg2rad(lla[ok, 1])
    dlon = (lon - lon0 + np.pi) % (2 * np.pi) - np.pi
    out[ok, 0] = EARTH_RADIUS_M * np.cos(lat0) * dlon
    out[ok, 1] = EARTH_RADIUS_M * (lat - lat0)
    out[ok, 2] = lla[ok, 2] - lla[ok, 2].mean()
    return out


def position_neighbours(positions: np.ndarray, neighbours: int, radius: float = 0.0) -> Pairs:
    """Each image with a finite position paired with its `neighbours` nearest ones, and (radius > 0) with every
    one within `radius`. Images without a position (NaN) get no pair."""
    pos = np.asarray(positions, np.float64)
    idx = np.flatnonzero(np.isfinite(pos).all(axis=1))
    if len(idx) < 2:
        return []
    p = pos[idx]
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    np.fill_diagonal(d, np.inf)
    order = np.argsort(d, axis=1, kind="stable")[:, :min(neighbours, len(idx) - 1)]
    pairs = {(idx[a], idx[b]) for a in range(len(idx)) for b in order[a]}
    if radius > 0:
        pairs |= {(idx[a], idx[b]) for a, b in zip(*np.nonzero(d <= radius))}
    return _sorted_pairs(pairs)


def geometry_pairs(centers: np.ndarray, registered: np.ndarray, existing: Pairs, neighbours: int) -> Pairs:
    """Pairs of registered cameras among each one's `neighbours` nearest by position that were not matched yet:
    what a registered model proposes before a final matching pass."""
    pos = np.where(np.asarray(registered, bool)[:, None], np.asarray(centers, np.float64), np.nan)
    done = set(map(tuple, existing))
    return [p for p in position_neighbours(pos, neighbours) if p not in done]


# ----------------------------------------------------------------------------------------------------- auto
def uses_gps(num_images: int, options: MatchesOptions) -> bool:
    """Whether `select_pairs` reads GPS positions for this many images (only `auto` above the exhaustive size): a
    caller can skip reading them (a PNG's EXIF is only found by decoding the whole image)."""
    return (options.pairs == "auto" and num_images >= options.auto_exhaustive_below and options.gps_neighbours > 0)


@dataclass(frozen=True, kw_only=True)
class PairPlan:
    """What the matches stage matches: `pairs` at once, then the loop candidates round by round (`loop_rounds`)."""
    pairs: Pairs  # matched at once: the window, retrieval pairs near in capture order, GPS (sorted)
    loop_candidates: list[Pairs]  # per image, its retrieval pairs far in capture order, most similar first
    summary: dict  # where the pairs came from

    @property
    def all_pairs(self) -> Pairs:
        """Every pair that may be matched (the candidates whether or not their round comes)."""
        return _sorted_pairs([*self.pairs, *(p for c in self.loop_candidates for p in c)])


def select_pairs(descriptors: list[np.ndarray], options: MatchesOptions,
                 gps: np.ndarray | None = None) -> tuple[Pairs, dict]:
    """Every pair the `options.pairs` mode may match (`plan_pairs`' pairs and loop candidates) and a summary of where
    the pairs came from."""
    plan = plan_pairs(descriptors, options, gps)
    return plan.all_pairs, plan.summary


def loop_reach(options: MatchesOptions) -> int:
    """Capture steps beyond which a retrieval pair is a loop candidate (0: none are; only with a window, and with
    loop_patience on). Why twice the window: pairs up to there are the window's own continuation (an image's
    partners' partners), which still overlap on a walk (the 50-view corridor: 9 of the 30 retrieval pairs 4-6 steps
    apart verify, none of the 161 beyond); a pair farther apart can only be a place visited again."""
    uses_window = options.pairs in ("sequential", "auto")
    return 2 * options.window if uses_window and options.loop_patience > 0 else 0


def plan_pairs(descriptors: Sequence[np.ndarray], options: MatchesOptions, gps: np.ndarray | None = None,
               map: Mapper = map) -> PairPlan:
    """The pairs `options.pairs` asks for, split into those matched at once and the loop candidates.

    descriptors: every image's (M_i, D) descriptors, in capture order; gps: (N, 3) latitude, longitude, altitude per
    image (NaN where the image has none) or None; map: how retrieval's per-image work fans out (the same result)."""
    # every option is read whatever the mode (the settings test checks each key reaches its stage)
    n, mode, o = len(descriptors), options.pairs, options
    window, neighbours, gps_k, gps_radius = o.window, o.retrieval_neighbours, o.gps_neighbours, o.gps_radius_m
    vocabulary = (o.vocabulary_size, o.vocabulary_seed, o.vocabulary_sample)
    reach = loop_reach(o)
    if mode == "exhaustive" or (mode == "auto" and n < o.auto_exhaustive_below):
        pairs = exhaustive(n)
        return PairPlan(pairs=pairs, loop_candidates=[[] for _ in range(n)],
                        summary={"mode": "exhaustive", "exhaustive": len(pairs)})
    if mode not in ("sequential", "retrieval", "auto"):
        raise ValueError(f"unknown pair mode {mode!r}")
    sources: dict[str, Pairs] = {}
    candidates: list[Pairs] = [[] for _ in range(n)]
    if mode in ("sequential", "auto"):
        sources["sequential"] = sequential(n, window)
    if neighbours > 0:
        g = global_descriptors(descriptors, *vocabulary, map=map)
        if mode == "sequential":
            sources["loops"] = loop_closures(g, window, neighbours)
        else:
            sources["retrieval"] = retrieval(g, neighbours)
        if reach:
            candidates = ranked_loop_candidates(similarity_ranking(g)[:, :neighbours], reach)
    if gps is not None and uses_gps(n, o):
        sources["gps"] = position_neighbours(gps_to_local(gps), gps_k, gps_radius)
    everything = _sorted_pairs(p for s in sources.values() for p in s)
    # A loop candidate another source also proposes (GPS) is matched at once.
    direct = {p for name, s in sources.items() if name not in ("retrieval", "loops") for p in s}
    direct |= {p for p in everything if p[1] - p[0] <= reach} if reach else set(everything)
    candidates = [[p for p in c if p not in direct] for c in candidates]
    pairs = [p for p in everything if p in direct]
    summary = {"mode": mode, **{k: len(v) for k, v in sources.items()}}
    if reach:
        summary["loop_candidates"] = len(everything) - len(pairs)
    log.info("pairs: %d of %d possible (%s)", len(everything), n * (n - 1) // 2,
             ", ".join(f"{k} {v}" for k, v in summary.items() if k != "mode"))
    return PairPlan(pairs=pairs, loop_candidates=candidates, summary=summary)


def ranked_loop_candidates(ranking: np.ndarray, reach: int) -> list[Pairs]:
    """Per image, the pairs with its ranked images (N, K: most similar first) more than `reach` capture steps away,
    in that order."""
    return [[(min(i, int(j)), max(i, int(j))) for j in row if abs(i - int(j)) > reach] for i, row in enumerate(ranking)]


def first_loop_proposals(candidates: list[Pairs], patience: int) -> Pairs:
    """The candidates `loop_rounds` matches whatever they find: each image's first `patience` (all with patience 0).
    The matches stage matches them with the other pairs, before any outcome is known."""
    return _sorted_pairs(p for c in candidates for p in (c if patience <= 0 else c[:patience]))


def loop_rounds(candidates: list[Pairs], patience: int, match_round: Callable[[Pairs], dict[tuple[int, int], bool]],
                found: dict[tuple[int, int], bool] | None = None) -> tuple[Pairs, int]:
    """The loop candidates matched, and the number of rounds: an image stops looking after `patience` of its
    candidates in a row (whoever proposed them) found too few; each round matches, for every image still looking, its
    next candidates up to the one whose miss would stop it (`match_round(pairs) -> {pair: found enough}`, pairs
    sorted, each pair once). So an image's candidates are matched up to and including its `patience`-th miss in a
    row. patience 0: every candidate in one round. `found`: outcomes of candidates matched before (a round not
    counted: `first_loop_proposals`, matched with the other pairs).

    Why: a walk's far retrieval pairs are mostly chance look-alikes (none of the 50-view corridor's 161 verifies)
    and cost as much to match as any pair, while a place visited again keeps yielding: its candidates find many
    matches, so its images keep looking, as do all images of a room, whose retrieval pairs all overlap. The outcome
    of a pair depends only on its matches, so the rounds, and the pairs they match, are deterministic."""
    found = dict(found or {})
    if patience <= 0:
        every = _sorted_pairs(p for c in candidates for p in c)
        rest = [p for p in every if p not in found]
        if rest:
            match_round(rest)
        return every, int(bool(rest))
    position, misses = [0] * len(candidates), [0] * len(candidates)
    rounds = 0
    while True:
        proposed = set()
        for i, mine in enumerate(candidates):
            while misses[i] < patience and position[i] < len(mine) and mine[position[i]] in found:
                misses[i] = 0 if found[mine[position[i]]] else misses[i] + 1
                position[i] += 1
            # The next candidates up to the miss that would stop the image: it reaches each of them whatever they
            # find, so they are matched in this round (a room, where nothing misses, needs fewer rounds).
            proposed.update(p for p in mine[position[i]:position[i] + patience - misses[i]] if p not in found)
        if not proposed:
            return sorted(found), rounds
        found.update(match_round(sorted(proposed)))
        rounds += 1
