"""Alternating convex search: the sweeps of one phase (W -> D -> X at one ray weight) with the
images re-sequenced as they go, the sequencing itself, the soft-ray weight and the soft phase's
stopping rule (docs/method.md, "The steps as implemented"). One event's solve, hard rays then
soft, runs them: ``pipeline.solve_event``."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .capture import Capture
from .embedding import line_embedding, mds_embedding, shape_embedding
from .events import SHORT_RUN, without_videos
from .options import Distance, Embedding, Options
from .problem import Normalised
from .rayplace import place_by_rays
from .robust import residuals_px
from .sequencing import (
    MDS_SAMPLE,
    affine_time,
    distance_matrix,
    orient,
    place_on_streams,
    stream_members,
)
from .steps import Problem, d_step, full_weights, temporal_ends, total_cost
from .wstep import select_candidates, w_step
from .xstep import x_step

logger = logging.getLogger("dloe_sfm")

Progress = Callable[[int, int, dict], None]
"""``progress(done, total, info)``: called after every sweep of a solve with the sweeps done so
far and the solve's sweep budget (hard plus soft phase); ``info`` holds the sweep's ``cost``
(total cost) and ``change`` (rms change of X, normalised units). A solve that converges before
its budget ends with one more call with ``done == total`` (same info). Every event and every
robust re-solve is a solve of its own: ``done`` starts again from 1. Within a solve it never
falls, sweeps that are later discarded (soft rays the held-out check rejects) included."""


def degrees(
    f: np.ndarray, prob: Problem, options: Options, D: np.ndarray | None = None
) -> np.ndarray:
    """D (default: fixed, all 1) with ``end_degree`` for the images at the ends of the time line."""
    D = np.ones(f.size) if D is None else D
    D[temporal_ends(f, prob.streams)] = options.end_degree
    return D


def sequence(
    X: np.ndarray, prob: Problem, frames: np.ndarray, options: Options, *, final: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """(prior embedding in length units, line embedding) of X, oriented by the streams.

    With the ``affine`` embedding and no two videos (``events.without_videos``), both are the
    shapes' line with the lone photos placed by their rays (:func:`lone_line`); with video
    streams, both come from the streams' affine clocks
    (the prior rescaled to the MDS embedding's length units, which the T term needs; that scale
    is measured on at most ``MDS_SAMPLE`` images spread over the capture, so no N x N table is
    made). Otherwise the loop uses classical MDS of the distances (fast) and ``final`` computes
    the order with ``options.embedding``.
    """
    if by_shapes(prob, options):
        f, _ = lone_line(X, prob, frames)
        return f, f
    needs_dtw = options.distance is Distance.ARC or options.embedding is Embedding.AFFINE
    placement = place_on_streams(X, prob.streams, frames) if needs_dtw else None
    if options.embedding is Embedding.AFFINE:
        t = affine_time(X, prob.streams, frames, placement, rates=prob.rates)
        if t is not None:
            sample = np.unique(np.linspace(0, t.size - 1, min(t.size, MDS_SAMPLE)).astype(int))
            Z = distance_matrix(X, prob.streams, frames, options.distance, placement, sample)
            mds = orient(mds_embedding(Z), prob.streams[sample], frames[sample])
            slope = np.polyfit(t[sample], mds, 1)[0]
            return t * abs(slope), t
    Z = distance_matrix(X, prob.streams, frames, options.distance, placement)
    mds = orient(mds_embedding(Z), prob.streams, frames)
    if not final or options.embedding is Embedding.MDS:
        return mds, mds
    kind = Embedding.SHP if options.embedding is Embedding.AFFINE else options.embedding
    return mds, orient(line_embedding(Z, kind), prob.streams, frames)


def by_shapes(prob: Problem, options: Options) -> bool:
    """Whether the images are sequenced by their shapes (:func:`lone_line`): the ``affine``
    embedding and no two videos (``events.without_videos``)."""
    return options.embedding is Embedding.AFFINE and without_videos(prob.streams)


def lone_line(
    X: np.ndarray, prob: Problem, frames: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(line embedding, order ambiguous) of images with no two videos (lone photos, bursts):
    the shapes' line (``embedding.shape_embedding``, oriented by the bursts), each lone photo
    then placed on it by its own rays and every burst (at most ``events.SHORT_RUN`` frames) by
    its frames' rays, in their order (``rayplace.place_by_rays``; which lone photos fit
    another time as well)."""
    f = orient(shape_embedding(X), prob.streams, frames)
    size = np.bincount(prob.streams)[prob.streams]
    bursts = [idx for idx in stream_members(prob.streams, frames)
              if 2 <= idx.size <= SHORT_RUN]
    return place_by_rays(X, prob.rays, prob.C, prob.visible, f, size == 1, bursts)


