"""One subject's reconstruction as a pipeline: initialise -> events -> per event: alternate ->
robust rounds -> clocks -> assemble (docs/method.md, "The steps as implemented")."""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from ..errors import InputError
from .alternation import (
    Phase,
    Progress,
    Search,
    alternate,
    degrees,
    discrepancy,
    sequence,
    soft_ray_weight,
)
from .bias import GAIN, stream_offsets, without_offsets
from .capture import Capture
from .clocks import (
    REACH,
    chain_predicted,
    fit_clocks,
    moved_periods,
    time_chain,
)
from .decisions import (
    Verdict,
    clock_verdict,
    clocks_checked,
    fit_trusted,
    soft_rays_kept,
    soft_rays_on_clocks,
)
from .events import segment_events
from .noise import estimate_noise_px, residual_floor_px
from .options import AUTO, Clocks, Options, RobustLoss
from .parallel import map_in_processes, worker_count
from .problem import Normalised, assemble, build_problem, initialise, normalise, parts
from .result import Result, merged_history
from .robust import (
    apply_swaps,
    find_swaps,
    loss_scale,
    loss_weights,
    predicted,
    residuals_px,
    reweighted,
    spare_mispredicted,
)
from .sequencing import affine_time, order_from_embedding
from .splines import ray_equations
from .steps import Problem
from .wstep import select_candidates, w_step
from .xstep import x_step

logger = logging.getLogger("dloe_sfm")

MOST_OF_AN_IMAGE = 0.5
"""Share of an image's observations beyond which the robust rounds take a misprediction for the
graph's, not the detector's: none of that image's observations is dropped
(``robust.spare_mispredicted``; docs/method.md, "Lone photos")."""


def solve_single(
    capture: Capture, options: Options, progress: Progress | None = None, subjects: int = 1
) -> Result:
    """Estimate every image's 3D points and the images' temporal graph and order (one subject).

    With ``options.segment_events``, temporally disjoint events are found first
    (:func:`initial_events`) and each event is sequenced and reconstructed on its own. With a
    robust loss (or symmetric pairs to check) the observations are then reweighted from the
    solution's residuals and the capture re-solved (:func:`robust_rounds`). Unless
    ``options.stream_clocks`` is ``off``, every event filmed by videos is finally placed on its
    streams' fitted clocks (:func:`clocked`; with ``auto`` only where they predict held-out
    detections about as well as the graph, ``decisions.clock_verdict``). ``subjects``: the people
    whose points the capture's columns hold (``multitarget.aggregate``), for the events."""
    started = time.perf_counter()
    X_world = initialise(capture, options)
    labels = np.zeros(capture.num_images, dtype=np.int64)
    if options.segment_events:
        labels = initial_events(capture, options, X_world, subjects)
    init_seconds = time.perf_counter() - started
    result = solve_events(capture, options, labels, X_world, progress)
    result, solved = robust_rounds(capture, options, labels, result, progress)
    auto_noise = options.noise_px == AUTO
    if auto_noise:
        options = options.replace(noise_px=result.noise_px)
    timings = {**result.timings, "init": result.timings["init"] + init_seconds}
    if options.stream_clocks is not Clocks.OFF:
        # the rounds' verdict is revisited where they found wrong detections
        checked = None
        if result.outliers.size or result.swaps.size:
            checked = result.solved if result.swaps.size else capture
        t_clocks = time.perf_counter()
        result = clocks_and_offsets(capture, solved, options, result, auto_noise=auto_noise,
                                    checked=checked)
        timings["clocks"] = time.perf_counter() - t_clocks
    return replace(result, timings=timings, seconds=time.perf_counter() - started)


def shape_space_graph(capture: Capture, options: Options, X_world: np.ndarray) -> sp.csr_matrix:
    """W_var of one W-step on shapes ``X_world`` with candidates and compactness in shape space
    (no time line yet: it is what events and subjects are found from)."""
    norm = normalise(capture, options, X_world)
    X = norm.to_normal(X_world)
    n = X.shape[0]
    cand = select_candidates(
        X.reshape(n, -1), norm.problem, options.num_candidates, min_angle=options.min_ray_angle
    )
    return w_step(
        X, np.ones(n), cand, norm.problem,
        lambda1=options.lambda1, lambda3=options.lambda3, ridge=options.ridge,
    )


