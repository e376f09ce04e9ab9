"""The detection noise estimated from the data, and the folds of the held-out checks
(docs/method.md, "Held-out checks").

Every observation's residual against the graph's prediction from the other images (``W X``,
``robust.residuals_px``) holds the detection's noise and the graph's own interpolation error,
so its level is only a candidate: exact detections of fast, accelerating joints leave
residuals too, and soft rays at their level would pull points off accurate detections. Which
ray model is right is asked of the data: the observations are split into folds, each fold is
solved without its detections under both models (each from its own solution), and the model
that predicts the held-out detections better wins (``alternation.soft_checks_out``). Whole
images held out (``image_folds``) ask the other question, when each image was taken: the
stream clocks' check (``pipeline.clocks_predict``); along the clocks they also see the depth
errors that hard rays keep from noisy detections, which single held-out detections cannot
(``pipeline.soft_on_clocks``)."""

from __future__ import annotations

import numpy as np

from .sequencing import stream_members

MEDIAN_RADIUS = float(np.sqrt(2.0 * np.log(2.0)))
"""Median radius of 2D Gaussian noise of unit std."""

FIT_RATIO = 0.75
"""Median residual over the noise's median radius: W, fitted to the noisy hard-ray shapes, predicts
the observations closer than their noise (0.72-0.86 on mocap at 1-5 px, lower at more noise)."""

MIN_OBSERVATIONS = 5
"""A point's median residual counts with at least this many observations."""

FOLDS = 3
"""Folds of the held-out checks."""

FOLD_SWEEPS = 5
"""Sweeps of each fold's solve by DLOE's graph, started from the model's solution."""

CHECK_IMAGES = 1000
"""Images (the middle of the time line) the held-out checks solve: a choice of model, which a
stretch of the capture answers as well as all of it."""

MARGIN = 0.95
"""Soft rays are taken when their median held-out residual is below this fraction of hard
rays' (a tie keeps the detections exact)."""

CHAIN_MIN_PX = 1.0
"""Soft rays along the stream clocks (``pipeline.soft_on_clocks``) are tried from this level up.
Below a pixel, the level the graph's fit leaves is the SfM cameras' error and the fit's own,
which soft rays trade in ways held-out images cannot judge: the demo at 0.58 px predicts them
0.70 x as far off, yet its error goes 6.11 -> 7.24 mm; detectors' noise is several pixels
(docs/method.md, "Held-out checks")."""


def estimate_noise_px(res: np.ndarray) -> float:
    """Std (pixels) of 2D Gaussian noise whose median radius explains the median of the (N, P)
    residuals ``res`` (NaN: unobserved) of the hard-ray solution; 0 when fewer than four points
    have ``MIN_OBSERVATIONS`` residuals. A candidate for :func:`soft_wins` to confirm."""
    seen = np.isfinite(res)
    if (seen.sum(axis=0) >= MIN_OBSERVATIONS).sum() < 4:
        return 0.0
    median = float(np.median(res[seen]))
    return median / residual_floor_px(1.0) if median > 0 else 0.0


def residual_floor_px(noise_px: float) -> float:
    """The median residual against the graph's prediction that detection noise of std
    ``noise_px`` leaves on its own (pixels): what no re-solve can remove."""
    return FIT_RATIO * MEDIAN_RADIUS * noise_px


def observation_folds(visible: np.ndarray, count: int = FOLDS) -> np.ndarray:
    """(N, P) fold of every visible observation in 0 .. count - 1 (-1 where not visible), drawn
    from a fixed seed: the same capture always gets the same folds."""
    rng = np.random.default_rng(0)
    return np.where(visible, rng.integers(0, count, visible.shape), -1)


def image_folds(streams: np.ndarray, frames: np.ndarray, count: int = FOLDS) -> np.ndarray:
    """(N,) fold in 0 .. count - 1 of every image held out whole: the images inside a stream of
    three or more, in turn along it (a held-out image's neighbours in its stream stay in); -1
    for the rest (a stream's ends and lone photos: nothing places them without their
    detections)."""
    fold = np.full(streams.size, -1)
    for members in stream_members(streams, frames):
        if members.size >= 3:
            fold[members[1:-1]] = np.arange(members.size - 2) % count
    return fold


def soft_wins(hard_px: np.ndarray, soft_px: np.ndarray) -> bool:
    """Whether soft rays predicted the held-out detections better: median residual below
    ``MARGIN`` times hard rays' (both (M,) pixels over the same observations, NaN ignored)."""
    return bool(np.nanmedian(soft_px) < MARGIN * np.nanmedian(hard_px))
