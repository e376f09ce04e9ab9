"""Several subjects in the same images (the paper's multi-target scenario, five steps).

1. Every detection of every image becomes a proxy image of its own (same camera, one subject).
2. DLOE's graph over all proxies, fitted in shape space to their initial shapes: a subject's
   proxies combine each other's shapes, not another subject's, so each subject becomes an event.
3. Association through the common source image: the proxies of one image are different
   subjects. A stream's consecutive images link the detections that barely moved between them
   (one person, tracked in the image); those runs merge, by the proxy graph's total link weight
   between them and never two holding one image, until one cluster per subject is left.
4. Aggregation: each image's subjects form one shape of S x P points.
5. DLOE over the original images with those shapes (streams, events, robust loss as usual).
"""

from __future__ import annotations

import heapq
import logging
import time
import warnings
from dataclasses import replace

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import connected_components

from .alternation import Progress
from .capture import Capture, project
from .decisions import SUBJECT_MISFIT, subject_count, subject_support
from .events import stream_runs, symmetrised
from .heldout import held_out_subjects
from .options import Options
from .pipeline import finish_single, plain_solve, reweighs, shape_space_graph, solve_single
from .problem import initialise
from .result import Result
from .robust import predicted

logger = logging.getLogger("dloe_sfm")


def proxy_capture(capture: Capture) -> tuple[Capture, np.ndarray, np.ndarray]:
    """Step 1: (proxies, source image (N',), detection slot (N',)) of an (N, M, P, 2) capture.

    Proxies are lone photos: a detector's slot order says nothing about identity, so no stream
    order links them in the graph (two proxies of one static camera are never neighbours
    anyway: their rays are parallel); the association tracks them along streams instead
    (:func:`stream_links`).
    """
    vis = capture.visible
    source, slot = np.nonzero(vis.any(axis=2))
    conf = capture.weights[source, slot]
    names = np.array([f"{capture.image_names[n]}#{m}" for n, m in zip(source, slot, strict=True)])
    proxies = Capture(
        x=np.where(vis[source, slot][..., None], capture.x[source, slot], np.nan),
        K=capture.K[source], R=capture.R[source], C=capture.C[source],
        stream=np.full(source.size, -1), frame=np.zeros(source.size, dtype=np.int64),
        confidence=conf, image_names=names,
    )
    return proxies, source, slot


STEP = 0.1
"""Largest displacement, in detection sizes, of a person between consecutive images of a
stream (median over the points both detections hold) for the two detections to be linked."""

DISTINCT = 2.0
"""How many times nearer a linked pair must be than either detection is to any other detection
of the other image: where two people are about as near, the link is left to the graph."""


def detection_sizes(capture: Capture, visible: np.ndarray) -> np.ndarray:
    """(N, M) the longer side of each detection's bounding box (0: no point); ``visible``
    (N, M, P) the capture's."""
    vis = visible[..., None]
    lo = np.where(vis, capture.x, np.inf).min(axis=2)
    hi = np.where(vis, capture.x, -np.inf).max(axis=2)
    return np.where(vis.any(axis=2), hi - lo, 0.0).max(axis=-1)


def step_costs(capture: Capture, visible: np.ndarray, sizes: np.ndarray, a: int, b: int
               ) -> np.ndarray:
    """(M, M) displacement between the detections of images ``a`` and ``b``: the median
    distance over the points both hold (at least 3, else inf) over the larger one's size;
    ``visible`` (N, M, P) the capture's."""
    both = visible[a][:, None] & visible[b][None]  # (M, M, P)
    d = np.linalg.norm(capture.x[a][:, None] - capture.x[b][None], axis=-1)
    with warnings.catch_warnings():  # all-NaN slices: pairs without a common point
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(np.where(both, d, np.nan), axis=-1)
    scale = np.maximum(np.maximum.outer(sizes[a], sizes[b]), 1e-12)
    return np.where(both.sum(axis=-1) >= 3, median / scale, np.inf)


