"""The stream clocks applied: every event filmed by videos placed on its fitted clocks, judged
(``core.decisions``) and kept, timing only or dropped, with the robust check along the clocks and
the streams' offsets of the detections around them (docs/method.md, "Stream clocks", "Judged
again on the clocks", "Stream offsets"). The entry is :func:`clocks_and_offsets`, the last step
of ``pipeline.solve_single`` but one; the clocks themselves are fitted by ``clocks.fit_clocks``.
The last, :func:`burst_times`, times the events of bursts and lone photos on their bursts'
clocks (``clocks.fit_burst_clocks``; docs/method.md, "Clocks of bursts").
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from .alternation import soft_ray_weight
from .bias import stream_offsets, without_offsets
from .capture import Capture
from .clocks import (
    REACH,
    by_rank,
    chain_predicted,
    fit_burst_clocks,
    fit_clocks,
    moved_periods,
    rank_times,
    reference_stream,
    time_chain,
)
from .decisions import (
    Verdict,
    burst_clocks_time,
    clock_verdict,
    clocks_checked,
    fit_trusted,
    offsets_kept,
    soft_rays_on_clocks,
)
from .events import without_videos
from .options import Options
from .parallel import map_in_processes, worker_count
from .problem import Normalised, assemble, build_problem, normalise, parts
from .result import Result
from .robust import loss_scale, loss_weights, residuals_px, reweighted
from .sequencing import affine_time
from .splines import ray_equations
from .steps import Problem
from .xstep import x_step

logger = logging.getLogger("dloe_sfm")


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


def placements(
    capture: Capture, options: Options, result: Result, *, auto_noise: bool = False,
    checked: Capture | None = None, offsets: bool = False
) -> list[Placement]:
    """Every event of ``result`` that is filmed by videos (two or more streams of three or more
    frames), placed on its fitted clocks (``core.clocks``): the points by the X-step on the chain
    along the clocks (soft rays with ``noise_px``, as the solve), the chain's W and D. ``capture``
    is the one the result was solved on (``pipeline.robust_rounds``). With ``auto_noise``
    (``noise_px`` was ``auto``) and hard rays kept by the graph's check, an event takes soft rays
    where the clocks' held-out images ask for them (``decisions.soft_rays_on_clocks``). With
    ``checked`` (the capture before the robust weights, swaps undone) the observations of every
    event are judged again against the chain along its clocks (:func:`robust_on_clocks`), and the
    held-out check will judge both models on that verdict. With ``offsets`` the clocks are fitted
    with each stream's offsets of each point's rays (:func:`event_clocks`), their rates held at the
    ratios of the streams' frame rates where the event's capture knows them all
    (``problem.known_rates``): fitted with the offsets, free rates drift where the motion is slow
    (docs/method.md, "Known frame rates"). The events are placed in ``options.workers``
    processes where there is enough work (``core.parallel``)."""
    n = capture.num_images
    rejected, residual = outlier_arrays(result)
    tasks = []
    for e in range(int(result.events.max()) + 1):
        idx = np.flatnonzero(result.events == e)
        if not filmed(capture.stream_ids[idx]):
            continue
        sub = capture.subset(idx) if idx.size < n else capture
        csub = None if checked is None else checked.subset(idx) if idx.size < n else checked
        tasks.append(EventToPlace(e, idx, sub, csub, options, result.X[idx], result.D[idx],
                                  result.W[idx][:, idx], rejected[idx], residual[idx],
                                  auto_noise, offsets))
    slots = sum(task.idx.size for task in tasks) * capture.num_points
    workers = worker_count(options.workers, len(tasks), slots)
    placed = map_in_processes(place_event, tasks, workers)
    return [p for p in placed if p is not None]


def filmed(streams: np.ndarray) -> bool:
    """Whether an event of images from ``streams`` is filmed by videos, for its clocks
    (:func:`placements`): two or more streams, each of three or more images. The others, of
    bursts and lone photos alone, are timed by :func:`burst_times`."""
    _, counts = np.unique(streams, return_counts=True)
    return counts.size >= 2 and counts.min() >= 3


class EventToPlace(NamedTuple):
    """What :func:`place_event` places: event ``e`` of images ``idx``, its capture ``sub`` and
    ``checked`` (:func:`placements`), the graph's points, D and W on it, the robust rounds'
    rejected observations and their residuals, and the flags of :func:`placements`."""

    e: int
    idx: np.ndarray
    sub: Capture
    checked: Capture | None
    options: Options
    X: np.ndarray
    D: np.ndarray
    W: sp.csr_matrix
    rejected: np.ndarray
    residual: np.ndarray
    auto_noise: bool
    offsets: bool


def place_event(task: EventToPlace) -> Placement | None:
    """One event of :func:`placements` on its clocks; None when its first guess places no
    stream (``sequencing.affine_time``)."""
    e, idx, sub, options = task.e, task.idx, task.sub, task.options
    offsets = task.offsets
    norm = normalise(sub, options, task.X)
    prob = norm.problem
    Xe = norm.to_normal(task.X)
    t0 = affine_time(Xe, prob.streams, sub.frame, rates=prob.rates)
    if t0 is None:
        return None
    rates = prob.rates if offsets else None
    t = event_clocks(t0, prob, sub.frame, options, offsets=offsets, rates=rates)
    moved = moved_periods(t0, t, prob.streams, sub.frame)
    if moved >= REACH:
        logger.info("event %d: the clock fit moved a stream %.1f frame periods from DLOE's "
                    "placement; the clocks are kept only if they predict held-out detections",
                    e, moved)
    noise, held = options.noise_px, None
    if task.auto_noise and noise == 0:
        noise, held = soft_rays_on_clocks(sub, options, task.X, task.D, task.W, t)
    ticked = options.replace(noise_px=noise)
    # the chain's weights come from the time line: no compactness term (as the oracle)
    W, D_e = time_chain(t)
    Xe = x_step(W, D_e, prob, lambda1=0.0, lambda2=soft_ray_weight(sub, ticked), X_prev=Xe)
    judged, rej_e, res_e = sub, task.rejected, task.residual
    if task.checked is not None:
        t, W, D_e, Xe, rej_e, res_e, weights = robust_on_clocks(
            task.checked, ticked, norm, t, Xe, rej_e, offsets=offsets, rates=rates)
        if weights is not None:  # both models are judged on the clocks' verdict
            judged, held = reweighted(task.checked, weights), None
    return Placement(idx, t, W, D_e, norm.to_world(Xe), rej_e, res_e, noise, judged, held,
                     moved)


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
    weighted by the robust loss of its residual as in ``pipeline.robust_rounds``, and the points
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


def verdicts(placed: list[Placement], options: Options, result: Result) -> list[Verdict]:
    """What ``options.stream_clocks`` makes of each placement: with ``auto`` the held-out check
    against the graph of ``result`` (``decisions.clock_verdict``); with ``on`` kept, except that
    a fit that moved a stream ``clocks.REACH`` frame periods or more from DLOE's placement is
    checked too (``decisions.clocks_checked``): the rays may not pin its clocks, or DLOE's
    placement was that far off (docs/method.md, "Stream clocks"). The checks run in
    ``options.workers`` processes as the placements do."""
    checked = [clocks_checked(options, p.moved) for p in placed]
    tasks = [(p.judged, options, result.X[p.idx], result.D[p.idx], p.t, p.noise, p.held)
             for p, check in zip(placed, checked, strict=True) if check]
    slots = sum(task[0].num_images for task in tasks) * result.X.shape[1]
    workers = worker_count(options.workers, len(tasks), slots)
    said = map_in_processes(_clock_verdict_task, tasks, workers)
    return [next(said) if check else Verdict.KEPT for check in checked]


def _clock_verdict_task(task: tuple) -> Verdict:
    """``decisions.clock_verdict`` of one placement's arguments (in a worker process)."""
    return clock_verdict(*task)


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


