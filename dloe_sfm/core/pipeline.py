"""One subject's reconstruction, the method's steps from the top (docs/method.md, "The steps as
implemented"): :func:`solve_single` initialises, finds the events (:func:`initial_events`),
solves each (:func:`plain_solve`: :func:`solve_events`, :func:`solve_event`: hard rays, the
noise level, soft rays, the order), then re-solves against wrong detections
(:func:`finish_single`: :func:`robust_rounds`) and places the events on their streams' clocks
(``clocked.clocks_and_offsets``); ``solver.reconstruct`` then assesses every image. The
choices the data make along the way are in ``core.decisions``."""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from ..errors import InputError
from .alternation import (
    Phase,
    Progress,
    Search,
    alternate,
    by_shapes,
    degrees,
    discrepancy,
    lone_line,
    sequence,
    soft_ray_weight,
)
from .capture import Capture
from .clocked import burst_times, clocks_and_offsets
from .decisions import (
    MOST_OF_AN_IMAGE,
    NOISE_KEPT,
    NOISY_ROUNDS,
    HardRaysSettled,
    robust_round_undone,
    soft_rays_kept,
    spare_mispredicted,
)
from .embedding import shape_embedding
from .events import numbered_by_first_image, runs_on, segment_events, without_videos
from .noise import estimate_noise_px, residual_floor_px
from .options import AUTO, Clocks, Options, RobustLoss
from .parallel import map_in_processes, worker_count
from .problem import assemble, initialise, normalise, parts
from .result import Result, merged_history
from .robust import (
    apply_swaps,
    find_swaps,
    loss_scale,
    loss_weights,
    predicted,
    residuals_px,
    reweighted,
)
from .sequencing import order_from_embedding, orient
from .wstep import select_candidates, w_step

logger = logging.getLogger("dloe_sfm")


def solve_single(
    capture: Capture, options: Options, progress: Progress | None = None
) -> Result:
    """Estimate every image's 3D points and the images' temporal graph and order (one subject).

    With ``options.segment_events``, temporally disjoint events are found first
    (:func:`initial_events`) and each event is sequenced and reconstructed on its own
    (:func:`plain_solve`). With a robust loss (or symmetric pairs to check) the observations are
    then reweighted from the solution's residuals and the capture re-solved; unless
    ``options.stream_clocks`` is ``off``, every event filmed by videos is finally placed on its
    streams' fitted clocks (:func:`finish_single`)."""
    return finish_single(capture, options, *plain_solve(capture, options, progress), progress)


def plain_solve(
    capture: Capture, options: Options, progress: Progress | None = None
) -> tuple[Result, np.ndarray]:
    """The first part of :func:`solve_single`: initialise, find the events and solve each
    (:func:`solve_events`); no robust round, no clocks. Returns the result and the (N,) event
    labels it was solved with."""
    started = time.perf_counter()
    X_world = initialise(capture, options)
    labels = np.zeros(capture.num_images, dtype=np.int64)
    if options.segment_events:
        labels = initial_events(capture, options, X_world)
    init_seconds = time.perf_counter() - started
    result = solve_events(capture, options, labels, X_world, progress)
    timings = {**result.timings, "init": result.timings["init"] + init_seconds}
    return replace(result, timings=timings, seconds=time.perf_counter() - started), labels