def initial_events(
    capture: Capture, options: Options, X_world: np.ndarray, subjects: int = 1
) -> np.ndarray:
    """(N,) event labels from the shape-space W of the initial shapes (``shape_space_graph``).

    The graph is W_var alone: the chain prior would tie the last image of one event to the
    first of the next in every stream (and time-line candidates would bridge events). With
    several ``subjects`` (columns s P .. s P + P - 1 are subject s) it is the sum of every
    subject's graph over the images that see it: two images are compared only on a subject
    both see, never on the values the initial shapes filled in where one is unseen (those tie
    each image to the images that miss the same subjects); a subject with an image no other
    stream's views at ``min_ray_angle`` links none (and with no subject left, the whole shapes
    link the images). An event seen by fewer than two streams cannot be triangulated; it joins
    the largest event.
    """
    n, p = capture.num_images, capture.num_points // subjects
    pieces = []
    if subjects > 1:
        for k, cols in enumerate(np.arange(subjects * p).reshape(subjects, p)):
            idx = np.flatnonzero(capture.visible[:, cols].any(axis=1))
            one = replace(capture.subset(idx), x=capture.x[idx][:, cols],
                          confidence=capture.weights[idx][:, cols], symmetric_pairs=None)
            try:
                pieces.append(parts(shape_space_graph(one, options, X_world[idx][:, cols]), idx))
            except InputError:  # an image of it no other stream views at an angle: it links none
                logger.debug("events: subject %d links no images (too few views)", k)
    # one subject, or none whose images other streams view: the images' whole shapes
    W_var = assemble(pieces, n) if pieces else shape_space_graph(capture, options, X_world)
    labels = segment_events(W_var, capture.stream, capture.frame, shapes=X_world)
    sizes = np.bincount(labels)
    for e in range(labels.max() + 1):
        if np.unique(capture.stream_ids[labels == e]).size < 2:
            labels[labels == e] = np.argmax(sizes)
    _, labels = np.unique(labels, return_inverse=True)
    return labels


def solve_events(
    capture: Capture,
    options: Options,
    labels: np.ndarray,
    X_world: np.ndarray | None,
    progress: Progress | None = None,
) -> Result:
    """Solve every event on its own (from ``X_world`` when given, else each initialised on its
    own) and assemble one result (orders concatenated by event). One event: its solve as is.
    Several: in ``options.workers`` processes (``core.parallel``); each reports to ``progress``
    once, when solved."""
    if labels.max() == 0:
        return solve_event(capture, options, X_world, progress)
    n, p = capture.num_images, capture.num_points
    X = np.empty((n, p, 3))
    embedding = np.empty(n)
    D = np.empty(n)
    A_parts, W_parts, order, results = [], [], [], []
    offset = 0.0
    events = [np.flatnonzero(labels == e) for e in range(int(labels.max()) + 1)]
    tasks = [(capture.subset(idx), options, None if X_world is None else X_world[idx])
             for idx in events]
    workers = worker_count(options.workers, len(tasks), n)
    for e, idx in enumerate(events):
        logger.info("event %d: %d images", e, idx.size)
    if workers > 1:
        logger.info("%d events in %d worker processes", len(tasks), workers)
        solved = map_in_processes(_solve_event_task, tasks, workers)
    else:
        solved = (solve_event(*task, progress) for task in tasks)
    for idx, r in zip(events, solved, strict=True):
        if workers > 1 and progress is not None:
            progress(r.nit, r.nit, {"cost": r.cost_history[-1], "change": r.change_history[-1]})
        results.append(r)
        X[idx], D[idx] = r.X, r.D
        embedding[idx] = r.embedding - r.embedding.min() + offset
        offset = embedding[idx].max() + 1.0
        order.append(idx[r.order])
        A_parts.append(parts(r.A, idx))
        W_parts.append(parts(r.W, idx))
    return Result(
        X=X,
        order=np.concatenate(order),
        A=assemble(A_parts, n),
        W=assemble(W_parts, n),
        D=D,
        events=labels,
        embedding=embedding,
        seconds=sum(r.seconds for r in results),
        scale=results[0].scale,
        **merged_history(results, "event"),
    )