def stream_links(capture: Capture) -> np.ndarray:
    """(L, 2) pairs of detections (flat indices ``image * M + slot``) of one person in
    consecutive images of a stream run (``events.stream_runs``): within a run a person moves
    little from image to image, which tells people apart over time better than their shapes.

    Each image pair's detections are matched one to one (Hungarian on ``step_costs``); a match
    is kept when it moved under :data:`STEP` sizes and :data:`DISTINCT` times less than to any
    other detection of either image. Lone photos have none.
    """
    m = capture.x.shape[1]
    visible = capture.visible
    sizes = detection_sizes(capture, visible)
    runs = stream_runs(capture.stream, capture.frame)
    order = np.lexsort((capture.frame, runs))
    pairs = []
    for a, b in zip(order[:-1], order[1:], strict=True):
        if runs[a] != runs[b]:
            continue
        cost = step_costs(capture, visible, sizes, a, b)
        rows, cols = linear_sum_assignment(np.minimum(cost, 1e300))
        for i, j in zip(rows, cols, strict=True):
            others = min(np.delete(cost[i], j).min(initial=np.inf),
                         np.delete(cost[:, j], i).min(initial=np.inf))
            if cost[i, j] < STEP and DISTINCT * cost[i, j] < others:
                pairs.append((a * m + i, b * m + j))
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def constrained_merging(
    G: sp.csr_matrix, start: np.ndarray, group: np.ndarray, k: int
) -> np.ndarray:
    """(N',) clusters 0..k-1 (or -1) of the nodes of affinity ``G`` (N', N'), by greedy merging.

    From the clusters ``start`` (N'), the two of the largest total link weight between them
    that share no ``group`` merge, until k are left or no two linked ones may merge: each merge
    takes the most weight it can out of the cut. A subject's proxies form a long chain along
    time, linked image to image; a spectral clustering cuts such chains where they thin out and
    pairs the pieces across people, while merging joins a chain's pieces wherever a link is
    left and the groups forbid the pieces of two people that are seen together. The k largest
    clusters are the result; the nodes of the others take, per group, the clusters their group
    left free (a Hungarian match on link weight; those beyond k in a group: -1).
    """
    _, start = np.unique(start, return_inverse=True)
    count = start.max() + 1
    P = sp.csr_matrix((np.ones(start.size), (start, np.arange(start.size))))
    S = sp.triu(P @ G @ P.T, k=1).tocoo()
    links = [{} for _ in range(count)]
    for a, b, w in zip(S.row, S.col, S.data, strict=True):
        links[a][b] = links[b][a] = w
    order = np.argsort(start, kind="stable")
    members = [list(m) for m in np.split(order, np.cumsum(np.bincount(start))[:-1])]
    groups = [set(group[m].tolist()) for m in members]
    heap = [(-w, a, b) for a, b, w in zip(S.row, S.col, S.data, strict=True)]
    heapq.heapify(heap)
    alive = count
    while heap and alive > k:
        w, a, b = heapq.heappop(heap)
        if links[a].get(b) != -w or groups[a] & groups[b]:
            continue  # stale (merged since), or never: clusters only grow
        if len(members[a]) < len(members[b]):
            a, b = b, a
        for c, v in links[b].items():
            del links[c][b]
            if c != a:
                links[a][c] = links[c][a] = links[a].get(c, 0.0) + v
                heapq.heappush(heap, (-links[a][c], min(a, c), max(a, c)))
        links[b] = {}
        members[a] += members[b]
        groups[a] |= groups[b]
        members[b], groups[b] = [], set()
        alive -= 1
    sizes = np.array([len(m) for m in members])
    labels = np.full(start.size, -1)
    for c, big in enumerate(np.argsort(-sizes, kind="stable")[:k]):
        labels[members[big]] = c
    kept = np.flatnonzero(labels >= 0)
    affinity = (G @ sp.csr_matrix((np.ones(kept.size), (kept, labels[kept])),
                                  shape=(labels.size, k))).toarray()
    for g in np.unique(group[labels < 0]):
        rest = np.flatnonzero((group == g) & (labels < 0))
        free = np.setdiff1d(np.arange(k), labels[group == g])
        rows, cols = linear_sum_assignment(-affinity[np.ix_(rest, free)])
        labels[rest[rows]] = free[cols]
    return labels


