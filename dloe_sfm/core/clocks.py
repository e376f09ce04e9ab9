"""Stream clocks: each video's affine clock ``t = a_s + b_s frame``, fitted to the rays.

At coarse sampling DLOE's graph places images by shape alone and a few tens of milliseconds off
their instants, and the depth along each ray follows the timing error. A video's images,
though, are not free on the time line: its frames are equally spaced, so the whole capture's
timing is a few numbers per stream.

For given clocks every point's trajectory is fitted as a cubic B-spline in time to its rays by
linear least squares (the residual is each observation's distance to its ray); the clocks that
minimise that residual make the rays of different cameras agree. Variable projection: the
spline coefficients are eliminated, the clocks go to Levenberg-Marquardt with the Kaufman
Jacobian. The residual has local minima a sampling interval apart, and the fit alone can stop in
one: before it, the clocks are fitted on knots four times wider (where those minima smooth out,
so a first guess periods off gets back), then the offsets searched on a grid over +-1/2 frame
period per stream. The last fit's residual is summed over knot spacings of 2-5 sampling
intervals of the merged streams: no single spacing suits every motion. Optionally each stream's
rays of each point take a constant offset, fitted with the trajectories (a detector's bias in
that view). The measurements behind these choices: docs/method.md, "Stream clocks" and
"Offsets fitted with the clocks".

Cost: a spline fit is one banded Cholesky factorisation of the points' normal equations, linear
in the observations (``splines.SplineFit``, with the ray equations and the offsets);
Levenberg-Marquardt sees the Kaufman Jacobian through its Gram matrix only (:func:`_condensed`),
which takes the same steps without forming it.

Bursts (streams of a few images, events without videos) get the same model in
:func:`fit_burst_clocks`, with a prior about the rank base (:func:`rank_times`) and the lone
photos left between them by rank (:func:`by_rank`); docs/method.md, "Clocks of bursts".
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from .robust import predicted
from .splines import Rays, SplineFit, offset_columns, visible_rays

SPACINGS = (2.0, 3.0, 4.0, 5.0)
"""Knot spacings in median sampling intervals of all streams merged (:func:`fit_clocks`)."""
INTERVAL_FLOOR = 0.5
"""The knots' sampling interval is at least this share of the streams' merged frame period
(:func:`merged_period`): first guesses that put streams nearly in phase collapse the median gap
between their times, and knots closer than a stream's frames overfit the rays (a sparse 7.5 Hz
walk whose first guess held the known rates: 0.099 against 0.25 frame; docs/method.md, "Stream
clocks")."""
REACH = 8
"""A stream that the fit moves this many frame periods or more from its first guess (median over
its images, against the others, :func:`moved_periods`) may not be pinned by the rays, or the
first guess was that far off: the clocks must then prove themselves on held-out detections
(``decisions.fit_trusted``). The splines' knots reach that far before the first guess."""
COARSE_KNOTS = 4.0
"""The first stage fits the clocks to the residual with knots this many times the middle spacing
apart: its local minima a sampling interval apart smooth out, and a first guess several periods
off (DLOE's placement of slow motion under detector errors: up to 5) comes back to the clocks'
basin."""
GRID_STEPS = 16
"""The second stage searches the offsets on a grid of this many points per frame period over
+-1/2 period."""
GRID_POINTS = 8
"""The grids' residual uses at least this many most-observed points, the fit after them all
of them..."""
GRID_SLOTS = 8000
"""...and as many as fit in this many (image, point) slots (all of them on a few hundred
images; docs/method.md, "Stream clocks")..."""
GRID_IMAGES = 2000
"""...and the middle this many images in the first-guess time order (all of them in the fit)."""
OUT_OF_RANGE = 1e150
"""The fit's cost at clocks that put an image before the splines' first knot, or past
:data:`SPAN_REACH` (a wild trial step of Levenberg-Marquardt): far above any real cost, so the
step is rejected and shortened."""
SPAN_REACH = 10.0
"""A trial step that puts an image later than the first guess's last time plus this many times
its span costs :data:`OUT_OF_RANGE`: its splines would need as many more knots (a step of
Levenberg-Marquardt on six streams reached times whose knots no memory holds)."""

