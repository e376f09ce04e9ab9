"""The detection noise estimated from the data (docs/method.md, "Held-out checks").

Every observation's residual against the graph's prediction from the other images (``W X``,
``robust.residuals_px``) holds the detection's noise and the graph's own interpolation error,
so its level is only a candidate: exact detections of fast, accelerating joints leave
residuals too, and soft rays at their level would pull points off accurate detections. Which
ray model is right is asked of the data: the observations are split into folds, each fold is
solved without its detections under both models (each from its own solution), and the model
that predicts the held-out detections better wins (``decisions.soft_rays_kept``; the folds:
``core.heldout``). Along the stream clocks, held-out images also see the depth errors that
hard rays keep from noisy detections, which single held-out detections cannot
(``decisions.soft_rays_on_clocks``)."""

from __future__ import annotations

import numpy as np

MEDIAN_RADIUS = float(np.sqrt(2.0 * np.log(2.0)))
"""Median radius of 2D Gaussian noise of unit std."""

FIT_RATIO = 0.75
"""Median residual over the noise's median radius: W, fitted to the noisy hard-ray shapes, predicts
the observations closer than their noise (0.72-0.86 on mocap at 1-5 px, lower at more noise)."""

MIN_OBSERVATIONS = 5
"""A point's median residual counts with at least this many observations."""


def estimate_noise_px(res: np.ndarray) -> float:
    """Std (pixels) of 2D Gaussian noise whose median radius explains the median of the (N, P)
    residuals ``res`` (NaN: unobserved) of the hard-ray solution; 0 when fewer than four points
    have ``MIN_OBSERVATIONS`` residuals. A candidate for ``decisions.soft_wins`` to confirm."""
    seen = np.isfinite(res)
    if (seen.sum(axis=0) >= MIN_OBSERVATIONS).sum() < 4:
        return 0.0
    median = float(np.median(res[seen]))
    return median / residual_floor_px(1.0) if median > 0 else 0.0


def residual_floor_px(noise_px: float) -> float:
    """The median residual against the graph's prediction that detection noise of std
    ``noise_px`` leaves on its own (pixels): what no re-solve can remove."""
    return FIT_RATIO * MEDIAN_RADIUS * noise_px


