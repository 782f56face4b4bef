"""Descriptor matching: nearest neighbours by blocked matrix products, Lowe's ratio test, mutual check."""

from __future__ import annotations

from collections.abc import Iterable
from functools import cache

import numpy as np

from fullview.sfm.options import MatchesOptions


BLOCK_ROWS = 128  # rows per matrix-product block: the reductions' passes over a block stay in cache. Measured on 28
# pairs of 6,900-feature panoramas, 64 projected dimensions, two threads: 1.32 s at 128 rows, 1.51 s at 256, 1.58 s
# at 512 (on 128 dimensions 256 rows had beaten 1,024: 0.122 against 0.146 s per pair)
RERANK_CANDIDATES = 3  # nearest candidates per feature, found on projected descriptors, re-ranked by full distances
# ... on the int8 search: rounding adds near-ties, and with 3 candidates 360_Flat kept 99.89% of the full search's
# matches (float32: 99.95%), with 4 99.95% and fewer extra ones (0.50% against 1.08%; README, "Fifth speed pass")
INT8_RERANK_CANDIDATES = 4
RESCORE_ROWS = 256  # rows re-ranked at a time: (256, 4, 128) float32 differences, 0.5 MB (all rows at once: 2x slower)
_UNIT_NORM_TOLERANCE = 1e-4  # |‖x‖² − 1| below which descriptors count as unit (RootSIFT: ~1e-7)
INT8_SCALE = 127.0  # projected unit rows have every coordinate in [−1, 1]: x ↦ round(127 x) fills int8
# An ONNX graph of one MatMulInteger(A uint8 with zero point 128, B int8) -> int32 (opset 13, IR 8), as
# onnx.helper writes it (tests/test_matching.py rebuilds it with onnx and compares the bytes).
_MATMUL_INTEGER_ONNX = (
    b'\x08\x08:u\n\x1d\n\x01A\n\x01B\n\x03azp\x12\x01Y"\rMatMulInteger\x12\x02mm*\x0b\x10\x02*\x02\x80\x01B\x03azp'
    b'Z\x15\n\x01A\x12\x10\n\x0e\x08\x02\x12\n\n\x03\x12\x01n\n\x03\x12\x01kZ\x15\n\x01B\x12\x10\n\x0e\x08\x03\x12\n\n\x03\x12'
    b'\x01k\n\x03\x12\x01mb\x15\n\x01Y\x12\x10\n\x0e\x08\x06\x12\n\n\x03\x12\x01n\n\x03\x12\x01mB\x04\n\x00\x10\r')


def descriptor_basis(descriptor_sets: Iterable[np.ndarray], dims: int) -> np.ndarray | None:
    """(128, dims − 1) float32: the leading eigenvectors of the descriptors' second-moment matrix, accumulated one
    set at a time (one image's descriptors in memory); None when `dims` is 0 or keeps every dimension.

    `project_descriptors` maps a descriptor on them plus one coordinate, the norm of what they miss. The projection
    keeps every row's norm (unit RootSIFT rows stay unit, so the search keeps its fast similarity form) and its
    distances approximate the full ones from below, missing only the dropped components' energy (~6% on RootSIFT
    at 64 dimensions): the ratio test and mutual check keep 99% of the full search's matches (README, "Speed of
    matching") for half the matrix product."""
    return basis_from_moments(map(second_moment, descriptor_sets), dims)


def second_moment(desc: np.ndarray) -> np.ndarray:
    """(128, 128) float64 DᵀD of one image's descriptors: `basis_from_moments` sums them."""
    d = np.asarray(desc, np.float64)
    return d.T @ d


def basis_from_moments(moments: Iterable[np.ndarray], dims: int) -> np.ndarray | None:
    """`descriptor_basis` from the images' `second_moment`s, summed in the order given (computed anywhere, e.g.
    on threads: the same basis, bit for bit, as one loop)."""
    outer = None
    for moment in moments:
        outer = moment if outer is None else outer + moment
    if not dims or outer is None or dims >= len(outer):
        return None
    _, vectors = np.linalg.eigh(outer)  # ascending eigenvalues
    return np.ascontiguousarray(vectors[:, ::-1][:, :dims - 1], np.float32)


