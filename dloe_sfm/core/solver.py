"""Alternating convex search for DLOE (Xu & Dunn, ICCV 2019) and the true-order oracle."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from tqdm.auto import tqdm

from ..errors import InputError
from .capture import Capture
from .clocks import fit_clocks, ray_equations, time_chain
from .events import segment_events
from .init import fill_missing, pseudo_triangulate
from .options import Distance, Embedding, Options, RobustLoss
from .result import Result
from .robust import (
    apply_swaps,
    find_swaps,
    loss_scale,
    loss_weights,
    predicted,
    residuals_px,
    reweighted,
)
from .sequencing import (
    affine_time,
    distance_matrix,
    line_embedding,
    mds_embedding,
    order_from_embedding,
    orient,
    place_on_streams,
)
from .steps import (
    Problem,
    chain_matrix,
    d_step,
    full_weights,
    select_candidates,
    temporal_ends,
    total_cost,
    w_step,
    x_step,
)

logger = logging.getLogger("dloe_sfm")


def normalisation(capture: Capture, X0: np.ndarray) -> tuple[np.ndarray, float]:
    """Origin and scale of the normalised frame: scene centroid, median camera-to-point distance."""
    origin = np.nanmean(X0.reshape(-1, 3), axis=0)
    dist = np.linalg.norm(X0 - capture.C[:, None, :], axis=2)
    scale = float(np.nanmedian(dist))
    return origin, scale if np.isfinite(scale) and scale > 0 else 1.0


def build_problem(capture: Capture, options: Options, origin: np.ndarray, scale: float) -> Problem:
    """The fixed data of a solve in normalised units."""
    rays = capture.rays()
    weights = capture.weights
    rays[weights <= 0] = np.nan
    streams = capture.stream_ids
    view = np.nansum(rays, axis=1)
    blind = ~np.isfinite(rays).all(axis=2).any(axis=1)
    view[blind] = capture.R[blind, 2]  # no observation left (all rejected): the optical axis
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    chain = chain_matrix(streams, capture.frame)
    has_chain = np.asarray(chain.sum(axis=1)).ravel() > 0
    return Problem(
        rays=rays,
        C=(capture.C - origin) / scale,
        weights=weights,
        streams=streams,
        view_dirs=view,
        chain=chain,
        prior=np.where(has_chain, options.prior_weight, 0.0),
    )


def initialise(capture: Capture, options: Options) -> np.ndarray:
    """Pseudo-triangulated (N, P, 3) shapes in world units (unobserved points interpolated)."""
    rays = capture.rays()
    rays[capture.weights <= 0] = np.nan
    depths, _ = pseudo_triangulate(
        rays, capture.C, capture.stream_ids, capture.frame, min_angle=options.min_ray_angle
    )
    X0 = capture.C[:, None, :] + depths[..., None] * rays
    if not np.isfinite(depths).any():
        raise InputError(
            f"no two images of different streams see a point at least {options.min_ray_angle:g} "
            "degrees from (anti)parallel (option 'min_ray_angle'): nothing to triangulate"
        )
    return fill_missing(X0, capture.stream_ids, capture.frame)


def _degrees(
    f: np.ndarray, prob: Problem, options: Options, D: np.ndarray | None = None
) -> np.ndarray:
    """D (default: fixed, all 1) with ``end_degree`` for the images at the ends of the time line."""
    D = np.ones(f.size) if D is None else D
    D[temporal_ends(f, prob.streams)] = options.end_degree
    return D


def _sequence(
    X: np.ndarray, prob: Problem, frames: np.ndarray, options: Options, *, final: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """(prior embedding in length units, line embedding) of X, oriented by the streams.

    With the ``affine`` embedding and video streams, both come from the streams' affine clocks
    (the prior rescaled to the MDS embedding's length units, which the T term needs). Otherwise
    the loop uses classical MDS of the distances (fast) and ``final`` computes the order with
    ``options.embedding``.
    """
    needs_dtw = options.distance is Distance.ARC or options.embedding is Embedding.AFFINE
    placement = place_on_streams(X, prob.streams, frames) if needs_dtw else None
    Z = distance_matrix(X, prob.streams, frames, options.distance, placement)
    mds = orient(mds_embedding(Z), prob.streams, frames)
    if options.embedding is Embedding.AFFINE:
        t = affine_time(X, prob.streams, frames, placement)
        if t is not None:
            slope = np.polyfit(t, mds, 1)[0]
            return t * abs(slope), t
    if not final or options.embedding is Embedding.MDS:
        return mds, mds
    kind = Embedding.SHP if options.embedding is Embedding.AFFINE else options.embedding
    return mds, orient(line_embedding(Z, kind), prob.streams, frames)


def reconstruct(capture: Capture, options: Options | None = None) -> Result:
    """Estimate every image's 3D points and the images' temporal graph and order.

    ``capture`` must be valid (``Capture.validate``). Returns a :class:`Result` in world units.
    With ``options.segment_events``, temporally disjoint events are found first (connected
    components of a W fitted in shape space to the initial shapes: time-line candidates would
    bridge events) and each event is sequenced and reconstructed on its own. With a robust loss
    (or symmetric pairs to check) the observations are then reweighted from the solution's
    residuals and the capture re-solved (``_reweight``). With stream clocks
    (``options.clocks_on``) every event filmed by videos is finally placed on its streams'
    fitted clocks (``_clocked``). A capture with several detections per image goes to
    :func:`dloe_sfm.core.multitarget.reconstruct_subjects`.
    """
    options = options or Options()
    if capture.x.ndim == 4:
        from .multitarget import reconstruct_subjects

        return reconstruct_subjects(capture, options)
    started = time.perf_counter()
    X_world = initialise(capture, options)
    labels = np.zeros(capture.num_images, dtype=np.int64)
    if options.segment_events:
        labels = initial_events(capture, options, X_world)
    init_seconds = time.perf_counter() - started
    result = _solve_all(capture, options, labels, X_world)
    result, solved = _reweight(capture, options, labels, result)
    if options.clocks_on:
        result = _clocked(solved, options, result)
    result.timings["init"] += init_seconds
    result.seconds = time.perf_counter() - started
    return result


def _solve_all(
    capture: Capture, options: Options, labels: np.ndarray, X_world: np.ndarray | None
) -> Result:
    """One event: ``_solve`` from ``X_world``; several: ``_solve_events`` (each event then
    initialised on its own unless a warm start ``X_world`` is given)."""
    if labels.max() > 0:
        return _solve_events(capture, options, labels, X_world)
    return _solve(capture, options, X_world)


def _reweight(
    capture: Capture, options: Options, labels: np.ndarray, result: Result
) -> tuple[Result, Capture]:
    """Iteratively reweighted re-solves against wrong detections and left/right swaps.

    Each round predicts every observation from the graph (``W X``), exchanges symmetric pairs
    that fit far better swapped, weights every observation by the robust loss of its residual
    (pixels), drops those weighted below 1/2 and re-solves from a fresh initialisation (one
    from shapes bent by the outliers stays bent). The first re-solve is kept only if it
    predicts the observations it used at least 5 % better (median residual) than the plain
    solve: real outliers bend the graph, so removing them tightens the fit, while at coarse
    sampling the largest residuals are the graph's own interpolation errors and dropping them
    helps nothing (sparse jumping: 92 mm with them dropped, 17 mm without). Stops when no pair
    was swapped and the rejected set changed by at most 0.1 % of the observations.
    ``result.outliers`` lists the observations the final solve left out, ``result.swaps``
    every exchange kept. Also returns the capture the result was solved on (swaps undone,
    observations reweighted).
    """
    robust = options.robust_loss is not RobustLoss.NONE
    pairs = capture.symmetric_pairs if options.fix_swaps else None
    if not robust and (pairs is None or pairs.size == 0):
        return result, capture
    current, swaps = capture, np.zeros((0, 3), dtype=np.int64)
    solved = capture
    rejected = np.zeros(capture.x.shape[:2], dtype=bool)
    plain, expected = result, None
    for it in range(options.robust_iterations + 1):
        X_pred = predicted(result.W, result.X)
        res = residuals_px(current, X_pred)
        if it == 1 and (fit := float(np.nanmedian(res[~rejected]))) > 0.95 * expected:
            logger.info("robust round 1 undone: the fit did not tighten (median residual "
                        "%.2f -> %.2f px)", expected, fit)
            result, current, swaps, solved = plain, capture, swaps[:0], capture
            rejected = np.zeros_like(rejected)
            break
        scale = loss_scale(res, options.robust_scale_px)
        new = find_swaps(current, X_pred, pairs, scale) if pairs is not None else swaps[:0]
        trial = apply_swaps(current, new) if new.size else current
        res = residuals_px(trial, X_pred)
        weights = loss_weights(res, scale, options.robust_loss)
        now = weights < 0.5
        if now.sum() > 0.5 * current.visible.sum():
            # a loss that drops most of the data is no longer rejecting outliers
            logger.warning("robust round %d not run: the loss scale (%.3g px median) would drop "
                           "%d of %d observations (robust_scale_px below the noise?)", it + 1,
                           float(np.median(scale)), int(now.sum()), int(current.visible.sum()))
            break
        settled = (now != rejected).sum() <= 1e-3 * current.visible.sum()
        if it == options.robust_iterations or (not new.size and settled):
            break
        expected = float(np.nanmedian(res[~now]))
        current, swaps, rejected = trial, np.concatenate([swaps, new]), now
        logger.info("robust round %d: %d swap(s), %d observation(s) beyond %.1f px (median)",
                    it + 1, len(new), int(rejected.sum()), float(np.median(scale)))
        previous = result
        solved = reweighted(current, weights) if robust else current
        result = _solve_all(solved, options, labels, None)
        result.nit += previous.nit
        result.timings = {k: v + previous.timings.get(k, 0.0) for k, v in result.timings.items()}
    if swaps.size:
        result.solved = current
    result.swaps = swaps
    img, col = np.nonzero(rejected)
    result.outliers = np.stack([img, col], axis=1).astype(np.int64)
    result.outlier_residual_px = residuals_px(current, predicted(result.W, result.X))[img, col]
    return result, solved


def shape_space_graph(capture: Capture, options: Options, X_world: np.ndarray) -> sp.csr_matrix:
    """W_var of one W-step on shapes ``X_world`` with candidates and compactness in shape space
    (no time line yet: it is what events and subjects are found from)."""
    origin, scale = normalisation(capture, X_world)
    prob = build_problem(capture, options, origin, scale)
    X = (X_world - origin) / scale
    n = X.shape[0]
    cand = select_candidates(
        X.reshape(n, -1), prob, options.num_candidates, min_angle=options.min_ray_angle
    )
    return w_step(
        X, np.ones(n), cand, prob,
        lambda1=options.lambda1, lambda3=options.lambda3, ridge=options.ridge,
    )


def initial_events(capture: Capture, options: Options, X_world: np.ndarray) -> np.ndarray:
    """(N,) event labels from the shape-space W of the initial shapes (``shape_space_graph``).

    The graph is W_var alone: the chain prior would tie the last image of one event to the
    first of the next in every stream. An event seen by fewer than two streams cannot be
    triangulated; it joins the largest event.
    """
    W_var = shape_space_graph(capture, options, X_world)
    labels = segment_events(W_var, capture.stream, capture.frame)
    sizes = np.bincount(labels)
    for e in range(labels.max() + 1):
        if np.unique(capture.stream_ids[labels == e]).size < 2:
            labels[labels == e] = np.argmax(sizes)
    _, labels = np.unique(labels, return_inverse=True)
    return labels


def _solve_events(
    capture: Capture, options: Options, labels: np.ndarray, X_world: np.ndarray | None = None
) -> Result:
    """Solve every event on its own (from ``X_world`` when given) and assemble one result
    (orders concatenated by event)."""
    n, p = capture.num_images, capture.num_points
    X = np.empty((n, p, 3))
    embedding = np.empty(n)
    D = np.empty(n)
    A_parts, W_parts, order, results = [], [], [], []
    offset = 0.0
    for e in range(int(labels.max()) + 1):
        idx = np.flatnonzero(labels == e)
        logger.info("event %d: %d images", e, idx.size)
        r = _solve(capture.subset(idx), options, None if X_world is None else X_world[idx])
        results.append(r)
        X[idx], D[idx] = r.X, r.D
        embedding[idx] = r.embedding - r.embedding.min() + offset
        offset = embedding[idx].max() + 1.0
        order.append(idx[r.order])
        for parts, M in ((A_parts, r.A), (W_parts, r.W)):
            coo = M.tocoo()
            parts.append((coo.data, idx[coo.row], idx[coo.col]))

    def assemble(parts: list) -> sp.csr_matrix:
        data, rows, cols = (np.concatenate(v) for v in zip(*parts, strict=True))
        return sp.csr_matrix((data, (rows, cols)), shape=(n, n))

    return Result(
        X=X,
        order=np.concatenate(order),
        A=assemble(A_parts),
        W=assemble(W_parts),
        D=D,
        events=labels,
        embedding=embedding,
        cost_history=np.concatenate([r.cost_history for r in results]),
        change_history=np.concatenate([r.change_history for r in results]),
        nit=sum(r.nit for r in results),
        success=all(r.success for r in results),
        message="; ".join(f"event {e}: {r.message}" for e, r in enumerate(results)),
        seconds=sum(r.seconds for r in results),
        timings={k: sum(r.timings.get(k, 0.0) for r in results) for k in results[0].timings},
        scale=results[0].scale,
    )


@dataclass
class _State:
    """The iterate of alternating convex search and its bookkeeping (normalised units)."""

    X: np.ndarray
    D: np.ndarray
    prior_f: np.ndarray
    f: np.ndarray
    W_var: sp.csr_matrix | None = None
    costs: list = field(default_factory=list)
    changes: list = field(default_factory=list)
    best: tuple | None = None


def _alternate(
    st: _State,
    prob: Problem,
    frames: np.ndarray,
    options: Options,
    lambda2: float,
    budget: int,
    timings: dict,
    bar,
    fit_px: tuple[Callable[[np.ndarray], float], float] | None = None,
) -> tuple[bool, str]:
    """Up to ``budget`` W -> D -> X sweeps at ray weight ``lambda2``; (converged, message).

    ``fit_px``: (callable, target): stop once the callable's median reprojection residual (pixels)
    of the best iterate is down to the target (the discrepancy principle of the soft phase).
    """
    n = st.X.shape[0]
    lam = {"lambda1": options.lambda1, "lambda2": lambda2, "lambda3": options.lambda3}
    st.best = None  # costs at another lambda2 are not comparable
    window = options.resequence_every
    for it in range(budget):
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
            st.D = _degrees(st.f, prob, options, D)
        t2 = time.perf_counter()
        X_new = x_step(W, st.D, prob, lambda1=options.lambda1, lambda2=lambda2, X_prev=st.X)
        t3 = time.perf_counter()
        timings["w_step"] += t1 - t0
        timings["d_step"] += t2 - t1
        timings["x_step"] += t3 - t2
        cost = total_cost(X_new, W, st.D, prob, **lam)["total"]
        change = float(np.sqrt(np.mean((X_new - st.X) ** 2)))
        st.costs.append(cost)
        st.changes.append(change)
        bar.update()
        bar.set_postfix(cost=f"{cost:.3e}", change=f"{change:.1e}")
        logger.debug("iteration %d: cost %.6e, rms change %.3e", len(st.costs), cost, change)
        if st.best is None or cost <= st.best[0]:
            st.best = (cost, X_new.copy(), st.W_var, W, st.D.copy())
            # over-relaxation: alternation creeps along smooth depth errors that W keeps
            # re-fitting; stepping omega times as far (affinely, so points stay on their rays)
            # cuts the number of sweeps; a step that raises the cost is undone below
            st.X = st.X + options.omega * (X_new - st.X)
        else:
            st.X, st.W_var, st.D = st.best[1].copy(), st.best[2], st.best[4].copy()
        if change < options.tolerance:
            return True, f"converged: rms change {change:.2e} < {options.tolerance:.0e}"
        if fit_px is not None and (fit := fit_px[0](st.best[1])) <= fit_px[1]:
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
            st.prior_f, st.f = _sequence(st.X, prob, frames, options)
            timings["sequencing"] += time.perf_counter() - t0
            if options.fixed_degree:
                st.D = _degrees(st.f, prob, options)
    return False, f"stopped after {budget} iterations"


def _solve(capture: Capture, options: Options, X_world: np.ndarray | None = None) -> Result:
    """One event: init (unless given), alternation, sequencing."""
    t_start = time.perf_counter()
    timings = {"init": 0.0, "w_step": 0.0, "d_step": 0.0, "x_step": 0.0, "sequencing": 0.0,
               "clocks": 0.0}
    if X_world is None:
        X_world = initialise(capture, options)
    origin, scale = normalisation(capture, X_world)
    prob = build_problem(capture, options, origin, scale)
    X = (X_world - origin) / scale
    timings["init"] = time.perf_counter() - t_start
    t0 = time.perf_counter()
    prior_f, f = _sequence(X, prob, capture.frame, options)
    timings["sequencing"] += time.perf_counter() - t0
    st = _State(X=X, D=_degrees(f, prob, options), prior_f=prior_f, f=f)
    lambda2 = _soft_ray_weight(capture, options)
    soft = np.isfinite(lambda2)
    total = options.max_iterations + (options.soft_iterations if soft else 0)
    with tqdm(
        total=total, desc="DLOE", unit="it", leave=False, disable=not options.progress
    ) as bar:
        # soft rays start from the hard-ray solution: its X-steps are several times cheaper and
        # settle W first; the soft phase then only refines
        success, message = _alternate(
            st, prob, capture.frame, options, np.inf, options.max_iterations, timings, bar
        )
        if soft:
            st.X = st.best[1].copy()
            success, message = _alternate(
                st, prob, capture.frame, options, lambda2, options.soft_iterations, timings, bar,
                _discrepancy(capture, options, origin, scale),
            )
        bar.total = bar.n  # converged before the iteration cap: the bar ends at 100 %
        bar.refresh()
    _, X, _, W, D = st.best
    t0 = time.perf_counter()
    _, f = _sequence(X, prob, capture.frame, options, final=True)
    timings["sequencing"] += time.perf_counter() - t0
    A = sp.csr_matrix(sp.diags(D) @ W)
    return Result(
        X=X * scale + origin,
        order=order_from_embedding(f),
        A=A,
        W=W,
        D=D,
        events=segment_events(A, capture.stream, capture.frame),
        embedding=f * scale,
        cost_history=np.array(st.costs),
        change_history=np.array(st.changes),
        nit=len(st.costs),
        success=success,
        message=message,
        seconds=time.perf_counter() - t_start,
        timings=timings,
        scale=scale,
    )


def _clocked(capture: Capture, options: Options, result: Result) -> Result:
    """``result`` with every event that is filmed by videos (two or more streams of three or
    more frames) placed on its streams' fitted affine clocks (``core.clocks``): the points by
    the X-step on the chain along the clocks (soft rays with ``noise_px``, as the solve), its
    W and D rows that chain's, its block of the order and its embedding (span kept) from the
    clocks. ``capture`` is the one the result was solved on (``_reweight``); an event whose
    clocks the rays do not pin keeps DLOE's graph. ``result.clock`` holds the times.
    """
    t_start = time.perf_counter()
    n = capture.num_images
    X, D = result.X.copy(), result.D.copy()
    order, embedding, rank = result.order.copy(), result.embedding.copy(), result.rank
    clock = np.full(n, np.nan)
    chains = []  # (data, rows, cols) of every clocked event's W
    for e in range(int(result.events.max()) + 1):
        idx = np.flatnonzero(result.events == e)
        ids, counts = np.unique(capture.stream_ids[idx], return_counts=True)
        if ids.size < 2 or counts.min() < 3:
            continue
        sub = capture.subset(idx) if idx.size < n else capture
        origin, scale = normalisation(sub, X[idx])
        prob = build_problem(sub, options, origin, scale)
        Xe = (X[idx] - origin) / scale
        t0 = affine_time(Xe, prob.streams, sub.frame)
        E, rhs = ray_equations(prob.rays, prob.C, prob.weights)
        t = None if t0 is None else fit_clocks(t0, prob.streams, sub.frame, E, rhs, prob.visible,
                                                shared_rate=options.shared_rate)
        if t is None:
            logger.info("event %d: the rays do not pin the streams' clocks (one moved by more "
                        "than a frame period); DLOE's graph is kept", e)
            continue
        # the chain's weights come from the time line: no compactness term (as the oracle)
        W, D[idx] = time_chain(t)
        Xe = x_step(W, D[idx], prob, lambda1=0.0, lambda2=_soft_ray_weight(sub, options),
                    X_prev=Xe)
        X[idx], clock[idx] = Xe * scale + origin, t
        coo = W.tocoo()
        chains.append((coo.data, idx[coo.row], idx[coo.col]))
        order[np.sort(rank[idx])] = idx[np.argsort(t, kind="stable")]
        lo, hi = embedding[idx].min(), embedding[idx].max()
        embedding[idx] = lo + (t - t.min()) * (hi - lo) / max(np.ptp(t), 1e-300)
    if chains:
        coo = result.W.tocoo()
        dloe = np.isnan(clock)[coo.row]  # rows of the events left to DLOE's graph
        chains.append((coo.data[dloe], coo.row[dloe], coo.col[dloe]))
        data, rows, cols = (np.concatenate(v) for v in zip(*chains, strict=True))
        result.W = sp.csr_matrix((data, (rows, cols)), shape=(n, n))
        result.A = sp.csr_matrix(sp.diags(D) @ result.W)
        result.X, result.D, result.clock = X, D, clock
        result.order, result.embedding = order, embedding
    result.timings["clocks"] = time.perf_counter() - t_start
    return result


def _soft_ray_weight(capture: Capture, options: Options) -> float:
    """The lambda2 of the soft-ray phase for this capture's median focal length; inf (hard rays
    only) without a finite ray weight or with ``soft_iterations`` = 0. A weight beyond 1e12
    pins the points to their rays to double precision anyway, and from about 1e18 the X-step's
    system is singular: it is taken as inf too."""
    lambda2 = options.ray_weight(float(np.median(capture.K[:, [0, 1], [0, 1]])))
    return lambda2 if lambda2 <= 1e12 and options.soft_iterations > 0 else np.inf


def _discrepancy(
    capture: Capture, options: Options, origin: np.ndarray, scale: float
) -> tuple[Callable[[np.ndarray], float], float] | None:
    """(median reprojection residual of normalised X in pixels, its expected value) when the
    ray weight comes from ``noise_px``: the median radius of 2D Gaussian noise of std
    ``noise_px``, ``noise_px sqrt(2 ln 2)``. None with an explicit ``lambda2``.

    The first soft sweep moves the points off the noisy rays to where the hard-ray graph puts
    them, often farther from their detections than the noise (running at 5 px: a median of
    1.7 sigma); as W settles they come back. Once they are as far as the noise itself, more
    sweeps only fit W to the noise (walking at 1 px: 4.0 mm after 4 sweeps, 4.6 after 40), while
    a noisy start needs tens of them (running at 5 px: 38.6 mm after 8, 25.5 after 60).
    """
    if options.lambda2 is not None:
        return None

    def median_px(X: np.ndarray) -> float:
        return float(np.nanmedian(residuals_px(capture, X * scale + origin)))

    return median_px, options.noise_px * np.sqrt(2.0 * np.log(2.0))


def oracle_reconstruct(
    capture: Capture, times: np.ndarray, *, lambda1: float = 0.0, lambda2: float = np.inf
) -> np.ndarray:
    """DLOE's X-step with the true temporal chain as W: the accuracy reference.

    Every image is linked to its temporal predecessor and successor among all images, with
    barycentric weights from the true times (so constant-velocity motion is reproduced exactly).
    The first and last images have no neighbour on one side: their rows get D = 0, and they are
    placed by their neighbours' rows. Returns (N, P, 3) in world units.
    """
    W, D = time_chain(times)
    options = Options()
    X0 = initialise(capture, options)
    origin, scale = normalisation(capture, X0)
    prob = build_problem(capture, options, origin, scale)
    X = x_step(W, D, prob, lambda1=lambda1, lambda2=lambda2, X_prev=(X0 - origin) / scale)
    return X * scale + origin
