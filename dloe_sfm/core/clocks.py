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
in the observations (:class:`_SplineFit`); Levenberg-Marquardt sees the Kaufman Jacobian through
its Gram matrix only (:func:`_condensed`), which takes the same steps without forming it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.optimize import least_squares

from .robust import predicted

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
(``pipeline.verdicts``). The splines' knots reach that far before the first guess."""
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
OFFSET_MIN_OBS = 10
"""A stream's observations of a point (other than the reference stream's) carry their own
offset in the fit when there are at least this many of them (:class:`_Offsets`)."""
HOLD_MARGIN = 1.05
"""The clocks are kept when their median held-out residual is at most this many times the graph's
(:func:`clocks_hold`)."""
TIMING_MARGIN = 1.5
"""Clocks dropped for the points still time their event when their median held-out residual is
at most this many times the graph's (:func:`clocks_time`)."""
OUT_OF_RANGE = 1e150
"""The fit's cost at clocks that put an image before the splines' first knot, or past
:data:`SPAN_REACH` (a wild trial step of Levenberg-Marquardt): far above any real cost, so the
step is rejected and shortened."""
SPAN_REACH = 10.0
"""A trial step that puts an image later than the first guess's last time plus this many times
its span costs :data:`OUT_OF_RANGE`: its splines would need as many more knots (a step of
Levenberg-Marquardt on six streams reached times whose knots no memory holds)."""


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


def clocks_hold(graph_px: np.ndarray, clock_px: np.ndarray) -> bool:
    """Whether the clocks predict held-out images' detections about as well as DLOE's graph: a
    median residual at most :data:`HOLD_MARGIN` times the graph's, or at least half of the
    detections predicted at least as well. ``graph_px``, ``clock_px``: the same detections'
    residuals, pixels, NaN ignored (``alternation.held_out_px``). Near-ties go to the clocks, a
    few numbers per stream where the graph has weights for every image: on exact data both
    models predict at the floor the cameras leave, where the medians alone decide by chance,
    and under detector noise the graph's many neighbours average the held-out detections' noise
    better than the chain's two, while the timing hardly shows (docs/method.md, "Far fits and
    near-ties")."""
    return bool(np.nanmedian(clock_px) <= HOLD_MARGIN * np.nanmedian(graph_px)
                or as_good_share(graph_px, clock_px) >= 0.5)


def clocks_time(graph_px: np.ndarray, clock_px: np.ndarray) -> bool:
    """Whether clocks that do not hold (:func:`clocks_hold`) lost narrowly enough to still time
    their event: a median held-out residual at most :data:`TIMING_MARGIN` times the graph's
    (arguments as :func:`clocks_hold`). Within it the loss is what the graph's many neighbours
    gain by averaging the detections' noise, which a frame of timing hardly moves; a clock fit
    that failed loses by twice and more (docs/method.md, "Times from dropped clocks")."""
    return bool(np.nanmedian(clock_px) <= TIMING_MARGIN * np.nanmedian(graph_px))


def as_good_share(graph_px: np.ndarray, clock_px: np.ndarray) -> float:
    """Share of the detections with both residuals (pixels) that the clocks predict at least as
    well as the graph (0 with none)."""
    both = np.isfinite(graph_px) & np.isfinite(clock_px)
    return float(np.mean(clock_px[both] <= graph_px[both])) if both.any() else 0.0


