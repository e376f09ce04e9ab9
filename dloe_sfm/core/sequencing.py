"""Sequencing: the images placed on the streams (DTW), distances between images, the streams'
affine time, orders (docs/method.md, "The steps as implemented"); the line embeddings of a
distance table or of the shapes alone are in :mod:`.embedding`.

Shapes: N images, P points, X (N, P, 3); streams / frames (N,) int.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .dtw import FULL_TABLE, CostFn, align_many, in_blocks
from .options import Distance

THEIL_SEN_POINTS = 256
"""Images of a stream (evenly spaced) the robust line of one stream against another uses
(``affine_time``: Theil-Sen's cost grows as their square)."""
REFERENCE_STREAMS = 8
"""Streams (the longest) every image is placed on (:class:`Placement`); up to this many, every
stream on every other."""
MEDIAN_BLOCK = 2**22
"""Numbers per temporary of :func:`arc_distance`'s medians through the reference lines."""
MDS_SAMPLE = 2000
"""Images the length scale of the affine clocks' prior is measured on
(``alternation.sequence``): a dense table of at most this size with videos."""


def stream_members(streams: np.ndarray, frames: np.ndarray) -> list[np.ndarray]:
    """Image indices of every stream in frame order (streams by id; one sort, not a scan of
    all images per stream: lone photos are streams of their own)."""
    order = np.lexsort((frames, streams))
    _, counts = np.unique(streams, return_counts=True)
    return np.split(order, np.cumsum(counts)[:-1])


def arc_length(F: np.ndarray) -> np.ndarray:
    """Cumulative path length along the rows of F (m, d): (m,), starting at 0."""
    if F.shape[0] == 0:
        return np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(F, axis=0), axis=1))])


