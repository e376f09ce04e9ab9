"""The problem data, the D- and X-steps of alternating convex search and the cost itself
(docs/method.md, "The paper's model"); the W-step is in :mod:`.wstep`.

Shapes: N images, P points; X (N, P, 3); rays (N, P, 3) unit with NaN = unobserved; C (N, 3).
All graph matrices are scipy CSR (N, N). Cost terms are divided by N * P (authors' convention):

    S = |D (I - W) X|^2,  T = l1 sum_ij D_ii W_ij dist_ij,  O = l2 sum_np |(X_np - C_n) x r_np|^2,
    R = l3 sum_ij (D_ii W_ij)^2 c_ij,  c_ij = sum_p (r_ip . r_jp)^2 over points both observe.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


@dataclass(kw_only=True)
class Problem:
    """Fixed data of one solve, in normalised units."""

    rays: np.ndarray  # (N, P, 3), NaN = unobserved
    C: np.ndarray  # (N, 3)
    weights: np.ndarray  # (N, P) observation weights, 0 = unobserved
    streams: np.ndarray  # (N,) stream ids, lone photos already given their own
    view_dirs: np.ndarray  # (N, 3) mean viewing direction of each image
    chain: sp.csr_matrix  # (N, N) intra-stream chain prior (rows sum to 1 or 0)
    prior: np.ndarray  # (N,) weight a_i of the chain prior in row i (0 for lone photos)

    @property
    def visible(self) -> np.ndarray:
        return self.weights > 0


def chain_matrix(streams: np.ndarray, frames: np.ndarray) -> sp.csr_matrix:
    """W_chain: the previous and next image of the same stream, barycentric in frame number.

    (1/2, 1/2 when no frame was dropped, as in the authors' code; a video's frame numbers are
    proportional to time.) A stream's first and last images get an empty row (the authors give
    them weight 1 to their one neighbour, which pulls a moving point back towards it: a bias
    measured at the clip ends).
    """
    n = streams.size
    order = np.lexsort((frames, streams))
    s = streams[order]
    interior = np.zeros(n, dtype=bool)
    interior[1:-1] = (s[1:-1] == s[:-2]) & (s[1:-1] == s[2:])
    pos = np.flatnonzero(interior)
    mid, prev, nxt = order[pos], order[pos - 1], order[pos + 1]
    f = frames.astype(np.float64)
    w_prev = (f[nxt] - f[mid]) / (f[nxt] - f[prev])
    rows = np.concatenate([mid, mid])
    cols = np.concatenate([prev, nxt])
    return sp.csr_matrix((np.concatenate([w_prev, 1.0 - w_prev]), (rows, cols)), shape=(n, n))


def temporal_ends(f: np.ndarray, streams: np.ndarray) -> np.ndarray:
    """(N,) bool: images with no image of another stream before them, or none after, along f.

    Their W rows could only extrapolate (a convex combination of later, or of earlier, shapes),
    so they get no smoothness row of their own; their neighbours' rows still place them.
    """
    ids, inv = np.unique(streams, return_inverse=True)
    if ids.size < 2:
        return np.zeros(f.size, dtype=bool)
    lo = np.full(ids.size, np.inf)
    hi = np.full(ids.size, -np.inf)
    np.minimum.at(lo, inv, f)
    np.maximum.at(hi, inv, f)

    def others(vals: np.ndarray, pick) -> np.ndarray:
        # the extreme over all streams but one's own: best and second best suffice
        order = pick(vals)
        first, second = order[0], order[1]
        return np.where(inv == first, vals[second], vals[first])

    return (f < others(lo, np.argsort)) | (f > others(hi, lambda v: np.argsort(-v)))


def full_weights(W_var: sp.csr_matrix, prob: Problem) -> sp.csr_matrix:
    """W = (1 - a_i) W_var + a_i W_chain row by row."""
    return sp.csr_matrix(sp.diags(1.0 - prob.prior) @ W_var + sp.diags(prob.prior) @ prob.chain)


def ray_coherence(rays: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """c_ij = sum_p (r_ip . r_jp)^2 over points observed in both images, for pairs (rows, cols)."""
    r = np.nan_to_num(rays)
    out = np.empty(rows.size)
    step = 1 << 16
    for lo in range(0, rows.size, step):
        a, b = rows[lo : lo + step], cols[lo : lo + step]
        out[lo : lo + step] = (np.einsum("epk,epk->ep", r[a], r[b]) ** 2).sum(axis=1)
    return out


def row_terms(
    X: np.ndarray,
    W: sp.csr_matrix,
    prob: Problem,
    *,
    lambda3: float,
    embedding: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-image cost pieces s, t, rho: S_i = d_i^2 s_i, T_i = d_i t_i, R_i = d_i^2 rho_i."""
    n = X.shape[0]
    Xf = X.reshape(n, -1)
    s = ((Xf - W @ Xf) ** 2).sum(axis=1)
    coo = W.tocoo()
    if embedding is None:
        dist = ((Xf[coo.row] - Xf[coo.col]) ** 2).sum(axis=1)
    else:
        dist = (embedding[coo.row] - embedding[coo.col]) ** 2
    t = np.bincount(coo.row, coo.data * dist, minlength=n)
    rho = np.zeros(n)
    if lambda3 > 0:
        coh = ray_coherence(prob.rays, coo.row, coo.col)
        rho = np.bincount(coo.row, coo.data**2 * coh, minlength=n)
    return s, t, rho


