"""Robust observations: what the graph predicts for each observation, and what that says of it.

DLOE's rows give every image's shape as a combination of its temporal neighbours' shapes, so
``W X`` predicts each point from the other images alone. A wrong detection sits far from that
prediction in its own image; a swapped left/right pair sits at the prediction of its partner.
The solver turns those residuals (pixels) into observation weights with a robust loss and
re-solves (iteratively reweighted least squares on the ray term).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from .capture import Capture, project
from .options import RobustLoss


def predicted(W: sp.spmatrix, X: np.ndarray) -> np.ndarray:
    """(N, P, 3) shapes predicted by the graph's rows from the other images: ``W X``."""
    n = X.shape[0]
    return np.asarray(sp.csr_matrix(W) @ X.reshape(n, -1)).reshape(X.shape)


def residual_vectors(capture: Capture, X_pred: np.ndarray) -> np.ndarray:
    """(N, P, 2) each observation less the projection of its prediction, pixels (NaN where
    unobserved or the prediction is behind the camera)."""
    cam_z = np.einsum("nk,npk->np", capture.R[:, 2], X_pred - capture.C[:, None, :])
    res = capture.x - project(X_pred, capture.K, capture.R, capture.C)
    res[~capture.visible | (cam_z <= 0)] = np.nan
    return res


def residuals_px(capture: Capture, X_pred: np.ndarray) -> np.ndarray:
    """(N, P) pixel distance between each observation and the projection of its prediction
    (NaN where unobserved or the prediction is behind the camera)."""
    return np.linalg.norm(residual_vectors(capture, X_pred), axis=2)


def loss_scale(res: np.ndarray, scale_px: float | None) -> np.ndarray:
    """(P,) scale c of the robust loss per point, pixels: ``scale_px``, or 5 sigma of the point's
    residuals (sigma = median / sqrt(2 ln 2), from the median radius of a 2D Gaussian) and at
    least 3 px. Per point, because fast joints (wrists, feet) are predicted less exactly."""
    p = res.shape[1]
    if scale_px is not None:
        return np.full(p, float(scale_px))
    seen = np.isfinite(res).any(axis=0)
    median = np.zeros(p)
    median[seen] = np.nanmedian(res[:, seen], axis=0)
    return np.maximum(3.0, 5.0 * median / np.sqrt(2 * np.log(2)))


def loss_weights(res: np.ndarray, scale: np.ndarray, loss: RobustLoss) -> np.ndarray:
    """IRLS weights rho'(r) / r of residuals ``res`` (N, P) at (P,) ``scale``; 1 where NaN."""
    r = np.nan_to_num(res, nan=0.0) / scale
    if loss is RobustLoss.CAUCHY:
        with np.errstate(over="ignore"):  # a tiny robust_scale_px: weight 1 / inf = 0
            return 1.0 / (1.0 + r**2)
    if loss is RobustLoss.HUBER:
        return np.minimum(1.0, 1.0 / np.maximum(r, 1e-300))
    return np.ones_like(r)


def find_swaps(
    capture: Capture, X_pred: np.ndarray, pairs: np.ndarray, scale: np.ndarray
) -> np.ndarray:
    """(K, 3) (image, a, b) of the symmetric pairs whose two observations fit the prediction
    far better exchanged: squared residuals summed over the pair drop below a quarter and the
    pair was off by more than its points' ``scale`` (P,) pixels."""
    if pairs is None or pairs.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    x_hat = project(X_pred, capture.K, capture.R, capture.C)
    a, b = pairs[:, 0], pairs[:, 1]

    def sq(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return ((x_hat[:, u] - capture.x[:, v]) ** 2).sum(axis=2)

    keep = sq(a, a) + sq(b, b)
    swap = sq(a, b) + sq(b, a)
    vis = capture.visible
    found = vis[:, a] & vis[:, b] & (swap < 0.25 * keep) & (keep > scale[a] ** 2 + scale[b] ** 2)
    img, k = np.nonzero(found)
    return np.stack([img, a[k], b[k]], axis=1).astype(np.int64)


def apply_swaps(capture: Capture, swaps: np.ndarray) -> Capture:
    """A copy of ``capture`` with the observations (and confidences) of each swap exchanged."""
    img, a, b = swaps.T

    def exchanged(values: np.ndarray | None) -> np.ndarray | None:
        if values is None:
            return None
        out = values.copy()
        out[img, a], out[img, b] = values[img, b], values[img, a]
        return out

    return replace(capture, x=exchanged(capture.x), confidence=exchanged(capture.confidence))


def reweighted(capture: Capture, weights: np.ndarray) -> Capture:
    """``capture`` with confidences multiplied by robust ``weights``, and the observations
    weighted below 1/2 dropped: the solver's first phase pins every observed point to its ray
    (hard rays), where a weight can only keep or drop an observation."""
    return replace(capture, confidence=np.where(weights < 0.5, 0.0, capture.weights * weights))
