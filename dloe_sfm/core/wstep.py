"""The W-step of alternating convex search: candidate neighbours and the optimal W_var rows
(docs/method.md, "The paper's model"). Shapes and conventions as in :mod:`.steps`."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..errors import InputError
from .simplex_qp import solve_simplex_qp
from .steps import Problem, ray_coherence


def select_candidates(
    features: np.ndarray,
    prob: Problem,
    k: int,
    *,
    min_angle: float,
    keep: sp.csr_matrix | None = None,
) -> np.ndarray:
    """k nearest admissible neighbours of every image in ``features`` space, (N, k') int, -1 = pad.

    Admissible: another stream, and viewing directions at least ``min_angle`` degrees from
    (anti)parallel (the static-camera / opposite-camera degeneracy). With a 1-D ``features``
    (a time-line embedding) the k are split evenly before and after the image, so W interpolates
    between temporal neighbours instead of extrapolating from one side. The support of ``keep``
    (previous W) is always included so a W-step never increases the cost. A k beyond the N - 1
    other images is taken as N - 1.
    """
    n = features.shape[0]
    k = min(k, max(n - 1, 1))
    cos_max = np.cos(np.deg2rad(min_angle))

    def admissible(rows: np.ndarray, nb: np.ndarray) -> np.ndarray:
        ok = prob.streams[nb] != prob.streams[rows, None]
        ok &= np.abs(np.einsum("ak,abk->ab", prob.view_dirs[rows], prob.view_dirs[nb])) < cos_max
        return ok

    if features.shape[1] == 1:
        found = _bracket(features[:, 0], k, admissible)
    else:
        found = _nearest(features, k, admissible)
    if keep is not None and keep.nnz:
        width = k + int(np.diff(keep.indptr).max())
        merged = np.full((n, width), -1)
        merged[:, :k] = found
        coo = keep.tocoo()
        order = np.lexsort((coo.col, coo.row))
        r, c = coo.row[order], coo.col[order]
        pos = np.arange(r.size) - keep.indptr[r]
        merged[r, k + pos] = c
        # drop duplicates (a previous neighbour that is also among the k nearest)
        srt = np.sort(merged, axis=1)
        dup = np.zeros_like(srt, dtype=bool)
        dup[:, 1:] = (srt[:, 1:] == srt[:, :-1]) & (srt[:, 1:] >= 0)
        srt[dup] = -1
        found = -np.sort(-srt, axis=1)
        found = found[:, : int((found >= 0).sum(axis=1).max())]
    alone = int((found < 0).all(axis=1).sum())
    if alone:
        raise InputError(
            f"{alone} of {n} images: no image of another stream views them at least "
            f"{min_angle:g} degrees from (anti)parallel (option 'min_ray_angle')"
        )
    return found


def _nearest(features: np.ndarray, k: int, admissible) -> np.ndarray:
    """(N, k) indices of the k nearest admissible rows of features (-1 = none left)."""
    n = features.shape[0]
    tree = cKDTree(features)
    found = np.full((n, k), -1)
    q = min(n, 4 * k + 1)
    pending = np.arange(n)
    while pending.size:
        _, nb = tree.query(features[pending], k=q)
        nb = np.atleast_2d(nb)
        ok = nb < n
        nbc = np.where(ok, nb, 0)
        ok &= admissible(pending, nbc)
        enough = (ok.sum(axis=1) >= k) | (q >= n)
        sel = pending[enough]
        idx = np.argsort(~ok[enough], axis=1, kind="stable")[:, :k]
        valid = np.take_along_axis(ok[enough], idx, axis=1)
        found[sel] = np.where(valid, np.take_along_axis(nbc[enough], idx, axis=1), -1)
        pending = pending[~enough]
        q = min(n, 4 * q)
    return found


def _bracket(f: np.ndarray, k: int, admissible) -> np.ndarray:
    """(N, k) indices: the ceil(k/2) nearest admissible images before f_i and floor(k/2) after."""
    n = f.size
    order = np.argsort(f, kind="stable")
    pos = np.empty(n, dtype=np.int64)
    pos[order] = np.arange(n)
    halves = ((k + 1) // 2, -1), (k // 2, 1)
    found = np.full((n, k), -1)
    col = 0
    for want, step in halves:
        if want == 0:
            continue
        got = np.zeros(n, dtype=np.int64)
        window = 4 * want + 4
        pending = np.arange(n)
        offset = 1
        while pending.size:
            steps = offset + np.arange(window)
            p = pos[pending, None] + step * steps[None, :]
            inside = (p >= 0) & (p < n)
            nb = order[np.clip(p, 0, n - 1)]
            ok = inside & admissible(pending, nb)
            for c in range(window):
                take = ok[:, c] & (got[pending] < want)
                rows = pending[take]
                found[rows, col + got[rows]] = nb[take, c]
                got[rows] += 1
            more = (got[pending] < want) & inside[:, -1]
            pending = pending[more]
            offset += window
        col += want
    return found


def w_step(
    X: np.ndarray,
    D: np.ndarray,
    cand: np.ndarray,
    prob: Problem,
    *,
    lambda1: float,
    lambda3: float,
    ridge: float,
    embedding: np.ndarray | None = None,
    start: sp.csr_matrix | None = None,
) -> sp.csr_matrix:
    """Optimal W_var rows on their candidate sets (each row a QP on the simplex, solved exactly;
    ``start``, e.g. the previous W_var, a warm start for it).

    Row i minimises, with W = (1 - a) W_var + a W_chain and everything else fixed:
    ``|X_i - (W X)_i|^2 + (l1 / D_ii) sum_j W_ij dist_ij + l3 sum_j W_ij^2 c_ij + ridge |w|^2``,
    where dist_ij = (f_i - f_j)^2 with an embedding f (spectral prior) or |X_i - X_j|^2.
    Returns W_var (N, N) CSR with rows on the simplex.
    """
    n = X.shape[0]
    Xf = X.reshape(n, -1)
    a = prob.prior
    mask = cand >= 0
    cc = np.where(mask, cand, 0)
    target = Xf - a[:, None] * (prob.chain @ Xf)  # X_i - a (W_chain X)_i
    E = target[:, :, None] - (1.0 - a)[:, None, None] * np.transpose(
        Xf[cc], (0, 2, 1)
    )  # (N, 3P, k)
    H = np.transpose(E, (0, 2, 1)) @ E  # (N, k, k) Gram matrices, by batched BLAS
    if embedding is None:
        dist = ((Xf[:, None, :] - Xf[cc]) ** 2).sum(axis=2)
    else:
        dist = (embedding[:, None] - embedding[cc]) ** 2
    rows = np.repeat(np.arange(n), cand.shape[1])
    coh = ray_coherence(prob.rays, rows, cc.ravel()).reshape(cand.shape)
    scale = np.trace(H, axis1=1, axis2=2) / cand.shape[1]
    diag = lambda3 * (1.0 - a[:, None]) ** 2 * coh + ridge + 1e-12 * scale[:, None]
    H[:, np.arange(cand.shape[1]), np.arange(cand.shape[1])] += diag
    # a row with D_ii = 0 carries no cost; any simplex point will do, keep the T-term ranking
    g = (lambda1 / (2.0 * np.where(D > 0, D, 1.0)))[:, None] * (1.0 - a[:, None]) * dist
    warm = None
    if start is not None and start.nnz:  # start's entries at (row, candidate), else 0
        keys = np.repeat(np.arange(n), np.diff(start.indptr)) * n + start.indices
        order = np.argsort(keys, kind="stable")
        want = rows * n + cc.ravel()
        at = np.minimum(np.searchsorted(keys, want, sorter=order), keys.size - 1)
        hit = keys[order[at]] == want
        warm = np.where(hit, start.data[order[at]], 0.0).reshape(cand.shape)
    w = solve_simplex_qp(H, g, mask, start=warm)
    keep = mask & (w > 0)
    return sp.csr_matrix((w[keep], (np.nonzero(keep)[0], cc[keep])), shape=(n, n))