def finish_single(
    capture: Capture,
    options: Options,
    result: Result,
    labels: np.ndarray,
    progress: Progress | None = None,
    *,
    resumed: bool = False,
) -> Result:
    """The rest of :func:`solve_single` after ``result``, a solve of ``capture`` with the events
    ``labels``: the robust rounds (:func:`robust_rounds`) and the stream clocks
    (``clocked.clocks_and_offsets``; with ``auto`` only where they predict held-out detections
    about as well as the graph, ``decisions.clock_verdict``).

    ``resumed``: ``result`` is the finished solve of other observations of these images (an
    association changed in a few of them, ``multitarget.reconstruct_subjects``): its prediction
    weights the first robust round, which re-solves ``capture`` whatever it rejects."""
    started, before = time.perf_counter(), result.seconds
    result, solved = robust_rounds(capture, options, labels, result, progress, resumed=resumed)
    auto_noise = options.noise_px == AUTO
    if auto_noise:
        options = options.replace(noise_px=result.noise_px)
    timings = dict(result.timings)
    if options.stream_clocks is not Clocks.OFF:
        # the rounds' verdict is revisited where they found wrong detections
        checked = None
        if result.outliers.size or result.swaps.size:
            checked = result.solved if result.swaps.size else capture
        t_clocks = time.perf_counter()
        result = clocks_and_offsets(capture, solved, options, result, auto_noise=auto_noise,
                                    checked=checked)
        result = burst_times(solved, options, result)
        timings["clocks"] = time.perf_counter() - t_clocks
    return replace(result, timings=timings, seconds=before + time.perf_counter() - started)


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


def initial_events(capture: Capture, options: Options, X_world: np.ndarray) -> np.ndarray:
    """(N,) event labels from the shape-space W of the initial shapes (``shape_space_graph``).

    The graph is W_var alone: the chain prior would tie the last image of one event to the
    first of the next in every stream (and time-line candidates would bridge events). With
    several subjects (``capture.subjects``: columns s P .. s P + P - 1 are subject s) it is the
    sum of every subject's graph over the images that see it: two images are compared only on
    a subject both see, never on the values the initial shapes filled in where one is unseen
    (those tie each image to the images that miss the same subjects); a subject with an image
    no other stream's views at ``min_ray_angle`` links none (and with no subject left, the
    whole shapes link the images). An event seen by fewer than two streams cannot be
    triangulated; it joins the largest event.
    """
    subjects = capture.subjects
    n, p = capture.num_images, capture.num_points // subjects
    pieces = []
    if subjects > 1:
        for k, cols in enumerate(np.arange(subjects * p).reshape(subjects, p)):
            idx = np.flatnonzero(capture.visible[:, cols].any(axis=1))
            one = replace(capture.subset(idx), x=capture.x[idx][:, cols],
                          confidence=capture.weights[idx][:, cols], symmetric_pairs=None,
                          subjects=1)
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
    ambiguous = np.zeros(n, dtype=bool)
    A_parts, W_parts, order, results = [], [], [], []
    offset = 0.0
    events = [np.flatnonzero(labels == e) for e in range(int(labels.max()) + 1)]
    tasks = [(capture.subset(idx), options, None if X_world is None else X_world[idx])
             for idx in events]
    workers = worker_count(options.workers, len(tasks), n * p)
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
        if r.order_ambiguous is not None:
            ambiguous[idx] = r.order_ambiguous
        A_parts.append(parts(r.A, idx))
        W_parts.append(parts(r.W, idx))
    sequence, flips = range(len(events)), [False] * len(events)
    lone = without_videos(capture.stream_ids)
    if lone:
        sequence, flips = events_along_shapes(capture, X, events, results)
    for e in sequence:
        idx, r = events[e], results[e]
        f = -r.embedding if flips[e] else r.embedding
        embedding[idx] = f - f.min() + offset
        offset = embedding[idx].max() + 1.0
        order.append(idx[r.order[::-1] if flips[e] else r.order])
    if lone:
        labels = joined_where_running_on(X, labels, list(sequence), order)
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
        order_ambiguous=ambiguous,
        **merged_history(results, "event"),
    )


def events_along_shapes(
    capture: Capture, X: np.ndarray, events: list[np.ndarray], results: list[Result]
) -> tuple[np.ndarray, list[bool]]:
    """The order of events of lone photos and bursts, and which to reverse: along the line of
    all their solved shapes ``X`` (``embedding.shape_embedding``, oriented by the bursts), by
    each event's median place on it, every event's own order turned to run the same way.

    Shapes cannot tell a time gap from fast motion seen by few photos, so such events may be
    one motion cut apart; then this is its order (a true gap's order no image can tell)."""
    g = orient(shape_embedding(X), capture.stream_ids, capture.frame)
    places = [float(np.median(g[idx])) for idx in events]
    flips = [_anticorrelated(r.embedding, g[idx]) for idx, r in zip(events, results, strict=True)]
    sequence = np.argsort(places, kind="stable")
    if not np.array_equal(sequence, np.arange(len(events))) or any(flips):
        logger.info("events of lone photos ordered along their shapes: %s",
                    ", ".join(f"{e}{' (reversed)' if flips[e] else ''}" for e in sequence))
    return sequence, flips


