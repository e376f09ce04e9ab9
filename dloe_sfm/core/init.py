"""Initialisation by two-view pseudo-triangulation (docs/method.md, "The steps as implemented")."""

from __future__ import annotations

import numpy as np


def closest_approach(
    C1: np.ndarray, r1: np.ndarray, C2: np.ndarray, r2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points of two families of rays ``C1 + s r1`` and ``C2 + t r2`` (broadcasting).

    C1, r1, C2, r2 (..., 3), rays unit. Returns depths s, t (...) and the gap (...) between the
    closest points; NaN where the rays are parallel.
    """
    w0 = C1 - C2
    b = np.sum(r1 * r2, axis=-1)
    d = np.sum(r1 * w0, axis=-1)
    e = np.sum(r2 * w0, axis=-1)
    denom = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-12, (b * e - d) / denom, np.nan)
        t = np.where(denom > 1e-12, (e - b * d) / denom, np.nan)
    gap = np.linalg.norm(w0 + s[..., None] * r1 - t[..., None] * r2, axis=-1)
    return s, t, gap


def _pair_scores(rays, C, streams, lo, hi, cos_max):
    """Closest-approach depths, validity and mean gaps of images lo:hi against all images."""
    vis = np.isfinite(rays).all(axis=2)
    r0 = np.nan_to_num(rays)
    s, t, gap = closest_approach(C[lo:hi, None, None], r0[lo:hi, None], C[None, :, None], r0[None])
    cosang = np.abs(np.einsum("apk,bpk->abp", r0[lo:hi], r0))
    ok = (
        vis[lo:hi, None]
        & vis[None]
        & (cosang < cos_max)
        & (s > 0)
        & (t > 0)
        & (streams[lo:hi, None, None] != streams[None, :, None])
    )
    count = ok.sum(axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        score = np.where(ok, gap, 0.0).sum(axis=2) / count
    score[count == 0] = np.inf
    score[count == 1] *= 1e6  # one shared point says little about simultaneity
    return s, ok, score


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
    lines, so with ``frames`` the partners in another stream are restricted to an order-preserving
    alignment of the two streams (DTW on the gaps, +-1 image). Each observed point takes the depth
    of the closest point on its ray to the partner's ray; a point the partner cannot serve takes
    the next-best partner that can.

    Parameters
    ----------
    rays : (N, P, 3) float, unit, NaN = unobserved
    C : (N, 3) float camera centres
    streams : (N,) int stream ids (pairs within one stream are never used)
    frames : (N,) int frame order inside streams, optional

    Returns
    -------
    depths : (N, P) float, NaN where unobserved or no partner could triangulate the point
    partner : (N,) int, the most convergent partner of each image (-1 = none)
    """
    n, p = rays.shape[:2]
    cos_max = np.cos(np.deg2rad(min_angle))
    score = np.empty((n, n))
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        score[lo:hi] = _pair_scores(rays, C, streams, lo, hi, cos_max)[2]
    if frames is not None:
        score = _align_streams(score, streams, frames)
    depths = np.full((n, p), np.nan)
    partner = np.full(n, -1)
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        s, ok, _ = _pair_scores(rays, C, streams, lo, hi, cos_max)
        sc = score[lo:hi]
        rank = np.argsort(sc, axis=1, kind="stable")
        bi = np.arange(hi - lo)[:, None]
        best = rank[:, 0]
        partner[lo:hi] = np.where(np.isfinite(sc[bi[:, 0], best]), best, -1)
        # per point: the best-ranked partner whose ray pair is valid for that point
        ok_ranked = np.take_along_axis(ok, rank[:, :, None], axis=1)  # (b, N, P)
        first = np.argmax(ok_ranked, axis=1)  # (b, P) position in the ranking
        chosen = np.take_along_axis(rank, first, axis=1)  # (b, P) partner image per point
        usable = ok_ranked.any(axis=1) & np.isfinite(sc[bi, chosen])
        depths[lo:hi] = np.where(usable, s[bi, chosen, np.arange(p)[None, :]], np.nan)
    return depths, partner


def _align_streams(score: np.ndarray, streams: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Keep, between two streams of 2+ images, only partners near an order-preserving alignment."""
    from .sequencing import monotone_assignment, stream_members

    out = score.copy()
    members = [m for m in stream_members(streams, frames) if m.size >= 2]
    for a in members:
        for b in members:
            if a is b:
                continue
            block = score[np.ix_(a, b)]
            finite = np.isfinite(block)
            if not finite.any():
                continue
            big = 10.0 * np.max(block[finite]) + 1.0
            path = monotone_assignment(np.where(finite, block, big))
            near = np.abs(np.arange(b.size)[None, :] - path[:, None]) <= 1
            out[np.ix_(a, b)] = np.where(near, block, np.inf)
    return out


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
