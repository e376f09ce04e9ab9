"""Exact batched solver for small QPs on the probability simplex (the W-step's rows)."""

from __future__ import annotations

import numpy as np


def solve_simplex_qp(
    H: np.ndarray,
    g: np.ndarray,
    mask: np.ndarray | None = None,
    *,
    start: np.ndarray | None = None,
    max_iter: int | None = None,
    tol: float = 1e-12,
) -> np.ndarray:
    """Minimise ``1/2 w^T H w + g^T w`` s.t. ``w >= 0``, ``sum(w) = 1`` for a batch of problems.

    A primal active-set method run on all problems at once (each iteration one batched KKT
    solve), so the answer is exact up to round-off, not an iterative approximation.

    Parameters
    ----------
    H : (B, k, k) float, symmetric positive definite on the masked entries
    g : (B, k) float
    mask : (B, k) bool, optional
        Entries allowed to be non-zero (padding = False); every row needs at least one.
    start : (B, k) float, optional
        A warm start (e.g. the previous solution): rows with positive allowed entries start
        there, scaled onto the simplex, their zero entries held at the bound at first; the
        others start uniform. The answer is the same, in fewer iterations when it is close.

    Returns
    -------
    w : (B, k) float, rows on the simplex, zero outside ``mask``.
    """
    B, k = g.shape
    if mask is None:
        mask = np.ones((B, k), dtype=bool)
    if not mask.any(axis=1).all():
        raise ValueError("every row needs at least one allowed entry")
    max_iter = max_iter or 10 * k + 10
    w = mask / mask.sum(axis=1, keepdims=True)
    if start is not None:
        warm = np.where(mask, np.maximum(start, 0.0), 0.0)
        total = warm.sum(axis=1)
        w[total > 0] = warm[total > 0] / total[total > 0, None]
    active = w == 0  # bounds w_j = 0 held in the working set (all of ~mask)
    done = np.zeros(B, dtype=bool)
    eye = np.eye(k + 1)
    for _ in range(max_iter):
        todo = np.flatnonzero(~done)
        if todo.size == 0:
            break
        Ht, gt, at, wt = H[todo], g[todo], active[todo], w[todo]
        free = ~at
        # KKT of the equality-constrained problem on the free set:
        # [H_FF -1; 1^T 0] [w_F; nu] = [-g_F; 1], fixed entries w_j = 0
        M = np.zeros((todo.size, k + 1, k + 1))
        M[:, :k, :k] = np.where(free[:, :, None] & free[:, None, :], Ht, 0.0)
        M[:, :k, k] = np.where(free, -1.0, 0.0)
        M[:, k, :k] = free
        fixed = np.concatenate([at, np.zeros((todo.size, 1), dtype=bool)], axis=1)
        M[fixed] = eye[np.nonzero(fixed)[1]]
        rhs = np.concatenate([np.where(free, -gt, 0.0), np.ones((todo.size, 1))], axis=1)
        sol = np.linalg.solve(M, rhs[..., None])[..., 0]
        w_star, nu = sol[:, :k], sol[:, k]
        w_star[at] = 0.0
        feasible = (w_star >= -tol).all(axis=1)
        # feasible rows: move to w*, then check the multipliers of the active bounds
        f_idx = np.flatnonzero(feasible)
        if f_idx.size:
            ws = np.maximum(w_star[f_idx], 0.0)
            ws /= ws.sum(axis=1, keepdims=True)
            w[todo[f_idx]] = ws
            grad = np.einsum("bij,bj->bi", Ht[f_idx], ws) + gt[f_idx]
            lam = grad - nu[f_idx, None]
            releasable = at[f_idx] & mask[todo[f_idx]]
            lam = np.where(releasable, lam, np.inf)
            j = np.argmin(lam, axis=1)
            lam_min = lam[np.arange(f_idx.size), j]
            scale = 1.0 + np.abs(gt[f_idx]).max(axis=1) + np.abs(Ht[f_idx]).max(axis=(1, 2))
            release = lam_min < -tol * scale
            done[todo[f_idx[~release]]] = True
            active[todo[f_idx[release]], j[release]] = False
        # infeasible rows: step towards w* until the first free entry hits zero, fix it
        i_idx = np.flatnonzero(~feasible)
        if i_idx.size:
            wc, wsi = wt[i_idx], w_star[i_idx]
            dec = free[i_idx] & (wsi < wc)
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(dec & (wsi < 0), wc / (wc - wsi), np.inf)
            j = np.argmin(ratio, axis=1)
            alpha = np.clip(ratio[np.arange(i_idx.size), j], 0.0, 1.0)
            wn = wc + alpha[:, None] * (wsi - wc)
            wn[np.arange(i_idx.size), j] = 0.0
            wn = np.where(active[todo[i_idx]], 0.0, np.maximum(wn, 0.0))
            w[todo[i_idx]] = wn / wn.sum(axis=1, keepdims=True)
            active[todo[i_idx], j] = True
    return w