def ray_equations(
    rays: np.ndarray, C: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Two unit normals ``e`` of every ray with ``e . X = e . C`` (times sqrt(weight)).

    rays (N, P, 3) unit, NaN where unobserved; C (N, 3); weights (N, P). Residuals of the
    equations are distances to the rays. Returns E (N, P, 2, 3) and rhs (N, P, 2).
    """
    r = np.nan_to_num(rays)
    helper = np.where(np.abs(r[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    u = np.cross(r, helper)
    u /= np.maximum(np.linalg.norm(u, axis=2, keepdims=True), 1e-300)
    v = np.cross(r, u)
    E = np.stack([u, v], axis=2) * np.sqrt(np.maximum(weights, 0.0))[..., None, None]
    return E, np.einsum("npkj,nj->npk", E, C)


def _cubic_bspline(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Uniform cubic B-spline weights of the 4 bases active at fraction ``s`` and their
    derivatives in ``s``: (M, 4) each."""
    s2, s3 = s * s, s * s * s
    b = np.stack([(1 - s) ** 3, 3 * s3 - 6 * s2 + 4, -3 * s3 + 3 * s2 + 3 * s + 1, s3], 1) / 6
    db = np.stack([-((1 - s) ** 2), 3 * s2 - 4 * s, -3 * s2 + 2 * s + 1, s2], 1) / 2
    return b, db


class _Rays(NamedTuple):
    """The ray equations of the visible observations, with what of them the clocks do not
    change (:func:`_rays`)."""

    img: np.ndarray
    """(M,) image of every observation (``np.nonzero(visible)`` order)."""
    pt: np.ndarray
    """(M,) point of every observation."""
    e: np.ndarray
    """(M, 2, 3) the observations' two normals."""
    rhs: np.ndarray
    """(M, 2) their right-hand sides."""
    normal: np.ndarray
    """(N, P, 6) ``sum_a e_a e_a^T`` per image and point, entries ``_PAIRS`` (0 unobserved)."""
    pull: np.ndarray
    """(N, P, 3) ``sum_a rhs_a e_a`` per image and point (0 unobserved)."""


_PAIRS = ((0, 0), (1, 0), (1, 1), (2, 0), (2, 1), (2, 2))
"""The lower triangle's (c, d) of a symmetric 3 x 3 block, in ``_Rays.normal``'s order."""
_SYMMETRIC = np.array([[0, 1, 3], [1, 2, 4], [3, 4, 5]])
"""Entry (c, d) of a symmetric 3 x 3 block -> its index in ``_PAIRS``."""
_SHIFT = np.repeat(np.arange(4), np.arange(4, 0, -1))
_FIRST = np.concatenate([np.arange(4 - d) for d in range(4)])
"""The 10 pairs (k, k + shift) of an image's 4 active bases, by shift then k."""


def _rays(E: np.ndarray, rhs: np.ndarray, visible: np.ndarray) -> _Rays:
    """:class:`_Rays` of ``E``, ``rhs`` (:func:`ray_equations`) on the ``visible`` (N, P)
    observations."""
    img, pt = np.nonzero(visible)
    e, r = E[img, pt], rhs[img, pt]
    c, d = np.array(_PAIRS).T
    normal = np.zeros((*visible.shape, len(_PAIRS)))
    normal[img, pt] = np.einsum("oac,oad->ocd", e, e)[:, c, d]
    pull = np.zeros((*visible.shape, 3))
    pull[img, pt] = np.einsum("oac,oa->oc", e, r)
    return _Rays(img, pt, e, r, normal, pull)


class _Offsets(NamedTuple):
    """Which observations carry an offset of their own in the fit: a detector places a joint
    a few pixels off, the same way in every frame of one camera, and along the motion that
    offset reads as a time shift. Each (stream, point) with enough observations
    (:data:`OFFSET_MIN_OBS`) takes a constant offset along its rays' two normals, fitted with
    the trajectories; the reference stream's rays keep none (they fix where the points are)."""

    stream: np.ndarray
    """(N,) every image's stream among the S streams with offsets, -1 for the reference."""
    active: np.ndarray
    """(S, P) the (stream, point) offsets fitted."""


def _offsets(stream: np.ndarray, visible: np.ndarray, count: int) -> _Offsets:
    """:class:`_Offsets` of images in ``stream`` (N,) (0 to ``count`` - 1, -1 the reference)
    observing the ``visible`` (N, P) points."""
    seen = np.stack([visible[stream == s].sum(axis=0) for s in range(count)])
    return _Offsets(stream, seen >= OFFSET_MIN_OBS)


def _banded_solver(bands: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """Solver of the symmetric positive definite system in lower banded storage ``bands``
    (``bands[i - j, j] = G[i, j]``): banded Cholesky, or SuperLU (which pivots) when rounding
    leaves G not positive definite (a ridge below the rounding of G's large entries)."""
    try:
        factor = la.cholesky_banded(bands, lower=True, check_finite=False)
    except la.LinAlgError:
        n = bands.shape[1]
        lower = sp.diags([bands[k, : n - k] for k in range(bands.shape[0])],
                         -np.arange(bands.shape[0]), shape=(n, n))
        return spla.splu((lower + sp.triu(lower.T, 1)).tocsc()).solve
    return lambda b: la.cho_solve_banded((factor, True), b, check_finite=False)


class _SplineFit:
    """Every point's least-squares cubic B-spline trajectory on its rays at times ``t``
    (:func:`spline_residuals`): ``beta`` (P, B, 3) the coefficients, ``res`` (2M,) the residuals;
    with ``offsets`` (:class:`_Offsets`) also ``g`` (2S, P), every (stream, point)'s offset
    along its rays' two normals (row ``2 s + a``; 0 where not fitted).

    ``beta`` solves ``G beta = A^T rhs``, ``G = A^T A + ridge I``, A the design (rows: the
    observations' normals; columns: point, basis, coordinate), which is never formed. G is block
    diagonal over points and banded (lower bandwidth 11): it is accumulated from the images'
    B-spline products and the rays' normal products, and factorised once by banded Cholesky.
    Products with A and A^T go through the (N, B) collocation matrix. The offsets add columns
    ``-S`` to the design (an observation's weight in its (stream, point, normal) column):
    eliminated through their diagonal ``H = S^T S + ridge``, they leave G less a low-rank term
    per point, solved by Woodbury with one banded solve per (stream, normal) for all points.
    """

    def __init__(
        self, t: np.ndarray, rays: _Rays, spacing: float, start: float, ridge: float = 1e-9,
        offsets: _Offsets | None = None
    ) -> None:
        n, p = rays.pull.shape[:2]
        u = (t - start) / spacing
        if not (np.isfinite(u).all() and u.min() >= 0):
            raise ValueError("spline times before the first knot or not finite")
        j = np.floor(u).astype(np.int64)
        nb = int(j.max()) + 4
        b, db = _cubic_bspline(u - j)
        active = j[:, None] + np.arange(4)
        self.basis = sp.csr_matrix((b.ravel(), active.ravel(), 4 * np.arange(n + 1)),
                                   shape=(n, nb))
        # knots k + shift and k of a point couple by sum_i b_i,k+shift b_i,k normal_i
        products = sp.csc_matrix(
            ((b[:, _FIRST] * b[:, _FIRST + _SHIFT]).ravel(),
             (_SHIFT * nb + j[:, None] + _FIRST).ravel(), 10 * np.arange(n + 1)),
            shape=(4 * nb, n),
        )
        K = (products @ rays.normal.reshape(n, -1)).reshape(4, nb, p, 6)
        bands = np.zeros((12, p, nb, 3))
        for shift in range(4):
            for c in range(3):
                for d in range(3 if shift else c + 1):  # row (k + shift, c), column (k, d)
                    bands[3 * shift + c - d, :, : nb - shift, d] = (
                        K[shift, : nb - shift, :, _SYMMETRIC[c, d]].T
                    )
        bands[0] += ridge
        self.solve_banded = _banded_solver(bands.reshape(12, -1))
        self.rays, self.spacing, self.ridge = rays, spacing, ridge
        self.b, self.db, self.active = b, db, active
        self.offsets = offsets
        if offsets is not None:
            self._eliminate(offsets)
        right = (self.basis.T @ rays.pull.reshape(n, -1)).reshape(nb, p, 3).swapaxes(0, 1)
        pull = None
        if offsets is not None:
            pull = -self._group_sums(rays.rhs * self.weight[:, None], np.ones((n, 1)))[0]
        beta, g = self.solve(right.reshape(1, -1), None if pull is None else pull[None])
        self.beta = beta.reshape(p, nb, 3)
        self.g = None if g is None else g[0]
        at = (self.basis @ self.beta.swapaxes(0, 1).reshape(nb, -1)).reshape(n, p, 3)
        res = np.einsum("oac,oc->oa", rays.e, at[rays.img, rays.pt]) - rays.rhs
        if self.g is not None:
            res -= self._at_groups(self.g[None])[0]
        self.res = res.ravel()

    def _eliminate(self, offsets: _Offsets) -> None:
        """The offsets' columns ``U = A^T S`` packed per (stream, normal) over all points,
        ``H``, ``Z = G^-1 U`` and every point's Woodbury capacitance ``H - U^T Z``, inverted."""
        rays, (n, nb) = self.rays, self.basis.shape
        p, m = rays.pull.shape[1], 2 * offsets.active.shape[0]
        stream = offsets.stream[rays.img]
        grouped = stream >= 0
        grouped[grouped] = offsets.active[stream[grouped], rays.pt[grouped]]
        self.grouped = grouped  # (M,) observations with an offset
        self.weight = np.where(grouped, np.linalg.norm(rays.e[:, 0], axis=1), 0.0)
        self.H = self._group_sums(self.weight[:, None] ** 2 * np.ones((1, 2)), np.ones((n, 1)))[0]
        self.H = np.where(offsets.active.repeat(2, axis=0), self.H + self.ridge, 1.0)
        # the collocation matrix with every stream's bases apart: (N, S B)
        expanded = sp.csr_matrix(
            (np.where(offsets.stream[:, None] >= 0, self.b, 0.0).ravel(),
             (np.maximum(offsets.stream, 0)[:, None] * nb + self.active).ravel(),
             4 * np.arange(n + 1)), shape=(n, m // 2 * nb))
        Q = np.zeros((n, p, 2, 3))
        Q[rays.img, rays.pt] = self.weight[:, None, None] * rays.e
        U = (expanded.T @ Q.reshape(n, -1)).reshape(m // 2, nb, p, 2, 3)
        # per point: U (P, 2S, B 3) and Z = G^-1 U
        self.U = np.ascontiguousarray(U.transpose(2, 0, 3, 1, 4).reshape(p, m, -1))
        Z = self.solve_banded(self.U.swapaxes(0, 1).reshape(m, -1).T).T.reshape(m, p, -1)
        self.Zt = np.ascontiguousarray(Z.transpose(1, 2, 0))  # (P, B 3, 2S)
        capacity = np.eye(m) * self.H.T[:, :, None] - self.U @ self.Zt
        self.capacity_inv = np.linalg.inv(capacity)

    def _group_sums(self, values: np.ndarray, dt: np.ndarray) -> np.ndarray:
        """(q, 2S, P) ``S^T (values dt)``: every (stream, point, normal) group's sum of its
        observations' ``values`` (M, 2) (times their weights already) times their images'
        ``dt`` (N, q)."""
        offsets, rays, n, p = self.offsets, self.rays, dt.shape[0], self.rays.pull.shape[1]
        count = offsets.active.shape[0]
        out = np.zeros((dt.shape[1], 2 * count, p))
        for a in range(2):
            T = np.zeros((n, p))
            T[rays.img, rays.pt] = np.where(self.grouped, values[:, a], 0.0)
            for s in range(count):
                rows = offsets.stream == s
                out[:, 2 * s + a] = dt[rows].T @ T[rows]
        return out

    def _at_groups(self, g: np.ndarray) -> np.ndarray:
        """(c, M, 2) ``S g`` of c offset vectors ``g`` (c, 2S, P): every observation's weight
        times its group's offset."""
        rays, stream = self.rays, self.offsets.stream[self.rays.img]
        rows = 2 * np.maximum(stream, 0)[:, None] + np.arange(2)
        at = g[:, rows, rays.pt[:, None]]  # (c, M, 2)
        return at * self.weight[None, :, None]

    def solve(self, u: np.ndarray, v: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """The normal equations of the coefficients and offsets with right-hand sides ``u``
        (c, P B 3) and ``v`` (c, 2S, P) (None without offsets): (coefficients, offsets)."""
        if self.offsets is None:
            return self.solve_banded(u.T).T, None
        c, p = u.shape[0], self.U.shape[0]
        scaled = (v / self.H).transpose(2, 0, 1)  # (P, c, 2S)
        y = u.reshape(c, p, -1) + (scaled @ self.U).swapaxes(0, 1)
        x = self.solve_banded(y.reshape(c, -1).T).reshape(p, -1, c)  # (P, B 3, c)
        beta = x + self.Zt @ (self.capacity_inv @ (self.U @ x))
        g = (v + (self.U @ beta).transpose(2, 1, 0)) / self.H
        return beta.transpose(2, 0, 1).reshape(c, -1), g

    def tangent(self, dt: np.ndarray) -> tuple[np.ndarray, tuple, tuple]:
        """With the coefficients and offsets held, the residuals' derivative ``D`` in q clock
        parameters (``dt`` (N, q) the times'): (M, 2) ``along`` (``D = along dt``), ``A^T D``
        and ``G^-1 A^T D`` with A and G the design and normal matrix of the coefficients and
        offsets (each a pair: (q, P B 3) the coefficients' part, (q, 2S, P) or None the
        offsets')."""
        rays, (n, nb), p, q = self.rays, self.basis.shape, self.beta.shape[0], dt.shape[1]
        velocity = np.einsum("ok,okc->oc", self.db[rays.img],
                             self.beta[rays.pt[:, None], self.active[rays.img]]) / self.spacing
        along = np.einsum("oac,oc->oa", rays.e, velocity)
        normal = np.zeros((n, p, 3))
        normal[rays.img, rays.pt] = np.einsum("oac,oa->oc", rays.e, along)
        # the collocation matrix times every parameter's derivative, side by side: (N, q B)
        cols = np.arange(q)[:, None] * nb + self.active[:, None, :]
        scaled = sp.csr_matrix(
            ((self.b[:, None, :] * dt[:, :, None]).ravel(), cols.ravel(), 4 * q * np.arange(n + 1)),
            shape=(n, q * nb),
        )
        w = (scaled.T @ normal.reshape(n, -1)).reshape(q, nb, p, 3).swapaxes(1, 2)
        w = w.reshape(q, -1)
        wg = None if self.offsets is None else -self._group_sums(along * self.weight[:, None], dt)
        return along, (w, wg), self.solve(w, wg)

    def jacobian(self, dt: np.ndarray) -> np.ndarray:
        """(2M, q) Kaufman Jacobian ``D - A G^-1 A^T D`` of the residuals in q clock parameters,
        ``dt`` (N, q) the times' derivative in them (A, G those of the coefficients and
        offsets)."""
        rays, (n, nb), p, q = self.rays, self.basis.shape, self.beta.shape[0], dt.shape[1]
        along, _, (y, yg) = self.tangent(dt)
        y = y.reshape(q, p, nb, 3).transpose(2, 0, 1, 3).reshape(nb, -1)
        at = (self.basis @ y).reshape(n, q, p, 3)[rays.img, :, rays.pt]  # (M, q, 3)
        d = along[..., None] * dt[rays.img][:, None, :]
        J = d - rays.e @ at.swapaxes(1, 2)
        if yg is not None:
            J += self._at_groups(yg).transpose(1, 2, 0)
        return J.reshape(-1, q)

    def gram(self, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``J^T J`` (q, q) and ``J^T res`` (q,) of :meth:`jacobian`'s J without forming it:
        ``D^T D - (A^T D)^T Y - ridge Y^T Y`` and ``D^T res + ridge Y^T theta``, with
        ``Y = G^-1 A^T D`` and theta the coefficients and offsets (as ``A^T A = G - ridge I``
        and ``A^T res = -ridge theta``)."""
        rays, n = self.rays, dt.shape[0]
        along, (w, wg), (y, yg) = self.tangent(dt)
        weight = np.bincount(rays.img, (along * along).sum(axis=1), minlength=n)
        pull = np.bincount(rays.img, (along * self.res.reshape(-1, 2)).sum(axis=1), minlength=n)
        jtj = (dt * weight[:, None]).T @ dt - w @ y.T - self.ridge * (y @ y.T)
        jtr = dt.T @ pull + self.ridge * (y @ self.beta.ravel())
        if yg is not None:
            q = dt.shape[1]  # offsets not fitted are 0 in y and theta alike
            wg, yg = wg.reshape(q, -1), yg.reshape(q, -1)
            jtj = jtj - wg @ yg.T - self.ridge * (yg @ yg.T)
            jtr = jtr + self.ridge * (yg @ self.g.ravel())
        return (jtj + jtj.T) / 2, jtr


def spline_residuals(
    t: np.ndarray,
    E: np.ndarray,
    rhs: np.ndarray,
    visible: np.ndarray,
    spacing: float,
    start: float,
    dt: np.ndarray | None = None,
    ridge: float = 1e-9,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Residuals of every point's least-squares B-spline trajectory on its rays.

    t (N,) times; knots every ``spacing`` from ``start`` (at most ``t.min()``). With ``dt``
    (N, q), the derivative of the times in q clock parameters, also the Kaufman Jacobian
    (2M, q) of the residuals (M observations) in those parameters. The solve: :class:`_SplineFit`.
    """
    fit = _SplineFit(t, _rays(E, rhs, visible), spacing, start, ridge)
    return fit.res if dt is None else (fit.res, fit.jacobian(dt))


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
    image in a stream; ``E``, ``rhs`` from :func:`ray_equations`. The longest stream is the
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
    trajectories (:class:`_Offsets`): a detector's offsets otherwise read as time shifts where
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
    grid_rays = _rays(E[win][:, seen], rhs[win][:, seen], visible[win][:, seen])
    window_offsets = all_offsets = None
    if offsets:
        position = np.full(k, -1)  # every stream's place among the free ones
        position[free] = np.arange(free.size)
        window_offsets = _offsets(position[inv[win]], visible[win][:, seen], free.size)
        all_offsets = _offsets(position[inv], visible, free.size)

    def fitted(x: np.ndarray, cols: np.ndarray, fits: Callable[[np.ndarray], list[_SplineFit]],
               rows: np.ndarray, first: float, norms: list[float],
               known: list[_SplineFit] | None = None) -> np.ndarray:
        """``x`` with its ``cols`` fitted by Levenberg-Marquardt to the residuals of ``fits``
        (the spline fits at clocks z on images ``rows``, knots from ``first``), each over its
        norm in ``norms``, seen through :func:`_condensed`. Fits are cached by ``x[cols]``,
        starting with ``known``, the fits at ``x``."""
        cache = {} if known is None else {x[cols].tobytes(): known}
        dt_fit = dt[rows][:, cols]

        def at(y: np.ndarray) -> list[_SplineFit]:
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

        sol = least_squares(lambda y: np.r_[np.zeros(cols.size), np.sqrt(squares(y))], x[cols],
                            jac=jacobian, method="lm", xtol=1e-6, ftol=1e-8)
        out = x.copy()
        out[cols] = sol.x
        return out

    def grid(x: np.ndarray) -> tuple[np.ndarray, float]:
        """Coordinate sweeps over the offsets from ``x`` until none moves: (x, residual)."""

        def residual(y: np.ndarray) -> float:
            t = times(y)[win]
            if t.min() < grid_start:  # a step beyond the knots
                return np.inf
            r = _SplineFit(t, grid_rays, h_mid, grid_start).res
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

    def coarse(z: np.ndarray) -> list[_SplineFit]:
        """The first stage's spline fit at clocks ``z``."""
        return [_SplineFit(times(z)[win], grid_rays, COARSE_KNOTS * h_mid, grid_start,
                           offsets=window_offsets)]

    shifts = np.arange(free.size)
    freed = [shifts] if held else [shifts, np.arange(shifts.size * 2)]
    found = [grid(fitted(x, cols, coarse, win, grid_start, [1.0]))
             for x in starts for cols in freed]
    x = min(found, key=lambda found: found[1])[0]
    start = float(times(x).min()) - 3 * period - max(hs)
    rays = _rays(E, rhs, visible)

    def fine(z: np.ndarray) -> list[_SplineFit]:
        """The last stage's spline fits at clocks ``z``: all images and points, every spacing."""
        return [_SplineFit(times(z), rays, h, start, offsets=all_offsets) for h in hs]

    everything = np.arange(t_init.size)
    at_grid = fine(x)
    norms = [np.sqrt(float(f.res @ f.res)) for f in at_grid]
    x = fitted(x, shifts, fine, everything, start, norms, at_grid)
    if not held:
        x = fitted(x, np.arange(x.size), fine, everything, start, norms)
    return times(x)


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
