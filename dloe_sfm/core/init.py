"""Initialisation by two-view pseudo-triangulation (docs/method.md, "The steps as implemented")."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from .dtw import align_many, in_blocks

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

    def depths(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Depths on a's rays, validity (.., P) and mean gaps (..) of images a against b
        (index arrays, broadcast)."""
        ra, rb = self.r[:, a], self.r[:, b]
        s, t, gap = closest_approach(self.C[:, a], ra, self.C[:, b], rb)
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
    image. Each observed point takes the depth of the closest point on its ray to the partner's
    ray; a point the partner cannot serve takes the next-best partner that can.

    Parameters
    ----------
    rays : (N, P, 3) float, unit, NaN = unobserved
    C : (N, 3) float camera centres
    streams : (N,) int stream ids (pairs within one stream are never used)
    frames : (N,) int frame order inside streams, optional
    chunk : images scored against all others at a time (lone photos, or without ``frames``)

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
        s, ok, score = pairs.depths(rows, cols)
        # group by image, best score first (ties: the lower image index, as a stable sort)
        order = np.lexsort((cols, score, rows))
        rows, cols, s, ok, score = rows[order], cols[order], s[order], ok[order], score[order]
        first = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
        img = rows[first]
        partner[img] = np.where(np.isfinite(score[first]), cols[first], -1)
        # per point: the best-ranked partner whose ray pair is valid for that point
        at = np.where(ok, np.arange(rows.size)[:, None], rows.size)
        chosen = np.minimum.reduceat(at, first, axis=0)  # (images, P)
        found = chosen < rows.size
        pick = np.minimum(chosen, rows.size - 1)
        usable = found & np.isfinite(score[pick])
        depths[img] = np.where(usable, np.take_along_axis(s, pick, axis=0), np.nan)
    return depths, partner


def _candidates(
    pairs: _Pairs, streams: np.ndarray, frames: np.ndarray | None, chunk: int
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(rows, cols) of the image pairs to score, every image's pairs in one batch: the images
    within one of the alignment in each of the stream's :func:`partner_streams` (with
    ``frames``), and every image of another stream for the rest (lone photos, or all images
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
    everyone = np.arange(n)
    for lo in range(0, rest.size, chunk):
        rows = rest[lo:lo + chunk]
        r, c = np.nonzero(streams[rows][:, None] != streams[None, :])
        yield rows[r], everyone[c]
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