@dataclass(frozen=True)
class Best:
    """The lowest-cost iterate of a phase (normalised units)."""

    cost: float
    X: np.ndarray
    W_var: sp.csr_matrix
    W: sp.csr_matrix
    D: np.ndarray


@dataclass(frozen=True)
class Phase:
    """Up to ``budget`` sweeps at ray weight ``lambda2``; ``fit_px``: (callable, target) stops
    once the callable's median reprojection residual (pixels) of the best iterate is down to
    the target (the discrepancy principle of the soft phase); ``settled``: called with the best
    iterate's W and X every ``resequence_every`` sweeps (after the re-sequencing, so that a
    phase it stopped can be resumed), stops the phase when it returns a reason (the hard
    phase: ``decisions.HardRaysSettled``)."""

    lambda2: float
    budget: int
    fit_px: tuple[Callable[[np.ndarray], float], float] | None = None
    settled: Callable[[sp.csr_matrix, np.ndarray], str | None] | None = None


@dataclass
class Search:
    """The iterate of alternating convex search and its bookkeeping (normalised units)."""

    X: np.ndarray
    D: np.ndarray
    prior_f: np.ndarray
    f: np.ndarray
    total: int  # sweep budget of the whole solve (progress)
    progress: Progress | None = None
    swept: int = 0  # sweeps run, discarded ones included (progress)
    W_var: sp.csr_matrix | None = None
    costs: list = field(default_factory=list)
    changes: list = field(default_factory=list)
    best: Best | None = None
    timings: dict = field(default_factory=lambda: dict.fromkeys(
        ("init", "w_step", "d_step", "x_step", "sequencing", "clocks"), 0.0))


