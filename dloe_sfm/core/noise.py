"""The detection noise estimated from the data: what the hard-ray graph cannot predict.

Every observation's residual against the graph's prediction from the other images (``W X``,
``robust.residuals_px``) holds the detection's noise and the graph's own interpolation error.
Noise is the same for every point; interpolation error is not (fast, accelerating joints are
predicted worse, slow ones almost exactly). So the noise is the residual level that nearly
every point shares, and it is taken as the detections' noise only where it explains the
residuals of almost every point; otherwise the model, not the detections, is what is off and
the detections are taken as exact (``noise_px`` 0: hard rays).
"""

from __future__ import annotations

import numpy as np

MEDIAN_RADIUS = float(np.sqrt(2.0 * np.log(2.0)))
"""Median radius of 2D Gaussian noise of unit std."""

FIT_RATIO = 0.75
"""Median residual over the noise's median radius: W, fitted to the noisy hard-ray shapes, predicts
the observations closer than their noise (0.72-0.86 on mocap at 1-5 px, lower at more noise)."""

SHARED = 0.9
"""The residual level that three quarters of the points exceed must be at least this fraction of
the median residual for the residuals to count as noise (mocap with noise: 0.93-0.97; noise-free,
sparse and the demo: 0.72-0.82)."""

MIN_OBSERVATIONS = 5
"""A point's median residual counts with at least this many observations."""


def estimate_noise_px(res: np.ndarray) -> float:
    """Std (pixels) of the detection noise from the (N, P) residuals ``res`` (NaN: unobserved) of
    the hard-ray solution; 0 when the residuals are not noise that every point shares, or when
    fewer than four points have ``MIN_OBSERVATIONS`` residuals."""
    seen = np.isfinite(res)
    counted = seen.sum(axis=0) >= MIN_OBSERVATIONS
    if counted.sum() < 4:
        return 0.0
    per_point = np.nanmedian(res[:, counted], axis=0)
    floor = float(np.percentile(per_point, 25))
    median = float(np.median(res[seen]))
    if not median > 0 or floor < SHARED * median:
        return 0.0
    return median / (FIT_RATIO * MEDIAN_RADIUS)
