"""The problem data, the D-step of alternating convex search and the cost itself
(docs/method.md, "The paper's model"); the W-step is in :mod:`.wstep`, the X-step in
:mod:`.xstep`.

Shapes: N images, P points; X (N, P, 3); rays (N, P, 3) unit with NaN = unobserved; C (N, 3).
All graph matrices are scipy CSR (N, N). Cost terms are divided by N * P (authors' convention):

    S = |D (I - W) X|^2,  T = l1 sum_ij D_ii W_ij dist_ij,  O = l2 sum_np |(X_np - C_n) x r_np|^2,
    R = l3 sum_ij (D_ii W_ij)^2 c_ij,  c_ij = sum_p (r_ip . r_jp)^2 over points both observe.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


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
    rates: np.ndarray | None = None  # (N,) every image's stream's known frame rate, or None
    subjects: int = 1  # the people whose points the columns hold, P / subjects each in turn

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

