"""Several subjects in the same images (the paper's multi-target scenario, five steps).

1. Every detection of every image becomes a proxy image of its own (same camera, one subject).
2. DLOE's graph over all proxies, fitted in shape space to their initial shapes: a subject's
   proxies combine each other's shapes, not another subject's, so each subject becomes an event.
3. Association through the common source image: the proxies of one image are different
   subjects, so they are split by a spectral clustering of the proxy graph whose assignment
   step matches each image's proxies to distinct subjects (Hungarian, per image).
4. Aggregation: each image's subjects form one shape of S x P points.
5. DLOE over the original images with those shapes (streams, events, robust loss as usual).
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from .alternation import Progress
from .capture import Capture, project
from .decisions import subject_count, subject_support
from .events import cluster_coordinates
from .options import Options
from .pipeline import shape_space_graph, solve_single
from .problem import initialise
from .result import Result
from .robust import predicted

logger = logging.getLogger("dloe_sfm")


def proxy_capture(capture: Capture) -> tuple[Capture, np.ndarray, np.ndarray]:
    """Step 1: (proxies, source image (N',), detection slot (N',)) of an (N, M, P, 2) capture.

    Proxies are lone photos: a detector's slot order says nothing about identity, so no stream
    order links them (two proxies of one static camera are never neighbours anyway: their
    rays are parallel).
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


def constrained_clusters(
    F: np.ndarray, group: np.ndarray, k: int, *, max_iterations: int = 100
) -> np.ndarray:
    """k-means of the rows of F (N', d) where rows of one ``group`` take distinct clusters.

    Seeds: the rows of the first group with k members (else farthest-point seeding); the
    assignment step solves one small assignment problem per group; the rows of a group of
    more than k that lose it are -1.
    """
    groups = [np.flatnonzero(group == g) for g in np.unique(group)]
    full = next((g for g in groups if g.size == k), None)
    if full is not None:
        centres = F[full].copy()
    else:
        centres = [F[0]]
        for _ in range(k - 1):
            d = np.min([((F - c) ** 2).sum(axis=1) for c in centres], axis=0)
            centres.append(F[int(np.argmax(d))])
        centres = np.array(centres)
    labels = np.full(F.shape[0], -1)
    for _ in range(max_iterations):
        cost = ((F[:, None, :] - centres[None]) ** 2).sum(axis=2)
        new = np.full_like(labels, -1)
        for g in groups:
            rows, cols = linear_sum_assignment(cost[g])
            new[g[rows]] = cols
        if (new == labels).all():
            break
        labels = new
        for c in range(k):
            if (labels == c).any():
                centres[c] = F[labels == c].mean(axis=0)
    return labels


def associate(capture: Capture, options: Options) -> np.ndarray:
    """Steps 1-3: (N, M) subject of every detection (-1: none), subjects numbered by first image.

    The number of subjects is ``decisions.subject_count``; with one, each image keeps its
    detection of the largest total score. A subject needs ``decisions.SUBJECT_IMAGES`` images
    and ``decisions.SUBJECT_VIEWS`` streams (all the capture's, when it has fewer:
    ``decisions.subject_support``); the detections of a cluster short of either support
    nobody and are left out (logged), except where one is its image's only detection. A capture
    in which no cluster passes keeps them all.
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
    F = cluster_coordinates(W, k)
    labels = constrained_clusters(F, source, k)
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
        image_names=capture.image_names, symmetric_pairs=pairs,
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


def reconstruct_subjects(
    capture: Capture,
    options: Options,
    *,
    rounds: int = 3,
    progress: Progress | None = None,
) -> Result:
    """All five steps: a :class:`Result` over the S P columns of the aggregated capture, with
    ``subject_id``, ``point_id``, ``assignment`` and ``solved`` (the aggregated capture).

    The association is then checked against the solution (``reassociate``) and, where it
    changed, aggregated and solved again, at most ``rounds`` times.
    """
    started = time.perf_counter()
    assignment = associate(capture, options)
    s = int(assignment.max()) + 1
    p = capture.num_points
    logger.info("%d subject(s) in %d images (%d detections unassigned)", s,
                capture.num_images, int(((assignment < 0) & capture.visible.any(axis=2)).sum()))
    for it in range(rounds):
        merged = aggregate(capture, assignment)
        result = solve_single(merged.validate("aggregated subjects"), options, progress, s)
        if s == 1 or it == rounds - 1:
            break
        new = reassociate(capture, assignment, result)
        changed = int((new != assignment).any(axis=1).sum())
        if not changed:
            break
        logger.info("association: %d image(s) changed, solving again", changed)
        assignment = new
    return replace(
        result,
        seconds=time.perf_counter() - started,
        subject_id=np.repeat(np.arange(s), p),
        point_id=np.tile(np.arange(p), s),
        assignment=assignment,
        solved=result.solved if result.solved is not None else merged,
    )