def alternate(
    st: Search, prob: Problem, frames: np.ndarray, options: Options, phase: Phase
) -> tuple[bool, str]:
    """The sweeps of one phase (W -> D -> X each, re-sequenced every ``resequence_every``);
    (converged, message)."""
    n = st.X.shape[0]
    lam = {"lambda1": options.lambda1, "lambda2": phase.lambda2, "lambda3": options.lambda3}
    st.best = None  # costs at another lambda2 are not comparable
    window = options.resequence_every
    for it in range(phase.budget):
        t0 = time.perf_counter()
        feats = st.prior_f[:, None] if options.spectral_prior else st.X.reshape(n, -1)
        prior = st.prior_f if options.spectral_prior else None
        cand = select_candidates(
            feats, prob, options.num_candidates, min_angle=options.min_ray_angle, keep=st.W_var
        )
        st.W_var = w_step(
            st.X,
            st.D,
            cand,
            prob,
            lambda1=options.lambda1,
            lambda3=options.lambda3,
            ridge=options.ridge,
            embedding=prior,
            start=st.W_var,
        )
        W = full_weights(st.W_var, prob)
        t1 = time.perf_counter()
        if not options.fixed_degree:
            D = d_step(
                st.X,
                W,
                prob,
                lambda1=options.lambda1,
                lambda3=options.lambda3,
                floor=options.degree_floor,
                embedding=prior,
            )
            st.D = degrees(st.f, prob, options, D)
        t2 = time.perf_counter()
        X_new = x_step(W, st.D, prob, lambda1=options.lambda1, lambda2=phase.lambda2,
                       X_prev=st.X)
        t3 = time.perf_counter()
        st.timings["w_step"] += t1 - t0
        st.timings["d_step"] += t2 - t1
        st.timings["x_step"] += t3 - t2
        cost = total_cost(X_new, W, st.D, prob, **lam)["total"]
        change = float(np.sqrt(np.mean((X_new - st.X) ** 2)))
        st.costs.append(cost)
        st.changes.append(change)
        st.swept += 1
        if st.progress is not None:
            st.progress(st.swept, st.total, {"cost": cost, "change": change})
        logger.debug("iteration %d: cost %.6e, rms change %.3e", len(st.costs), cost, change)
        if st.best is None or cost <= st.best.cost:
            st.best = Best(cost, X_new.copy(), st.W_var, W, st.D.copy())
            # over-relaxation: alternation creeps along smooth depth errors that W keeps
            # re-fitting; stepping omega times as far (affinely, so points stay on their rays)
            # cuts the number of sweeps; a step that raises the cost is undone below
            st.X = st.X + options.omega * (X_new - st.X)
        else:
            st.X, st.W_var, st.D = st.best.X.copy(), st.best.W_var, st.best.D.copy()
        if change < options.tolerance:
            return True, f"converged: rms change {change:.2e} < {options.tolerance:.0e}"
        if phase.fit_px is not None and (fit := phase.fit_px[0](st.best.X)) <= phase.fit_px[1]:
            return True, f"soft rays fit the detections to the noise level ({fit:.2f} px median)"
        recent = st.costs[-(it + 1) :]
        if (
            len(recent) > window
            and recent[-window - 1] - min(recent[-window:])
            <= options.cost_tolerance * recent[-window - 1]
        ):
            return (
                True,
                f"converged: cost fell by < {options.cost_tolerance:.0e} in {window} sweeps",
            )
        if (it + 1) % window == 0:
            t0 = time.perf_counter()
            st.prior_f, st.f = sequence(st.X, prob, frames, options)
            st.timings["sequencing"] += time.perf_counter() - t0
            if options.fixed_degree:
                st.D = degrees(st.f, prob, options)
            if phase.settled is not None and (why := phase.settled(st.best.W, st.best.X)):
                return True, why
    return False, f"stopped after {phase.budget} iterations"


def soft_ray_weight(capture: Capture, options: Options) -> float:
    """The lambda2 of the soft-ray phase for this capture's median focal length; inf (hard rays
    only) without a finite ray weight or with ``soft_iterations`` = 0. A weight beyond 1e12
    pins the points to their rays to double precision anyway, and from about 1e18 the X-step's
    system is singular: it is taken as inf too."""
    lambda2 = options.ray_weight(float(np.median(capture.K[:, [0, 1], [0, 1]])))
    return lambda2 if lambda2 <= 1e12 and options.soft_iterations > 0 else np.inf


def discrepancy(
    capture: Capture, options: Options, norm: Normalised
) -> tuple[Callable[[np.ndarray], float], float] | None:
    """(median reprojection residual of normalised X in pixels, its expected value) when the
    ray weight comes from ``noise_px``: the median radius of 2D Gaussian noise of std
    ``noise_px``, ``noise_px sqrt(2 ln 2)``. None with an explicit ``lambda2``.

    The first soft sweep moves the points off the noisy rays to where the hard-ray graph puts
    them, often farther from their detections than the noise; as W settles they come back.
    Once they are as far as the noise itself, more sweeps only fit W to the noise, while a noisy
    start needs tens of them (docs/method.md, "Departures from the paper", noisy detections).
    """
    if options.lambda2 is not None:
        return None

    def median_px(X: np.ndarray) -> float:
        return float(np.nanmedian(residuals_px(capture, norm.to_world(X))))

    return median_px, options.noise_px * np.sqrt(2.0 * np.log(2.0))