STALL_EVALUATIONS = 10
STALL_SHARE = 1e-3
"""The last stage's fits of :func:`fit_clocks` (all images and points) stop at the best clocks
so far once their residual fell by less than this share of itself in the last
:data:`STALL_EVALUATIONS` evaluations: on 64 streams they crawled on to 125 and 109
evaluations without a better sync (docs/method.md, "Many cameras, measured"). The wide-knot
fits from first guesses periods off cross plateaus on their way and run to convergence."""

BURST_PRIOR = 2.0
"""Standard deviation of the prior that ties the times of bursts' images to the rank base, in
median gaps between those times (:func:`fit_burst_clocks`)..."""
BURST_STAGES = (4.0, 2.0, 1.0, 1.0)
"""...the knots of its stages, in multiples of the spacings (the last twice: the rays' noise
is estimated again at the clocks of the one before)..."""
BURST_KNOTS_BEFORE = 3.0
"""...and how many of a stage's widest knot spacings its knots start before the first time."""


class _Stalled(Exception):
    """Raised by a fit's residual to stop its Levenberg-Marquardt (:data:`STALL_SHARE`)."""


def sampling_interval(t: np.ndarray) -> float:
    """The median gap between the distinct times ``t`` of all streams merged: the unit of the
    knot spacings."""
    return float(np.median(np.diff(np.unique(t))))


def merged_period(slopes: np.ndarray, inv: np.ndarray, f: np.ndarray) -> float:
    """The streams' merged frame period: one over the sum of their frame rates, in the units of
    ``slopes`` (every stream's time per frame); the gap between their merged times where they
    are evenly out of phase, whatever phases a first guess gives them. ``inv`` (N,) every
    image's stream index, ``f`` (N,) its frame."""
    steps = np.array([np.median(np.diff(np.unique(f[inv == s]))) for s in range(slopes.size)])
    return float(1.0 / np.sum(1.0 / (slopes * steps)))


def _condensed(jtj: np.ndarray, jtr: np.ndarray, squares: float) -> np.ndarray:
    """(q + 1, q) Jacobian J' of the residuals r' = (0, ..., 0, |r|) that has the least-squares
    problem's ``J^T J`` and ``J^T r`` (from ``squares`` = ``|r|^2``): the same Gauss-Newton
    model, so Levenberg-Marquardt takes the same steps as on (r, J), at a size independent of
    the observations. Its last row is ``J^T r / |r|``, the rest a square root of
    ``J^T (I - r r^T / |r|^2) J``."""
    norm = max(np.sqrt(squares), np.finfo(float).tiny)
    last = jtr / norm
    value, vector = np.linalg.eigh(jtj - np.outer(last, last))
    return np.vstack([np.sqrt(np.maximum(value, 0.0))[:, None] * vector.T, last])


