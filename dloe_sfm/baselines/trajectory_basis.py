"""TB: trajectory-basis reconstruction (Park, Shiratori, Matthews & Sheikh, ECCV 2010 / IJCV 2015).

Every point moves as ``X_p(t) = sum_k theta_k(t) beta_pk`` with a continuous DCT basis over the
true time span; the coefficients follow from the linear projection equations by least squares. The
number of bases K is chosen by cross-validation on held-out reprojection error. Needs time stamps.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.linalg as sla

from ..core.capture import Capture, project

logger = logging.getLogger("dloe_sfm")


def dct_basis(times: np.ndarray, num_bases: int, span: tuple[float, float] | None = None
              ) -> np.ndarray:
    """Continuous DCT basis ``theta_k(t) = cos(pi k s)``, ``s = (t - t0) / (t1 - t0)`` in [0, 1].

    times (N,) seconds, ``span`` (t0, t1) (default: the range of ``times``) -> (N, num_bases).
    """
    t = np.asarray(times, dtype=np.float64)
    t0, t1 = span if span is not None else (float(t.min()), float(t.max()))
    s = (t - t0) / max(t1 - t0, 1e-300)
    return np.cos(np.pi * np.arange(num_bases)[None, :] * s[:, None])


def projection_equations(capture: Capture) -> tuple[np.ndarray, np.ndarray]:
    """The two linear equations ``e . X = e . C`` of every observation of ``x ~ K R (X - C)``.

    With ``(a, b, 1) ~ K^-1 [x; 1]``: ``e1 = R_1 - a R_3``, ``e2 = R_2 - b R_3`` (rows of R), i.e.
    the cross-product form ``[u]_x R (X - C) = 0`` without its dependent third row.
    Returns E (N, P, 2, 3) and rhs (N, P, 2), NaN where unobserved.
    """
    n, p = capture.x.shape[:2]
    h = np.concatenate([capture.x, np.ones((n, p, 1))], axis=2)
    u = np.einsum("nij,npj->npi", np.linalg.inv(capture.K), h)
    u = u[..., :2] / u[..., 2:3]
    R = capture.R
    E = R[:, None, :2, :] - u[..., :, None] * R[:, None, None, 2, :]  # (N, P, 2, 3)
    rhs = np.einsum("npkj,nj->npk", E, capture.C)
    return E, rhs


def _design(theta: np.ndarray, E: np.ndarray) -> np.ndarray:
    """Least-squares design (2m, 3K) of coefficients beta (K, 3) row-major: basis rows theta
    (m, K), equations E (m, 2, 3). The first 3k columns are the design with k bases."""
    return (theta[:, None, :, None] * E[:, :, None, :]).reshape(-1, theta.shape[1] * 3)


def _fit_point(theta: np.ndarray, E: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Least-squares coefficients (K, 3): equations E (m, 2, 3), rhs (m, 2), basis rows (m, K)."""
    beta, *_ = np.linalg.lstsq(_design(theta, E), rhs.ravel(), rcond=None)
    return beta.reshape(-1, 3)


def select_num_bases(capture: Capture, times: np.ndarray, *, max_bases: int = 60,
                     holdout: float = 0.2, tolerance: float = 0.01, seed: int = 0
                     ) -> tuple[int, np.ndarray]:
    """Number of DCT bases by cross-validation on held-out reprojection error.

    A random ``holdout`` fraction of the observations is left out, trajectories with K = 1 ..
    ``max_bases`` bases are fitted to the rest, and each K scores the mean pixel distance between
    the held-out observations and the reprojected fit. The chosen K is the smallest whose score is
    within ``tolerance`` (relative) of the best (the simplest model among equally good ones).

    Returns (K, scores (max_bases,) px; inf where K is not determined by the kept equations).
    """
    t = np.asarray(times, dtype=np.float64)
    vis = capture.visible
    p = vis.shape[1]
    rng = np.random.default_rng(seed)
    held = vis & (rng.random(vis.shape) < holdout)
    kept = vis & ~held
    E, rhs = projection_equations(capture)
    # K = 1 .. k_max with every point's kept equations outnumbering its 3K unknowns
    k_max = min(max_bases, int(2 * kept.sum(axis=0).min()) // 3)
    theta = dct_basis(t, k_max, (float(t.min()), float(t.max())))
    # nested least squares: one QR of the k_max design per point serves every K (its first 3K
    # columns are the design with K bases, so the fit is R[:3K, :3K]^-1 (Q^T b)[:3K])
    beta = np.zeros((k_max, p, 3 * k_max))
    for j in range(p):
        obs = kept[:, j]
        q, r = np.linalg.qr(_design(theta[obs], E[obs, j]))
        qb = q.T @ rhs[obs, j].ravel()
        for k in range(1, k_max + 1):
            m = 3 * k
            beta[k - 1, j, :m] = sla.solve_triangular(r[:m, :m], qb[:m], check_finite=False)
    scores = np.full(max_bases, np.inf)
    for k in range(1, k_max + 1):
        X = np.einsum("nk,pkc->npc", theta[:, :k], beta[k - 1, :, :3 * k].reshape(p, k, 3))
        x_hat = project(X, capture.K, capture.R, capture.C)
        err = np.linalg.norm(x_hat[held] - capture.x[held], axis=1).mean()
        scores[k - 1] = err if np.isfinite(err) else np.inf
    best = np.min(scores)
    num = int(np.flatnonzero(scores <= best * (1.0 + tolerance) + 1e-12)[0]) + 1
    logger.debug("TB: K = %d (held-out reprojection %.3f px)", num, scores[num - 1])
    return num, scores


def trajectory_basis(capture: Capture, times: np.ndarray, *, num_bases: int | None = None,
                     max_bases: int = 60, holdout: float = 0.2, seed: int = 0) -> np.ndarray:
    """TB reconstruction: per point a DCT trajectory fitted to all observations, (N, P, 3).

    ``times`` (N,) true time stamps (seconds). ``num_bases`` K fixes the basis size; ``None``
    chooses it with :func:`select_num_bases` (then the fit is redone on all observations).
    The equations are algebraic (in normalised image coordinates, not pixels), as in Park et al.
    """
    t = np.asarray(times, dtype=np.float64)
    if num_bases is None:
        num_bases, _ = select_num_bases(capture, t, max_bases=max_bases, holdout=holdout, seed=seed)
    vis = capture.visible
    E, rhs = projection_equations(capture)
    theta = dct_basis(t, num_bases)
    X = np.empty((t.size, vis.shape[1], 3))
    for j in range(vis.shape[1]):
        obs = vis[:, j]
        X[:, j] = theta @ _fit_point(theta[obs], E[obs, j], rhs[obs, j])
    return X
