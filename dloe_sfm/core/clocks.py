"""Stream clocks: each video's affine clock ``t = a_s + b_s frame``, fitted to the rays.

At coarse sampling DLOE's graph places images by shape alone and a few tens of milliseconds off
their instants, and the depth along each ray follows the timing error. A video's images,
though, are not free on the time line: its frames are equally spaced, so the whole capture's
timing is a few numbers per stream.

For given clocks every point's trajectory is fitted as a cubic B-spline in time to its rays by
linear least squares (the residual is each observation's distance to its ray); the clocks that
minimise that residual make the rays of different cameras agree. Variable projection: the
spline coefficients are eliminated, the clocks go to Levenberg-Marquardt with the Kaufman
Jacobian, after a coordinate grid over +-1/2 frame period per stream (the residual has local
minima a sampling interval apart, and the fit alone can stop in one). The residual is summed
over knot spacings of 2-5 sampling intervals of the merged streams: no single spacing suits
every motion. The measurements behind these choices: docs/method.md, "Stream clocks".
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.optimize import least_squares

SPACINGS = (2.0, 3.0, 4.0, 5.0)
"""Knot spacings in median sampling intervals of all streams merged."""
GRID_STEPS = 16
"""Grid points per frame period of the coordinate search."""
GRID_POINTS = 8
"""The grid's residual uses this many most-observed points, the fit after it all of them (a
fraction of the cost, the same clocks: docs/method.md, "Stream clocks")."""


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
    (2M, q) of the residuals (M observations) in those parameters.
    """
    img, pt = np.nonzero(visible)
    p = visible.shape[1]
    u = (t - start) / spacing
    j = np.floor(u).astype(np.int64)
    nb = int(j.max()) + 4
    b, db = _cubic_bspline(u - j)
    e = E[img, pt]  # (M, 2, 3)
    m = img.size
    # design: row (o, a), column (point, basis j_o + k, coordinate c) = b_ok e_oac
    rows = np.broadcast_to(
        2 * np.arange(m)[:, None, None, None] + np.arange(2)[None, None, :, None], (m, 4, 2, 3)
    )
    cols = (pt[:, None, None, None] * nb + j[img][:, None, None, None]
            + np.arange(4)[None, :, None, None]) * 3 + np.arange(3)[None, None, None, :]
    vals = b[img][:, :, None, None] * e[:, None, :, :]
    A = sp.csr_matrix((vals.ravel(), (rows.ravel(), np.broadcast_to(cols, rows.shape).ravel())),
                      shape=(2 * m, 3 * nb * p))
    G = (A.T @ A + ridge * sp.identity(A.shape[1])).tocsc()
    lu = spla.splu(G)
    beta = lu.solve(A.T @ rhs[img, pt].ravel())
    res = A @ beta - rhs[img, pt].ravel()
    if dt is None:
        return res
    coef = beta.reshape(p, nb, 3)
    idx = j[img][:, None] + np.arange(4)
    velocity = np.einsum("ok,okc->oc", db[img], coef[pt[:, None], idx]) / spacing
    dr = np.einsum("oac,oc->oa", e, velocity).reshape(-1, 1) * np.repeat(dt[img], 2, axis=0)
    return res, dr - A @ lu.solve(A.T @ dr)


