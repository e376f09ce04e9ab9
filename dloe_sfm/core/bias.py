"""Stream offsets: a detector's constant offset of each point in each video.

A keypoint detector does not place a joint where a marker would be, and where it places it
depends on the view: a hip seen from the side sits elsewhere on the body than seen from the
front. Per video and point the detections are then off by a nearly constant 2D offset, which
the rays cannot tell from the motion: where a moving point is seen by one camera at a time, an
offset along the motion reads as a time shift, and the streams' clocks take it.

On an event placed on its streams' clocks every observation is predicted from its neighbours
along them (``clocks.chain_predicted``), which are other cameras' images: the median, over a
stream's images, of one point's residuals is that stream's offset of the point less what the
streams around it share. It is kept only where it predicts: estimated on every other frame of
each stream, it must shrink the residuals of the frames in between (both ways round) by
``decisions.OFFSET_GAIN``; interpolation errors of fast motion and noise do not repeat from
frame to frame, an offset does. What one 3D shift of the point explains of them (its image
motion in every observation, least squares) moves no ray against another: it is left to the
point, and the offsets taken out are the smallest that explain the residuals (docs/method.md,
"Stream offsets")."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .capture import Capture, project
from .robust import residual_vectors
from .sequencing import stream_members

MIN_IMAGES = 5
"""A stream's offset of a point is estimated from at least this many of its images' residuals
in each half (every other frame): fewer leave it 0."""


def _medians(res: np.ndarray, ok: np.ndarray, stream: np.ndarray) -> np.ndarray:
    """(N, P, 2) each observation's stream median of its point's residuals ``res`` (N, P, 2)
    over the observations ``ok`` (N, P); NaN where fewer than :data:`MIN_IMAGES` of them."""
    out = np.full(res.shape, np.nan)
    for s in np.unique(stream):
        rows = stream == s
        if rows.sum() < MIN_IMAGES:
            continue
        r = np.where(ok[rows, :, None], res[rows], np.nan)
        enough = ok[rows].sum(axis=0) >= MIN_IMAGES
        median = np.full(r.shape[1:], np.nan)
        median[enough] = np.nanmedian(r[:, enough], axis=0)
        out[rows] = median
    return out


def stream_offsets(
    capture: Capture, X_pred: np.ndarray, rejected: np.ndarray
) -> tuple[np.ndarray, float, float] | None:
    """Each stream's constant pixel offset of each point (module docstring).

    ``X_pred`` (N, P, 3) every image's shapes predicted from its neighbours along the clocks,
    ``rejected`` (N, P) observations left out. Returns the (N, P, 2) offsets of the
    observations (0 where a stream has too few of a point), with the cross-validated median
    residual without and with them (pixels), or None when a stream has too few images for any
    offset at all."""
    res = residual_vectors(capture, X_pred)
    ok = ~rejected & np.isfinite(res).all(axis=2)
    stream = capture.stream_ids
    rank = np.empty(stream.size, dtype=np.int64)
    for members in stream_members(stream, capture.frame):
        rank[members] = np.arange(members.size)
    even = (rank % 2 == 0)[:, None]
    halves = [_medians(res, ok & even, stream), _medians(res, ok & ~even, stream)]
    other = np.where(even[..., None], halves[1], halves[0])  # from the frames in between
    tested = ok & np.isfinite(halves[0]).all(axis=2) & np.isfinite(halves[1]).all(axis=2)
    if not tested.any():
        return None
    before = float(np.median(np.linalg.norm(res[tested], axis=1)))
    after = float(np.median(np.linalg.norm(res[tested] - other[tested], axis=1)))
    offsets = np.nan_to_num(_medians(res, ok, stream))
    offsets = _without_shift(capture, X_pred, offsets, ok)
    return offsets, before, after


def _without_shift(capture: Capture, X: np.ndarray, offsets: np.ndarray,
                   fit: np.ndarray) -> np.ndarray:
    """``offsets`` (N, P, 2) less, per point, the image motion of the 3D shift that best
    explains them on the observations ``fit`` (N, P): the medians are each stream's offset
    less what the streams around it share, and what they share as one shift of the point in
    space is the point's to keep (it moves no ray against another)."""
    shifted = np.abs(offsets).sum(axis=2) > 0
    fit = fit & shifted
    on = np.isfinite(X).all(axis=2) & shifted
    ahead = capture.C[:, None, :] + capture.R[:, None, 2, :]  # a unit in front of each camera
    Xf = np.where(on[..., None], X, ahead)
    depth = np.einsum("nk,npk->np", capture.R[:, 2], Xf - capture.C[:, None, :])
    h = 1e-6 * float(np.median(np.abs(depth[fit]))) if fit.any() else 1e-6
    base = project(Xf, capture.K, capture.R, capture.C)
    J = np.stack([(project(Xf + h * e, capture.K, capture.R, capture.C) - base) / h
                  for e in np.eye(3)], axis=-1)  # (N, P, 2, 3): pixels per unit shift
    out = offsets.copy()
    for k in np.flatnonzero(fit.sum(axis=0) >= 2):
        delta = np.linalg.lstsq(J[fit[:, k], k].reshape(-1, 3),
                                offsets[fit[:, k], k].reshape(-1), rcond=None)[0]
        out[on[:, k], k] -= J[on[:, k], k] @ delta
    return out


def per_stream(offsets: np.ndarray, stream: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(S,) the stream ids and (S, P, 2) each stream's offset of each point: the median of the
    observations' ``offsets`` (N, P, 2) over the stream's images (``stream`` (N,))."""
    ids = np.unique(stream)
    return ids, np.stack([np.median(offsets[stream == s], axis=0) for s in ids])


def without_offsets(capture: Capture, offsets: np.ndarray) -> Capture:
    """``capture`` with the (N, P, 2) pixel ``offsets`` taken out of its observations."""
    return replace(capture, x=capture.x - offsets)
