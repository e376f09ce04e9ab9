"""The solver's decisions: the model choices made on held-out detections (docs/method.md,
"Held-out checks"; the evidence: ``core.heldout``).
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp

from .alternation import Best, Search, soft_ray_weight
from .capture import Capture
from .heldout import held_out_px, middle_window
from .noise import estimate_noise_px
from .options import Options
from .problem import Normalised
from .robust import predicted, residuals_px

logger = logging.getLogger("dloe_sfm")

SOFT_MARGIN = 0.95
"""Soft rays are taken when their median held-out residual is below this fraction of hard
rays' (a tie keeps the detections exact)."""

CHAIN_MIN_PX = 1.0
"""Soft rays along the stream clocks (:func:`soft_rays_on_clocks`) are tried from this level up.
Below a pixel, the level the graph's fit leaves is the SfM cameras' error and the fit's own,
which soft rays trade in ways held-out images cannot judge: the demo at 0.58 px predicts them
0.70 x as far off, yet its error goes 6.11 -> 7.24 mm; detectors' noise is several pixels
(docs/method.md, "Held-out checks")."""


def soft_wins(hard_px: np.ndarray, soft_px: np.ndarray) -> bool:
    """Whether soft rays predicted the held-out detections better: median residual below
    ``SOFT_MARGIN`` times hard rays' (both (M,) pixels over the same observations, NaN ignored)."""
    return bool(np.nanmedian(soft_px) < SOFT_MARGIN * np.nanmedian(hard_px))


def soft_rays_kept(
    capture: Capture, options: Options, norm: Normalised, hard: Best, st: Search
) -> bool:
    """Whether the soft-ray solution ``st.best`` (at ``options.noise_px``, the estimate of
    ``auto``) predicts held-out detections better than the hard-ray one ``hard``
    (:func:`soft_wins`; observation folds, each model's folds started from its own solution,
    on at most ``heldout.CHECK_IMAGES`` images in the middle of the time line), logged."""
    window, sub = middle_window(capture, st.f)
    hard_px = held_out_px(sub, options.replace(noise_px=0.0), norm.to_world(hard.X)[window],
                          hard.D[window], np.inf)
    soft_px = held_out_px(sub, options, norm.to_world(st.best.X)[window], st.best.D[window],
                          soft_ray_weight(capture, options))
    wins = soft_wins(hard_px, soft_px)
    logger.info("held-out detections, median residual: hard rays %.2f px, soft rays at %.2f px "
                "noise %.2f px: %s", np.nanmedian(hard_px), options.noise_px,
                np.nanmedian(soft_px), "soft rays kept" if wins else "hard rays kept")
    return wins


def soft_rays_on_clocks(
    capture: Capture, options: Options, X_world: np.ndarray, D: np.ndarray, W_graph: sp.spmatrix,
    t: np.ndarray
) -> tuple[float, np.ndarray | None]:
    """The detection noise (pixels) of one event placed on its clocks ``t`` whose graph solve
    kept hard rays: the level the graph's fit ``W_graph`` leaves (``noise.estimate_noise_px``),
    if it is at least :data:`CHAIN_MIN_PX` and soft rays at it predict held-out images,
    chained along the clocks, better than hard rays (:func:`soft_wins`); else 0. With it, the
    held-out residuals of the rays kept (None when the level was not tried). Logged when tried.

    The graph's own check (:func:`soft_rays_kept`) holds out single detections: the
    image's other points fix its shape, and the depth error along the camera's rays that hard
    rays keep from noisy detections does not show. A held-out image is predicted from other
    cameras' images, and their depth errors show in it (docs/method.md, "Held-out checks")."""
    candidate = estimate_noise_px(residuals_px(capture, predicted(W_graph, X_world)))
    if candidate < CHAIN_MIN_PX:
        return 0.0, None
    window, sub = middle_window(capture, t)
    soft = options.replace(noise_px=candidate)
    hard_px = held_out_px(sub, options, X_world[window], D[window],
                          soft_ray_weight(capture, options), times=t[window], images=True)
    soft_px = held_out_px(sub, soft, X_world[window], D[window], soft_ray_weight(capture, soft),
                          times=t[window], images=True)
    wins = soft_wins(hard_px, soft_px)
    logger.info("held-out images along the stream clocks, median residual: hard rays %.2f px, "
                "soft rays at %.2f px noise %.2f px: %s", np.nanmedian(hard_px), candidate,
                np.nanmedian(soft_px), "soft rays kept" if wins else "hard rays kept")
    return (candidate, soft_px) if wins else (0.0, hard_px)