def project_descriptors(desc: np.ndarray, basis: np.ndarray | None) -> np.ndarray:
    """Descriptors on `descriptor_basis`'s components plus their residual norm (float32 unchanged if basis is None)."""
    desc = np.asarray(desc, np.float32)
    if basis is None:
        return desc
    projected = desc @ basis
    residual_sq = np.einsum("ij,ij->i", desc, desc) - np.einsum("ij,ij->i", projected, projected)
    return np.column_stack([projected, np.sqrt(np.maximum(residual_sq, 0.0))]).astype(np.float32)


def match_pair(desc_i, desc_j, options: MatchesOptions, noise_i: float, noise_j: float, *, full=None
               ) -> tuple[np.ndarray, int]:
    """`match_descriptors` of a pair at `ratio_for_pair`'s ratio, and how many of its matches (a prefix: they come
    most distinctive first) pass the strict `options.ratio`: the filter draws its hypotheses from those alone."""
    ratio = ratio_for_pair(options, noise_i, noise_j)
    if ratio == options.ratio:
        matches = match_descriptors(desc_i, desc_j, options, full=full)
        return matches, len(matches)
    matches, ratios = match_descriptors(desc_i, desc_j, options, full=full, ratio=ratio, with_ratios=True)
    return matches, int(np.searchsorted(ratios, options.ratio, side="left"))


def ratio_for_pair(options: MatchesOptions, noise_i: float, noise_j: float) -> float:
    """The ratio test of a pair whose images measure `noise_i`, `noise_j` grey levels of sensor noise: `noisy_ratio`
    when the noisier one exceeds `noisy_min_noise` and it is the looser, else `ratio`. Why: noise adds about the same
    energy to the nearest and the second nearest descriptor distance, pushing true matches' ratios towards 1 (README,
    "homenoise")."""
    if max(noise_i, noise_j) <= options.noisy_min_noise or options.noisy_ratio <= options.ratio:
        return options.ratio  # (noisy_ratio only ever loosens the test: 0, or below `ratio`, leaves it)
    return options.noisy_ratio


