"""Initialisation by two-view pseudo-triangulation (docs/method.md, "The steps as implemented")."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from scipy.spatial import cKDTree

from .dtw import align_many, in_blocks

LONE_EXACT = 1024
"""Lone photos paired with every image of another stream up to this many of them; beyond, by
the sparse search of :func:`_lone_pairs` (docs/method.md, "Many lone photos": it triangulates
better under detector noise, but changes the solves of some smaller captures for the worse, so
it is kept to the sizes where all pairs cost too much)."""
LONE_REFERENCES = 128
"""Images spread over the capture whose shapes are triangulated first, every lone photo then
scored against them alone (:func:`_lone_pairs`)."""
LONE_HYPOTHESES = 2
"""A lone photo's best references whose pair shapes each look for its nearest images."""
LONE_NEIGHBOURS = 32
"""Nearest images in shape a lone photo is scored against, per shape looked for."""
LONE_ROUNDS = 2
"""Rounds of that search, each from the shapes the last one triangulated."""

PARTNER_STREAMS = 7
"""Other streams whose images an image of a stream is scored against for its partner
(:func:`partner_streams`): every other stream up to eight streams, a bounded number beyond."""


def closest_approach(
    C1: np.ndarray, r1: np.ndarray, C2: np.ndarray, r2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points of two families of rays ``C1 + s r1`` and ``C2 + t r2`` (broadcasting).

    C1, r1, C2, r2 (3, ...): coordinates first (each coordinate a contiguous array), rays unit.
    Returns depths s, t (...) and the gap (...) between the closest points; NaN where the rays
    are parallel.
    """
    w0 = C1 - C2
    b = _dot(r1, r2)
    d = _dot(r1, w0)
    e = _dot(r2, w0)
    denom = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-12, (b * e - d) / denom, np.nan)
        t = np.where(denom > 1e-12, (e - b * d) / denom, np.nan)
    g = [w0[c] + s * r1[c] - t * r2[c] for c in range(3)]
    return s, t, np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Dot products of (3, ...) coordinate-first vectors."""
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


class _Pairs:
    """Closest-approach scores of image pairs (rays (N, P, 3) unit, NaN = unobserved)."""

    def __init__(self, rays: np.ndarray, C: np.ndarray, streams: np.ndarray, cos_max: float):
        self.vis = np.isfinite(rays).all(axis=2)
        self.r = np.ascontiguousarray(np.moveaxis(np.nan_to_num(rays), 2, 0))  # (3, N, P)
        self.C = np.ascontiguousarray(C.T)[:, :, None]  # (3, N, 1)
        self.streams, self.cos_max = streams, cos_max

    def depths(
        self, a: np.ndarray, b: np.ndarray, known: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Depths on a's rays, validity (.., P) and mean gaps (..) of images a against b
        (index arrays, broadcast). With ``known`` (N, P) depths (NaN = unknown), each point's
        gap adds the distance of its closest point on b's ray from b's known point: views that
        are not simultaneous can meet closely where the motion runs along their epipolar
        lines, but then not at b's point."""
        ra, rb = self.r[:, a], self.r[:, b]
        s, t, gap = closest_approach(self.C[:, a], ra, self.C[:, b], rb)
        if known is not None:
            gap = gap + np.nan_to_num(np.abs(t - known[b]))
        cosang = np.abs(_dot(ra, rb))
        ok = (
            self.vis[a]
            & self.vis[b]
            & (cosang < self.cos_max)
            & (s > 0)
            & (t > 0)
            & (self.streams[a] != self.streams[b])[..., None]
        )
        count = ok.sum(axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            score = np.where(ok, gap, 0.0).sum(axis=-1) / count
        score[count == 0] = np.inf
        score[count == 1] *= 1e6  # one shared point says little about simultaneity
        return s, ok, score

    def score(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return self.depths(a, b)[2]


def pseudo_triangulate(
    rays: np.ndarray,
    C: np.ndarray,
    streams: np.ndarray,
    frames: np.ndarray | None = None,
    *,
    min_angle: float = 15.0,
    chunk: int = 64,
) -> tuple[np.ndarray, np.ndarray]:
    """Two-view pseudo-triangulation of every image with its most convergent partner.

    For image n, every image m of another stream is scored by the mean closest-approach gap of the
    rays of the points both observe, counting only rays that meet in front of both cameras at an
    angle of at least ``min_angle`` degrees from (anti)parallel; the partner is the image with the
    smallest mean gap. Two views cannot tell times apart when the motion runs along their epipolar
    lines, so with ``frames`` the partners in another stream of two or more images (one of
    :func:`partner_streams`: the most convergent views) are only the
    images within one of an order-preserving alignment of the two streams (DTW on the gaps,
    ``core.dtw.align_many``: linear in the streams' lengths); lone photos are scored against every
    image, or beyond :data:`LONE_EXACT` of them against those a sparse search in shape finds
    (:func:`_lone_pairs`). Each observed point takes the depth of the closest point on its ray to
    the partner's ray; a point the partner cannot serve takes the next-best partner that can.

    Parameters
    ----------
    rays : (N, P, 3) float, unit, NaN = unobserved
    C : (N, 3) float camera centres
    streams : (N,) int stream ids (pairs within one stream are never used)
    frames : (N,) int frame order inside streams, optional
    chunk : lone photos scored at a time

    Returns
    -------
    depths : (N, P) float, NaN where unobserved or no partner could triangulate the point
    partner : (N,) int, the most convergent partner of each image (-1 = none)
    """
    n, p = rays.shape[:2]
    pairs = _Pairs(rays, C, streams, np.cos(np.deg2rad(min_angle)))
    depths = np.full((n, p), np.nan)
    partner = np.full(n, -1)
    for rows, cols in _candidates(pairs, streams, frames, chunk):
        img, best, d = _best_partners(pairs, rows, cols)
        partner[img], depths[img] = best, d
    return depths, partner


def _ranked(
    pairs: _Pairs, rows: np.ndarray, cols: np.ndarray, known: np.ndarray | None = None
) -> tuple[np.ndarray, ...]:
    """The pairs ``rows`` x ``cols`` grouped by image, best score (``_Pairs.depths``) first
    (ties: the lower image index): (rows, cols, depths, validity, scores, the start of each
    image's group)."""
    s, ok, score = pairs.depths(rows, cols, known)
    order = np.lexsort((cols, score, rows))
    rows = rows[order]
    first = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    return rows, cols[order], s[order], ok[order], score[order], first


def _best_partners(
    pairs: _Pairs, rows: np.ndarray, cols: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(images, partner (-1 = none), depths (images, P)) of the pairs ``rows`` x ``cols``, each
    image's pairs all among them: the partner of the smallest score, and each point's depth
    from the best-ranked partner whose ray pair is valid for that point."""
    return _best_of(_ranked(pairs, rows, cols))


def _best_of(ranked: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_best_partners` of pairs already :func:`_ranked`."""
    rows, cols, s, ok, score, first = ranked
    img = rows[first]
    partner = np.where(np.isfinite(score[first]), cols[first], -1)
    at = np.where(ok, np.arange(rows.size)[:, None], rows.size)
    chosen = np.minimum.reduceat(at, first, axis=0)  # (images, P)
    found = chosen < rows.size
    pick = np.minimum(chosen, rows.size - 1)
    usable = found & np.isfinite(score[pick])
    return img, partner, np.where(usable, np.take_along_axis(s, pick, axis=0), np.nan)


def _candidates(
    pairs: _Pairs, streams: np.ndarray, frames: np.ndarray | None, chunk: int
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(rows, cols) of the image pairs to score, every image's pairs in one batch: the images
    within one of the alignment in each of the stream's :func:`partner_streams` (with
    ``frames``), and those :func:`_lone_pairs` finds for the rest (lone photos, or all images
    without ``frames``)."""
    from .sequencing import stream_members

    n, p = pairs.vis.shape
    members = [] if frames is None else [m for m in stream_members(streams, frames)
                                         if m.size >= 2]
    partners = partner_streams(pairs.r, members)
    aligned = np.zeros(n, dtype=bool)
    for m in members:
        aligned[m] = True
    rest = np.flatnonzero(~aligned)
    yield from _lone_pairs(pairs, rest, chunk)
    paths = iter(align_many([
        (in_blocks(lambda i, j, a=a, b=b: pairs.score(a[i], b[j]), 3 * p), a.size, b.size)
        for a, near in zip(members, partners, strict=True) for b in (members[j] for j in near)
    ]))
    for a, near in zip(members, partners, strict=True):
        rows, cols = [], []
        for b in (members[j] for j in near):
            path = next(paths)
            near = np.clip(path[:, None] + np.arange(-1, 2)[None, :], 0, b.size - 1)
            keep = np.r_[near[:, 0] < near[:, 1], [True] * a.size, near[:, 2] > near[:, 1]]
            rows.append(np.tile(a, 3)[keep])
            cols.append(b[near.T.ravel()][keep])
        r, c = np.nonzero(streams[a][:, None] != streams[None, rest])
        rows.append(a[r])
        cols.append(rest[c])
        yield np.concatenate(rows), np.concatenate(cols)


def _all_pairs(
    streams: np.ndarray, images: np.ndarray, chunk: int
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(rows, cols): each of ``images`` with every image of another stream, ``chunk`` images
    at a time."""
    for lo in range(0, images.size, chunk):
        rows = images[lo:lo + chunk]
        r, c = np.nonzero(streams[rows][:, None] != streams[None, :])
        yield rows[r], c


def _lone_pairs(
    pairs: _Pairs, rest: np.ndarray, chunk: int
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(rows, cols) of the pairs to score of the images ``rest`` (lone photos), every image's
    pairs in one batch of ``chunk`` images: every image of another stream, up to
    :data:`LONE_EXACT` of them; beyond, those found without scoring all N^2 pairs:

    1. :data:`LONE_REFERENCES` images spread over the capture are paired with every image;
       their shapes are then known.
    2. Every image is scored against the references with the distance to their known points
       added (``_Pairs.depths``): a view at another instant may meet a reference's rays closely
       where the motion runs along their epipolar lines, but not at its points. Its
       :data:`LONE_HYPOTHESES` best give shapes of its rays.
    3. Its pairs are the :data:`LONE_NEIGHBOURS` images nearest each of those shapes among all
       images' shapes (a simultaneous view sees the same shape) and its best so far; scored,
       they give better shapes and the search is made again from them, :data:`LONE_ROUNDS` in
       all.

    Linear in N for a bounded number of references; on the simulator's lone photos its
    partners triangulate better than the best of all pairs."""
    n, p = pairs.vis.shape
    streams = pairs.streams
    if rest.size <= LONE_EXACT:
        yield from _all_pairs(streams, rest, chunk)
        return
    refs = np.unique(np.linspace(0, n - 1, LONE_REFERENCES).round().astype(np.int64))
    known = np.full((n, p), np.nan)
    for rows, cols in _all_pairs(streams, refs, chunk):
        img, _, known[img] = _best_partners(pairs, rows, cols)
    depth = np.full((n, p), np.nan)
    best = np.full(n, -1)
    guesses = np.full((n, LONE_HYPOTHESES, p), np.nan)
    for lo in range(0, n, chunk):
        rows = np.arange(lo, min(lo + chunk, n))
        r, c = np.nonzero(streams[rows][:, None] != streams[None, refs])
        ranked = _ranked(pairs, rows[r], refs[c], known)
        img, best[img], depth[img] = _best_of(ranked)
        rows, _, s, ok, _, first = ranked
        rank = np.arange(rows.size) - np.repeat(first, np.diff(np.r_[first, rows.size]))
        top = rank < LONE_HYPOTHESES
        guesses[rows[top], rank[top]] = np.where(ok[top], s[top], np.nan)
    for last in [False] * (LONE_ROUNDS - 1) + [True]:
        X = np.moveaxis(pairs.C + depth[None] * pairs.r, 0, 2)  # (N, P, 3)
        mean = _masked_mean(X, np.isfinite(depth), axis=0)
        tree = cKDTree(np.where(np.isfinite(X), X, np.nan_to_num(mean)).reshape(n, -1))
        d = np.where(np.isfinite(guesses[rest]), guesses[rest], depth[rest, None])
        Q = pairs.C[:, rest, None] + d[None] * pairs.r[:, rest, None]  # (3, rest, H, P)
        Q = np.moveaxis(Q, 0, -1)
        Q = np.where(np.isfinite(Q), Q, np.nan_to_num(mean)).reshape(rest.size * d.shape[1], -1)
        _, near = tree.query(Q, k=min(LONE_NEIGHBOURS + 1, n))
        near = np.c_[near.reshape(rest.size, -1), best[rest]]
        for lo in range(0, rest.size, chunk):
            rows = rest[lo:lo + chunk]
            cand = np.sort(near[lo:lo + chunk], axis=1)
            keep = (cand >= 0) & (cand < n) & (streams[cand % n] != streams[rows, None])
            keep[:, 1:] &= cand[:, 1:] != cand[:, :-1]
            r, c = np.nonzero(keep)
            if last:
                yield rows[r], cand[r, c]
            else:
                img, best[img], depth[img] = _best_partners(pairs, rows[r], cand[r, c])
        guesses = depth[:, None]


def partner_streams(rays: np.ndarray, members: list[np.ndarray]) -> list[np.ndarray]:
    """The streams (indices into ``members``, ascending) whose images each stream's are
    paired with: the :data:`PARTNER_STREAMS` others whose mean viewing directions are the most
    convergent with its own (ties: the lower index), every other up to that many. ``rays``
    (3, N, P) unit, 0 = unobserved."""
    view = np.array([rays[:, m].sum(axis=(1, 2)) for m in members]).reshape(-1, 3)
    view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), np.finfo(float).tiny)
    cos = np.abs(view @ view.T)
    np.fill_diagonal(cos, np.inf)
    near = np.argsort(cos, axis=1, kind="stable")[:, :min(PARTNER_STREAMS, len(members) - 1)]
    return list(np.sort(near, axis=1))


def fill_missing(X: np.ndarray, streams: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Fill NaN points of (N, P, 3) X: linear interpolation along the point's stream, else the mean.

    Only an initial guess for points no ray constrains; the X-step replaces them.
    """
    X = X.copy()
    for s in np.unique(streams):
        idx = np.flatnonzero(streams == s)
        idx = idx[np.argsort(frames[idx], kind="stable")]
        for p in range(X.shape[1]):
            col = X[idx, p]
            good = np.isfinite(col).all(axis=1)
            if good.all() or good.sum() < 1:
                continue
            pos = np.arange(idx.size)
            for k in range(3):
                col[~good, k] = np.interp(pos[~good], pos[good], col[good, k])
            X[idx, p] = col
    # then the point's mean; for a point no pair of rays triangulated anywhere, the mean of
    # its image's other points; failing that, of all points
    finite = np.isfinite(X).all(axis=2)
    for mean in (_masked_mean(X, finite, axis=0)[None], _masked_mean(X, finite, axis=1)[:, None],
                 _masked_mean(X.reshape(-1, 3), finite.ravel(), axis=0)[None, None]):
        gaps = ~np.isfinite(X)
        X[gaps] = np.broadcast_to(mean, X.shape)[gaps]
    return X


def _masked_mean(X: np.ndarray, mask: np.ndarray, axis: int) -> np.ndarray:
    """Mean of the rows of X (.., 3) where ``mask``, along ``axis``; NaN where none."""
    count = mask.sum(axis=axis)[..., None]
    total = np.where(mask[..., None], X, 0.0).sum(axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)