def burst_times(capture: Capture, options: Options, result: Result) -> Result:
    """``result`` with every event of bursts and lone photos alone (``events.without_videos``,
    not :func:`filmed`) timed on its bursts' clocks (``clocks.fit_burst_clocks``) from the rank
    base (``clocks.rank_times``; the reference, the stream of most images), its lone photos
    evenly by rank between the bursts' images (``clocks.by_rank``), where those times predict
    held-out detections better than the rank base (``decisions.burst_clocks_time``; logged
    either way). The event's block of the order is theirs; its points go on the chain along
    them where they predict held-out detections as well as the graph's (:func:`verdicts`, as a
    video's clocks; then the times are ``clock``), else they stay the graph's and the times go
    to ``clock_dropped`` (docs/method.md, "Clocks of bursts"; lone photos timed on their own
    did worse). An event needs two streams of two or more images and no clocks of its own; a
    fit that puts a stream's frames out of their order is not taken (logged). ``capture`` is
    the one the result was solved on."""
    n, stream_ids = capture.num_images, capture.stream_ids
    times = np.full(n, np.nan) if result.clock_dropped is None else result.clock_dropped.copy()
    order, rank = result.order.copy(), result.rank
    timed = np.isfinite(times) | (np.zeros(n, dtype=bool) if result.clock is None
                                  else np.isfinite(result.clock))
    changed, placed = False, []
    for e in np.unique(result.events):
        idx = np.flatnonzero(result.events == e)
        idx = idx[np.argsort(rank[idx], kind="stable")]
        streams, frames = stream_ids[idx], capture.frame[idx]
        bursts, ref = reference_stream(streams, frames)
        if timed[idx].any() or len(bursts) < 2 or filmed(streams) or not without_videos(streams):
            continue
        t0 = rank_times(streams, frames, ref)
        if t0 is None:
            continue
        burst = np.isin(streams, bursts)
        prob = normalise(capture.subset(idx[burst]), options, result.X[idx[burst]]).problem
        E, rhs = ray_equations(prob.rays, prob.C, prob.weights)
        t = fit_burst_clocks(t0[burst], streams[burst], frames[burst], E, rhs, prob.visible)
        backwards = [s for s in bursts if np.polyfit(frames[streams == s], t[streams[burst] == s],
                                                     1)[0] <= 0]
        if backwards:
            logger.info("event %d: the clocks of its bursts put stream(s) %s backwards in time; "
                        "it keeps the rank base", e, backwards)
            continue
        t = by_rank(burst, t)
        sub = capture.subset(idx)
        said = [residuals_px(sub, chain_predicted(time_chain(x)[0], x, result.X[idx]))
                for x in (t0, t)]
        if not all(np.isfinite(px).any() for px in said):
            logger.info("event %d: no detection to judge its bursts' clocks on; it keeps the "
                        "rank base", e)
            continue
        kept = burst_clocks_time(*said)
        logger.info("event %d: %d bursts and %d lone photo(s); held-out detections along the "
                    "bursts' clocks %.2f px, along the rank base %.2f px (median): %s", e,
                    len(bursts), int((~burst).sum()), np.nanmedian(said[1]),
                    np.nanmedian(said[0]), "timed on the clocks" if kept else "the rank base kept")
        if not kept:
            continue
        times[idx], changed = t, True
        order[np.sort(rank[idx])] = idx[np.argsort(t, kind="stable")]
        placed.append(_on_burst_clocks(sub, options, result, idx, t))
    if not changed:
        return result
    result = replace(result, clock_dropped=times, order=order)
    kept = [p for p, v in zip(placed, verdicts(placed, options, result), strict=True)
            if v is Verdict.KEPT]
    for p in kept:  # timed and placed on their clocks
        times[p.idx] = np.nan
    return on_clocks(replace(result, clock_dropped=times if np.isfinite(times).any() else None),
                     kept, checked=False)