def associate(capture: Capture, options: Options) -> np.ndarray:
    """Steps 1-3: (N, M) subject of every detection (-1: none), subjects numbered by first image.

    The number of subjects is ``decisions.subject_count``; with one, each image keeps its
    detection of the largest total score. With more, the runs of one person along streams
    (:func:`stream_links`) merge over the proxy graph (:func:`constrained_merging`). A subject
    needs ``decisions.SUBJECT_IMAGES`` images and ``decisions.SUBJECT_VIEWS`` streams (all the
    capture's, when it has fewer: ``decisions.subject_support``); the detections of a cluster
    short of either support nobody and are left out (logged), except where one is its image's
    only detection. A capture in which no cluster passes keeps them all.
    """
    proxies, source, slot = proxy_capture(capture)
    k = subject_count(source)
    assignment = np.full(capture.x.shape[:2], -1)
    if k == 1:
        best = np.argmax(capture.weights.sum(axis=2), axis=1)
        img = np.unique(source)
        assignment[img, best[img]] = 0
        return assignment
    W = shape_space_graph(proxies, options, initialise(proxies, options))
    proxy = np.full(capture.x.shape[:2], -1)
    proxy[source, slot] = np.arange(source.size)
    linked = proxy.ravel()[stream_links(capture)]  # detections of points: proxies all
    tracked = sp.coo_matrix((np.ones(len(linked)), (linked[:, 0], linked[:, 1])),
                            shape=(source.size, source.size))
    labels = constrained_merging(symmetrised(W), connected_components(tracked, directed=False)[1],
                                 source, k)
    streams = capture.stream_ids[source]
    images, views = subject_support(np.unique(capture.stream_ids).size)
    lonely = np.bincount(source)[source] == 1
    seen = [(int(np.unique(source[labels == c]).size), int(np.unique(streams[labels == c]).size))
            for c in range(k)]
    stray = [c for c in range(k) if seen[c][0] < images or seen[c][1] < views]
    if len(stray) < k:  # a capture too small for any subject to pass keeps them all
        for c in stray:
            logger.warning("%d detection(s) support no subject (in %d image(s), seen by %d "
                           "stream(s); a subject needs %d images and %d streams): left out",
                           int(((labels == c) & ~lonely).sum()), *seen[c], images, views)
        labels[np.isin(labels, stray) & ~lonely] = -1
    ranked = sorted(np.unique(labels[labels >= 0]), key=lambda c: np.argmax(labels == c))
    remap = np.full(k, -1)
    remap[ranked] = np.arange(len(ranked))
    assignment[source, slot] = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
    return assignment


def aggregate(capture: Capture, assignment: np.ndarray) -> Capture:
    """Step 4: the (N, S P, 2) capture whose columns s P .. s P + P - 1 are subject s."""
    n, _, p = capture.x.shape[:3]
    s = int(assignment.max()) + 1
    x = np.full((n, s, p, 2), np.nan)
    conf = np.zeros((n, s, p))
    img, det = np.nonzero(assignment >= 0)
    x[img, assignment[img, det]] = capture.x[img, det]
    conf[img, assignment[img, det]] = capture.weights[img, det]
    pairs = capture.symmetric_pairs
    if pairs is not None:
        pairs = np.concatenate([pairs + k * p for k in range(s)])
    return Capture(
        x=x.reshape(n, s * p, 2), K=capture.K, R=capture.R, C=capture.C,
        stream=capture.stream, frame=capture.frame, fps=capture.fps,
        confidence=conf.reshape(n, s * p),
        image_names=capture.image_names, symmetric_pairs=pairs, subjects=s,
        image_ids=capture.image_ids,
    )


CAP_PX = 50.0
"""Largest pixel distance one point adds to a detection's fit to a subject (a wrong or swapped
point does not decide it)."""


