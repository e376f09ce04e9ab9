"""A capture too large for one solve, in overlapping time windows solved apart and stitched.

The videos' first-guess clocks (``sequencing.affine_time`` on the pseudo-triangulated shapes)
order the images; consecutive runs of ``size`` images in that order, ``overlap`` of them shared
with the next run, are solved as captures of their own (:func:`.pipeline.solve_single`:
events, robust rounds and clocks included), in parallel processes (``core.parallel``). Every
image then takes the solution of the window it lies deepest in (farthest from that window's
ends in the first-guess order): its points, its row of W and D. The order comes from the
streams' affine clocks fitted to the stitched shapes over the whole capture (as a single solve's
final sequencing: a short window may hold too little motion to place its streams' offsets); the
fitted clocks of the windows that have them (``Result.clock``) are mapped onto that time line by
a straight line through the window's own images.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Iterator
from functools import partial

import numpy as np
import scipy.sparse as sp

from ..errors import InputError
from .bias import without_offsets
from .capture import Capture
from .events import segment_events
from .options import Options
from .parallel import map_in_processes, worker_count
from .pipeline import solve_single
from .problem import assemble, initialise, known_rates, parts
from .result import Result, merged_history
from .robust import apply_swaps
from .sequencing import affine_time

logger = logging.getLogger("dloe_sfm")

Mapper = Callable[[Callable, Iterable], Iterator]
"""``mapper(fn, items)``: ``fn`` over ``items``, results in order (e.g. Dask's)."""


def plan_windows(times: np.ndarray, size: int, overlap: int) -> tuple[list[np.ndarray], np.ndarray]:
    """(image indices of every window, the window each image is taken from).

    Windows are runs of ``size`` images in the order of ``times``, each starting
    ``size - overlap`` after the previous one (the last ends at the last image); an image is
    taken from the window whose nearer end is farthest from it.
    """
    n = times.size
    if size >= n:
        return [np.arange(n)], np.zeros(n, dtype=np.int64)
    if not 0 <= overlap < size:
        raise InputError(f"window overlap must be in [0, {size}), got {overlap}")
    by_time = np.argsort(times, kind="stable")
    step = size - overlap
    starts = list(range(0, n - size, step)) + [n - size]
    depth = np.full(n, -1)
    home = np.zeros(n, dtype=np.int64)
    for w, lo in enumerate(starts):
        rank = np.arange(size)
        inner = np.minimum(rank, size - 1 - rank)
        idx = by_time[lo:lo + size]
        deeper = inner > depth[idx]
        depth[idx[deeper]] = inner[deeper]
        home[idx[deeper]] = w
    return [np.sort(by_time[lo:lo + size]) for lo in starts], home


def first_guess_times(capture: Capture, options: Options) -> np.ndarray:
    """Every image's time on its stream's first-guess affine clock (reference-stream frames),
    from the pseudo-triangulated shapes. InputError without two video streams (no clocks)."""
    t = affine_time(initialise(capture, options), capture.stream_ids, capture.frame,
                    rates=known_rates(capture))
    if t is None:
        raise InputError("a windowed solve needs two or more video streams (streams of two or "
                         "more frames) to order the images first")
    return t


def solve_windowed(
    capture: Capture,
    options: Options,
    size: int,
    overlap: int,
    mapper: Mapper | None = None,
) -> Result:
    """One subject's :class:`Result` from overlapping windows of ``size`` images (module
    docstring), the windows solved by ``mapper`` (default: ``options.workers`` processes)."""
    started = time.perf_counter()
    n = capture.num_images
    t0 = first_guess_times(capture, options)
    windows, home = plan_windows(t0, size, overlap)
    logger.info("%d images in %d windows of %d (%d shared with the next)", n, len(windows),
                size, overlap)
    tasks = [(capture.subset(idx), options) for idx in windows]
    if mapper is None:
        workers = worker_count(options.workers, len(tasks), n * capture.num_points)
        mapper = partial(map_in_processes, workers=workers)
    results = list(mapper(_solve_window, tasks))
    return stitch(capture, windows, home, results, t0, time.perf_counter() - started)


def _solve_window(task: tuple[Capture, Options]) -> Result:
    """:func:`.pipeline.solve_single` of one window (a worker's task)."""
    return solve_single(*task)


def stitch(
    capture: Capture,
    windows: list[np.ndarray],
    home: np.ndarray,
    results: list[Result],
    t0: np.ndarray,
    seconds: float,
) -> Result:
    """The windows' results as one (module docstring); ``t0`` the first-guess times."""
    n, p = capture.num_images, capture.num_points
    X = np.empty((n, p, 3))
    D = np.empty(n)
    offsets = np.zeros((n, p, 2))
    W_parts, outliers, residuals, swaps = [], [], [], []
    for w, (idx, r) in enumerate(zip(windows, results, strict=True)):
        mine = home[idx] == w
        X[idx[mine]], D[idx[mine]] = r.X[mine], r.D[mine]
        if r.offset_px is not None:
            offsets[idx[mine]] = r.offset_px[mine]
        data, rows, cols = parts(r.W, idx)
        keep = home[rows] == w
        W_parts.append((data[keep], rows[keep], cols[keep]))
        if r.outliers.size:
            kept = mine[r.outliers[:, 0]]
            outliers.append(np.c_[idx[r.outliers[kept, 0]], r.outliers[kept, 1]])
            residuals.append(r.outlier_residual_px[kept])
        if r.swaps.size:
            kept = mine[r.swaps[:, 0]]
            swaps.append(np.c_[idx[r.swaps[kept, 0]], r.swaps[kept, 1:]])
    t = affine_time(X, capture.stream_ids, capture.frame, rates=known_rates(capture))
    t = t0 if t is None else t
    clock = np.full(n, np.nan)
    for w, (idx, r) in enumerate(zip(windows, results, strict=True)):
        mine = home[idx] == w
        if r.clock is not None and np.isfinite(r.clock[mine]).all():
            slope, icpt = np.polyfit(r.clock[mine], t[idx[mine]], 1)
            clock[idx[mine]] = icpt + slope * r.clock[mine]
    W = assemble(W_parts, n)
    A = sp.csr_matrix(sp.diags(D) @ W)
    swaps_all = np.concatenate(swaps) if swaps else np.zeros((0, 3), dtype=np.int64)
    solved = apply_swaps(capture, swaps_all) if swaps_all.size else None
    shifted = bool(offsets.any())
    if shifted:
        solved = without_offsets(capture if solved is None else solved, offsets)
    return Result(
        X=X,
        order=np.argsort(t, kind="stable"),
        A=A,
        W=W,
        D=D,
        events=segment_events(A, capture.stream, capture.frame),
        embedding=t,
        seconds=seconds,
        scale=float(np.median([r.scale for r in results])),
        **merged_history(results, "window"),
        clock=None if np.isnan(clock).all() else clock,
        outliers=np.concatenate(outliers) if outliers else np.zeros((0, 2), dtype=np.int64),
        outlier_residual_px=np.concatenate(residuals) if residuals else np.zeros(0),
        swaps=swaps_all,
        solved=solved,
        offset_px=offsets if shifted else None,
    )