def _on_burst_clocks(sub: Capture, options: Options, result: Result, idx: np.ndarray,
                     t: np.ndarray) -> Placement:
    """The event of images ``idx`` (``sub``) of ``result`` placed on its bursts' clocks ``t``
    (:func:`burst_times`): the points by the X-step on the chain along them, the rays as the
    solve's, for the held-out check against the graph (:func:`verdicts`)."""
    norm = normalise(sub, options, result.X[idx])
    W, D = time_chain(t)
    X = x_step(W, D, norm.problem, lambda1=0.0, lambda2=soft_ray_weight(sub, options),
               X_prev=norm.to_normal(result.X[idx]))
    rejected, residual = outlier_arrays(result)
    return Placement(idx, t, W, D, norm.to_world(X), rejected[idx], residual[idx],
                     options.noise_px, sub, None, 0.0)


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
    keep = offsets_kept(before, after)
    logger.info("stream offsets of the detections, median %.2f px: residuals of the frames they "
                "were not estimated on %.2f -> %.2f px (median), %s", np.median(size[size > 0]),
                before, after, "taken out" if keep else "not taken out")
    return offsets if keep else None


def outlier_arrays(result: Result) -> tuple[np.ndarray, np.ndarray]:
    """(N, P) the observations ``result`` left out (``outliers``) and their residuals in
    pixels (``outlier_residual_px``; NaN elsewhere)."""
    rejected = np.zeros(result.X.shape[:2], dtype=bool)
    residual = np.full(result.X.shape[:2], np.nan)
    if result.outliers.size:
        rejected[tuple(result.outliers.T)] = True
        residual[tuple(result.outliers.T)] = result.outlier_residual_px
    return rejected, residual
