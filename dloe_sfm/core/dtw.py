"""Order-preserving alignment of two sequences (dynamic time warping where each row of a cost
table takes one column), in linear time and memory for long sequences.

A table of m x q costs is never formed when m q is large: the alignment of the sequences
subsampled by two (recursively) gives a band around which the full-resolution alignment is
searched (coarse to fine, as FastDTW). Tables up to ``FULL_TABLE`` entries are solved whole.
Many independent alignments are solved together (:func:`align_many`), level by level, each
level's row recursion running once over all of them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

FULL_TABLE = 64 * 64
"""Largest cost table (rows x columns) aligned whole; longer sequences go coarse to fine."""
RADIUS = 2
"""Columns searched beyond the coarse alignment's band on either side, at every level."""
BLOCK = 2**16
"""Numbers per temporary a cost wrapped by :func:`in_blocks` forms at a time: small blocks stay
in cache, large fresh arrays cost page faults."""
MIN_STACK_WIDTH = 32
"""Tables up to this many columns are stacked together whatever their widths; wider ones with
tables of widths within a factor two (padding costs memory and time in proportion)."""

CostFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``cost(rows, cols)``: the costs of rows (m, 1) against columns (m, w) or (1, q), broadcast."""


def banded_assignment(costs: Sequence[np.ndarray], lows: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Assign every row of each table one column, columns never decreasing, minimum total cost
    (dynamic time warping where each row takes exactly one column), within bands: row i of a
    table may take columns ``lo[i] .. lo[i] + w - 1`` with costs ``cost[i]`` (m, w); ``lo`` never
    decreasing (all 0 for a whole table), inf marks a column outside the band. Returns the (m,)
    column indices (of the full table) of every table. Tables of similar widths are padded to
    one stack and solved together."""
    groups: dict[int, list[int]] = {}
    for j, cost in enumerate(costs):
        groups.setdefault((max(cost.shape[1], MIN_STACK_WIDTH) - 1).bit_length(), []).append(j)
    paths: list[np.ndarray] = [np.empty(0, dtype=np.int64)] * len(costs)
    for group in groups.values():
        for j, path in zip(group, _stacked_assignment([costs[j] for j in group],
                                                      [lows[j] for j in group]), strict=True):
            paths[j] = path
    return paths


def _stacked_assignment(costs: list[np.ndarray], lows: list[np.ndarray]) -> list[np.ndarray]:
    """:func:`banded_assignment` of tables padded to one (M, P, W) stack: inf costs beyond a
    table's columns (never the running minimum, so every table's result is its own), rows beyond
    its last repeat its last ``lo`` and are never traced back."""
    p = len(costs)
    last = np.array([c.shape[0] - 1 for c in costs])
    rows, w = int(last.max()) + 1, max(c.shape[1] for c in costs)
    cost = np.full((rows, p, w), np.inf)
    lo = np.empty((rows, p), dtype=np.int64)
    for j, (c, low) in enumerate(zip(costs, lows, strict=True)):
        cost[: c.shape[0], j, : c.shape[1]] = c
        lo[:, j] = low[np.minimum(np.arange(rows), last[j])]
    acc = np.empty_like(cost)
    back = np.empty((rows, p, w), dtype=np.int64)
    acc[0] = cost[0]
    k = np.arange(w)
    first = np.ones((p, 1), dtype=bool)
    for i in range(1, rows):
        prev_best = np.minimum.accumulate(acc[i - 1], axis=1)
        # argmin over k' <= k of acc[i-1]: where the running minimum was last lowered
        is_new = np.concatenate([first, acc[i - 1, :, 1:] < prev_best[:, :-1]], axis=1)
        prev_arg = np.maximum.accumulate(np.where(is_new, k, 0), axis=1)
        # column lo[i] + j sees the previous row's window up to its own column
        reach = np.minimum((lo[i] - lo[i - 1])[:, None] + k, w - 1)
        back[i] = np.take_along_axis(prev_arg, reach, axis=1)
        acc[i] = cost[i] + np.take_along_axis(prev_best, reach, axis=1)
    tables = np.arange(p)
    end = np.argmin(acc[last, tables], axis=1)
    path = np.empty((rows, p), dtype=np.int64)
    col = end
    for i in range(rows - 1, -1, -1):
        col = np.where(last == i, end, col)
        path[i] = col
        if i:
            col = back[i, tables, col]
    return [lo[: n + 1, j] + path[: n + 1, j] for j, n in enumerate(last)]


