"""The solver's result object."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .capture import Capture


@dataclass(kw_only=True)
class Result:
    """What :func:`dloe_sfm.reconstruct` returns (shapes: N images, P points).

    Attributes
    ----------
    X : (N, P, 3) float
        Reconstructed points of every image, also where the point was not observed.
    order : (N,) int
        Image indices sorted by estimated time (first = earliest; direction follows the streams;
        in an event with stream clocks, kept or dropped, by their times).
    A : (N, N) scipy.sparse.csr_matrix
        Estimated affinity ``D W``.
    W : (N, N) csr_matrix
        Row-stochastic neighbour weights (chain prior included).
    D : (N,) float
        Degrees (diagonal of D).
    events : (N,) int
        Event (connected component) label of every image, 0..E-1.
    embedding : (N,) float
        Position of every image on the estimated time line (arc-length units within an event).
    cost_history, change_history : (iters,) float
        Total cost and relative change of X per outer iteration.
    nit : int
    success : bool
        Whether the stopping tolerance was reached.
    message : str
    seconds : float
        Wall time of the solve.
    timings : dict
        Seconds spent per stage (init, w_step, d_step, x_step, sequencing, ..., assess: the
        per-image checks, which ``seconds`` does not include).
    scale : float
        The normalisation length (median camera-to-scene distance, world units).
    noise_px : float
        The detection noise (std, pixels) the solve used: ``Options.noise_px``, or its estimate
        with ``auto`` (0: the detections were taken as exact; with several events, the largest).
    clock : (N,) float or None
        With stream clocks (``Options.stream_clocks``): every image's time on its stream's
        fitted clock, in frames of its event's longest stream (NaN in an event without them);
        None when no event has them. The points of those events are on the chain along them
        (an event of bursts and lone photos on its bursts' clocks too,
        ``core.clocked.burst_times``).
    clock_dropped : (N,) float or None
        Every image's time on the clocks fitted for its event but not kept for its points (the
        held-out check preferred DLOE's graph), as ``clock`` counts it (NaN elsewhere); None
        when no event's clocks were dropped. Such an event is still ordered and timed by them
        (``order``, the exports), and the sync report takes their disagreement with DLOE's own
        time line (``embedding``) into its uncertainty (``core.sync.stream_clocks``). An event
        of bursts and lone photos alone whose bursts' clocks (``core.clocked.burst_times``)
        time it but do not hold its points has them here too, counted in frames of its stream
        of most images.
    subject_id, point_id : (P',) int or None
        With several subjects: column k of X is point ``point_id[k]`` of subject
        ``subject_id[k]`` (P' = subjects x P). None for one subject.
    assignment : (N, M) int or None
        With several subjects: the subject of detection m of image n (-1 = none).
    outliers : (K, 2) int
        (image, column of X) of the observations the robust loss rejected...
    outlier_residual_px : (K,) float
        ...and their distance in pixels from what the rest of the solution predicts there.
    swaps : (K, 3) int
        (image, column a, column b): left/right detections found swapped and exchanged.
    solved : Capture or None
        The (N, P', 2) observations X refers to (subjects aggregated, swaps undone, stream
        offsets taken out); None when that is the input capture itself.
    offset_px : (N, P', 2) float or None
        The pixel offset of its stream's detections of the point (``core.bias``) taken out of
        every observation in ``solved``; None when none was.
    image_status : (N,) str or None
        Per-image check of the solution (``core.assess``): ``ok``, ``uncertain`` (the data
        determine its shape weakly) or ``inconsistent`` (its shape disagrees with its rays or
        its temporal neighbours far beyond the capture's own spread)...
    status_reason : (N,) str or None
        ...why ("" when ok).
    residual_px : (N,) float or None
        Median reprojection residual of each image's observed points in its own camera, pixels.
    neighbour_deviation : (N,) float or None
        RMS distance of each image's points from its graph neighbours' prediction ``W X``, in
        typical neighbour steps (NaN: no neighbour).
    depth_sd : (N, P') float or None
        Standard deviation of every observed point's depth along its ray (of every unobserved
        point's position) given the rays and the graph, world units.
    supported : (N, P') bool or None
        Points the data support: False where unobserved and weakly determined, or in an
        ``inconsistent`` image (NaN in the exports).
    order_ambiguous : (N,) bool or None
        Lone photos whose rays fit another time on the line as well as their place in
        ``order`` (a pose seen again, ``core.rayplace``): their place is a guess.
    """

    X: np.ndarray
    order: np.ndarray
    A: sp.csr_matrix
    W: sp.csr_matrix
    D: np.ndarray
    events: np.ndarray
    embedding: np.ndarray
    cost_history: np.ndarray
    change_history: np.ndarray
    nit: int
    success: bool
    message: str
    seconds: float
    timings: dict = field(default_factory=dict)
    scale: float = 1.0
    noise_px: float = 0.0
    clock: np.ndarray | None = None
    clock_dropped: np.ndarray | None = None
    subject_id: np.ndarray | None = None
    point_id: np.ndarray | None = None
    assignment: np.ndarray | None = None
    outliers: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    outlier_residual_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    swaps: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))
    solved: Capture | None = None
    offset_px: np.ndarray | None = None
    image_status: np.ndarray | None = None
    status_reason: np.ndarray | None = None
    residual_px: np.ndarray | None = None
    neighbour_deviation: np.ndarray | None = None
    depth_sd: np.ndarray | None = None
    supported: np.ndarray | None = None
    order_ambiguous: np.ndarray | None = None

    @property
    def rank(self) -> np.ndarray:
        """(N,) int: position of every image in ``order``."""
        rank = np.empty_like(self.order)
        rank[self.order] = np.arange(self.order.size)
        return rank


def merged_history(results: list[Result], label: str) -> dict:
    """The fields of one :class:`Result` made of ``results`` solved apart (events, windows) that
    only sum up theirs: sweeps, costs, messages (``"<label> k: ..."``), timings, the noise."""
    return {
        "cost_history": np.concatenate([r.cost_history for r in results]),
        "change_history": np.concatenate([r.change_history for r in results]),
        "nit": sum(r.nit for r in results),
        "success": all(r.success for r in results),
        "message": "; ".join(f"{label} {k}: {r.message}" for k, r in enumerate(results)),
        "timings": {k: sum(r.timings.get(k, 0.0) for r in results) for k in results[0].timings},
        "noise_px": max(r.noise_px for r in results),
    }