def pair_blocks(pairs: list[tuple[int, int]], block_images: int) -> list[list[int]]:
    """Indices into `pairs` grouped so that a group's pairs touch at most 2 x `block_images` images: pair (i, j) goes
    to block (i // block_images, j // block_images). Streaming the groups bounds the descriptors in memory."""
    groups: dict[tuple[int, int], list[int]] = {}
    for k, (i, j) in enumerate(pairs):
        groups.setdefault((i // block_images, j // block_images), []).append(k)
    return [groups[key] for key in sorted(groups)]


def _nearest_both_ways(a: np.ndarray, b: np.ndarray, block: int, allowed=None, candidates: int = 2,
                       mutual: bool = True):
    """One pass over the distance matrix, in row blocks.

    Returns for each row of a its `candidates` nearest rows of b (N, candidates), nearest first, the squared
    distances to them, and whether each is mutual: the row is also the nearest row of a to that row of b.
    `allowed(start, stop)`, when given, returns the (rows, len(b)) bool mask of the candidates each row may match
    (others count as infinitely far). With `mutual` False the unit-row search skips the column pass and reports
    every candidate as mutual.
    """
    a_sq = np.einsum("ij,ij->i", a, a)
    b_sq = np.einsum("ij,ij->i", b, b)
    if allowed is None and np.allclose(a_sq, 1.0, rtol=0.0, atol=_UNIT_NORM_TOLERANCE):
        return _nearest_by_similarity(a, b, a_sq, b_sq, block, candidates, mutual)
    nn = np.empty((len(a), candidates), np.int64)
    d2 = np.empty((len(a), candidates), np.float32)
    col_min = np.full(len(b), np.inf, np.float32)
    b_t = np.ascontiguousarray(b.T)  # see _nearest_by_similarity
    for s in range(0, len(a), block):
        dist = (a[s:s + block] @ b_t) * np.float32(-2.0)
        dist += b_sq[None, :]
        dist += a_sq[s:s + block, None]
        if allowed is not None:
            dist[~allowed(s, s + len(dist))] = np.inf
        np.minimum(col_min, dist.min(axis=0), out=col_min)
        nn[s:s + block], d2[s:s + block] = _k_best(dist, np.argmin, np.inf, candidates)
    # a's row r and its candidate c are mutual iff d(r, c) is column c's minimum (column minima reduce fast, column
    # argmins do not); float32 rounding can dip below 0.
    return nn, np.maximum(d2, 0.0), d2 <= col_min[nn]


def _k_best(scores: np.ndarray, arg_best, worst: float, k: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Per row of `scores` the columns of its k best scores, best first (`arg_best`: np.argmin or np.argmax), and
    those scores; overwrites each of them with `worst`."""
    rows = np.arange(len(scores))
    columns, best = np.empty((len(scores), k), np.int64), np.empty((len(scores), k), scores.dtype)
    for q in range(k):
        columns[:, q] = arg_best(scores, axis=1)
        best[:, q] = scores[rows, columns[:, q]]
        scores[rows, columns[:, q]] = worst
    return columns, best


def _nearest_by_similarity(a: np.ndarray, b: np.ndarray, a_sq: np.ndarray, b_sq: np.ndarray, block: int,
                           candidates: int = 2, mutual: bool = True):
    """`_nearest_both_ways` for unit rows of a (RootSIFT): ‖a_r − b_c‖² = ‖a_r‖² + ‖b_c‖² − 2 a_r·b_c, so the
    nearest c of row r maximises h = a_r·b_c − ½‖b_c‖² and, with ‖a_r‖ = 1, the nearest r of column c maximises
    the same h. The matrix product is then the only full pass besides the reductions (column maxima unless
    `mutual` is off, one row maximum per candidate; the distance form needs three more passes; the offset pass is
    skipped when b's rows are unit too)."""
    b_unit = np.allclose(b_sq, 1.0, rtol=0.0, atol=_UNIT_NORM_TOLERANCE)
    half_b = (np.float32(0.5) * b_sq).astype(np.float32)
    nn = np.empty((len(a), candidates), np.int64)
    h = np.empty((len(a), candidates), np.float32)
    col_max = np.full(len(b), -np.inf, np.float32)
    # bᵀ copied once per pair: OpenBLAS's kernel on a contiguous right operand is 15-20% faster than on the
    # transposed view, at the cost of one (dims, len(b)) copy (README, "Third speed pass")
    b_t = np.ascontiguousarray(b.T)
    for s in range(0, len(a), block):
        sim = a[s:s + block] @ b_t
        if not b_unit:
            sim -= half_b[None, :]
        if mutual:
            np.maximum(col_max, sim.max(axis=0), out=col_max)
        nn[s:s + block], h[s:s + block] = _k_best(sim, np.argmax, -np.inf, candidates)
    offset = np.where(b_unit, 0.5, 0.0).astype(np.float32)  # h lacks the −½‖b‖² = −½ term when b is unit
    d2 = a_sq[:, None] - 2.0 * (h - offset)
    return nn, np.maximum(d2, 0.0), h >= col_max[nn]


def quantize(desc: np.ndarray) -> np.ndarray:
    """int8 round(127 x) of projected unit descriptors (`project_descriptors`): the int8 search's operands."""
    return np.rint(np.asarray(desc, np.float32) * np.float32(INT8_SCALE)).astype(np.int8)


@cache
def _int8_session():
    """An onnxruntime session of one MatMulInteger, run on the calling thread (None without onnxruntime)."""
    try:  # int8 products on the CPU's integer dot-product kernels; imported here, not at start-up (0.25 s)
        import onnxruntime
    except ImportError:  # the same scores from float32 products, slower
        return None
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1  # the stages parallelise over pairs themselves
    return onnxruntime.InferenceSession(_MATMUL_INTEGER_ONNX, options, providers=["CPUExecutionProvider"])


def _nearest_on_int8(a: np.ndarray, b: np.ndarray, block: int, candidates: int) -> np.ndarray:
    """(len(a), candidates) the rows of b with the largest integer products with each row of a (int8 `quantize`d
    unit rows: the nearest first, ties to the lower index), in row blocks.

    The products run on onnxruntime's integer kernels (VNNI: a third of the float32 product's time at 32
    dimensions), else as float32 products of the same integers: sums of at most 128 products of at most 127² are
    exact in float32 (below 2²⁴), so both give the same scores and the same neighbours."""
    session = _int8_session()
    b_t = np.ascontiguousarray(b.T)
    if session is None:
        rows, columns = a.astype(np.float32), b_t.astype(np.float32)
        product, worst = (lambda r: r @ columns), -np.inf  # noqa: E731
    else:
        rows = a.view(np.uint8) ^ np.uint8(128)  # uint8 with zero point 128: the kernel's u8 x s8 form
        product, worst = (lambda r: session.run(None, {"A": r, "B": b_t})[0]), np.iinfo(np.int32).min  # noqa: E731
    nn = np.empty((len(a), candidates), np.int64)
    for s in range(0, len(a), block):
        nn[s:s + block], _ = _k_best(product(rows[s:s + block]), np.argmax, worst, candidates)
    return nn


def _is_unit(x: np.ndarray) -> bool:
    return bool(np.allclose(np.einsum("ij,ij->i", x, x), 1.0, rtol=0.0, atol=_UNIT_NORM_TOLERANCE))


def _rescore(nn: np.ndarray, full_i: np.ndarray, full_j: np.ndarray, rows: int = RESCORE_ROWS
             ) -> tuple[np.ndarray, np.ndarray]:
    """Each row's candidates (found on projected descriptors) re-ranked by their full squared distances: the two
    nearest (N, 2) and those distances. The ratio test then compares true distances, and the nearest is the true
    nearest whenever it was among the candidates. Taken `rows` rows at a time: each row's sums are the same bits
    whatever the chunk, and the chunk's temporary stays in cache."""
    d_full = np.empty(nn.shape, np.float32)
    for s in range(0, len(nn), rows):
        diff = full_j[nn[s:s + rows]]  # (rows, k, dims), worked in place: one temporary instead of three
        diff -= full_i[s:s + rows, None, :]
        diff *= diff
        d_full[s:s + rows] = diff.sum(axis=2, dtype=np.float32)
    order = np.argsort(d_full, axis=1, kind="stable")[:, :2]
    return np.take_along_axis(nn, order, axis=1), np.take_along_axis(d_full, order, axis=1)


def _mutual_after_rescore(rows: np.ndarray, nearest: np.ndarray, desc_i, desc_j, full_i, full_j, block: int,
                          candidates: int, quantized: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(len(rows),) whether row r of i is the nearest, by full distance, of its nearest `nearest[r]` in j.

    The projected search's column maxima judge the mutual check on projected distances, which at few dimensions
    rejects true mutual matches (on 360_Flat at 32 dimensions all of the matches it lost against the full search
    were lost there). Instead, the columns that rows still in the running chose are searched back, on projected
    descriptors with their `candidates` nearest re-ranked by full distances, like the rows (on the `quantize`d
    descriptors (of i, of j) when given, as the rows were)."""
    columns, back = np.unique(nearest, return_inverse=True)
    k = min(candidates, len(desc_i))
    if quantized is not None:
        nn = _nearest_on_int8(quantized[1][columns], quantized[0], block, k)
    else:
        nn, _, _ = _nearest_both_ways(desc_j[columns], desc_i, block, None, k, mutual=False)
    best_row, _ = _rescore(nn, full_j[columns], full_i)
    return best_row[back, 0] == rows


def match_descriptors(desc_i: np.ndarray, desc_j: np.ndarray, options: MatchesOptions, *,
                      block_rows: int = BLOCK_ROWS, allowed=None, full=None,
                      rerank_candidates: int | None = None, ratio: float | None = None, with_ratios: bool = False):
    """(M, 2) int array of (feature in i, feature in j) passing the ratio test (and the mutual check), ordered from
    the most distinctive match (smallest ratio) to the least. With `allowed` (see `_nearest_both_ways`) the
    neighbours, the ratio test and the mutual check are taken among the allowed candidates only. With `full` =
    (full descriptors of i, of j), desc_i / desc_j are their projections (`project_descriptors`): the search runs on
    them, each row's `rerank_candidates` nearest are re-ranked by full distances (`_rescore`), and the mutual check
    searches back from the chosen features of j the same way (`_mutual_after_rescore`). On unit rows with
    `options.int8_search` the search multiplies their `quantize`d coordinates (`_nearest_on_int8`), with
    `INT8_RERANK_CANDIDATES` candidates unless `rerank_candidates` is given. `ratio` replaces `options.ratio` in
    the ratio test (a noisy pair's, `ratio_for_pair`). With `with_ratios`, also the (M,)
    distance ratios (nearest / second nearest) of the matches, ascending."""
    if len(desc_i) < 2 or len(desc_j) < 2:
        empty = np.zeros((0, 2), np.int64)
        return (empty, np.zeros(0)) if with_ratios else empty
    desc_i = np.ascontiguousarray(desc_i, np.float32)
    desc_j = np.ascontiguousarray(desc_j, np.float32)
    quantized = None
    if full is not None and allowed is None and options.int8_search and _is_unit(desc_i) and _is_unit(desc_j):
        quantized = quantize(desc_i), quantize(desc_j)
    if rerank_candidates is None:
        rerank_candidates = RERANK_CANDIDATES if quantized is None else INT8_RERANK_CANDIDATES
    candidates = 2 if full is None else max(2, min(rerank_candidates, len(desc_j)))
    if quantized is not None:
        nn = _nearest_on_int8(*quantized, block_rows, candidates)
    else:
        nn, d2, mutual = _nearest_both_ways(desc_i, desc_j, block_rows, allowed, candidates, mutual=full is None)
    if full is not None:
        full_i, full_j = (np.asarray(f, np.float32) for f in full)
        nn, d2 = _rescore(nn, full_i, full_j)
    with np.errstate(invalid="ignore"):  # inf second distances: a single candidate passes the ratio test
        bound = options.ratio if ratio is None else ratio
        keep = np.isfinite(d2[:, 0]) & (d2[:, 0] < (bound**2) * d2[:, 1])
    if options.mutual and full is None:
        keep &= mutual[:, 0]
    elif options.mutual and keep.any():
        running = np.flatnonzero(keep)
        keep[running] = _mutual_after_rescore(running, nn[running, 0], desc_i, desc_j, full_i, full_j, block_rows,
                                              candidates, quantized)
    rows = np.flatnonzero(keep)
    # Most distinctive first (smallest distance ratio): robust estimation samples the head more often.
    squared_ratios = d2[rows, 0] / np.maximum(d2[rows, 1], 1e-30)
    order = np.argsort(squared_ratios, kind="stable")
    matches = np.column_stack([rows[order], nn[rows[order], 0]])
    return (matches, np.sqrt(squared_ratios[order])) if with_ratios else matches


def epipolar_candidates(b_i: np.ndarray, b_j: np.ndarray, F: np.ndarray, threshold_rad: float):
    """`allowed` for guided matching: feature k of i may match the features of j within `threshold_rad` of its
    epipolar great circle (b_iᵀ F b_j = 0)."""
    normals = (b_i @ F).astype(np.float32)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    b_j32, limit = b_j.astype(np.float32).T, np.float32(np.sin(threshold_rad))
    return lambda start, stop: np.abs(normals[start:stop] @ b_j32) <= limit
