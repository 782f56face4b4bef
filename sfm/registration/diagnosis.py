"""Why an image is not registered: the reason a user can act on, from the view graph and the pair statistics."""

from __future__ import annotations

import numpy as np

from fullview.sfm.registration.view_graph import component_labels


def unregistered_reasons(*, names: list[str], registered: np.ndarray, num_features: np.ndarray, pairs: np.ndarray,
                         num_inliers: np.ndarray, usable: np.ndarray, no_baseline: np.ndarray,
                         min_features: int, min_inliers: int) -> dict[str, str]:
    """For every unregistered image, one of: too few features; no usable pair (only pairs without baseline, or too
    few inliers); a separate group of the verified-pair graph (which images); rejected as inconsistent."""
    labels = component_labels(len(names), pairs, usable)
    model_labels = set(labels[registered].tolist())
    reasons = {}
    for k in np.flatnonzero(~registered):
        touching = (pairs == k).any(axis=1)
        if num_features[k] < min_features:
            reasons[names[k]] = f"too few features ({int(num_features[k])})"
        elif not (usable & touching).any():
            reasons[names[k]] = _no_pair_reason(touching, num_inliers, no_baseline, min_inliers)
        elif labels[k] not in model_labels:
            group = [names[j] for j in np.flatnonzero(labels == labels[k])]
            reasons[names[k]] = (f"in a separate group of {len(group)} image(s) joined by verified pairs to each "
                                 f"other but not to the model: {', '.join(group)}")
        else:
            reasons[names[k]] = "rejected as inconsistent by registration (its pairs disagree with the model)"
    return reasons


def _no_pair_reason(touching: np.ndarray, num_inliers: np.ndarray, no_baseline: np.ndarray, min_inliers: int) -> str:
    if (no_baseline & touching).any() and not (num_inliers[touching & ~no_baseline] >= min_inliers).any():
        return "no verified pair: its matching images show it from the same place (no baseline)"
    strong = int((touching & (num_inliers >= min_inliers)).sum())
    if strong:
        return (f"its {strong} verified pair(s) give no valid relative pose (too few inliers in front of both "
                "cameras: epipoles.min_cheiral_ratio)")
    best = int(num_inliers[touching].max()) if touching.any() else 0
    return f"no verified pair with >= {min_inliers} inliers (best: {best})"


def pairs_toward_main(*, pairs: np.ndarray, num_raw: np.ndarray, model_id: np.ndarray, model: int, main: int = 0,
                      count: int = 3) -> list[tuple[int, int, int]]:
    """Up to ``count`` pairs (image of ``model``, image of ``main``, raw matches) between two models with the most raw
    matches, most first: where a user can add hand points to join the models (a doorway pair has 30-40 raw matches,
    about a quarter of them true, too few to verify alone; 8 hand points across it verify it)."""
    i, j = pairs[:, 0], pairs[:, 1]
    across = ((model_id[i] == model) & (model_id[j] == main)) | ((model_id[i] == main) & (model_id[j] == model))
    order = np.flatnonzero(across & (num_raw > 0))
    order = order[np.argsort(-num_raw[order], kind="stable")][:count]
    return [(int(i[k]), int(j[k]), int(num_raw[k])) if model_id[i[k]] == model else (int(j[k]), int(i[k]),
                                                                                      int(num_raw[k]))
            for k in order]