def _solve_event_task(task: tuple[Capture, Options, np.ndarray | None]) -> Result:
    """:func:`solve_event` of one (capture, options, X_world) in a worker process."""
    return solve_event(*task)


def solve_event(
    capture: Capture,
    options: Options,
    X_world: np.ndarray | None = None,
    progress: Progress | None = None,
) -> Result:
    """One event: init (unless given), alternation (hard rays, then soft ones with a finite ray
    weight; with ``noise_px`` = ``auto`` at the level estimated from the hard-ray solution, kept
    only if they predict held-out detections better: ``decisions.soft_rays_kept``), sequencing.
    Returns a :class:`Result` in world units."""
    t_start = time.perf_counter()
    if X_world is None:
        X_world = initialise(capture, options)
    norm = normalise(capture, options, X_world)
    prob = norm.problem
    X = norm.to_normal(X_world)
    init_seconds = time.perf_counter() - t_start
    t0 = time.perf_counter()
    prior_f, f = sequence(X, prob, capture.frame, options)
    sequencing_seconds = time.perf_counter() - t0
    auto = options.noise_px == AUTO
    soft = auto or np.isfinite(soft_ray_weight(capture, options))
    st = Search(X=X, D=degrees(f, prob, options), prior_f=prior_f, f=f, progress=progress,
                total=options.max_iterations + (options.soft_iterations if soft else 0))
    st.timings["init"] = init_seconds
    st.timings["sequencing"] += sequencing_seconds
    # soft rays start from the hard-ray solution: its X-steps are several times cheaper and
    # settle W first; the soft phase then only refines
    success, message = alternate(st, prob, capture.frame, options,
                                 Phase(np.inf, options.max_iterations))
    hard, hard_outcome, hard_sweeps = st.best, (success, message), len(st.costs)
    if auto:
        X_pred = predicted(hard.W, norm.to_world(hard.X))
        options = options.replace(noise_px=estimate_noise_px(residuals_px(capture, X_pred)))
    lambda2 = soft_ray_weight(capture, options)
    if np.isfinite(lambda2):
        st.X = st.best.X.copy()
        success, message = alternate(
            st, prob, capture.frame, options,
            Phase(lambda2, options.soft_iterations, discrepancy(capture, options, norm)),
        )
        if auto and not soft_rays_kept(capture, options, norm, hard, st):
            # the hard-ray solve stands, with its own history
            st.best, (success, message) = hard, hard_outcome
            del st.costs[hard_sweeps:], st.changes[hard_sweeps:]
            options = options.replace(noise_px=0.0)
    if auto:
        logger.info("detection noise estimated from the data: %.2f px", options.noise_px)
    if progress is not None and len(st.costs) < st.total:
        progress(st.total, st.total, {"cost": st.costs[-1], "change": st.changes[-1]})
    best = st.best
    t0 = time.perf_counter()
    _, f = sequence(best.X, prob, capture.frame, options, final=True)
    st.timings["sequencing"] += time.perf_counter() - t0
    A = sp.csr_matrix(sp.diags(best.D) @ best.W)
    return Result(
        X=norm.to_world(best.X),
        order=order_from_embedding(f),
        A=A,
        W=best.W,
        D=best.D,
        events=segment_events(A, capture.stream, capture.frame, shapes=best.X),
        embedding=f * norm.scale,
        cost_history=np.array(st.costs),
        change_history=np.array(st.changes),
        nit=len(st.costs),
        success=success,
        message=message,
        seconds=time.perf_counter() - t_start,
        timings=st.timings,
        scale=norm.scale,
        noise_px=float(options.noise_px),
    )


