"""Order-preserving alignment of two sequences (dynamic time warping where each row of a cost
table takes one column), in linear time and memory for long sequences.

A table of m x q costs is never formed when m q is large: the alignment of the sequences
subsampled by two (recursively) gives a band around which the full-resolution alignment is
searched (coarse to fine, as FastDTW). Tables up to ``FULL_TABLE`` entries are solved whole.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

FULL_TABLE = 64 * 64
"""Largest cost table (rows x columns) aligned whole; longer sequences go coarse to fine."""
RADIUS = 2
"""Columns searched beyond the coarse alignment's band on either side, at every level."""

CostFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``cost(rows, cols)``: the costs of rows (m, 1) against columns (m, w) or (1, q), broadcast."""


def monotone_assignment(cost: np.ndarray) -> np.ndarray:
    """Assign every row of cost (m, q) one column, columns never decreasing, minimum total cost.

    Dynamic time warping where each row takes exactly one column. Returns (m,) column indices.
    """
    return banded_assignment(cost, np.zeros(cost.shape[0], dtype=np.int64))


def banded_assignment(cost: np.ndarray, lo: np.ndarray) -> np.ndarray:
    """:func:`monotone_assignment` restricted to a band: row i may take columns
    ``lo[i] .. lo[i] + w - 1`` with costs ``cost[i]`` (m, w); ``lo`` never decreasing, inf marks
    a column outside the band. Returns (m,) column indices (of the full table)."""
    m, w = cost.shape
    acc = np.empty_like(cost, dtype=np.float64)
    back = np.empty((m, w), dtype=np.int64)
    acc[0] = cost[0]
    k = np.arange(w)
    for i in range(1, m):
        prev_best = np.minimum.accumulate(acc[i - 1])
        # argmin over k' <= k of acc[i-1]: where the running minimum was last lowered
        is_new = np.concatenate([[True], acc[i - 1, 1:] < prev_best[:-1]])
        prev_arg = np.maximum.accumulate(np.where(is_new, k, 0))
        # column lo[i] + j sees the previous row's window up to its own column
        reach = np.minimum(lo[i] - lo[i - 1] + k, w - 1)
        back[i] = prev_arg[reach]
        acc[i] = cost[i] + prev_best[reach]
    path = np.empty(m, dtype=np.int64)
    path[-1] = int(np.argmin(acc[-1]))
    for i in range(m - 1, 0, -1):
        path[i - 1] = back[i, path[i]]
    return lo + path


def align(cost: CostFn, m: int, q: int, *, full_table: int = FULL_TABLE) -> np.ndarray:
    """(m,) non-decreasing columns of q aligning m rows at minimum total ``cost`` (see
    :data:`CostFn`; non-finite costs are replaced by ten times the largest finite one plus one,
    so that they are taken only where nothing else is). Exact (:func:`monotone_assignment`) up to
    ``full_table`` entries; beyond, coarse to fine: the rows and columns subsampled by two are
    aligned first and the full resolution is searched within :data:`RADIUS` columns of that
    alignment's band, so time and memory grow as (m + q) times the band's width."""
    rows = np.arange(m)[:, None]
    if m * q <= full_table or m < 4 or q < 4:
        return monotone_assignment(_finite(cost(rows, np.arange(q)[None, :])))

    def coarse_cost(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        return cost(2 * r, 2 * c)

    coarse = 2 * align(coarse_cost, (m + 1) // 2, (q + 1) // 2, full_table=full_table)
    half = np.minimum(np.arange(m) // 2, coarse.size - 1)
    before = coarse[np.maximum(half - 1, 0)]
    after = coarse[np.minimum(half + 1, coarse.size - 1)]
    lo = np.maximum(before - RADIUS, 0)
    hi = np.minimum(after + 1 + RADIUS, q - 1)
    w = int((hi - lo).max()) + 1
    cols = lo[:, None] + np.arange(w)[None, :]
    inside = cols <= hi[:, None]
    table = cost(rows, np.minimum(cols, q - 1))
    table = np.where(inside, _finite(np.where(inside, table, np.nan)), np.inf)
    return banded_assignment(table, lo)


def _finite(cost: np.ndarray) -> np.ndarray:
    """Non-finite costs replaced by ten times the largest finite cost plus one."""
    finite = np.isfinite(cost)
    if finite.all():
        return cost
    big = 10.0 * np.max(cost[finite]) + 1.0 if finite.any() else 1.0
    return np.where(finite, cost, big)