def _anticorrelated(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether ``a`` and ``b`` run opposite ways: their covariance is negative (the sign of
    their correlation). Not where either is constant: it has no way to run."""
    if np.ptp(a) == 0 or np.ptp(b) == 0:
        return False
    return bool(np.dot(a - a.mean(), b - b.mean()) < 0)


def joined_where_running_on(
    X: np.ndarray, labels: np.ndarray, sequence: list[int], order: list[np.ndarray]
) -> np.ndarray:
    """``labels`` with every two events of lone photos and bursts that follow one another on the
    line (``sequence``, each event's images in ``order``) made one where the motion runs on
    across their junction (``events.runs_on``): solved apart, reported as the one event they
    are. Numbered by their first image, as ``segment_events`` numbers them."""
    out = labels.copy()
    joined = []
    for k in range(1, len(sequence)):
        if runs_on(X, order[k - 1], order[k], labels.size):
            out[out == sequence[k]] = out[order[k - 1][0]]
            joined.append((sequence[k - 1], sequence[k]))
    if joined:
        logger.info("events of lone photos one motion across their junction, reported as one: "
                    "%s", ", ".join(f"{a}+{b}" for a, b in joined))
    return numbered_by_first_image(out)


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
    Where soft rays may follow, the hard-ray phase stops once the graph's prediction has
    settled (``decisions.HardRaysSettled``), and resumes to its end where hard rays are kept.
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
    settled = HardRaysSettled(capture, options, norm) if soft else None
    success, message = alternate(st, prob, capture.frame, options,
                                 Phase(np.inf, options.max_iterations, settled=settled))
    hard, hard_outcome, hard_sweeps = st.best, (success, message), len(st.costs)
    # a phase the settled prediction stopped: its state, to resume it if hard rays are the answer
    paused = ((st.X.copy(), st.D.copy(), st.W_var, st.prior_f, st.f)
              if settled is not None and settled.reason is not None else None)
    if auto:
        X_pred = predicted(hard.W, norm.to_world(hard.X))
        options = options.replace(noise_px=estimate_noise_px(residuals_px(capture, X_pred)))
    lambda2 = soft_ray_weight(capture, options)
    soft_kept = np.isfinite(lambda2)
    if soft_kept:
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
            soft_kept = False
    resume = options.max_iterations - hard_sweeps
    if not soft_kept and paused is not None and resume > 0:
        # hard rays are the answer: their phase, stopped for the soft rays, runs to its end
        st.X, st.D, st.W_var, st.prior_f, st.f = paused
        success, message = alternate(st, prob, capture.frame, options, Phase(np.inf, resume))
    if auto:
        logger.info("detection noise estimated from the data: %.2f px", options.noise_px)
    if progress is not None and st.swept < st.total:
        progress(st.total, st.total, {"cost": st.costs[-1], "change": st.changes[-1]})
    best = st.best
    t0 = time.perf_counter()
    if by_shapes(prob, options):
        f, ambiguous = lone_line(best.X, prob, capture.frame)
    else:
        _, f = sequence(best.X, prob, capture.frame, options, final=True)
        ambiguous = np.zeros(f.size, dtype=bool)
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
        order_ambiguous=ambiguous,
    )


def reweighs(capture: Capture, options: Options) -> bool:
    """Whether :func:`robust_rounds` re-solves ``capture`` at all: with a robust loss, or with
    symmetric pairs whose swaps to fix."""
    pairs = capture.symmetric_pairs if options.fix_swaps else None
    return options.robust_loss is not RobustLoss.NONE or (pairs is not None and pairs.size > 0)


def robust_rounds(
    capture: Capture,
    options: Options,
    labels: np.ndarray,
    result: Result,
    progress: Progress | None = None,
    *,
    resumed: bool = False,
) -> tuple[Result, Capture]:
    """Iteratively reweighted re-solves against wrong detections and left/right swaps.

    Each round predicts every observation from the graph (``W X``), exchanges symmetric pairs
    that fit far better swapped, weights every observation by the robust loss of its residual
    (pixels), drops those weighted below 1/2 and re-solves from a fresh initialisation (one from
    shapes bent by the outliers stays bent). The first re-solve is kept only if it predicts the
    observations it used at least 5 % better (median residual) than the plain solve, beyond what
    the detection noise leaves (``decisions.robust_round_undone``). An image the graph
    mispredicts in most of its observations keeps them all (``decisions.spare_mispredicted``).
    Stops when no pair was swapped and the rejected set changed by at most 0.1 % of the
    observations (1 % with soft rays: under noise it drifts by a few tenths of a percent a round
    without changing the result), and after ``decisions.NOISY_ROUNDS`` rounds where the last
    solve still found detection noise (``decisions.NOISE_KEPT``). Returns ``result`` re-solved,
    with ``outliers`` the observations the final solve left out and ``swaps`` every exchange
    kept, and the capture it was solved on (swaps undone, observations reweighted).

    ``resumed``: ``result`` is the robust solve of other observations of these images
    (:func:`finish_single`), so the first round re-solves whatever it rejects, and is never
    undone: a robust solution's fit is no plain solve's to compare with; where no round runs
    (``robust_iterations`` 0, a loss scale that would drop most of the data) the capture is
    solved on its own."""
    robust = options.robust_loss is not RobustLoss.NONE
    pairs = capture.symmetric_pairs if options.fix_swaps else None
    if not reweighs(capture, options):
        return result, capture
    current, swaps = capture, np.zeros((0, 3), dtype=np.int64)
    solved = capture
    rejected = np.zeros(capture.x.shape[:2], dtype=bool)
    plain, expected, before = result, None, result.noise_px
    floor = residual_floor_px(result.noise_px)
    for it in range(options.robust_iterations + 1):
        X_pred = predicted(result.W, result.X)
        res = residuals_px(current, X_pred)
        if it == 1 and not resumed and robust_round_undone(
                fit := float(np.nanmedian(res[~rejected])), expected, floor):
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
        changed = int((now != rejected).sum())
        settled = changed <= settle * current.visible.sum()
        rounds = options.robust_iterations
        if result.noise_px >= NOISE_KEPT * before > 0:
            # the detectors' noise: the scale, from a fit without the last rejects, only tightens
            rounds = min(rounds, NOISY_ROUNDS)
        if it >= rounds or (not new.size and settled and not (resumed and it == 0)):
            break
        before = result.noise_px
        expected = float(np.nanmedian(res[~now]))
        logger.info("robust round %d: %d swap(s), %d observation(s) beyond %.1f px (median; "
                    "%d changed)%s", it + 1, len(new), int(now.sum()), float(np.median(scale)),
                    changed,
                    f"; {int(mispredicted.sum())} image(s) mispredicted in most of their points "
                    "kept whole" if mispredicted.any() else "")
        current, swaps, rejected = trial, np.concatenate([swaps, new]), now
        solved = reweighted(current, weights) if robust else current
        again = solve_events(solved, options, labels, None, progress)
        result = replace(
            again,
            nit=again.nit + result.nit,
            timings={k: v + result.timings.get(k, 0.0) for k, v in again.timings.items()},
        )
    if resumed and result is plain:
        # no round re-solved: ``plain`` is a solve of other observations, this capture needs its own
        logger.info("robust rounds not resumed: the capture solved on its own")
        result = solve_events(capture, options, labels, None, progress)
    img, col = np.nonzero(rejected)
    return replace(
        result,
        solved=current if swaps.size else result.solved,
        swaps=swaps,
        outliers=np.stack([img, col], axis=1).astype(np.int64),
        outlier_residual_px=residuals_px(current, predicted(result.W, result.X))[img, col],
    ), solved