def align_many(
    problems: Sequence[tuple[CostFn, int, int]], *, full_table: int = FULL_TABLE
) -> list[np.ndarray]:
    """For every ``(cost, m, q)`` (m >= 1 rows): the (m,) non-decreasing columns of q aligning m
    rows at minimum total ``cost`` (see :data:`CostFn`; non-finite costs are replaced by ten times
    the largest finite one plus one, so that they are taken only where nothing else is). Exact
    up to ``full_table`` entries; beyond, coarse to fine: the rows and columns subsampled by two
    are aligned first and the full resolution is searched within :data:`RADIUS` columns of that
    alignment's band, so time and memory grow as (m + q) times the band's width. All problems
    together, level by level: the whole tables of a level in one stack and the bands in another
    (:func:`banded_assignment`)."""
    is_whole = [m * q <= full_table or m < 4 or q < 4 for _, m, q in problems]
    whole = [j for j, w in enumerate(is_whole) if w]
    fine = [j for j, w in enumerate(is_whole) if not w]
    paths: list[np.ndarray] = [np.empty(0, dtype=np.int64)] * len(problems)
    tables = [
        _finite(cost(np.arange(m)[:, None], np.arange(q)[None, :]))
        for cost, m, q in (problems[j] for j in whole)
    ]
    lows = [np.zeros(t.shape[0], dtype=np.int64) for t in tables]
    for j, path in zip(whole, banded_assignment(tables, lows), strict=True):
        paths[j] = path
    if not fine:
        return paths
    coarse = align_many(
        [(_subsampled(cost), (m + 1) // 2, (q + 1) // 2) for cost, m, q in
         (problems[j] for j in fine)],
        full_table=full_table,
    )
    bands = [_band(*problems[j], 2 * c) for j, c in zip(fine, coarse, strict=True)]
    for j, path in zip(fine, banded_assignment(*zip(*bands, strict=True)), strict=True):
        paths[j] = path
    return paths


def in_blocks(cost: CostFn, size: int) -> CostFn:
    """``cost`` evaluated a block of rows at a time, ``size`` numbers per entry (the length of the
    vectors an entry's cost is computed from): the same costs, from temporaries of about
    :data:`BLOCK` numbers. The rows are (m,) or (m, 1) (any :data:`CostFn`'s)."""

    def blocked(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        shape = np.broadcast_shapes(rows.shape, cols.shape)
        cols = np.broadcast_to(cols, shape)
        out = np.empty(shape)
        step = max(BLOCK // max(math.prod(shape[1:]) * size, 1), 1)
        for r in range(0, shape[0], step):
            out[r:r + step] = cost(rows[r:r + step], cols[r:r + step])
        return out

    return blocked


def _subsampled(cost: CostFn) -> CostFn:
    """``cost`` of the rows and columns subsampled by two."""

    def coarse_cost(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        return cost(2 * r, 2 * c)

    return coarse_cost


def _band(cost: CostFn, m: int, q: int, coarse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Costs (m, w) and first columns (m,) of the band within :data:`RADIUS` columns of the
    coarse alignment's band (``coarse``: the half-resolution path in full-resolution columns)."""
    half = np.minimum(np.arange(m) // 2, coarse.size - 1)
    before = coarse[np.maximum(half - 1, 0)]
    after = coarse[np.minimum(half + 1, coarse.size - 1)]
    lo = np.maximum(before - RADIUS, 0)
    hi = np.minimum(after + 1 + RADIUS, q - 1)
    w = int((hi - lo).max()) + 1
    cols = lo[:, None] + np.arange(w)[None, :]
    inside = cols <= hi[:, None]
    table = cost(np.arange(m)[:, None], np.minimum(cols, q - 1))
    return np.where(inside, _finite(np.where(inside, table, np.nan)), np.inf), lo


def _finite(cost: np.ndarray) -> np.ndarray:
    """Non-finite costs replaced by ten times the largest finite cost plus one."""
    finite = np.isfinite(cost)
    if finite.all():
        return cost
    big = 10.0 * np.max(cost[finite]) + 1.0 if finite.any() else 1.0
    return np.where(finite, cost, big)