def fit_clocks(
    t0: np.ndarray,
    streams: np.ndarray,
    frames: np.ndarray,
    E: np.ndarray,
    rhs: np.ndarray,
    visible: np.ndarray,
    *,
    shared_rate: bool = False,
    offsets: bool = False,
    rates: np.ndarray | None = None,
    spacings: tuple[float, ...] = SPACINGS,
    grid_steps: int = GRID_STEPS,
    grid_points: int = GRID_POINTS,
) -> np.ndarray:
    """(N,) times on the streams' affine clocks that best explain the rays (module docstring).

    ``t0`` (N,) first-guess times (DTW placement), ``streams`` / ``frames`` (N,) with every
    image in a stream; ``E``, ``rhs`` from ``splines.ray_equations``. The longest stream is the
    reference (its first-guess start and rate are kept). The other streams start at the median
    of all streams' first-guess rates (the first guess of one stream's rate is noisy on few
    images) and, unless ``shared_rate`` (all streams at the median), at their own (streams
    filmed at different frame rates), through their first-guess times. From each start, on the
    most-observed points (at least ``grid_points``) of the middle :data:`GRID_IMAGES` images:
    Levenberg-Marquardt on wide knots (:data:`COARSE_KNOTS`) fits the offsets, and apart the
    offsets and rates (unless ``shared_rate``: freed rates can warp, held ones cannot follow a
    stream whose rate is off), then a grid of ``grid_steps`` per frame period over +-1/2 period
    moves the offsets. The candidate whose grid ends lower is fitted at those rates on all
    images and points, then, unless ``shared_rate``, with the rates freed too. With ``offsets``
    the first and last fits take every (stream, point)'s offset of its rays with the
    trajectories (``splines.Offsets``): a detector's offsets otherwise read as time shifts where
    the motion is steady. ``rates`` (N,), every image's stream's known frame rate: the rates are
    held at their ratios (one start, through the first-guess times; the offsets alone fitted).
    The knots are ``spacings`` sampling intervals apart (:func:`sampling_interval`), the larger
    of the starts': at the median rate, streams filmed at other rates can fall nearly in phase
    all along, and the gaps between their times collapse; and at least :data:`INTERVAL_FLOOR`
    of the streams' merged frame period, for a first guess that put them in phase itself
    (docs/method.md, "Stream clocks").

    With two streams each ray's depth is seen by one other stream only, and a knot interval of
    two merged sampling intervals holds one of its frames: the spacings grow by half (doubled,
    they are too wide for fast motion). How far the fit moved the streams from ``t0``:
    :func:`moved_periods`. The measurements: docs/method.md, "Stream clocks".
    """
    f = frames.astype(np.float64)
    ids, inv = np.unique(streams, return_inverse=True)
    k = ids.size
    own = np.array([np.polyfit(f[inv == s], t0[inv == s], 1)[0] for s in range(k)])
    ref = int(np.argmax(np.bincount(inv)))
    if rates is not None:
        known = np.array([rates[inv == s][0] for s in range(k)])
        own = own[ref] * known[ref] / known
    elif shared_rate:
        own[:] = np.median(own)
    held = shared_rate or rates is not None
    free = np.flatnonzero(np.arange(k) != ref)
    onehot = (inv[:, None] == free[None, :]).astype(np.float64)
    dt = np.concatenate([onehot, onehot * f[:, None]], axis=1)  # d t / d (offsets, rates)

    def start_at(slopes: np.ndarray) -> np.ndarray:
        """The free streams' (offsets, rates) at ``slopes`` (every stream's time per frame)
        through their first-guess times."""
        a0 = [np.median(t0[inv == s] - slopes[s] * f[inv == s]) for s in free]
        return np.concatenate([a0, slopes[free]])

    base = (np.median(t0[inv == ref] - own[ref] * f[inv == ref]) + own[ref] * f) * (inv == ref)

    def times(x: np.ndarray) -> np.ndarray:
        return base + dt @ x

    starts = [start_at(own)] if held else [start_at(np.full(k, np.median(own))), start_at(own)]
    t_init = times(starts[0])
    interval = max(max(sampling_interval(times(x)) for x in starts),
                   INTERVAL_FLOOR * merged_period(own, inv, f))
    hs = [h * interval * (1.5 if k == 2 else 1.0) for h in spacings]
    period = _reference_period(t0, inv, f)
    h_mid = hs[len(hs) // 2]
    # the offsets are the same all along: the first stages look at the middle GRID_IMAGES only
    win = np.arange(t_init.size)
    if t_init.size > GRID_IMAGES:
        lo = (t_init.size - GRID_IMAGES) // 2
        win = np.sort(np.argsort(t_init, kind="stable")[lo:lo + GRID_IMAGES])
    reach = REACH * period
    last = float(t_init.max()) + SPAN_REACH * float(np.ptp(t_init))
    grid_start = min(float(times(x)[win].min()) for x in starts) - reach - COARSE_KNOTS * h_mid
    seen = np.argsort(-visible.sum(axis=0), kind="stable")[:max(grid_points,
                                                              GRID_SLOTS // win.size)]
    grid_rays = visible_rays(E[win][:, seen], rhs[win][:, seen], visible[win][:, seen])
    window_offsets = all_offsets = None
    if offsets:
        position = np.full(k, -1)  # every stream's place among the free ones
        position[free] = np.arange(free.size)
        window_offsets = offset_columns(position[inv[win]], visible[win][:, seen], free.size)
        all_offsets = offset_columns(position[inv], visible, free.size)

    def fitted(x: np.ndarray, cols: np.ndarray, fits: Callable[[np.ndarray], list[SplineFit]],
               rows: np.ndarray, first: float, norms: list[float],
               known: list[SplineFit] | None = None, stall: bool = False) -> np.ndarray:
        """``x`` with its ``cols`` fitted by Levenberg-Marquardt to the residuals of ``fits``
        (the spline fits at clocks z on images ``rows``, knots from ``first``), each over its
        norm in ``norms``, seen through :func:`_condensed`. Fits are cached by ``x[cols]``,
        starting with ``known``, the fits at ``x``; with ``stall`` it stops where its residual
        stalls (:data:`STALL_SHARE`)."""
        cache = {} if known is None else {x[cols].tobytes(): known}
        dt_fit = dt[rows][:, cols]

        def at(y: np.ndarray) -> list[SplineFit]:
            key = y.tobytes()
            if key not in cache:
                z = x.copy()
                z[cols] = y
                cache.clear()
                cache[key] = fits(z)
            return cache[key]

        def squares(y: np.ndarray) -> float:
            z = x.copy()
            z[cols] = y
            t = times(z)[rows]
            if t.min() < first or t.max() > last:  # a wild trial step: rejected as worse
                return OUT_OF_RANGE
            return sum(float(f.res @ f.res) / n**2 for f, n in zip(at(y), norms, strict=True))

        def jacobian(y: np.ndarray) -> np.ndarray:
            grams = [f.gram(dt_fit) for f in at(y)]
            jtj = sum(g / n**2 for (g, _), n in zip(grams, norms, strict=True))
            jtr = sum(g / n**2 for (_, g), n in zip(grams, norms, strict=True))
            return _condensed(jtj, jtr, squares(y))

        best = [squares(x[cols]), x[cols]]
        trail = []  # the best residual after every evaluation

        def residual(y: np.ndarray) -> np.ndarray:
            value = squares(y)
            if value < best[0]:
                best[:] = [value, y.copy()]
            trail.append(best[0])
            if (stall and len(trail) > STALL_EVALUATIONS and trail[-STALL_EVALUATIONS - 1] - best[0]
                    <= STALL_SHARE * trail[-STALL_EVALUATIONS - 1]):
                raise _Stalled
            return np.r_[np.zeros(cols.size), np.sqrt(value)]

        out = x.copy()
        try:
            out[cols] = least_squares(residual, x[cols], jac=jacobian, method="lm", xtol=1e-6,
                                      ftol=1e-8).x
        except _Stalled:
            out[cols] = best[1]
        return out

    def grid(x: np.ndarray) -> tuple[np.ndarray, float]:
        """Coordinate sweeps over the offsets from ``x`` until none moves: (x, residual)."""

        def residual(y: np.ndarray) -> float:
            t = times(y)[win]
            if t.min() < grid_start:  # a step beyond the knots
                return np.inf
            r = SplineFit(t, grid_rays, h_mid, grid_start).res
            return float(r @ r)

        steps = (np.arange(grid_steps + 1) - grid_steps / 2) * period / grid_steps
        value = residual(x)
        for _ in range(3):
            before = x.copy()
            for c in range(free.size):
                trials = [x + d * (np.arange(x.size) == c) for d in steps]
                values = [value if d == 0 else residual(y)
                          for d, y in zip(steps, trials, strict=True)]
                best = int(np.argmin(values))
                x, value = trials[best], values[best]
            if np.array_equal(x, before):
                break
        return x, value

    def coarse(z: np.ndarray) -> list[SplineFit]:
        """The first stage's spline fit at clocks ``z``."""
        return [SplineFit(times(z)[win], grid_rays, COARSE_KNOTS * h_mid, grid_start,
                           offsets=window_offsets)]

    shifts = np.arange(free.size)
    freed = [shifts] if held else [shifts, np.arange(shifts.size * 2)]
    found = [grid(fitted(x, cols, coarse, win, grid_start, [1.0]))
             for x in starts for cols in freed]
    x = min(found, key=lambda found: found[1])[0]
    start = float(times(x).min()) - 3 * period - max(hs)
    rays = visible_rays(E, rhs, visible)

    def fine(z: np.ndarray) -> list[SplineFit]:
        """The last stage's spline fits at clocks ``z``: all images and points, every spacing."""
        return [SplineFit(times(z), rays, h, start, offsets=all_offsets) for h in hs]

    everything = np.arange(t_init.size)
    at_grid = fine(x)
    norms = [np.sqrt(float(f.res @ f.res)) for f in at_grid]
    x = fitted(x, shifts, fine, everything, start, norms, at_grid, stall=True)
    if not held:
        x = fitted(x, np.arange(x.size), fine, everything, start, norms, stall=True)
    return times(x)


def reference_stream(streams: np.ndarray, frames: np.ndarray) -> tuple[list[int], int | None]:
    """The streams among an event's images (``streams`` / ``frames``) with two or more distinct
    frames (its videos and bursts), and its reference stream among them: the one of most
    images, the lowest id on a tie; None without any. What the exports count time in
    (``mocap_export.image_times``), and the first guess of :func:`fit_burst_clocks`."""
    ids, counts = np.unique(streams, return_counts=True)
    videos = [int(s) for s in ids if np.unique(frames[streams == s]).size >= 2]
    ref = max(videos, key=lambda s: (counts[ids == s][0], -s)) if videos else None
    return videos, ref


def rank_times(streams: np.ndarray, frames: np.ndarray, ref: int) -> np.ndarray | None:
    """(m,) times of an event's images in their estimated order (``streams``, ``frames`` in
    that order): the reference stream ``ref``'s at their frames, the others evenly between them
    by rank (:func:`by_rank`); None when the order contradicts the reference stream's frame
    order. The rank base of captures without videos."""
    f = frames[streams == ref].astype(np.float64)
    if (np.diff(f) <= 0).any():
        return None
    return by_rank(streams == ref, f)


def by_rank(known: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(m,) times of m images in their estimated order: those ``known`` (m,) at their times
    ``t`` (in that order), the others evenly between their neighbours among them by rank, and
    beyond the first or last on at the known images' mean step per rank."""
    pos = np.flatnonzero(known).astype(np.float64)
    slope = (t[-1] - t[0]) / (pos[-1] - pos[0])
    rank = np.arange(known.size, dtype=np.float64)
    inside = np.interp(rank, pos, t)
    return np.where(rank < pos[0], t[0] - (pos[0] - rank) * slope,
                    np.where(rank > pos[-1], t[-1] + (rank - pos[-1]) * slope, inside))


def fit_burst_clocks(
    t0: np.ndarray,
    streams: np.ndarray,
    frames: np.ndarray,
    E: np.ndarray,
    rhs: np.ndarray,
    visible: np.ndarray,
    *,
    prior: float = BURST_PRIOR,
    stages: tuple[float, ...] = BURST_STAGES,
    spacings: tuple[float, ...] = SPACINGS,
) -> np.ndarray:
    """(N,) times of the images of bursts (streams of two or more images, ``streams`` /
    ``frames``): every burst on an affine clock of its own, fitted to the rays.

    ``t0`` (N,) the rank base's times (:func:`rank_times`), the rest as :func:`fit_clocks`
    takes them. The residual is :func:`fit_clocks`'s, the points' B-spline trajectories on the
    rays summed over ``spacings`` median gaps between the times ``t0``, over the rays' noise,
    plus every image's time from ``t0`` over ``prior`` gaps: the rank base ties down the time
    line's origin and scale, which the rays leave free. Levenberg-Marquardt (on the Gram matrix
    of the Kaufman Jacobian, as :func:`fit_clocks`) on knots ``stages`` times wider in turn: on
    the knots of the last stage alone it stopped in a local minimum 68 ms off where the rank
    base was 91 ms off. The noise is the residual's RMS at ``t0``, then at every stage's clocks
    (docs/method.md, "Clocks of bursts")."""
    dt, bursts = _burst_design(streams, frames)
    f = frames.astype(np.float64)
    lines = np.array([np.polyfit(f[streams == s], t0[streams == s], 1) for s in bursts])
    x = np.concatenate([lines[:, 1], lines[:, 0]])
    gap = sampling_interval(t0)
    rays = visible_rays(E, rhs, visible)

    def noise(t: np.ndarray) -> float:
        r = np.concatenate([fit.res for fit in _spacing_fits(t, rays, gap, spacings)])
        return max(float(np.sqrt(np.mean(r**2))), np.finfo(float).tiny)

    scale = noise(t0)
    for stage in stages:
        hs = [stage * h * gap for h in spacings]
        first = float(min(t0.min(), (dt @ x).min())) - BURST_KNOTS_BEFORE * max(hs)
        x = _burst_stage(x, t0, dt, _BurstModel(rays, hs, first, scale, gap, prior * gap))
        scale = noise(dt @ x)
    return dt @ x


class _BurstModel(NamedTuple):
    """One stage of :func:`fit_burst_clocks`: the rays, the knot spacings and first knot, the
    rays' noise, the median gap between the first-guess times (the clocks' scale) and the
    prior's standard deviation."""

    rays: Rays
    spacings: list[float]
    first: float
    noise: float
    gap: float
    prior_sd: float


def _burst_stage(x: np.ndarray, t0: np.ndarray, dt: np.ndarray, model: _BurstModel
                 ) -> np.ndarray:
    """The bursts' clocks ``x`` fitted by Levenberg-Marquardt to one stage's residual
    (:func:`fit_burst_clocks`); ``dt`` the times' derivative in them."""
    weight = 1.0 / (model.noise * np.sqrt(len(model.spacings)))
    cache: dict[bytes, list[SplineFit]] = {}

    def fits(y: np.ndarray) -> list[SplineFit]:
        key = y.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = [SplineFit(dt @ y, model.rays, h, model.first) for h in model.spacings]
        return cache[key]

    def squares(y: np.ndarray) -> float:
        t = dt @ y
        if t.min() < model.first:  # a wild trial step: rejected as worse
            return OUT_OF_RANGE
        return (sum(float(fit.res @ fit.res) for fit in fits(y)) * weight**2
                + float(np.sum((t - t0) ** 2)) / model.prior_sd**2)

    def jacobian(y: np.ndarray) -> np.ndarray:
        grams = [fit.gram(dt) for fit in fits(y)]
        jtj = sum(g for g, _ in grams) * weight**2 + dt.T @ dt / model.prior_sd**2
        jtr = sum(g for _, g in grams) * weight**2 + dt.T @ (dt @ y - t0) / model.prior_sd**2
        return _condensed(jtj, jtr, squares(y))

    return least_squares(lambda y: np.r_[np.zeros(y.size), np.sqrt(squares(y))], x,
                         jac=jacobian, method="lm", x_scale=model.gap).x


def _spacing_fits(t: np.ndarray, rays: Rays, gap: float, spacings: tuple[float, ...]
                  ) -> list[SplineFit]:
    """The spline fits at times ``t`` of :func:`fit_burst_clocks`'s residual at its last
    stage's knots, ``spacings`` times ``gap`` apart, from :data:`BURST_KNOTS_BEFORE` of the
    widest before the first time."""
    first = float(t.min()) - BURST_KNOTS_BEFORE * max(spacings) * gap
    return [SplineFit(t, rays, h * gap, first) for h in spacings]


def _burst_design(streams: np.ndarray, frames: np.ndarray, fixed: int | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2q) derivative of the times of bursts' images in the offsets, then the rates, of
    their q streams but ``fixed``; and those streams' ids, in the order of the columns."""
    bursts = np.setdiff1d(np.unique(streams), [] if fixed is None else [fixed])
    onehot = (streams[:, None] == bursts[None, :]).astype(np.float64)
    return np.concatenate([onehot, onehot * frames[:, None]], axis=1), bursts


def burst_covariance(
    t: np.ndarray,
    streams: np.ndarray,
    frames: np.ndarray,
    E: np.ndarray,
    rhs: np.ndarray,
    visible: np.ndarray,
    ref: int,
    *,
    prior: float = BURST_PRIOR,
    spacings: tuple[float, ...] = SPACINGS,
) -> tuple[np.ndarray, np.ndarray]:
    """(streams, covariance (2q, 2q)): the offsets then the rates, relative to ``ref``'s clock,
    of the q bursts but ``ref`` of the images of bursts timed by :func:`fit_burst_clocks` at
    their times ``t`` (in ``ref``'s frames: its clock offset 0, rate 1). The inverse of the
    Gauss-Newton information of that fit's residual at ``t`` in every burst's clock (the prior
    ties the time line down, as in the fit), the rays' part over their noise (the residual
    there per degree of freedom) and the prior's, plus the outer product of the step that each
    knot spacing's residual alone would take from ``t`` (the spline model's own error, as
    ``core.sync`` adds for video clocks); then carried to the clocks relative to ``ref``'s,
    whose own error they share."""
    dt, bursts = _burst_design(streams, frames)
    rays = visible_rays(E, rhs, visible)
    gap = sampling_interval(t)
    fits = _spacing_fits(t, rays, gap, spacings)
    # the rays' noise per degree of freedom: on few images per knot the splines take up most
    # of the residual
    free = sum(fit.res.size - dt.shape[1] - 3 * np.unique(
        rays.pt[:, None] * fit.basis.shape[1] + fit.active[rays.img]).size for fit in fits)
    noise2 = max(sum(float(fit.res @ fit.res) for fit in fits) / max(free, len(fits)),
                 np.finfo(float).tiny)
    grams = [fit.gram(dt) for fit in fits]
    cov = np.linalg.pinv(sum(jtj for jtj, _ in grams) / (noise2 * len(fits))
                         + dt.T @ dt / (prior * gap) ** 2)
    # how far each knot spacing alone would move the times: the spline model's own error
    steps = [cov @ jtr / noise2 for _, jtr in grams]
    cov = cov + sum(np.outer(step, step) for step in steps) / len(steps)
    # offset (a_s - a_ref) / b_ref and rate b_s / b_ref, linearised at a_ref = 0, b_ref = 1
    b, k = bursts.size, int(np.flatnonzero(bursts == ref)[0])
    others = np.flatnonzero(bursts != ref)
    lines = np.array([np.polyfit(frames[streams == s], t[streams == s], 1) for s in bursts])
    G = np.zeros((2 * others.size, 2 * b))
    rows = np.arange(others.size)
    G[rows, others] = 1.0
    G[rows, k] = -1.0
    G[rows, b + k] = -lines[others, 1]
    G[others.size + rows, b + others] = 1.0
    G[others.size + rows, b + k] = -lines[others, 0]
    return bursts[others], G @ cov @ G.T


def moved_periods(t0: np.ndarray, t: np.ndarray, streams: np.ndarray, frames: np.ndarray
                  ) -> float:
    """The most that clocks ``t`` moved any stream from the first guess ``t0`` (median over its
    images, up to one affine map of the time line), in frame periods of the longest stream (as
    ``t0`` counts them); the streams and frames as :func:`fit_clocks` takes them."""
    ids, inv = np.unique(streams, return_inverse=True)
    moved = np.abs(t - np.polyval(np.polyfit(t0, t, 1), t0))
    return (max(float(np.median(moved[inv == s])) for s in range(ids.size))
            / _reference_period(t0, inv, frames.astype(np.float64)))


def _reference_period(t0: np.ndarray, inv: np.ndarray, f: np.ndarray) -> float:
    """The longest stream's frame period in the units of ``t0``: its first-guess rate times its
    median frame step; ``inv`` (N,) every image's stream index, ``f`` (N,) its frame."""
    ref = inv == np.argmax(np.bincount(inv))
    return float(np.polyfit(f[ref], t0[ref], 1)[0] * np.median(np.diff(np.unique(f[ref]))))


def time_chain(times: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """(W, D) of the chain along ``times``: every image's row links its predecessor and successor
    with barycentric weights (constant-velocity motion is reproduced exactly). The first and last
    images have D = 0 (they are placed by their neighbours' rows); their rows link their one
    neighbour, so that every row of W still predicts its image (``robust.predicted``)."""
    times = np.asarray(times, dtype=np.float64)
    n = times.size
    order = np.argsort(times, kind="stable")
    t = times[order]
    prev, mid, nxt = order[:-2], order[1:-1], order[2:]
    span = t[2:] - t[:-2]
    with np.errstate(divide="ignore", invalid="ignore"):
        w_prev = np.where(span > 0, (t[2:] - t[1:-1]) / span, 0.5)
    rows = np.concatenate([mid, mid, order[[0, -1]]])
    cols = np.concatenate([prev, nxt, order[[1, -2]]])
    data = np.concatenate([w_prev, 1.0 - w_prev, [1.0, 1.0]])
    W = sp.csr_matrix((data, (rows, cols)), shape=(n, n))
    D = np.ones(n)
    D[order[[0, -1]]] = 0.0
    return W, D


def chain_predicted(W: sp.spmatrix, times: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(N, P, 3) every image's shapes ``X`` predicted from its neighbours along ``times``: the
    barycentric interpolation of ``W``, the chain along them (:func:`time_chain`), inside; the
    first two and the last two images by linear extrapolation from the next two inwards. The
    chain's end images have no row of their own (D = 0): a point they do not observe is placed
    by their neighbour's row alone, so it would predict that neighbour by its own observation,
    a wrong one included."""
    pred = predicted(W, X)
    if X.shape[0] < 4:
        return pred
    order = np.argsort(times, kind="stable")
    for end in (order[:4], order[::-1][:4]):
        b, c = end[2], end[3]
        step = times[b] - times[c]
        for a in end[:2]:
            s = (times[a] - times[b]) / step if step != 0 else 0.0
            pred[a] = X[b] + s * (X[b] - X[c])
    return pred
