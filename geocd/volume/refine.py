"""Adaptive refinement (Crispell et al. eq. 26).

A leaf is split into its 8 children when its largest possible occlusion
probability ``P(Q_max) = 1 - exp(-ℓ_max α)``, with ``ℓ_max`` the cell diagonal,
exceeds a threshold. Children inherit the parent's α (a density: it does not
depend on the cell size) and appearance. New nodes are appended to the flat
arrays, so existing node indices never change.
"""

from __future__ import annotations

import math

import numpy as np

from .scene import VolumeModel


def cells_to_split(model: VolumeModel, threshold: float | None = None) -> np.ndarray:
    """Indices of the leaves eq. 26 would split (below the finest level)."""
    thr = model.params.refine_threshold if threshold is None else float(threshold)
    g = model.geometry
    leaf = (model.child < 0) & (model.level < g.max_depth)
    idx = np.nonzero(leaf)[0]
    if idx.size == 0:
        return idx
    size = g.block_size_m / (2.0 ** model.level[idx].astype(np.float64))
    p_max = -np.expm1(-math.sqrt(3.0) * size * model.alpha[idx].astype(np.float64))
    return idx[p_max > thr]


def refine_model(model: VolumeModel, threshold: float | None = None, max_new_nodes: int | None = None) -> int:
    """Split every leaf whose ``P(Q_max)`` exceeds ``threshold`` (default: the model's); in place.

    Parameters
    ----------
    max_new_nodes : int, optional
        Cap on the nodes added in this call (the leaves with the largest α are
        split first); protects memory on a badly initialised model.

    Returns
    -------
    int
        Number of leaves split.
    """
    idx = cells_to_split(model, threshold)
    if idx.size == 0:
        return 0
    if max_new_nodes is not None and 8 * idx.size > max_new_nodes:
        order = np.argsort(-model.alpha[idx], kind="stable")
        idx = np.sort(idx[order[: max(max_new_nodes // 8, 0)]])
        if idx.size == 0:
            return 0
    return split_leaves(model, idx)


def split_leaves(model: VolumeModel, idx: np.ndarray) -> int:
    """Split the given leaves (below the finest level) into 8 children inheriting α and appearance; in place."""
    idx = np.asarray(idx, dtype=np.int64)
    idx = idx[(model.child[idx] < 0) & (model.level[idx] < model.geometry.max_depth)]
    if idx.size == 0:
        return 0
    n_old = model.child.size
    k = idx.size
    parent = np.repeat(idx, 8)
    model.child[idx] = (n_old + 8 * np.arange(k)).astype(np.int32)
    model.child = np.concatenate([model.child, np.full(8 * k, -1, dtype=np.int32)])
    model.level = np.concatenate([model.level, (model.level[parent] + 1).astype(np.uint8)])
    model.alpha = np.concatenate([model.alpha, model.alpha[parent]])
    model.app = np.concatenate([model.app, model.app[parent]])
    return int(k)


def compact_model(model: VolumeModel) -> int:
    """Drop unreachable nodes and renumber (each block breadth-first); in place. Returns nodes removed."""
    from . import _kernels as K

    order, new_child, new_root = K.compact_order(model.block_root, model.child)
    removed = model.child.size - order.size
    if removed == 0 and np.array_equal(order, np.arange(order.size)):
        return 0
    model.child = new_child
    model.block_root = new_root
    model.level = model.level[order]
    model.alpha = model.alpha[order]
    model.app = model.app[order]
    return int(removed)


def coarsen_model(model: VolumeModel, threshold: float | None = None, max_rounds: int = 8) -> int:
    """Merge sibling leaves that eq. 26 would not split at their parent's size, then compact.

    The inverse of refinement, with hysteresis (``threshold`` defaults to half the
    split threshold): free space that an early, greedy update refined is given
    back once later images have lowered its density. α is a density, so the
    parent takes the children's mean. Returns the number of merges.
    """
    from . import _kernels as K

    thr = 0.5 * model.params.refine_threshold if threshold is None else float(threshold)
    total = 0
    for _ in range(max_rounds):
        n = K.merge_pass(model.child, model.level, model.alpha, model.app, model.geometry.block_size_m, thr)
        total += n
        if n == 0:
            break
    if total:
        compact_model(model)
    return int(total)