def robust_rounds(
    capture: Capture,
    options: Options,
    labels: np.ndarray,
    result: Result,
    progress: Progress | None = None,
) -> tuple[Result, Capture]:
    """Iteratively reweighted re-solves against wrong detections and left/right swaps.

    Each round predicts every observation from the graph (``W X``), exchanges symmetric pairs
    that fit far better swapped, weights every observation by the robust loss of its residual
    (pixels), drops those weighted below 1/2 and re-solves from a fresh initialisation (one
    from shapes bent by the outliers stays bent). The first re-solve is kept only if it
    predicts the observations it used at least 5 % better (median residual) than the plain
    solve, beyond what the detection noise leaves (``noise.residual_floor_px``): real outliers
    bend the graph, so removing them tightens the fit, while at coarse sampling the largest
    residuals are the graph's own interpolation errors and dropping them helps nothing
    (docs/method.md, "Wrong detections (robust rounds)"). Stops when no pair was swapped and the
    rejected set changed by at most 0.1 % of the observations (1 % with soft rays: under noise
    it drifts by a few tenths of a percent a round without changing the result).
    Returns ``result`` re-solved, with ``outliers`` the observations the final solve left out
    and ``swaps`` every exchange kept, and the capture it was solved on (swaps undone,
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
    floor = residual_floor_px(result.noise_px)
    for it in range(options.robust_iterations + 1):
        X_pred = predicted(result.W, result.X)
        res = residuals_px(current, X_pred)
        if it == 1 and (fit := float(np.nanmedian(res[~rejected]))) - floor > 0.95 * (
            expected - floor
        ):
            logger.info("robust round 1 undone: the fit did not tighten (median residual "
                        "%.2f -> %.2f px, %.2f px of it noise)", expected, fit, floor)
            result, current, swaps, solved = plain, capture, swaps[:0], capture
            rejected = np.zeros_like(rejected)
            break
        scale = loss_scale(res, options.robust_scale_px)
        new = find_swaps(current, X_pred, pairs, scale) if pairs is not None else swaps[:0]
        trial = apply_swaps(current, new) if new.size else current
        res = residuals_px(trial, X_pred)
        weights, mispredicted = spare_mispredicted(
            loss_weights(res, scale, options.robust_loss), current.visible, MOST_OF_AN_IMAGE)
        now = weights < 0.5
        if now.sum() > 0.5 * current.visible.sum():
            # a loss that drops most of the data is no longer rejecting outliers
            logger.warning("robust round %d not run: the loss scale (%.3g px median) would drop "
                           "%d of %d observations (robust_scale_px below the noise?)", it + 1,
                           float(np.median(scale)), int(now.sum()), int(current.visible.sum()))
            break
        # under noise (soft rays) the rejected set drifts a little every round
        settle = 1e-2 if result.noise_px > 0 else 1e-3
        settled = (now != rejected).sum() <= settle * current.visible.sum()
        if it == options.robust_iterations or (not new.size and settled):
            break
        expected = float(np.nanmedian(res[~now]))
        current, swaps, rejected = trial, np.concatenate([swaps, new]), now
        logger.info("robust round %d: %d swap(s), %d observation(s) beyond %.1f px (median)%s",
                    it + 1, len(new), int(rejected.sum()), float(np.median(scale)),
                    f"; {int(mispredicted.sum())} image(s) mispredicted in most of their points "
                    "kept whole" if mispredicted.any() else "")
        solved = reweighted(current, weights) if robust else current
        again = solve_events(solved, options, labels, None, progress)
        result = replace(
            again,
            nit=again.nit + result.nit,
            timings={k: v + result.timings.get(k, 0.0) for k, v in again.timings.items()},
        )
    img, col = np.nonzero(rejected)
    return replace(
        result,
        solved=current if swaps.size else result.solved,
        swaps=swaps,
        outliers=np.stack([img, col], axis=1).astype(np.int64),
        outlier_residual_px=residuals_px(current, predicted(result.W, result.X))[img, col],
    ), solved


def event_clocks(
    t0: np.ndarray, prob: Problem, frame: np.ndarray, options: Options, *, offsets: bool = False,
    rates: np.ndarray | None = None
) -> np.ndarray:
    """One event's stream clocks fitted to the rays of ``prob`` from the first guess ``t0``
    (``clocks.fit_clocks``; ``options.shared_rate``; with ``offsets``, each stream's offsets
    of each point's rays fitted with them; ``rates``, every image's stream's known frame rate,
    the rates held at their ratios)."""
    E, rhs = ray_equations(prob.rays, prob.C, prob.weights)
    return fit_clocks(t0, prob.streams, frame, E, rhs, prob.visible,
                      shared_rate=options.shared_rate, offsets=offsets, rates=rates)


def outlier_arrays(result: Result) -> tuple[np.ndarray, np.ndarray]:
    """(N, P) the observations ``result`` left out (``outliers``) and their residuals in
    pixels (``outlier_residual_px``; NaN elsewhere)."""
    rejected = np.zeros(result.X.shape[:2], dtype=bool)
    residual = np.full(result.X.shape[:2], np.nan)
    if result.outliers.size:
        rejected[tuple(result.outliers.T)] = True
        residual[tuple(result.outliers.T)] = result.outlier_residual_px
    return rejected, residual


class Placement(NamedTuple):
    """One event placed on its stream clocks (:func:`placements`): its images ``idx``, clocks
    ``t``, the chain's ``W`` and ``D``, points ``X`` (world), rejected observations and their
    residuals (pixels), the detection ``noise`` its rays took, and what the held-out check
    (``decisions.clock_verdict``) judges it on: the capture ``judged`` and the clocks' held-out
    residuals ``held`` when known; ``moved``, how far the fit moved a stream from DLOE's placement
    (``clocks.moved_periods``)."""

    idx: np.ndarray
    t: np.ndarray
    W: sp.csr_matrix
    D: np.ndarray
    X: np.ndarray
    rejected: np.ndarray
    residual: np.ndarray
    noise: float
    judged: Capture
    held: np.ndarray | None
    moved: float


def placements(
    capture: Capture, options: Options, result: Result, *, auto_noise: bool = False,
    checked: Capture | None = None, offsets: bool = False
) -> list[Placement]:
    """Every event of ``result`` that is filmed by videos (two or more streams of three or more
    frames), placed on its fitted clocks (``core.clocks``): the points by the X-step on the
    chain along the clocks (soft rays with ``noise_px``, as the solve), the chain's W and D.
    ``capture`` is the one the result was solved on (:func:`robust_rounds`). With
    ``auto_noise`` (``noise_px`` was ``auto``) and hard rays kept by the graph's check, an
    event takes soft rays where the clocks' held-out images ask for them
    (:func:`soft_rays_on_clocks`). With ``checked`` (the capture before the robust weights, swaps
    undone) the observations of every event are judged again against the chain along its
    clocks (:func:`robust_on_clocks`), and the held-out check will judge both models on that
    verdict. With ``offsets`` the clocks are fitted with each stream's offsets of each point's
    rays (:func:`event_clocks`), their rates held at the ratios of the streams' frame rates
    where the event's capture knows them all (``problem.known_rates``): fitted with the offsets,
    free rates drift where the motion is slow (docs/method.md, "Known frame rates")."""
    n = capture.num_images
    rejected, residual = outlier_arrays(result)
    placed = []
    for e in range(int(result.events.max()) + 1):
        idx = np.flatnonzero(result.events == e)
        ids, counts = np.unique(capture.stream_ids[idx], return_counts=True)
        if ids.size < 2 or counts.min() < 3:
            continue
        sub = capture.subset(idx) if idx.size < n else capture
        norm = normalise(sub, options, result.X[idx])
        prob = norm.problem
        Xe = norm.to_normal(result.X[idx])
        t0 = affine_time(Xe, prob.streams, sub.frame, rates=prob.rates)
        if t0 is None:
            continue
        rates = prob.rates if offsets else None
        t = event_clocks(t0, prob, sub.frame, options, offsets=offsets, rates=rates)
        moved = moved_periods(t0, t, prob.streams, sub.frame)
        if moved >= REACH:
            logger.info("event %d: the clock fit moved a stream %.1f frame periods from DLOE's "
                        "placement; the clocks are kept only if they predict held-out detections",
                        e, moved)
        noise, held = options.noise_px, None
        if auto_noise and noise == 0:
            noise, held = soft_rays_on_clocks(sub, options, result.X[idx], result.D[idx],
                                         result.W[idx][:, idx], t)
        ticked = options.replace(noise_px=noise)
        # the chain's weights come from the time line: no compactness term (as the oracle)
        W, D_e = time_chain(t)
        Xe = x_step(W, D_e, prob, lambda1=0.0, lambda2=soft_ray_weight(sub, ticked), X_prev=Xe)
        judged, rej_e, res_e = sub, rejected[idx], residual[idx]
        if checked is not None:
            csub = checked.subset(idx) if idx.size < n else checked
            t, W, D_e, Xe, rej_e, res_e, weights = robust_on_clocks(
                csub, ticked, norm, t, Xe, rej_e, offsets=offsets, rates=rates)
            if weights is not None:  # both models are judged on the clocks' verdict
                judged, held = reweighted(csub, weights), None
        placed.append(Placement(idx, t, W, D_e, norm.to_world(Xe), rej_e, res_e, noise, judged,
                                held, moved))
    return placed


def verdicts(placed: list[Placement], options: Options, result: Result) -> list[Verdict]:
    """What ``options.stream_clocks`` makes of each placement: with ``auto`` the held-out check
    against the graph of ``result`` (``decisions.clock_verdict``); with ``on`` kept, except that
    a fit that moved a stream ``clocks.REACH`` frame periods or more from DLOE's placement is
    checked too (``decisions.clocks_checked``): the rays may not pin its clocks, or DLOE's
    placement was that far off (docs/method.md, "Stream clocks")."""
    return [clock_verdict(p.judged, options, result.X[p.idx], result.D[p.idx], p.t, p.noise,
                          p.held) if clocks_checked(options, p.moved) else Verdict.KEPT
            for p in placed]


def judged(result: Result, placed: list[Placement], options: Options, *, checked: bool
           ) -> Result:
    """``result`` with the events of ``placed`` that ``options.stream_clocks`` keeps on their
    clocks (:func:`verdicts`, :func:`on_clocks`), and those whose clocks lost the held-out
    check narrowly ordered by them, which go to ``clock_dropped``."""
    said = verdicts(placed, options, result)
    kept = [p for p, v in zip(placed, said, strict=True) if v is Verdict.KEPT]
    timing = [p for p, v in zip(placed, said, strict=True) if v is Verdict.TIMING]
    return on_clocks(result, kept, checked=checked, dropped=timing)


def on_clocks(result: Result, placed: list[Placement], *, checked: bool,
              dropped: list[Placement] | None = None) -> Result:
    """``result`` with the events of ``placed`` on their clocks: points, W and D rows the
    chain's, their block of the order and their embedding (span kept) from the clocks,
    ``clock`` the times, ``noise_px`` the largest their rays took; with ``checked`` (the
    observations were judged again on the clocks) ``outliers`` theirs on those events. The
    events of ``dropped`` (their clocks not kept) keep DLOE's points, graph and embedding, but
    take their block of the order from their clocks, whose times go to ``clock_dropped``: the
    held-out check judges the points, and under detector noise a frame of timing hardly moves
    a held-out image's residual, while the clock fit is the timing's own estimate from the rays
    (docs/method.md, "Times from dropped clocks")."""
    n = result.X.shape[0]
    if dropped:
        times, order, rank = np.full(n, np.nan), result.order.copy(), result.rank
        for p in dropped:
            times[p.idx] = p.t
            order[np.sort(rank[p.idx])] = p.idx[np.argsort(p.t, kind="stable")]
        result = replace(result, clock_dropped=times, order=order)
    if not placed:
        return result
    X, D = result.X.copy(), result.D.copy()
    order, embedding, rank = result.order.copy(), result.embedding.copy(), result.rank
    clock = np.full(n, np.nan)
    noise_px = result.noise_px
    rejected, residual = outlier_arrays(result)
    chains = []  # (data, rows, cols) of every clocked event's W
    for p in placed:
        idx, t = p.idx, p.t
        noise_px = max(noise_px, p.noise)
        D[idx], rejected[idx], residual[idx] = p.D, p.rejected, p.residual
        X[idx], clock[idx] = p.X, t
        chains.append(parts(p.W, idx))
        order[np.sort(rank[idx])] = idx[np.argsort(t, kind="stable")]
        lo, hi = embedding[idx].min(), embedding[idx].max()
        embedding[idx] = lo + (t - t.min()) * (hi - lo) / max(np.ptp(t), 1e-300)
    coo = result.W.tocoo()
    dloe = np.isnan(clock)[coo.row]  # rows of the events left to DLOE's graph
    chains.append((coo.data[dloe], coo.row[dloe], coo.col[dloe]))
    W = assemble(chains, n)
    if checked:
        img, col = np.nonzero(rejected)
        result = replace(result, outliers=np.stack([img, col], axis=1).astype(np.int64),
                         outlier_residual_px=residual[img, col])
    return replace(result, X=X, D=D, W=W, A=sp.csr_matrix(sp.diags(D) @ W), clock=clock,
                   order=order, embedding=embedding, noise_px=noise_px)


def clocked(
    capture: Capture, options: Options, result: Result, *, auto_noise: bool = False,
    checked: Capture | None = None, offsets: bool = False
) -> Result:
    """``result`` with every event that is filmed by videos placed on its streams' fitted
    affine clocks (:func:`placements`) where ``options.stream_clocks`` keeps them
    (:func:`judged`); the others keep DLOE's points and graph, ordered by their clocks
    (``clock_dropped``).
    ``outliers`` follow the events that keep their clocks. ``offsets``: as
    :func:`placements` takes it."""
    placed = placements(capture, options, result, auto_noise=auto_noise, checked=checked,
                        offsets=offsets)
    return judged(result, placed, options, checked=checked is not None)


def clocks_and_offsets(
    capture: Capture, solved: Capture, options: Options, graph: Result, *, auto_noise: bool,
    checked: Capture | None
) -> Result:
    """:func:`clocked` with the streams' offsets of the detections taken out (``core.bias``).

    The offsets are estimated (:func:`clock_offsets`) with every event on its clocks, before the
    held-out check. Where they predict, they are taken out of the observations and the events
    placed and judged again on the detections without them, the clocks fitted with each stream's
    offsets of each point's rays: the first clocks took part of the detections' offsets as time
    shifts (the offsets estimated along them keep that part), and fitted together the two come
    apart where the motion's speed changes (docs/method.md, "Offsets fitted with the clocks"),
    and at the known frame rates' ratios where the capture has them (the first clocks keep their
    rates free: they are what the offsets are estimated along); ``solved`` and ``offset_px`` of
    the result hold them where its points are on clocks. Else, or without
    ``options.stream_offsets``, the placements are judged on the detections as they are.
    ``capture``: the solver's input; ``solved``, the capture it was solved on and ``checked`` as
    :func:`clocked` takes them."""
    if not options.stream_offsets:
        return clocked(solved, options, graph, auto_noise=auto_noise, checked=checked)
    placed = placements(solved, options, graph, auto_noise=auto_noise, checked=checked)
    offsets = None
    if placed:
        offsets = clock_offsets(capture, on_clocks(graph, placed, checked=checked is not None))
    if offsets is None:
        return judged(graph, placed, options, checked=checked is not None)
    result = clocked(without_offsets(solved, offsets), options, graph, auto_noise=auto_noise,
                     checked=None if checked is None else without_offsets(checked, offsets),
                     offsets=True)
    if result.clock is None:
        return result
    offsets[np.isnan(result.clock)] = 0.0  # only where the points are on the clocks
    base = capture if graph.solved is None else graph.solved
    return replace(result, solved=without_offsets(base, offsets), offset_px=offsets)


def clock_offsets(capture: Capture, result: Result) -> np.ndarray | None:
    """(N, P, 2) pixel offsets of each stream's detections of each point on the events
    ``result`` placed on its clocks (``bias.stream_offsets``: residuals against the chain along
    them, the outliers left out; 0 elsewhere), or None where there are none or they do not
    predict the frames they were not estimated on; logged when estimated. ``capture``: the
    solver's input."""
    placed = np.isfinite(result.clock)
    X_pred = np.full(result.X.shape, np.nan)
    for e in np.unique(result.events[placed]):
        idx = np.flatnonzero(placed & (result.events == e))
        X_pred[idx] = chain_predicted(result.W[idx][:, idx], result.clock[idx], result.X[idx])
    found = stream_offsets(capture if result.solved is None else result.solved, X_pred,
                           outlier_arrays(result)[0])
    if found is None:
        return None
    offsets, before, after = found
    offsets[~placed] = 0.0
    size = np.linalg.norm(offsets, axis=2)
    if not size.any():
        return None
    keep = after <= GAIN * before
    logger.info("stream offsets of the detections, median %.2f px: residuals of the frames they "
                "were not estimated on %.2f -> %.2f px (median), %s", np.median(size[size > 0]),
                before, after, "taken out" if keep else "not taken out")
    return offsets if keep else None