def prediction_distances(capture: Capture, subjects: int, result: Result) -> np.ndarray:
    """(N, M, S, P) pixel distance of every detected point to each subject's graph prediction
    (``W X``, from the other images); NaN where the point is not detected."""
    n, m, p = capture.x.shape[:3]
    X_pred = predicted(result.W, result.X).reshape(n, subjects, p, 3)
    x_hat = np.stack(
        [project(X_pred[:, k], capture.K, capture.R, capture.C) for k in range(subjects)], axis=1
    )
    d = np.linalg.norm(capture.x[:, :, None] - x_hat[:, None], axis=-1)
    return np.where(capture.visible[:, :, None, :], np.nan_to_num(d, nan=CAP_PX), np.nan)


def fit_costs(capture: Capture, assignment: np.ndarray, result: Result) -> np.ndarray:
    """(N, M, S) mean pixel distance of every detection to each subject's graph prediction
    (``prediction_distances``), each point's capped at ``CAP_PX``; 0 where none seen."""
    d = prediction_distances(capture, int(assignment.max()) + 1, result)
    seen = np.isfinite(d)
    cost = np.where(seen, np.minimum(d, CAP_PX), 0.0).sum(axis=-1)
    return cost / np.maximum(seen.sum(axis=-1), 1)


def reassociate(capture: Capture, assignment: np.ndarray, result: Result) -> np.ndarray:
    """(N, M) assignment matched again to the solution: each image's assigned detections go to
    the subjects whose graph prediction they fit best (``fit_costs``), one subject per
    detection."""
    cost = fit_costs(capture, assignment, result)
    out = assignment.copy()
    for i in range(capture.num_images):
        dets = np.flatnonzero(assignment[i] >= 0)
        rows, cols = linear_sum_assignment(cost[i, dets])
        out[i, dets[rows]] = cols
    return out


def detection_confidence(capture: Capture, assignment: np.ndarray, result: Result
                         ) -> np.ndarray:
    """(N, M) how surely each assigned detection is its subject's, in [0, 1] (NaN: unassigned):
    1 - its median point distance to its subject's graph prediction over that to the nearest
    other subject's (``prediction_distances``). 1: on its subject's prediction (and always
    with one subject: there is no other to take it for); 0: as near another subject's."""
    s = int(assignment.max()) + 1
    confidence = np.where(assignment >= 0, 1.0, np.nan)
    if s < 2:
        return confidence
    with warnings.catch_warnings():  # all-NaN slices: detections of no point
        warnings.simplefilter("ignore", RuntimeWarning)
        d = np.nanmedian(prediction_distances(capture, s, result), axis=-1)  # (N, M, S)
    mine = np.maximum(assignment, 0)[..., None]
    own = np.take_along_axis(d, mine, axis=2)[..., 0]
    others = np.where(np.arange(s) == mine, np.inf, d).min(axis=2)
    ratio = np.clip(1.0 - own / np.maximum(others, 1e-12), 0.0, 1.0)
    return np.where(assignment >= 0, ratio, np.nan)


def checked_again(capture: Capture, assignment: np.ndarray, result: Result
                  ) -> tuple[np.ndarray, bool]:
    """(assignment matched again to ``result``, whether any image changed) (``reassociate``)."""
    new = reassociate(capture, assignment, result)
    changed = int((new != assignment).any(axis=1).sum())
    if changed:
        logger.info("association: %d image(s) changed, solving again", changed)
    return new, changed > 0


def unfit_subjects(merged: Capture, assignment: np.ndarray, result: Result,
                   options: Options) -> np.ndarray:
    """The subjects of ``result`` (solved on ``merged``, the capture aggregated by
    ``assignment``) that are no person: their detections, each held out, are predicted
    (``heldout.held_out_subjects``, median) more than ``decisions.SUBJECT_MISFIT`` times farther
    than all subjects' detections (median); unless leaving their detections out would leave an
    image with none, or no subject. Each is logged."""
    s = int(assignment.max()) + 1
    if s < 2:
        return np.zeros(0, dtype=np.int64)
    held = held_out_subjects(merged, s, result, options)
    typical = float(np.nanmedian(held))
    with warnings.catch_warnings():  # a subject none of whose points is in front of a camera
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(held, axis=0)
    unfit = np.flatnonzero(median > SUBJECT_MISFIT * typical)
    others = (assignment >= 0) & ~np.isin(assignment, unfit)
    if unfit.size == s or not others.any(axis=1)[(assignment >= 0).any(axis=1)].all():
        return np.zeros(0, dtype=np.int64)
    for k in unfit:
        logger.warning("%d detection(s) in %d image(s) follow no motion (held out, predicted "
                       "%.0f px off, median; all detections %.1f px): left out",
                       int((assignment == k).sum()), int((assignment == k).any(axis=1).sum()),
                       median[k], typical)
    return unfit


