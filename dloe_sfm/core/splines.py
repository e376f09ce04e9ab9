"""Every point's trajectory as a cubic B-spline in time fitted to its rays: the model whose
residual the stream clocks minimise (``clocks.fit_clocks``) and whose Jacobian gives their
uncertainty (``sync``).

For given times each point's spline is fitted to its rays by linear least squares (the residual
is each observation's distance to its ray, :func:`ray_equations`); optionally each stream's rays
of each point take a constant offset, fitted with the trajectories (a detector's bias in that
view, :class:`Offsets`). Cost: a spline fit is one banded Cholesky factorisation of the points'
normal equations, linear in the observations (:class:`SplineFit`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla

OFFSET_MIN_OBS = 10
"""A stream's observations of a point (other than the reference stream's) carry their own
offset in the fit when there are at least this many of them (:class:`Offsets`)."""


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


class Rays(NamedTuple):
    """The ray equations of the visible observations, with what of them the clocks do not
    change (:func:`visible_rays`)."""

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
"""The lower triangle's (c, d) of a symmetric 3 x 3 block, in ``Rays.normal``'s order."""
_SYMMETRIC = np.array([[0, 1, 3], [1, 2, 4], [3, 4, 5]])
"""Entry (c, d) of a symmetric 3 x 3 block -> its index in ``_PAIRS``."""
_SHIFT = np.repeat(np.arange(4), np.arange(4, 0, -1))
_FIRST = np.concatenate([np.arange(4 - d) for d in range(4)])
"""The 10 pairs (k, k + shift) of an image's 4 active bases, by shift then k."""


def visible_rays(E: np.ndarray, rhs: np.ndarray, visible: np.ndarray) -> Rays:
    """:class:`Rays` of ``E``, ``rhs`` (:func:`ray_equations`) on the ``visible`` (N, P)
    observations."""
    img, pt = np.nonzero(visible)
    e, r = E[img, pt], rhs[img, pt]
    c, d = np.array(_PAIRS).T
    normal = np.zeros((*visible.shape, len(_PAIRS)))
    normal[img, pt] = np.einsum("oac,oad->ocd", e, e)[:, c, d]
    pull = np.zeros((*visible.shape, 3))
    pull[img, pt] = np.einsum("oac,oa->oc", e, r)
    return Rays(img, pt, e, r, normal, pull)


class Offsets(NamedTuple):
    """Which observations carry an offset of their own in the fit: a detector places a joint
    a few pixels off, the same way in every frame of one camera, and along the motion that
    offset reads as a time shift. Each (stream, point) with enough observations
    (:data:`OFFSET_MIN_OBS`) takes a constant offset along its rays' two normals, fitted with
    the trajectories; the reference stream's rays keep none (they fix where the points are)."""

    stream: np.ndarray
    """(N,) every image's stream among the S streams with offsets, -1 for the reference."""
    active: np.ndarray
    """(S, P) the (stream, point) offsets fitted."""


def offset_columns(stream: np.ndarray, visible: np.ndarray, count: int) -> Offsets:
    """:class:`Offsets` of images in ``stream`` (N,) (0 to ``count`` - 1, -1 the reference)
    observing the ``visible`` (N, P) points."""
    seen = np.stack([visible[stream == s].sum(axis=0) for s in range(count)])
    return Offsets(stream, seen >= OFFSET_MIN_OBS)


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


class SplineFit:
    """Every point's least-squares cubic B-spline trajectory on its rays at times ``t``
    (:func:`spline_residuals`): ``beta`` (P, B, 3) the coefficients, ``res`` (2M,) the residuals;
    with ``offsets`` (:class:`Offsets`) also ``g`` (2S, P), every (stream, point)'s offset
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
        self, t: np.ndarray, rays: Rays, spacing: float, start: float, ridge: float = 1e-9,
        offsets: Offsets | None = None
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

    def _eliminate(self, offsets: Offsets) -> None:
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
    (2M, q) of the residuals (M observations) in those parameters. The solve: :class:`SplineFit`.
    """
    fit = SplineFit(t, visible_rays(E, rhs, visible), spacing, start, ridge)
    return fit.res if dt is None else (fit.res, fit.jacobian(dt))
