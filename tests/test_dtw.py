"""Order-preserving alignment (core.dtw) and the DTW placement of one stream on another's
polyline (core.sequencing.dtw_positions)."""

import numpy as np
import pytest

from dloe_sfm.core.dtw import align_many, banded_assignment, in_blocks
from dloe_sfm.core.sequencing import dtw_positions


def whole(cost: np.ndarray) -> np.ndarray:
    """The exact assignment of a whole (m, q) table."""
    return banded_assignment([cost], [np.zeros(cost.shape[0], dtype=np.int64)])[0]


def align(cost, m: int, q: int, *, full_table: int) -> np.ndarray:
    """One problem alone."""
    return align_many([(cost, m, q)], full_table=full_table)[0]


def optimum(cost: np.ndarray) -> float:
    """Least total cost of a non-decreasing column per row of (m, q) ``cost`` (inf allowed)."""
    acc = cost[0]
    for row in cost[1:]:
        acc = row + np.minimum.accumulate(acc)
    return float(acc.min())


def replaced(cost: np.ndarray) -> np.ndarray:
    """``cost`` with non-finite entries as ``align_many`` takes them."""
    finite = np.isfinite(cost)
    return np.where(finite, cost, 10 * cost[finite].max() + 1 if finite.any() else 1.0)


def path_cost(cost: np.ndarray, path: np.ndarray) -> float:
    assert path.shape == (cost.shape[0],) and (np.diff(path) >= 0).all()
    assert path.min() >= 0 and path.max() < cost.shape[1]
    return float(cost[np.arange(cost.shape[0]), path].sum())


def curve(u: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(3 * u), np.sin(3 * u), u], axis=1)


def test_whole_table_assignment_respects_order(rng):
    cost = rng.random((30, 20))
    path = whole(cost)
    assert (np.diff(path) >= 0).all()
    # brute-force check of optimality on a tiny instance
    small = rng.random((4, 3))
    best = min(
        (sum(small[i, c[i]] for i in range(4)), c)
        for c in np.array(np.meshgrid(*[range(3)] * 4)).reshape(4, -1).T
        if (np.diff(c) >= 0).all()
    )
    p = whole(small)
    assert abs(small[np.arange(4), p].sum() - best[0]) < 1e-12


def test_banded_assignment_of_many_bands_is_each_bands_optimum(rng):
    # bands of mixed lengths and widths (one stack per width class, padded): every table's
    # path is its own optimum, and the one it gets alone
    costs, lows, tables = [], [], []
    for m, w in [(1, 1), (1, 5), (2, 3), (7, 1), (40, 6), (25, 9), (60, 3), (3, 40), (12, 70)]:
        cost = rng.random((m, w))
        cost[rng.random((m, w)) < 0.2] = np.inf
        cost[:, 0] = rng.random(m)  # a finite path exists
        lo = np.sort(rng.integers(0, 5, m))
        full = np.full((m, lo[-1] + w), np.inf)
        for i in range(m):
            full[i, lo[i]:lo[i] + w] = cost[i]
        costs.append(cost)
        lows.append(lo)
        tables.append(full)
    paths = banded_assignment(costs, lows)
    for cost, lo, full, path in zip(costs, lows, tables, paths, strict=True):
        assert path_cost(full, path) == pytest.approx(optimum(full), rel=1e-12)
        assert np.array_equal(path, banded_assignment([cost], [lo])[0])


def random_problem(rng: np.random.Generator, m: int, q: int, kind: str):
    """(cost function, m, q, table): smooth costs (two samplings of a curve) or random ones,
    optionally with inf entries."""
    if kind == "random":
        table = rng.random((m, q))
    else:
        A = curve(np.sort(rng.uniform(0, 1, m)))
        B = curve(np.linspace(0, 1, q))
        table = np.linalg.norm(A[:, None] - B[None], axis=2)
    if kind == "inf":
        table[rng.random((m, q)) < 0.05] = np.inf
        table[:, min(3, q - 1)] = np.inf

    def cost(i, j):
        return table[i, j]

    return cost, m, q, table


SIZES = [(1, 1), (1, 30), (30, 1), (3, 200), (200, 3), (2, 2), (5, 4), (4, 5), (60, 60), (64, 64),
         (65, 64), (90, 40), (300, 170), (170, 300), (513, 77), (8, 1000)]