def d_step(
    X: np.ndarray,
    W: sp.csr_matrix,
    prob: Problem,
    *,
    lambda1: float,
    lambda3: float,
    floor: float,
    embedding: np.ndarray | None = None,
) -> np.ndarray:
    """Optimal degrees: min sum_i d_i^2 (s_i + l3 rho_i) + l1 d_i t_i s.t. sum d = N, d >= floor.

    Separable with one equality constraint, solved exactly by water-filling on its multiplier:
    d_i(mu) = max(floor, (mu - l1 t_i) / (2 a_i)), with mu found by bisection.
    """
    n = X.shape[0]
    s, t, rho = row_terms(X, W, prob, lambda3=lambda3, embedding=embedding)
    quad = s + lambda3 * rho
    quad = np.maximum(quad, 1e-12 * max(quad.max(), 1e-300))
    lin = lambda1 * t
    if floor * n >= n:
        return np.full(n, 1.0)

    def degrees(mu: float) -> np.ndarray:
        return np.maximum(floor, (mu - lin) / (2.0 * quad))

    lo = float((lin + 2 * quad * floor).min())  # here every d_i sits on the floor
    hi = float((lin + 2 * quad * n).max())  # here every d_i >= n
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if degrees(mid).sum() > n:
            hi = mid
        else:
            lo = mid
        if hi - lo <= 1e-15 * max(abs(hi), 1e-300):
            break
    return degrees(0.5 * (lo + hi))


def smoothness_matrix(W: sp.csr_matrix, D: np.ndarray, lambda1: float) -> sp.csr_matrix:
    """Q = (D (I - W))^T D (I - W) + l1 M, M the Laplacian form of sum_ij A_ij |X_i - X_j|^2."""
    n = W.shape[0]
    L = sp.diags(D) @ (sp.identity(n, format="csr") - W)
    A = sp.diags(D) @ W
    deg = np.asarray(A.sum(axis=1)).ravel() + np.asarray(A.sum(axis=0)).ravel()
    M = sp.diags(deg) - A - A.T
    return sp.csr_matrix(L.T @ L + lambda1 * M)


