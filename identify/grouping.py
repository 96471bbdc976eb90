"""Grouping table rows by key columns with numpy, in order of first appearance.

The static table's readings repeat per (pose, load, marker); averaging them is a grouped
reduction. ``np.unique(..., return_inverse=True)`` numbers the groups, ``np.bincount`` sums per
group: one pass over the rows, no Python loop per row or per group (benchmarks/bench_identify.py).
"""

from __future__ import annotations

import numpy as np


def first_seen(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(code per row, first row of each code): codes number the distinct values in order of
    first appearance (0 for the first value seen), like ``dict.fromkeys``."""
    values = np.asarray(values)
    if values.size == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    _, first, inverse = np.unique(values, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[inverse.reshape(-1)], first[order]


def combine(*codes: np.ndarray) -> np.ndarray:
    """One integer key per row from several code columns (each 0 <= code < its max + 1)."""
    key = np.zeros(len(codes[0]), dtype=np.int64)
    for c in codes:
        c = np.asarray(c, dtype=np.int64)
        key = key * (int(c.max()) + 1 if c.size else 1) + c
    return key


def group_sum(codes: np.ndarray, values: np.ndarray, n_groups: int) -> np.ndarray:
    """Sum of ``values`` (n,) or (n, k) per group code: (G,) or (G, k)."""
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        return np.bincount(codes, weights=values, minlength=n_groups)
    return np.stack([np.bincount(codes, weights=values[:, j], minlength=n_groups)
                     for j in range(values.shape[1])], axis=1).reshape(n_groups, values.shape[1])


def group_count(codes: np.ndarray, n_groups: int) -> np.ndarray:
    return np.bincount(codes, minlength=n_groups)


def sums_per_group(values: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Sum of all entries of each group of consecutive rows of ``values`` (group sizes
    ``sizes``), each summed as numpy sums that group's own (size, k) array -- pairwise over its
    entries -- so that a result equals a loop over the groups to the last bit."""
    sizes = np.asarray(sizes, dtype=np.intp)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.intp)
    out = np.empty(len(sizes))
    for size in np.unique(sizes):      # one pass per distinct group size (the repeats: one or two)
        which = np.flatnonzero(sizes == size)
        block = values[starts[which][:, None] + np.arange(size)]
        out[which] = np.ascontiguousarray(block).reshape(len(which), -1).sum(axis=1)
    return out