def fit_clocks(
    t0: np.ndarray,
    streams: np.ndarray,
    frames: np.ndarray,
    E: np.ndarray,
    rhs: np.ndarray,
    visible: np.ndarray,
    *,
    shared_rate: bool = False,
    spacings: tuple[float, ...] = SPACINGS,
    grid_steps: int = GRID_STEPS,
    grid_points: int = GRID_POINTS,
) -> np.ndarray | None:
    """(N,) times on the streams' affine clocks that best explain the rays (module docstring).

    ``t0`` (N,) first-guess times (DTW placement), ``streams`` / ``frames`` (N,) with every
    image in a stream; ``E``, ``rhs`` from :func:`ray_equations`. The longest stream is the
    reference (its first-guess start and the streams' median first-guess rate are kept). The
    other streams' offsets are searched on a grid of ``grid_steps`` per frame period (its
    residual on the ``grid_points`` most-observed points), then fitted with one shared rate;
    unless ``shared_rate`` is True, their rates are then freed too, starting from that fit.

    With two streams each ray's depth is seen by one other stream only, and a knot interval of
    two merged sampling intervals holds one of its frames: the spacings grow by half (doubled,
    they are too wide for fast motion). Returns None when the fit moved a stream by more than a
    frame period against the others from ``t0`` (median over its images): the grid searches
    half a period, so the rays did not pin the clocks. The measurements: docs/method.md,
    "Stream clocks".
    """
    f = frames.astype(np.float64)
    ids, inv = np.unique(streams, return_inverse=True)
    k = ids.size
    rate = float(np.median([np.polyfit(f[inv == s], t0[inv == s], 1)[0] for s in range(k)]))
    a0 = np.array([np.median(t0[inv == s] - rate * f[inv == s]) for s in range(k)])
    ref = int(np.argmax(np.bincount(inv)))
    free = np.flatnonzero(np.arange(k) != ref)
    onehot = (inv[:, None] == free[None, :]).astype(np.float64)
    dt = np.concatenate([onehot, onehot * f[:, None]], axis=1)  # d t / d (offsets, rates)
    x0 = np.concatenate([a0[free], np.full(free.size, rate)])

    def times(x: np.ndarray) -> np.ndarray:
        return a0[inv] + rate * f + dt @ (x - x0)

    t_init = times(x0)
    interval = float(np.median(np.diff(np.unique(t_init))))
    hs = [h * interval * (1.5 if k == 2 else 1.0) for h in spacings]
    period = rate * float(np.median(np.diff(np.unique(f[inv == ref]))))
    start = float(t_init.min()) - 3 * period - max(hs)

    def total(x: np.ndarray, h: float, eq: tuple = (E, rhs, visible)) -> float:
        r = spline_residuals(times(x), *eq, h, start)
        return float(r @ r)

    x = x0.copy()
    h_mid = hs[len(hs) // 2]
    steps = (np.arange(grid_steps + 1) - grid_steps / 2) * period / grid_steps
    seen = np.argsort(-visible.sum(axis=0), kind="stable")[:grid_points]
    grid_eq = (E[:, seen], rhs[:, seen], visible[:, seen])
    for _ in range(3):  # coordinate sweeps until none moves
        before = x.copy()
        for c in range(free.size):
            trials = [x + d * (np.arange(x.size) == c) for d in steps]
            x = trials[int(np.argmin([total(y, h_mid, grid_eq) for y in trials]))]
        if np.array_equal(x, before):
            break
    norms = [np.sqrt(total(x, h)) for h in hs]

    def refine(x: np.ndarray, cols: np.ndarray) -> np.ndarray:
        cache: dict = {}

        def evaluate(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            key = y.tobytes()
            if key not in cache:
                z = x.copy()
                z[cols] = y
                parts = [spline_residuals(times(z), E, rhs, visible, h, start, dt[:, cols])
                         for h in hs]
                cache.clear()
                cache[key] = (
                    np.concatenate([r / n for (r, _), n in zip(parts, norms, strict=True)]),
                    np.vstack([J / n for (_, J), n in zip(parts, norms, strict=True)]),
                )
            return cache[key]

        sol = least_squares(lambda y: evaluate(y)[0], x[cols], jac=lambda y: evaluate(y)[1],
                            method="lm", xtol=1e-8, ftol=1e-10)
        out = x.copy()
        out[cols] = sol.x
        return out

    x = refine(x, np.arange(free.size))
    if not shared_rate:
        x = refine(x, np.arange(x.size))
    t = times(x)
    moved = np.abs(t - np.polyval(np.polyfit(t0, t, 1), t0))  # up to one map of the time line
    return None if max(np.median(moved[inv == s]) for s in range(k)) > period else t


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
