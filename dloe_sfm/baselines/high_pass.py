"""HPF: the high-pass-filter trajectory prior (Valmadre & Lucey, CVPR 2012).

Observed points lie on their viewing rays, ``X_np = C_n + l_np r_np``; unobserved points are free.
The trajectory of every point minimises the energy ``sum_g |G_g X_p|^2`` of a bank of difference
filters applied along the true temporal order: one sparse linear system per point, no parameters.
Needs the full sequencing (the order, not the time stamps).
"""

from __future__ import annotations

from collections.abc import Sequence
from math import comb

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..core.capture import Capture


def difference_matrix(order: np.ndarray, degree: int) -> sp.csr_matrix:
    """Finite-difference filter of ``degree`` along ``order`` (image indices, earliest first).

    Returns G (N - degree, N): row k applies the binomial filter (e.g. [1, -2, 1] for degree 2)
    to images ``order[k], ..., order[k + degree]``. It annihilates polynomials of degree < degree
    in the sample index (degree 2: constant-velocity motion sampled uniformly).
    """
    order = np.asarray(order)
    n = order.size
    taps = np.array([(-1.0) ** (degree - i) * comb(degree, i) for i in range(degree + 1)])
    m = max(n - degree, 0)
    rows = np.repeat(np.arange(m), degree + 1)
    cols = order[(np.arange(m)[:, None] + np.arange(degree + 1)[None, :]).ravel()]
    return sp.csr_matrix((np.tile(taps, m), (rows, cols)), shape=(m, n))


def solve_on_rays(Q: sp.spmatrix, rays: np.ndarray, C: np.ndarray, visible: np.ndarray
                  ) -> np.ndarray:
    """Minimise ``sum_p X_p^T (Q kron I3) X_p`` with observed points pinned to their rays.

    Q (N, N) symmetric positive semi-definite sparse, rays (N, P, 3) unit, C (N, 3), visible
    (N, P) bool. Unknowns per point: a depth per observed image (``X_np = C_n + l_np r_np``) and
    the three coordinates of every unobserved one. Returns X (N, P, 3).
    """
    n, p = visible.shape
    Q3 = sp.kron(sp.csr_matrix(Q), sp.identity(3), format="csr")
    reg = 1e-10 * max(float(np.abs(Q.diagonal()).mean()), 1e-300)
    r0 = np.nan_to_num(rays)
    X = np.empty((n, p, 3))
    for j in range(p):
        obs = visible[:, j]
        seen, miss = np.flatnonzero(obs), np.flatnonzero(~obs)
        # X_p (3N) = c + B z, z = (depths of seen images, xyz of missing ones)
        rows = np.concatenate([(3 * seen[:, None] + np.arange(3)).ravel(),
                               (3 * miss[:, None] + np.arange(3)).ravel()])
        cols = np.concatenate([np.repeat(np.arange(seen.size), 3),
                               seen.size + np.arange(3 * miss.size)])
        vals = np.concatenate([r0[seen, j].ravel(), np.ones(3 * miss.size)])
        B = sp.csr_matrix((vals, (rows, cols)), shape=(3 * n, seen.size + 3 * miss.size))
        c = np.where(obs[:, None], C, 0.0).ravel()
        H = sp.csc_matrix(B.T @ Q3 @ B + reg * sp.identity(B.shape[1]))
        z = spla.splu(H, permc_spec="MMD_AT_PLUS_A").solve(-(B.T @ (Q3 @ c)))
        X[:, j] = (c + B @ z).reshape(n, 3)
    return X


def high_pass_filter(capture: Capture, times: np.ndarray, *, degrees: Sequence[int] = (1, 2)
                     ) -> np.ndarray:
    """HPF reconstruction along the true order of ``times`` (N,), returns (N, P, 3) world units.

    ``degrees``: the difference filters in the bank, each with unit weight; the default is the
    first + second difference bank. Each filter has zero energy on its own class of motion: with
    ``(2,)`` constant-velocity motion is reproduced exactly, with ``(1,)`` or ``(1, 2)`` static
    points. Only the order of ``times`` is used: the filters assume uniform sampling along it.
    """
    order = np.argsort(np.asarray(times), kind="stable")
    n = order.size
    Q = sp.csr_matrix((n, n))
    for degree in degrees:
        G = difference_matrix(order, degree)
        Q = Q + G.T @ G
    return solve_on_rays(Q, capture.rays(), capture.C, capture.visible)