def dtw_positions(pairs: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[np.ndarray]:
    """Arc-length position on polyline B of every row of A, assigned in order, for every pair.

    A (m, d) a stream's shapes in frame order, B (q, d) with q >= 2 another stream's polyline.
    Each row of A is assigned to one segment of B, the segment index never decreasing along A
    (dynamic time warping with point-to-segment costs), and placed at the foot of its
    perpendicular on that segment. Tables of up to ``dtw.FULL_TABLE`` entries are aligned whole
    (from matrix products); longer streams coarse to fine, in linear time; all pairs together
    (``dtw.align_many``). Returns (m,) positions in B's arc length for every pair.
    """
    problems, places = [], []
    for A, B in pairs:
        problem, place = _dtw_problem(A, B)
        problems.append(problem)
        places.append(place)
    return [place(path) for place, path in zip(places, align_many(problems), strict=True)]


def _dtw_problem(
    A: np.ndarray, B: np.ndarray
) -> tuple[tuple[CostFn, int, int], Callable[[np.ndarray], np.ndarray]]:
    """The alignment problem of one pair of :func:`dtw_positions`, and its path's positions."""
    seg = np.diff(B, axis=0)  # (q-1, d)
    seg_len2 = (seg**2).sum(axis=1)
    start = B[:-1]
    m = A.shape[0]
    s = arc_length(B)
    if m * seg.shape[0] > FULL_TABLE:
        def foot(i: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """(t, distance) of rows i of A to segments k (broadcast)."""
            rel = A[i] - start[k]
            seg_k = seg[k]
            a_dot_s = np.einsum("...d,...d->...", rel, seg_k)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.nan_to_num(np.clip(a_dot_s / seg_len2[k], 0.0, 1.0))
            gap = rel - t[..., None] * seg_k
            return t, np.sqrt(np.einsum("...d,...d->...", gap, gap))

        def banded(path: np.ndarray) -> np.ndarray:
            return s[path] + foot(np.arange(m), path)[0] * np.sqrt(seg_len2[path])

        return (in_blocks(lambda i, k: foot(i, k)[1], A.shape[1]), m, seg.shape[0]), banded
    # |a - b_k - t s_k|^2 from matrix products, never an (m, q, d) temporary
    a_dot_s = A @ seg.T - (start * seg).sum(axis=1)  # (a - b_k) . s_k
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(a_dot_s / seg_len2, 0.0, 1.0)
    t = np.nan_to_num(t)
    d2 = (A**2).sum(axis=1)[:, None] + (start**2).sum(axis=1)[None] - 2 * A @ start.T
    cost = np.sqrt(np.maximum(d2 - 2 * t * a_dot_s + t**2 * seg_len2, 0.0))  # (m, q-1)

    def whole(path: np.ndarray) -> np.ndarray:
        return s[path] + t[np.arange(m), path] * np.sqrt(seg_len2[path])

    return (lambda i, k: cost[i, k], m, seg.shape[0]), whole


@dataclass
class Placement:
    """Images placed on the streams' polylines (streams of 2+ images) in 3D shape space.

    ``placed[c]``: the images placed on polyline ``lines[c]`` (ascending), ``pos[c]`` their
    arc-length positions on it (its own images at their own arc length, another stream's by
    order-preserving DTW). Every image is placed on the :data:`REFERENCE_STREAMS` longest
    lines (``full``), and their images on every line; with more streams, two others meet only
    through the references, so the placements grow as the streams, not their square.
    """

    lines: list[np.ndarray]
    placed: list[np.ndarray]
    pos: list[np.ndarray]
    full: np.ndarray

    def table(self, images: np.ndarray) -> np.ndarray:
        """(lines, images) positions of ``images`` on every line, NaN where not placed."""
        out = np.full((len(self.lines), images.size), np.nan)
        for c, (placed, pos) in enumerate(zip(self.placed, self.pos, strict=True)):
            at = np.minimum(np.searchsorted(placed, images), placed.size - 1)
            hit = placed[at] == images
            out[c, hit] = pos[at[hit]]
        return out

    def on(self, c: int, images: np.ndarray) -> np.ndarray:
        """Positions on line ``c`` of ``images``, all placed on it."""
        return self.pos[c][np.searchsorted(self.placed[c], images)]


def place_on_streams(X: np.ndarray, streams: np.ndarray, frames: np.ndarray) -> Placement:
    """The DTW placements shared by :func:`arc_distance` and :func:`affine_time`
    (:class:`Placement`: on the references, and the references' images on every line)."""
    n = X.shape[0]
    F = X.reshape(n, -1)
    members = stream_members(streams, frames)
    lines = [m for m in members if m.size >= 2]
    full = np.zeros(len(lines), dtype=bool)
    full[np.argsort([-m.size for m in lines], kind="stable")[:REFERENCE_STREAMS]] = True
    line_of = np.cumsum([m.size >= 2 for m in members]) - 1
    reference = [m.size >= 2 and bool(full[c]) for m, c in zip(members, line_of, strict=True)]
    shapes = [F[m] for m in members]
    placed = [[idx] for idx in lines]
    pos = [[arc_length(F[idx])] for idx in lines]
    pairs, targets = [], []
    for c, idx in enumerate(lines):
        B = F[idx]
        for other, A, ref in zip(members, shapes, reference, strict=True):
            if other is not idx and (full[c] or ref):
                pairs.append((A, B))
                targets.append((c, other))
    for (c, other), p in zip(targets, dtw_positions(pairs), strict=True):
        placed[c].append(other)
        pos[c].append(p)
    placed = [np.concatenate(ims) for ims in placed]
    order = [np.argsort(ims) for ims in placed]
    return Placement(lines=lines, placed=[ims[o] for ims, o in zip(placed, order, strict=True)],
                     pos=[np.concatenate(p)[o] for p, o in zip(pos, order, strict=True)],
                     full=full)


def arc_distance(
    X: np.ndarray,
    streams: np.ndarray,
    frames: np.ndarray,
    placement: Placement | None = None,
    subset: np.ndarray | None = None,
) -> np.ndarray:
    """Arc distance between images, (N, N) symmetric (between the images ``subset`` only, when
    given: the same entries, placed on the polylines of all images).

    Within a stream: path length of its 3D shapes between the two images. Across streams a and b:
    each image of a is placed on b's polyline by order-preserving DTW and the distance is the arc
    length between the positions (and vice versa), averaged over the directions available. Two
    images neither of whose polylines holds the other (two lone photos, or two streams beyond
    the references, :class:`Placement`) are compared through the reference polylines (median).
    Without any stream of two or more images this falls back to the Euclidean distance.
    """
    subset = np.arange(X.shape[0]) if subset is None else subset
    n = subset.size
    pl = placement or place_on_streams(X, streams, frames)
    if not pl.lines:
        return euclidean_distance(X[subset])
    pos = pl.table(subset)
    line_of = np.full(X.shape[0], -1)
    for c, idx in enumerate(pl.lines):
        line_of[idx] = c
    line_of = line_of[subset]
    Z = np.zeros((n, n))
    cnt = np.zeros((n, n))
    for c in range(len(pl.lines)):
        # the pairs placed on line c with at least one image of its own stream: its images'
        # rows, then the other placed images' rows at its images' columns
        there = np.isfinite(pos[c])
        own = np.flatnonzero((line_of == c) & there)
        placed = np.flatnonzero(there)
        other = np.flatnonzero(there & (line_of != c))
        for rows, cols in ((own, placed), (other, own)):
            at = np.ix_(rows, cols)
            Z[at] += np.abs(pos[c][rows][:, None] - pos[c][cols][None, :])
            cnt[at] += 1
    neither = cnt == 0
    refs = pos[pl.full]
    step = max(1, MEDIAN_BLOCK // (refs.shape[0] * n))
    for lo in range(0, n, step):
        rows = slice(lo, lo + step)
        if neither[rows].any():
            med = np.median(np.abs(refs[:, rows, None] - refs[:, None, :]), axis=0)
            Z[rows][neither[rows]] = med[neither[rows]]
    cnt[neither] = 1
    Z /= cnt
    Z = 0.5 * (Z + Z.T)
    np.fill_diagonal(Z, 0.0)
    return Z


def theil_sen(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(slope, intercept) of the Theil-Sen line of y on x: the median of the slopes between all
    pairs of points with distinct x, and the median of y less the slope times the median of x
    (``scipy.stats.theilslopes`` with its default ``separate`` method, whose argument checks and
    confidence interval cost more than the line in the sequencing's many small fits)."""
    dx = x[:, None] - x
    dy = y[:, None] - y
    up = dx > 0
    slope = float(np.median(dy[up] / dx[up]))
    return slope, float(np.median(y) - slope * np.median(x))


def affine_time(
    X: np.ndarray, streams: np.ndarray, frames: np.ndarray, placement: Placement | None = None,
    rates: np.ndarray | None = None,
) -> np.ndarray | None:
    """Time of every image assuming each stream runs at a constant frame rate (videos).

    Stream s's images are at ``t = a_s + b_s frame``. Every image of a stream is placed on the
    polylines of the other streams it meets (:class:`Placement`: all, up to
    :data:`REFERENCE_STREAMS`) by order-preserving DTW, which gives it a fractional frame number
    there; a robust (Theil-Sen) line through those pairs (at most ``THEIL_SEN_POINTS`` of
    them, evenly spaced) gives the relative offset and rate of
    the two streams, and a least-squares fit over those pairs gives every (a_s, b_s), with the
    longest stream as the reference clock. With ``rates`` (N,), every image's stream's known
    frame rate, the rates are their ratios and each pair gives its offset alone, the median of
    the placed frame numbers less the rate ratio times the frames: the DTW placements of noisy
    shapes stall and jump, and a line through them can miss the rate by tens of percent
    (docs/method.md, "Known rates in the placement"). Lone photos take the median time at which
    the reference polylines place them. Returns (N,) times in the reference stream's frames, or
    None when no two streams have two or more images.
    """
    n = X.shape[0]
    pl = placement or place_on_streams(X, streams, frames)
    lines = pl.lines
    if len(lines) < 2:
        return None
    k = len(lines)
    # fractional frame number of line c at which every image placed on it sits
    at = []
    for c, idx in enumerate(lines):
        arc, keep = np.unique(pl.on(c, idx), return_index=True)
        fr = frames[idx].astype(float)[keep]
        at.append(np.interp(pl.pos[c], arc, fr) if arc.size > 1
                  else np.full(pl.placed[c].size, fr[0]))
    ref = int(np.argmax([m.size for m in lines]))
    known = None if rates is None else np.array([rates[idx[0]] for idx in lines])
    pairs = []  # (d, c, log slope, intercept, size): f_c = icpt + slope f_d
    for c in range(k):
        for d, other in enumerate(lines):
            if d == c or not (pl.full[c] or pl.full[d]):
                continue
            if known is not None:
                slope = known[c] / known[d]
                icpt = float(np.median(at[c][np.searchsorted(pl.placed[c], other)]
                                       - slope * frames[other]))
            else:
                # Theil-Sen takes all pairs of points: on evenly spaced ones of a long stream
                few = other[np.unique(np.linspace(0, other.size - 1,
                                                  min(other.size, THEIL_SEN_POINTS)).astype(int))]
                slope, icpt = theil_sen(frames[few].astype(float),
                                        at[c][np.searchsorted(pl.placed[c], few)])
            if slope > 0:
                pairs.append((d, c, np.log(slope), icpt, other.size))
    # t = a_s + b_s f  =>  log b_d - log b_c = log slope,  a_d - a_c = b_c icpt: one weighted
    # system of the pairs (the reference's row pins it) for both
    A = np.zeros((len(pairs) + 1, k))
    wts = np.ones(len(pairs) + 1)
    for r, (d, c, _, _, size) in enumerate(pairs):
        A[r, d], A[r, c], wts[r] = 1.0, -1.0, np.sqrt(size)
    A[-1, ref], wts[-1] = 1.0, 1e3
    Aw = A * wts[:, None]
    if known is not None:
        b = known[ref] / known
    else:
        lslope = np.array([pair[2] for pair in pairs] + [0.0])
        b = np.exp(np.linalg.lstsq(Aw, lslope * wts, rcond=None)[0])
    icpt = np.array([b[c] * i for _, c, _, i, _ in pairs] + [0.0])
    a = np.linalg.lstsq(Aw, icpt * wts, rcond=None)[0]
    t = np.empty(n)
    lone = np.ones(n, dtype=bool)
    for c, idx in enumerate(lines):
        t[idx] = a[c] + b[c] * frames[idx]
        lone[idx] = False
    if lone.any():  # through every reference line
        lone = np.flatnonzero(lone)
        t[lone] = np.median([a[c] + b[c] * at[c][np.searchsorted(pl.placed[c], lone)]
                             for c in np.flatnonzero(pl.full)], axis=0)
    return t


def euclidean_distance(X: np.ndarray) -> np.ndarray:
    """|X_i - X_j| between whole shapes, (N, N)."""
    F = X.reshape(X.shape[0], -1)
    sq = (F**2).sum(axis=1)
    d2 = np.maximum(sq[:, None] + sq[None, :] - 2 * F @ F.T, 0.0)
    np.fill_diagonal(d2, 0.0)
    return np.sqrt(d2)


def distance_matrix(
    X: np.ndarray,
    streams: np.ndarray,
    frames: np.ndarray,
    kind: Distance | str = Distance.ARC,
    placement: Placement | None = None,
    subset: np.ndarray | None = None,
) -> np.ndarray:
    """Distances between images (``subset``: between those only), (N, N): dense, so the
    sequencing of a capture with videos uses a subset (``alternation.sequence``)."""
    if Distance(kind) is Distance.ARC:
        return arc_distance(X, streams, frames, placement, subset)
    return euclidean_distance(X if subset is None else X[subset])


def orient(f: np.ndarray, streams: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Flip f so that it increases with frame number inside streams (when streams say anything)."""
    score = 0.0
    for idx in stream_members(streams, frames):
        if idx.size >= 2:
            score += np.sum(np.sign(np.diff(f[idx])))
    return -f if score < 0 else f


def order_from_embedding(f: np.ndarray) -> np.ndarray:
    return np.argsort(f, kind="stable")


def kendall_tau(order: np.ndarray, times: np.ndarray) -> float:
    """|Kendall tau| between an estimated order (image indices, earliest first) and true times.
    (``scipy.stats`` is imported here: it takes most of a second, and only evaluation needs it.)"""
    from scipy.stats import kendalltau

    rank = np.empty(order.size)
    rank[order] = np.arange(order.size)
    tau = kendalltau(rank, times).statistic
    return float(abs(tau)) if np.isfinite(tau) else 0.0
