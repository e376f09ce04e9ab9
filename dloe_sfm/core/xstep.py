"""The X-step of alternating convex search: the optimal points for fixed W and D, per point one
sparse banded system (docs/method.md, "The steps as implemented"); the problem data and the other
steps are in :mod:`.steps`, the W-step in :mod:`.wstep`."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.sparse.csgraph import reverse_cuthill_mckee
from threadpoolctl import ThreadpoolController

from .steps import Problem, smoothness_matrix

BLAS = ThreadpoolController()
"""The BLAS libraries numpy and scipy loaded (made here, after ``scipy.linalg`` loaded its own):
the X-step's factorisations (:func:`x_step`) and the whole solve (``solver.reconstruct``) run
on one thread of theirs."""

BAND_WIDTH = 128
"""The X-step factors a system of m unknowns as a band up to a bandwidth of
``max(BAND_WIDTH, sqrt(m))`` (at most O(m^2) operations), or wider where the band's work m b^2 is
at most :data:`BAND_WORK`; the others by SuperLU (:func:`x_step`)."""
BAND_WORK = 2**29
"""Largest m b^2 of a band wider than ``BAND_WIDTH`` the X-step still factors as a band: at most
tens of milliseconds of LAPACK, less than SuperLU takes on those systems, whose long edges
fill in its factors (docs/method.md, "Speed")."""
BATCH = 2**20
"""With hard rays the X-step solves the points in groups of about this many of Q's entries over
all of them (:func:`_hard_points`: one factorisation per group, memory bounded at any size)."""


ABSENT_SHARE = 0.5
"""A subject absent from at least this share of an X-step's images (none of its points seen)
has those images eliminated from its points' systems (:func:`_absent_eliminated`): they are
the most unknowns of the systems, 3 per image, and widen their bands. Eliminating the few
images a subject seen throughout misses adds links that widen its band instead."""
ELIMINATED_ENTRIES = 2**22
"""Largest dense block (absent images x the other images they link to) an elimination solves
for; a subject whose block is larger keeps its absent images as unknowns."""


@BLAS.wrap(limits=1, user_api="blas")
def x_step(
    W: sp.csr_matrix,
    D: np.ndarray,
    prob: Problem,
    *,
    lambda1: float,
    lambda2: float,
    X_prev: np.ndarray,
) -> np.ndarray:
    """Optimal X for fixed W, D: per point p a sparse symmetric linear system.

    With ``lambda2 = inf`` observed points are pinned to their rays, ``X_np = C_n + l_np r_np``,
    and only the depths l_np (plus the 3 coordinates of unobserved points) are unknown
    (:func:`_hard_points`). Otherwise the O term ``l2 w_np |(X_np - C_n) x r_np|^2`` joins the
    smoothness form Q, 3 unknowns per image (:func:`_soft_band`). X_prev fills in points no
    equation reaches (never the case on a connected graph).

    W's graph is chain-like in time, so the images are ordered once per call by reverse
    Cuthill-McKee on Q's pattern, and each point's unknowns follow its images in that order
    (1 or 3 per image): its system is then a band, assembled directly from Q's entries and
    solved by LAPACK's banded Cholesky in O(m b^2) for m unknowns and bandwidth b. A band wider
    than ``max(BAND_WIDTH, sqrt(m))`` (a graph with long edges, where the band would approach a
    dense matrix) unless its work is small (:func:`_band_pays`), or a system the banded
    Cholesky finds not numerically positive definite, goes to SuperLU instead
    (:func:`_superlu`).

    With several subjects (``prob.subjects``), one absent from at least :data:`ABSENT_SHARE`
    of the images is solved on the others alone (:func:`_absent_eliminated`), the same X.

    The BLAS runs on one thread here: the banded Cholesky's blocks are too small to share, and
    OpenBLAS's threads, which wait for each block, took 15 times as long as one thread when
    another process kept a core busy (docs/method.md, "Speed").
    """
    n, p = prob.rays.shape[:2]
    Q = smoothness_matrix(W, D, lambda1)
    reg = 1e-10 * max(Q.diagonal().mean(), 1e-300)
    vis = prob.visible
    r0 = np.nan_to_num(prob.rays)
    X = np.empty((n, p, 3))
    rest = np.ones(p, dtype=bool)
    for cols in np.split(np.arange(p), prob.subjects) if prob.subjects > 1 else ():
        absent = ~vis[:, cols].any(axis=1)
        if absent.all() or absent.sum() < ABSENT_SHARE * n:
            continue
        eliminated = _absent_eliminated(Q, absent, reg)
        if eliminated is None:
            continue
        Q_kept, solve_absent, kept = eliminated
        X_kept = _points(Q_kept, reg, lambda2, r0[kept][:, cols], vis[kept][:, cols],
                         prob.C[kept], prob.weights[kept][:, cols])
        X[np.ix_(kept, cols)] = X_kept
        X[np.ix_(absent, cols)] = solve_absent(X_kept)
        rest[cols] = False
    if rest.all():
        X = _points(Q, reg, lambda2, r0, vis, prob.C, prob.weights)
    elif rest.any():
        X[:, rest] = _points(Q, reg, lambda2, r0[:, rest], vis[:, rest], prob.C,
                             prob.weights[:, rest])
    bad = ~np.isfinite(X)
    X[bad] = X_prev[bad]
    return X


def _absent_eliminated(
    Q: sp.csr_matrix, absent: np.ndarray, reg: float
) -> tuple[sp.csr_matrix, Callable[[np.ndarray], np.ndarray], np.ndarray] | None:
    """The X-step of a subject's points without the images it is ``absent`` from (N,): (the
    smoothness form on the other images, the absent images' X (A, S, 3) from the others'
    (K, S, 3), the other images (K,)); None when the elimination's dense block exceeds
    :data:`ELIMINATED_ENTRIES`.

    In an absent image a point is 3 free coordinates, each seeing Q alone, so minimising over
    them leaves Q's Schur complement ``Q_kk - Q_ka (Q_aa + reg I)^-1 Q_ak`` on the other images
    (Kron reduction), for every coordinate and every point of the subject alike; the absent
    points are then ``-(Q_aa + reg I)^-1 Q_ak X_k``. The complement links the images next to
    each stretch the subject is absent from, as the stretch did.
    """
    kept, gone = np.flatnonzero(~absent), np.flatnonzero(absent)
    rows = Q[gone]
    Q_ak = rows[:, kept].tocsc()
    linked = np.flatnonzero(np.diff(Q_ak.indptr) > 0)  # the other images the absent ones link
    if gone.size * linked.size > ELIMINATED_ENTRIES:
        return None
    Q_aa = sp.csc_matrix(rows[:, gone] + reg * sp.identity(gone.size, format="csr"))
    lu = spla.splu(
        Q_aa, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
    )
    Q_al = Q_ak[:, linked]
    fill = np.asarray(Q_al.T @ lu.solve(Q_al.toarray())) if linked.size else np.zeros((0, 0))
    i, j = np.nonzero(fill)
    Q_kept = sp.csr_matrix(
        Q[kept][:, kept]
        - sp.csr_matrix((fill[i, j], (linked[i], linked[j])), shape=(kept.size, kept.size))
    )

    def solve_absent(X_kept: np.ndarray) -> np.ndarray:
        """The absent images' X (A, S, 3) from the other images' ``X_kept`` (K, S, 3)."""
        rhs = -(Q_ak @ X_kept.reshape(kept.size, -1))
        return lu.solve(rhs).reshape(gone.size, *X_kept.shape[1:])

    return Q_kept, solve_absent, kept


def _points(
    Q: sp.csr_matrix,
    reg: float,
    lambda2: float,
    r0: np.ndarray,
    vis: np.ndarray,
    C: np.ndarray,
    weights: np.ndarray,
) -> np.ndarray:
    """X (N, P, 3) of the points of rays ``r0`` (N, P, 3, zero where unobserved) seen in the
    images ``vis`` (N, P) with ``weights`` (N, P), for the smoothness form Q (:func:`x_step`)."""
    n, p = vis.shape
    perm = reverse_cuthill_mckee(Q, symmetric_mode=True)
    rank = np.empty(n, dtype=np.int64)
    rank[perm] = np.arange(n)
    coo = Q.tocoo()
    upper = rank[coo.row] <= rank[coo.col]
    qi, qk, q = coo.row[upper].astype(np.int64), coo.col[upper].astype(np.int64), coo.data[upper]
    X = np.empty((n, p, 3))
    if np.isinf(lambda2):
        # points solved together: about BATCH of Q's entries over all of them
        for c in np.array_split(np.arange(p), min(p, max(1, -(-p * qi.size // BATCH)))):
            X[:, c] = _hard_points(Q, perm, qi, qk, q, r0[:, c], vis[:, c], C, reg)
    else:
        width = max(3 * int((rank[qk] - rank[qi]).max(initial=0)), 2)
        band_Q = None
        if _band_pays(3 * n, width):
            # kron(Q, I3) as a band (_banded_cholesky), image n's coordinates at 3 rank_n + t
            band_Q = np.zeros((3 * n, width + 1))
            band_Q[3 * rank[qi][:, None] + np.arange(3), 3 * (rank[qk] - rank[qi])[:, None]] = (
                q[:, None])
        for j in range(p):
            wgt = lambda2 * weights[:, j]
            z = None if band_Q is None else _soft_band(band_Q, rank, r0[:, j], C, wgt, reg)
            if z is None:
                H, rhs = _soft_system(Q, r0[:, j], C, wgt, reg)
                X[:, j] = _superlu(H, rhs).reshape(n, 3)
            else:
                X[:, j] = z.reshape(n, 3)[rank]
    return X


def _hard_points(
    Q: sp.csr_matrix,
    perm: np.ndarray,
    qi: np.ndarray,
    qk: np.ndarray,
    q: np.ndarray,
    rays: np.ndarray,
    vis: np.ndarray,
    C: np.ndarray,
    reg: float,
) -> np.ndarray:
    """X (N, P, 3) of every point with hard rays ``rays`` (N, P, 3, zero where unobserved) in
    the images ``vis`` (N, P). Point p: ``X = c + B z``, one depth column r_n of B per observed
    image (c_n = C_n) and three unit columns per unobserved one (c_n = 0),
    ``(B^T kron(Q, I3) B + reg I) z = -B^T kron(Q, I3) c``.

    Each point's unknowns follow the images in the band order ``perm``, and its system is
    assembled from Q's entries ``q`` at (``qi``, ``qk``), ``qi`` no later than ``qk`` in that
    order, rather than as sparse products: Q_nm r_n . r_m between observed images, Q_nm r_n (or
    r_m) between an observed and an unobserved one, Q_nm I3 between unobserved ones. The points'
    systems are independent: those narrow enough for a band are the blocks of one band matrix,
    factored by a single banded Cholesky (zero entries between the blocks); the others, and all
    of them when that matrix is not numerically positive definite, are solved one by one
    (:func:`_point_system`).
    """
    n, p = vis.shape
    size = np.where(vis, 1, 3)
    ends = np.cumsum(size[perm], axis=0)
    m = ends[-1]
    base = np.concatenate([[0], np.cumsum(m)[:-1]])
    start = np.empty((n, p), dtype=np.int64)  # first unknown of (image, point), points stacked
    start[perm] = ends - size[perm] + base
    si, sk = start[qi], start[qk]  # (E, P): every entry of Q for every point
    oi, ok = vis[qi], vis[qk]
    ri, rk = rays[qi], rays[qk]
    qq = q[:, None]
    kinds = (oi & ok, oi & ~ok, ~oi & ok, ~oi & ~ok)
    width = (sk - si + 2 * kinds[1]).max(axis=0, initial=0)
    banded = width <= np.maximum(BAND_WIDTH, np.sqrt(m))

    a, b, qs = si.ravel(), sk.ravel(), np.broadcast_to(qq, si.shape).ravel()
    dot = ((ri[..., 0] * rk[..., 0] + ri[..., 1] * rk[..., 1]) + ri[..., 2] * rk[..., 2]).ravel()
    ri_t = [ri[..., t].ravel() for t in range(3)]
    rk_t = [rk[..., t].ravel() for t in range(3)]
    flat = [np.flatnonzero(kind) for kind in kinds]  # each kind's flat (E, P) indices
    point = [f % p for f in flat]

    def entries(at: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """H's entries on and below the diagonal (rows >= cols) at the flat (E, P) indices
        ``at`` of each of the four kinds."""
        rows, cols, vals = [b[at[0]]], [a[at[0]]], [qs[at[0]] * dot[at[0]]]
        for t in range(3):
            rows += [b[at[1]] + t, b[at[2]], b[at[3]] + t]
            cols += [a[at[1]], a[at[2]] + t, a[at[3]] + t]
            vals += [qs[at[1]] * ri_t[t][at[1]], qs[at[2]] * rk_t[t][at[2]], qs[at[3]]]
        return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)

    g = (Q @ np.where(vis[..., None], C[:, None, :], 0.0).reshape(n, 3 * p)).reshape(n, p, 3)
    rhs = np.empty(int(m.sum()))  # -B^T kron(Q, I3) c, g (N, P, 3) the product's second factor
    img, pj = np.nonzero(vis)
    rhs[start[img, pj]] = -((rays[img, pj, 0] * g[img, pj, 0] + rays[img, pj, 1] * g[img, pj, 1])
                            + rays[img, pj, 2] * g[img, pj, 2])
    hole, qj = np.nonzero(~vis)
    rhs[start[hole, qj][:, None] + np.arange(3)] = -g[hole, qj]
    z = np.empty(rhs.size)
    solved = np.zeros(p, dtype=bool)
    if banded.any():
        rows, col, vals = entries([f[banded[j]] for f, j in zip(flat, point, strict=True)])
        w = int(width[banded].max())
        band = np.zeros((rhs.size, w + 1))  # rows of the other points: reg on the diagonal only
        band.reshape(-1)[col * (w + 1) + (rows - col)] = vals
        band[:, 0] += reg
        zb = _banded_cholesky(band, np.where(np.repeat(banded, m), rhs, 0.0))
        if zb is not None:
            z, solved = zb, banded
    rest = np.flatnonzero(~solved)
    if rest.size:  # one by one: each kind's indices grouped by point (flat order within one)
        single = [np.argsort(j, kind="stable") for j in point]
        ends = [np.searchsorted(j[o], np.arange(p + 1)) for j, o in zip(point, single, strict=True)]
    for j in rest:
        lo, hi = base[j], base[j] + m[j]
        rows, col, vals = entries([f[o[e[j]:e[j + 1]]]
                                   for f, o, e in zip(flat, single, ends, strict=True)])
        z[lo:hi] = _point_system(rows - lo, col - lo, vals, int(m[j]), rhs[lo:hi], reg,
                                 width=int(width[j]) if _band_pays(m[j], width[j]) else None)
    X = np.empty((n, p, 3))
    X[img, pj] = C[img] + rays[img, pj] * z[start[img, pj]][:, None]
    X[hole, qj] = z[start[hole, qj][:, None] + np.arange(3)]
    return X


def _band_pays(m: int, width: int) -> bool:
    """Whether a system of m unknowns and bandwidth ``width`` is factored as a band."""
    return width <= max(BAND_WIDTH, np.sqrt(m)) or m * width**2 <= BAND_WORK


def _point_system(rows: np.ndarray, cols: np.ndarray, vals: np.ndarray, m: int,
                  rhs: np.ndarray, reg: float, *, width: int | None) -> np.ndarray:
    """z of one point's system of :func:`_hard_points` (its entries at or below the diagonal):
    by banded Cholesky with a ``width`` when positive definite, else by SuperLU."""
    z = None
    if width is not None:
        band = np.zeros((m, width + 1))
        band.reshape(-1)[cols * (width + 1) + (rows - cols)] = vals
        band[:, 0] += reg
        z = _banded_cholesky(band, rhs.copy())
    if z is None:
        off = rows != cols
        H = sp.csc_matrix(
            (np.concatenate([vals, vals[off]]),
             (np.concatenate([rows, cols[off]]), np.concatenate([cols, rows[off]]))),
            shape=(m, m),
        )
        z = _superlu(sp.csc_matrix(H + reg * sp.identity(m, format="csc")), rhs)
    return z


def _soft_band(
    band_Q: np.ndarray, rank: np.ndarray, r: np.ndarray, C: np.ndarray, wgt: np.ndarray, reg: float
) -> np.ndarray | None:
    """z (3N,) of one point with soft rays by banded Cholesky, image n's coordinates at
    ``3 rank_n + (0, 1, 2)``: the system of :func:`_soft_system` with its diagonal blocks
    ``w_n (I - r_n r_n^T)`` added to ``band_Q``, kron(Q, I3) as a band (:func:`_banded_cholesky`).
    None when it is not numerically positive definite."""
    ray = wgt[:, None, None] * (np.eye(3)[None] - r[:, :, None] * r[:, None, :])  # (N, 3, 3)
    s, u = np.triu_indices(3)
    band = band_Q.copy()
    band[3 * rank[:, None] + s, u - s] += ray[:, s, u]
    band[:, 0] += reg
    rhs = np.empty((r.shape[0], 3))
    rhs[rank] = (
        (0.0 + ray[:, :, 0] * C[:, None, 0]) + ray[:, :, 1] * C[:, None, 1]
    ) + ray[:, :, 2] * C[:, None, 2]
    return _banded_cholesky(band, rhs.ravel())


def _banded_cholesky(band: np.ndarray, rhs: np.ndarray) -> np.ndarray | None:
    """z of ``H z = rhs``, H (m, m) symmetric of bandwidth b given by ``band`` (m, b + 1),
    ``H[i, j]`` at ``band[j, i - j]`` for ``j <= i <= j + b`` (so ``band.T`` is LAPACK's lower
    band storage, in Fortran order); None when H is not numerically positive definite. Both
    ``band`` and ``rhs`` are overwritten. A non-finite H gives a non-finite z or None.

    Lower rather than upper storage: with upper storage LAPACK's banded Cholesky updates with
    strided vectors, and OpenBLAS was found to start its threads for each of those small BLAS
    calls, which costs far more than the work itself when the cores are busy; the unit-stride
    calls of lower storage run without that overhead."""
    try:
        factor = cholesky_banded(band.T, overwrite_ab=True, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    return cho_solve_banded((factor, True), rhs, overwrite_b=True, check_finite=False)


def _superlu(H: sp.csc_matrix, rhs: np.ndarray) -> np.ndarray:
    """z of ``H z = rhs`` by SuperLU: symmetric mode and minimum degree ordering on A^T + A,
    faster than its defaults on these systems (docs/method.md, "Speed")."""
    lu = spla.splu(
        H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
    )
    return lu.solve(rhs)


def _soft_system(
    Q: sp.csr_matrix, r: np.ndarray, C: np.ndarray, wgt: np.ndarray, reg: float
) -> tuple[sp.csc_matrix, np.ndarray]:
    """(H, rhs) of one point with soft rays r (N, 3) of weights ``wgt`` (N,), 3 unknowns per
    image: ``H = kron(Q, I3) + blockdiag(w_n (I - r_n r_n^T)) + reg I``, ``rhs`` the block
    diagonal times C.

    Assembled entry by entry with the floating-point operations (and their order) of those
    sparse sums and products, exact zeros left out as they leave them out, without building the
    N blocks as sparse matrices.
    """
    n = r.shape[0]
    P_perp = np.eye(3)[None] - r[:, :, None] * r[:, None, :]  # (N, 3, 3)
    ray = wgt[:, None, None] * P_perp
    coo = Q.tocoo()
    qi, qk, q = coo.row.astype(np.int64), coo.col.astype(np.int64), coo.data
    three = np.arange(3)
    off = qi != qk
    block = ray.copy()
    on = qi[~off][:, None]
    block[on, three, three] = q[~off][:, None] + ray[on, three, three]
    diag = np.broadcast_to(three[:, None] == three[None, :], (n, 3, 3)).ravel()
    base = 3 * np.arange(n)[:, None, None]
    rows = np.concatenate([(3 * qi[off][:, None] + three).ravel(),
                           np.broadcast_to(base + three[:, None], (n, 3, 3)).ravel()])
    cols = np.concatenate([(3 * qk[off][:, None] + three).ravel(),
                           np.broadcast_to(base + three[None, :], (n, 3, 3)).ravel()])
    vals = np.concatenate([np.repeat(q[off], 3), block.ravel()])
    on_diag = np.concatenate([np.zeros(3 * int(off.sum()), dtype=bool), diag])
    vals = np.where(on_diag, vals + reg, vals)
    keep = vals != 0
    H = sp.csc_matrix((vals[keep], (rows[keep], cols[keep])), shape=(3 * n, 3 * n))
    rhs = (
        (0.0 + ray[:, :, 0] * C[:, None, 0]) + ray[:, :, 1] * C[:, None, 1]
    ) + ray[:, :, 2] * C[:, None, 2]
    return H, rhs.ravel()
