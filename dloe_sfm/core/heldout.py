"""Held-out residuals: the evidence of the held-out checks (``core.decisions``; docs/method.md,
"Held-out checks").

Each candidate model predicts detections it was not given: the observations or images of one
fold are left out, the rest solved from the model's own solution, and the left-out detections'
pixel residuals compared. Observation folds (:func:`observation_folds`) ask whether the
detections are exact (the image's other points fix when it was taken); whole images held out
(:func:`image_folds`) ask when each image was taken, and along the stream clocks they also see
the depth errors that hard rays keep from noisy detections, which single held-out detections
cannot. A check solves at most :data:`CHECK_IMAGES` images in the middle of the time line
(:func:`middle_window`). Each subject's detections held out whole (:func:`held_out_subjects`) ask
whether a subject follows a motion at all.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np

from .alternation import Phase, Search, alternate, sequence, soft_ray_weight
from .capture import Capture
from .clocks import time_chain
from .options import Options
from .problem import normalise
from .result import Result
from .robust import residuals_px
from .sequencing import stream_members
from .xstep import x_step

FOLDS = 3
"""Folds of the held-out checks."""

FOLD_SWEEPS = 5
"""Sweeps of each fold's solve by DLOE's graph, started from the model's solution."""

CHECK_IMAGES = 1000
"""Images (the middle of the time line) the held-out checks solve: a choice of model, which a
stretch of the capture answers as well as all of it."""


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


def middle_window(
    capture: Capture, f: np.ndarray, size: int = CHECK_IMAGES
) -> tuple[np.ndarray, Capture]:
    """(sorted indices, capture) of the (at most) ``size`` images in the middle of the time line
    ``f``: the capture itself when it has no more."""
    if f.size <= size:
        return np.arange(f.size), capture
    lo = (f.size - size) // 2
    window = np.sort(np.argsort(f, kind="stable")[lo:lo + size])
    return window, capture.subset(window)


def held_out_px(
    capture: Capture,
    options: Options,
    X_world: np.ndarray,
    D: np.ndarray,
    lambda2: float,
    *,
    times: np.ndarray | None = None,
    images: bool = False,
) -> np.ndarray:
    """Pixel residuals of held-out detections predicted without them (NaN behind the camera).

    Each fold is left out in turn and the rest solved from ``X_world`` (world units) at ray
    weight ``lambda2``: by DLOE's graph (:data:`FOLD_SWEEPS` sweeps of the alternation from
    degrees ``D``), or with ``times`` by the X-step on the chain along those times
    (``clocks.time_chain``, as the clocks place the points). The folds are observations
    (:func:`observation_folds`: the image's other points fix when it was taken, so the
    check is on the detections' noise), or with ``images`` whole images
    (:func:`image_folds`: the check is on when each image was taken). A held-out image starts
    from the X-step on the chain along the model's own time line (the graph's: its sequencing
    embedding), which links it to images of other streams: started from its own stream's
    neighbours, whose points lie on the same camera's rays, the graph would be handed that
    camera's view of the held-out instant (docs/method.md, "Stream clocks")."""
    norm = normalise(capture, options, X_world)
    prob = norm.problem
    X = norm.to_normal(X_world)
    if times is None:
        prior_f, f = sequence(X, prob, capture.frame, options)
    if images or times is not None:  # the chain along the model's own time line
        W, D_chain = time_chain(np.ravel(f) if times is None else times)
    if images:
        fold = np.repeat(image_folds(prob.streams, capture.frame)[:, None], X.shape[1], axis=1)
        fold[~prob.visible] = -1
        # points the chain leaves undetermined: from the stream neighbours' mean, not their own
        fill = (prob.chain @ X.reshape(X.shape[0], -1)).reshape(X.shape)
    else:
        fold = observation_folds(prob.visible)
    out = np.full(fold.shape, np.nan)
    for k in range(int(fold.max()) + 1):
        held = fold == k
        pk = replace(prob, weights=np.where(held, 0.0, prob.weights),
                     rays=np.where(held[..., None], np.nan, prob.rays))
        start = X
        if images or times is not None:
            prev = X
            if images:
                outside = held.any(axis=1)[:, None, None]
                prev = np.where(outside, fill, X)
            chained = x_step(W, D_chain, pk, lambda1=0.0, lambda2=lambda2, X_prev=prev)
            if times is not None:
                out[held] = residuals_px(capture, norm.to_world(chained))[held]
                continue
            start = np.where(outside, chained, X)  # the graph's held-out images
        sk = Search(X=start.copy(), D=D.copy(), prior_f=prior_f, f=f, total=FOLD_SWEEPS)
        alternate(sk, pk, capture.frame, options, Phase(lambda2, FOLD_SWEEPS))
        out[held] = residuals_px(capture, norm.to_world(sk.best.X))[held]
    return out[fold >= 0]


def held_out_subjects(
    capture: Capture, subjects: int, result: Result, options: Options, folds: int = FOLDS
) -> np.ndarray:
    """(N, S) median pixel residual of each subject's detection in each image, predicted by
    ``result``'s graph without it (NaN where the image does not see the subject).

    ``capture``: the aggregated capture ``result`` solved (columns s P .. s P + P - 1 are
    subject s). The (image, subject) pairs fall in ``folds`` folds (fixed seed); each fold's
    detections are held out whole and the rest solved by one X-step on the solution's W and D,
    at the ray weight of the noise it found. A person's detection is predicted about as well as
    the graph predicts any other (its neighbours in time see the same motion); a detection that
    only fits because its own rays pull its neighbours' points is predicted far off."""
    n, p = capture.num_images, capture.num_points // subjects
    options = options.replace(noise_px=result.noise_px)
    norm = normalise(capture, options, result.X)
    prob = norm.problem
    X = norm.to_normal(result.X)
    lambda2 = soft_ray_weight(capture, options)
    fold = np.random.default_rng(0).integers(0, folds, (n, subjects))
    out = np.full((n, subjects), np.nan)
    for k in range(folds):
        held = np.repeat(fold == k, p, axis=1) & prob.visible
        pk = replace(prob, weights=np.where(held, 0.0, prob.weights),
                     rays=np.where(held[..., None], np.nan, prob.rays))
        Xk = x_step(result.W, result.D, pk, lambda1=options.lambda1, lambda2=lambda2, X_prev=X)
        res = np.where(held, residuals_px(capture, norm.to_world(Xk)), np.nan)
        seen = held.reshape(n, subjects, p).any(axis=2)
        with warnings.catch_warnings():  # all-NaN rows: points behind the camera
            warnings.simplefilter("ignore", RuntimeWarning)
            out[seen] = np.nanmedian(res.reshape(n, subjects, p)[seen], axis=1)
    return out