@pytest.mark.parametrize("full_table", [64, 64 * 64])
def test_align_many_equals_align_one_at_a_time(rng, full_table):
    # whole tables and coarse-to-fine bands of mixed sizes in one batch: each path is exactly
    # the one its problem gets alone, and whole tables are solved exactly
    problems = [random_problem(rng, m, q, kind) for m, q in SIZES
                for kind in ("smooth", "random", "inf")]
    paths = align_many([p[:3] for p in problems], full_table=full_table)
    for (cost, m, q, table), path in zip(problems, paths, strict=True):
        assert np.array_equal(path, align(cost, m, q, full_table=full_table))
        if m * q <= full_table or m < 4 or q < 4:
            full = replaced(table)
            assert path_cost(full, path) == pytest.approx(optimum(full), rel=1e-12)
        else:
            path_cost(table, path)  # a valid path
    assert align_many([]) == []


def test_in_blocks_gives_the_same_costs(rng, monkeypatch):
    from dloe_sfm.core import dtw

    monkeypatch.setattr(dtw, "BLOCK", 50)  # blocks of a few rows
    table = rng.random((37, 23))

    def cost(i, j):
        return table[i, j]

    blocked = in_blocks(cost, 3)
    rows = np.arange(37)[:, None]
    cols = np.minimum(np.arange(37)[:, None] // 2 + np.arange(5)[None, :], 22)
    assert np.array_equal(blocked(rows, cols), table[rows, cols])
    assert np.array_equal(blocked(rows, np.arange(23)[None, :]), table)
    assert np.array_equal(blocked(np.arange(37), cols[:, 0]), table[np.arange(37), cols[:, 0]])


def test_align_coarse_to_fine_matches_the_whole_table(rng):
    # two samplings of one curve at different rates and offsets: the coarse-to-fine alignment
    # (tables of at most 64 entries) finds the exact DTW path of the whole table
    def curve(u):
        return np.stack([np.cos(5 * u), np.sin(3 * u), u], axis=1)

    A = curve(np.sort(rng.uniform(0.05, 0.95, 300)))
    B = curve(np.linspace(0, 1, 170))
    d = np.linalg.norm(A[:, None] - B[None], axis=2)

    def cost(i, j):
        return d[i, j]

    exact = whole(d)
    assert np.array_equal(align(cost, 300, 170, full_table=64), exact)
    assert np.array_equal(align(cost, 300, 170, full_table=300 * 170), exact)  # whole table
    # a non-finite cost is taken only where nothing else is
    d[:, 10] = np.inf
    assert not (align(cost, 300, 170, full_table=64) == 10).any()


def test_dtw_positions_long_streams_in_a_band():
    s = np.linspace(0, 1, 400)
    B = curve(s)
    A = curve(np.linspace(0.001, 0.999, 700))  # 700 x 399 > dtw.FULL_TABLE: coarse to fine
    (pos,) = dtw_positions([(A, B)])
    arc_b = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(B, axis=0), axis=1))])
    true = np.interp(np.linspace(0.001, 0.999, 700), s, arc_b)
    assert (np.diff(pos) >= 0).all()
    assert np.abs(pos - true).max() < 1e-4 * arc_b[-1]


def test_dtw_positions_on_a_shared_curve():
    s = np.linspace(0, 1, 40)
    B = curve(s)
    A = curve(s[:-1] + 0.5 / 39)  # interleaved samples of the same curve
    (pos,) = dtw_positions([(A, B)])
    assert (np.diff(pos) > 0).all()
    arc_b = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(B, axis=0), axis=1))])
    mid = 0.5 * (arc_b[:-1] + arc_b[1:])
    assert np.abs(pos - mid).max() < 1e-3


def test_dtw_positions_of_many_pairs_equal_one_at_a_time(rng):
    # whole tables (matrix products), bands (point-to-segment feet) and a stuttering polyline
    # (repeated shapes: zero-length segments) in one batch
    stutter = curve(np.repeat(np.linspace(0, 1, 30), 2))
    pairs = [
        (curve(np.sort(rng.uniform(0, 1, m))) + 0.01 * rng.normal(size=(m, 3)),
         curve(np.sort(rng.uniform(0, 1, q))))
        for m, q in [(1, 2), (3, 500), (50, 40), (700, 400), (120, 90)]
    ] + [(curve(np.sort(rng.uniform(0, 1, 200))), stutter)]
    batch = dtw_positions(pairs)
    for pair, pos in zip(pairs, batch, strict=True):
        assert np.array_equal(pos, dtw_positions([pair])[0])
        length = np.linalg.norm(np.diff(pair[1], axis=0), axis=1).sum()
        assert pos.shape == (pair[0].shape[0],)
        assert (pos >= 0).all() and (pos <= length + 1e-9).all()