def robust_on_clocks(
    capture: Capture, options: Options, norm: Normalised, t: np.ndarray, X: np.ndarray,
    rejected: np.ndarray, *, offsets: bool = False, rates: np.ndarray | None = None
) -> tuple[
    np.ndarray, sp.csr_matrix, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None
]:
    """One clocked event's observations judged again against its clocks ``t``: the robust
    rounds judged them by DLOE's graph, and the event's points now come from the chain along
    the clocks. Every observation of ``capture`` (the event before the robust weights, swaps
    undone) is predicted from its neighbours along the clocks (``clocks.chain_predicted``),
    weighted by the robust loss of its residual as in :func:`robust_rounds`, and the points
    placed again by the X-step on the chain, until the rejected set holds (at most
    ``robust_iterations`` times). A wrong detection the graph missed is pinned to its ray with
    exact detections (``noise_px`` 0) and bent the clock fit: the first time such a one is
    rejected, the clocks are fitted again without it (kept unless the fit moved a stream
    ``clocks.REACH`` frame periods or more; ``offsets`` and ``rates`` as :func:`event_clocks`
    takes them).

    ``X`` (N, P, 3) in ``norm``'s frame, ``rejected`` (N, P) the robust rounds' verdict.
    Returns the clocks, the chain's W and D, the points, the rejected set, the residuals in
    pixels (NaN where unobserved) and the observation weights the points were placed with
    (None when the rounds' verdict held)."""
    lambda2 = soft_ray_weight(capture, options)
    W, D = time_chain(t)
    used = None
    refit = options.noise_px == 0
    res = residuals_px(capture, chain_predicted(W, t, norm.to_world(X)))
    for _ in range(options.robust_iterations):
        weights = loss_weights(res, loss_scale(res, options.robust_scale_px), options.robust_loss)
        now = (weights < 0.5) & capture.visible
        if (now == rejected).all():
            break
        if now.sum() > 0.5 * capture.visible.sum():
            logger.warning("robust check on the stream clocks not taken: it would drop %d of %d "
                           "observations; the previous verdict stands", int(now.sum()),
                           int(capture.visible.sum()))
            break
        logger.info("robust check on the stream clocks: %d observation(s) rejected, %d admitted "
                    "again", int((now & ~rejected).sum()), int((rejected & ~now).sum()))
        prob = build_problem(reweighted(capture, weights), options, norm.origin, norm.scale)
        if refit and (now & ~rejected).any():
            refit = False
            fitted = event_clocks(t, prob, capture.frame, options, offsets=offsets, rates=rates)
            if fit_trusted(moved_periods(t, fitted, prob.streams, capture.frame)):
                t = fitted
                W, D = time_chain(t)
        rejected, used = now, weights
        X = x_step(W, D, prob, lambda1=0.0, lambda2=lambda2, X_prev=X)
        res = residuals_px(capture, chain_predicted(W, t, norm.to_world(X)))
    return t, W, D, X, rejected, res, used