def x_step(
    W: sp.csr_matrix,
    D: np.ndarray,
    prob: Problem,
    *,
    lambda1: float,
    lambda2: float,
    X_prev: np.ndarray,
) -> np.ndarray:
    """Optimal X for fixed W, D: per point p a sparse linear system.

    With ``lambda2 = inf`` observed points are pinned to their rays, ``X_np = C_n + l_np r_np``,
    and only the depths l_np (plus the 3 coordinates of unobserved points) are unknown. Otherwise
    the O term ``l2 w_np |(X_np - C_n) x r_np|^2`` joins the smoothness form Q. X_prev fills in
    points no equation reaches (never the case on a connected graph).
    """
    n, p = prob.rays.shape[:2]
    Q = smoothness_matrix(W, D, lambda1)
    hard = np.isinf(lambda2)
    Q3 = sp.kron(Q, sp.identity(3), format="csr") if hard else None
    vis = prob.visible
    r0 = np.nan_to_num(prob.rays)
    X = np.empty((n, p, 3))
    reg = 1e-10 * max(Q.diagonal().mean(), 1e-300)
    for j in range(p):
        if hard:
            obs = vis[:, j]
            # X_vec (3N) = c + B z: one depth column per observed image, 3 unit columns otherwise
            n_obs = int(obs.sum())
            col_of = np.empty(n, dtype=np.int64)
            col_of[obs] = np.arange(n_obs)
            miss = np.flatnonzero(~obs)
            col_of[miss] = n_obs + 3 * np.arange(miss.size)
            rows_o = (3 * np.flatnonzero(obs)[:, None] + np.arange(3)).ravel()
            cols_o = np.repeat(col_of[obs], 3)
            vals_o = r0[obs, j].ravel()
            rows_m = (3 * miss[:, None] + np.arange(3)).ravel()
            cols_m = (col_of[miss][:, None] + np.arange(3)).ravel()
            Bm = sp.csr_matrix(
                (
                    np.concatenate([vals_o, np.ones(rows_m.size)]),
                    (np.concatenate([rows_o, rows_m]), np.concatenate([cols_o, cols_m])),
                ),
                shape=(3 * n, n_obs + 3 * miss.size),
            )
            c = np.where(obs[:, None], prob.C, 0.0).ravel()
            H = sp.csc_matrix(Bm.T @ Q3 @ Bm)
            rhs = -(Bm.T @ (Q3 @ c))
            H = sp.csc_matrix(H + reg * sp.identity(H.shape[0], format="csc"))
        else:
            H, rhs = _soft_system(Q, r0[:, j], prob.C, lambda2 * prob.weights[:, j], reg)
            c = np.zeros(3 * n)
            Bm = None
        # symmetric mode + minimum degree on A^T + A: faster than SuperLU's defaults here
        # (docs/method.md, "Speed")
        lu = spla.splu(
            H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
        z = lu.solve(rhs)
        X[:, j] = (c + (Bm @ z if Bm is not None else z)).reshape(n, 3)
    bad = ~np.isfinite(X)
    X[bad] = X_prev[bad]
    return X


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


def total_cost(
    X: np.ndarray,
    W: sp.csr_matrix,
    D: np.ndarray,
    prob: Problem,
    *,
    lambda1: float,
    lambda2: float,
    lambda3: float,
) -> dict[str, float]:
    """The four terms S, T, O, R (Euclidean T) and their sum, each divided by N * P."""
    n, p = X.shape[:2]
    s, t, rho = row_terms(X, W, prob, lambda3=lambda3)
    terms = {
        "S": float((D**2 * s).sum()),
        "T": lambda1 * float((D * t).sum()),
        "R": lambda3 * float((D**2 * rho).sum()),
        "O": 0.0,
    }
    if np.isfinite(lambda2):
        r0 = np.nan_to_num(prob.rays)
        cross = np.cross(X - prob.C[:, None, :], r0)
        terms["O"] = lambda2 * float((prob.weights * (cross**2).sum(axis=2)).sum())
    terms = {k: v / (n * p) for k, v in terms.items()}
    terms["total"] = sum(terms.values())
    return terms