def without_subjects(assignment: np.ndarray, subjects: np.ndarray) -> np.ndarray:
    """``assignment`` without ``subjects``: their detections -1, the others renumbered in
    order."""
    s = int(assignment.max()) + 1
    remap = np.full(s, -1)
    keep = np.setdiff1d(np.arange(s), subjects)
    remap[keep] = np.arange(keep.size)
    return np.where(assignment >= 0, remap[np.maximum(assignment, 0)], -1)


def reconstruct_subjects(
    capture: Capture,
    options: Options,
    *,
    rounds: int = 3,
    progress: Progress | None = None,
) -> Result:
    """All five steps: a :class:`Result` over the S P columns of the aggregated capture, with
    ``subject_id``, ``point_id``, ``assignment`` and ``solved`` (the aggregated capture).

    The association is checked against the solution (``reassociate``) and, where it changed,
    aggregated and solved again, at most ``rounds`` associations in all. Under detector noise
    (the plain solve found some, and the robust rounds run) the first check is against the
    plain solve, before its robust round, and each new association is solved by the robust
    round resumed from the last solution (``pipeline.finish_single``), since a few images
    changed: one solve per association after the first instead of two. A subject whose
    detections follow no motion (:func:`unfit_subjects`: held out, the last solution predicts
    them far off) is then dropped, its detections left out, and the capture solved again from
    the start without it. It is checked last: through the rounds the false detections that
    people's subjects took move to it, and leave with it.
    """
    started = time.perf_counter()
    assignment = associate(capture, options)
    s = int(assignment.max()) + 1
    p = capture.num_points
    logger.info("%d subject(s) in %d images (%d detections unassigned)", s,
                capture.num_images, int(((assignment < 0) & capture.visible.any(axis=2)).sum()))

    def aggregated(assignment: np.ndarray) -> Capture:
        """The capture aggregated by ``assignment`` (step 4), checked for the solve."""
        return aggregate(capture, assignment).validate("aggregated subjects")

    merged = aggregated(assignment)
    result, labels = plain_solve(merged, options, progress)
    # under detector noise the robust rounds re-solve once, from a solution's prediction: the
    # association is checked against the plain solve already, and a later round re-solves
    # from the last solution (finish_single's resumed) rather than from the start
    resume = s > 1 and reweighs(merged, options) and result.noise_px > 0
    checks, changed = (rounds - 1 if s > 1 else 0), False
    if resume and checks:
        assignment, changed = checked_again(capture, assignment, result)
        checks -= 1
        if changed:
            merged = aggregated(assignment)
    result = finish_single(merged, options, result, labels, progress, resumed=changed)
    for _ in range(checks):
        assignment, changed = checked_again(capture, assignment, result)
        if not changed:
            break
        merged = aggregated(assignment)
        result = (finish_single(merged, options, result, labels, progress, resumed=True)
                  if resume else solve_single(merged, options, progress))
    unfit = unfit_subjects(merged, assignment, result, options)
    if unfit.size:  # solved from the start: the robust rounds weight the others afresh
        assignment = without_subjects(assignment, unfit)
        s = int(assignment.max()) + 1
        merged = aggregated(assignment)
        result = solve_single(merged, options, progress)
    return replace(
        result,
        seconds=time.perf_counter() - started,
        subject_id=np.repeat(np.arange(s), p),
        point_id=np.tile(np.arange(p), s),
        assignment=assignment,
        solved=result.solved if result.solved is not None else merged,
    )
