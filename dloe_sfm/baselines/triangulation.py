"""Triangulation references: DLOE's pseudo-triangulation and per-instant least squares."""

from __future__ import annotations

import numpy as np

from ..core.capture import Capture
from ..core.options import Options
from ..core.problem import initialise


def pseudo_triangulation(capture: Capture, options: Options | None = None) -> np.ndarray:
    """DLOE's initialisation as a baseline: two-view pseudo-triangulation, (N, P, 3) world units.

    Each image's point is the point of its ray closest to the ray of the most convergent image
    of another stream; unobserved points are interpolated along the stream.
    """
    return initialise(capture, options or Options())


def triangulate_instants(capture: Capture, instants: np.ndarray) -> np.ndarray:
    """Linear least-squares triangulation of images that share an instant.

    Images with equal ``instants`` (N,) (a time stamp or any instant label) form one group; every
    point seen by at least two of the group's images gets the point minimising the sum of squared
    distances to their viewing rays, ``sum_n |(I - r_n r_n^T)(X - C_n)|^2``, which is exact for
    noise-free concurrent views. On an asynchronous capture no two images share an instant, so
    this is only a reference with given (synchronised) groups.

    Returns (N, P, 3): the group's point in each of its images; NaN where fewer than two of the
    group's images see the point.
    """
    instants = np.asarray(instants)
    rays = capture.rays()
    vis = capture.visible
    n, p = vis.shape
    X = np.full((n, p, 3), np.nan)
    r = np.nan_to_num(rays)
    # per (image, point) projector onto the plane normal to the ray, zero when unobserved
    proj = (np.eye(3)[None, None] - r[..., :, None] * r[..., None, :]) * vis[..., None, None]
    _, group = np.unique(instants, return_inverse=True)
    for g in range(group.max() + 1):
        idx = np.flatnonzero(group == g)
        enough = vis[idx].sum(axis=0) >= 2
        if not enough.any():
            continue
        H = proj[idx][:, enough].sum(axis=0)  # (P', 3, 3)
        b = np.einsum("npij,nj->pi", proj[idx][:, enough], capture.C[idx])
        X[np.ix_(idx, np.flatnonzero(enough))] = np.linalg.solve(H, b[..., None])[None, :, :, 0]
    return X
