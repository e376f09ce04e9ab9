"""Per-image checks of a solution and its reconstructability (docs/method.md, "Per-image status
and reconstructability").

After the solve every image's shape is checked against its own rays (reprojection residual of
its observed points) and against its temporal neighbours (distance from the graph's prediction
``W X``), and every (image, point) gets a depth standard deviation from the hard-ray X-step's
system ``B^T Q B l = b``: ``sd = sigma sqrt(diag((B^T Q B)^-1))``, ``sigma`` the solution's
residual. Thresholds are robust z-scores against the capture's own median / MAD over images.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.sparse.csgraph import reverse_cuthill_mckee

from .capture import Capture
from .result import Result
from .robust import predicted, residuals_px
from .steps import smoothness_matrix

Z_FLAG = 6.0
"""Robust z-score (against median / 1.4826 MAD over images) beyond which a statistic flags."""
RATIO_FLAG = 3.0
"""...and the factor above the images' median it must also exceed (a MAD near 0 flags nothing)."""
WEAK_POINT_RATIO = 10.0
"""An unobserved point whose position sd exceeds this many times the median depth sd of the
observed points has no support (NaN in the exports)."""
BLOCK = 256
"""Columns of the identity solved at once for the diagonal of an inverse."""
STATUS = ("ok", "uncertain", "inconsistent")


def inverse_diagonal(H: sp.spmatrix) -> np.ndarray:
    """Exact diagonal of ``H^-1`` (H sparse symmetric positive definite): reordered into a band
    (reverse Cuthill-McKee), its banded Cholesky factor (LAPACK), then solves on blocks of
    ``BLOCK`` identity columns keeping only their diagonal entries: O(m b^2) to factor and
    O(m^2 b) to solve for bandwidth b, never the dense inverse. Inf when H is numerically
    singular (nothing determines the unknowns)."""
    m = H.shape[0]
    H = sp.csr_matrix(H)
    perm = reverse_cuthill_mckee(H, symmetric_mode=True)
    band = H[perm][:, perm].tocoo()
    upper = band.col >= band.row
    rows, cols, vals = band.row[upper], band.col[upper], band.data[upper]
    width = int((cols - rows).max()) if rows.size else 0
    ab = np.zeros((width + 1, m))
    ab[width + rows - cols, cols] = vals  # LAPACK upper band storage
    try:
        factor = cholesky_banded(ab)
    except np.linalg.LinAlgError:
        return np.full(m, np.inf)
    out = np.empty(m)
    for lo in range(0, m, BLOCK):
        hi = min(lo + BLOCK, m)
        E = np.zeros((m, hi - lo))
        E[np.arange(lo, hi), np.arange(hi - lo)] = 1.0
        out[lo:hi] = cho_solve_banded((factor, False), E)[np.arange(lo, hi), np.arange(hi - lo)]
    diag = np.empty(m)
    diag[perm] = out
    return diag


def depth_variances(Q: sp.csr_matrix, rays: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """(N, P) diagonal of the inverse of each point's hard-ray system, up to the residual scale.

    Point p: ``X_p = c + B z`` with one depth column ``r_np`` per observed image and three unit
    columns per unobserved one (as ``steps.x_step`` with ``lambda2 = inf``); the system is
    ``B^T (Q kron I3) B``. Observed entries: the depth's variance factor; unobserved: the trace
    of the position's 3 x 3 block.
    """
    n, p = observed.shape
    Q3 = sp.kron(Q, sp.identity(3), format="csr")
    reg = 1e-10 * max(Q.diagonal().mean(), 1e-300)
    r0 = np.nan_to_num(rays)
    out = np.empty((n, p))
    for j in range(p):
        obs = observed[:, j]
        seen, miss = np.flatnonzero(obs), np.flatnonzero(~obs)
        col_of = np.empty(n, dtype=np.int64)
        col_of[seen] = np.arange(seen.size)
        col_of[miss] = seen.size + 3 * np.arange(miss.size)
        rows = np.concatenate([(3 * seen[:, None] + np.arange(3)).ravel(),
                               (3 * miss[:, None] + np.arange(3)).ravel()])
        cols = np.concatenate([np.repeat(col_of[seen], 3),
                               (col_of[miss][:, None] + np.arange(3)).ravel()])
        vals = np.concatenate([r0[seen, j].ravel(), np.ones(3 * miss.size)])
        B = sp.csr_matrix((vals, (rows, cols)), shape=(3 * n, seen.size + 3 * miss.size))
        H = B.T @ Q3 @ B + reg * sp.identity(B.shape[1])
        diag = inverse_diagonal(H)
        out[seen, j] = diag[: seen.size]
        out[miss, j] = diag[seen.size :].reshape(-1, 3).sum(axis=1)
    return out


def robust_stats(values: np.ndarray, floor: float = 0.0) -> tuple[float, float]:
    """Median and ``max(1.4826 MAD, floor)`` of the finite ``values`` (NaN, 1 when none)."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return np.nan, 1.0
    med = float(np.median(finite))
    return med, max(1.4826 * float(np.median(np.abs(finite - med))), floor, 1e-300)


def outlying(values: np.ndarray, stats: tuple[float, float], ratio_to: np.ndarray | float
             ) -> np.ndarray:
    """(N,) bool: robust z against ``stats`` > ``Z_FLAG`` and ``ratio_to`` (the same statistic
    on a linear scale) > ``RATIO_FLAG`` x its median."""
    med, spread = stats
    ratio = np.asarray(ratio_to, dtype=np.float64)
    finite = ratio[np.isfinite(ratio)]
    if finite.size == 0:
        return np.zeros(values.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        return ((values - med) / spread > Z_FLAG) & (ratio > RATIO_FLAG * np.median(finite))


def neighbour_deviation(X: np.ndarray, W: sp.csr_matrix, observed: np.ndarray,
                        excluded: np.ndarray) -> np.ndarray:
    """(N,) RMS distance of each image's observed points (all when none) from the prediction of
    its graph row with the ``excluded`` images' columns dropped (row renormalised); NaN for an
    image with no neighbour left."""
    Wk = sp.csr_matrix(W @ sp.diags((~excluded).astype(np.float64)))
    sums = np.asarray(Wk.sum(axis=1)).ravel()
    with np.errstate(divide="ignore"):
        Wk = sp.csr_matrix(sp.diags(np.where(sums > 0, 1.0 / sums, 0.0)) @ Wk)
    d2 = ((X - predicted(Wk, X)) ** 2).sum(axis=2)
    pick = np.where(observed.any(axis=1)[:, None], observed, True)
    dev = np.sqrt((d2 * pick).sum(axis=1) / pick.sum(axis=1))
    dev[sums <= 0] = np.nan
    return dev


def typical_step(X: np.ndarray, W: sp.csr_matrix) -> float:
    """Median over images of the W-weighted RMS distance to their neighbours' shapes (1 when
    nothing moves)."""
    coo = W.tocoo()
    d = np.sqrt(((X[coo.row] - X[coo.col]) ** 2).sum(axis=2).mean(axis=1))
    n = X.shape[0]
    sums = np.bincount(coo.row, coo.data, minlength=n)
    step = np.bincount(coo.row, coo.data * d, minlength=n)[sums > 0] / sums[sums > 0]
    typical = float(np.median(step)) if step.size else 0.0
    return typical if typical > 0 else 1.0


def assess(capture: Capture, result: Result, *, lambda1: float) -> Result:
    """``result`` with ``image_status``, ``status_reason``, ``residual_px``,
    ``neighbour_deviation``, ``depth_sd`` and ``supported`` filled in.

    ``capture`` is the solver's input (``result.solved`` replaces it when set); ``lambda1`` the
    compactness weight of the X-step's system.
    """
    started = time.perf_counter()
    cap = result.solved if result.solved is not None else capture
    X = result.X
    n = X.shape[0]
    observed = cap.weights > 0
    observed[result.outliers[:, 0], result.outliers[:, 1]] = False

    res = residuals_px(cap, X)
    res[~observed] = np.nan
    seen = observed.any(axis=1)
    detected = capture.visible.reshape(n, -1).any(axis=1)
    residual = np.full(n, np.nan)
    residual[seen] = np.nanmedian(res[seen], axis=1)
    # the capture's own pixel scale: how well the graph predicts the observations
    pred = residuals_px(cap, predicted(result.W, X))
    pred_scale = float(np.nanmedian(pred[observed])) if np.isfinite(pred[observed]).any() else 0
    bad_residual = outlying(residual, robust_stats(residual, pred_scale), residual)

    step = typical_step(X, result.W)
    deviation = neighbour_deviation(X, result.W, observed, np.zeros(n, dtype=bool)) / step
    # spread at least one step: the clip's ends extrapolate by about one
    stats = robust_stats(deviation, 1.0)
    bad_neighbour = np.zeros(n, dtype=bool)
    while True:
        # flag the worst image, then re-predict its neighbours without it
        fresh = outlying(deviation, stats, deviation) & ~bad_neighbour
        if not fresh.any():
            break
        bad_neighbour[np.flatnonzero(fresh)[np.argmax(deviation[fresh])]] = True
        deviation = neighbour_deviation(X, result.W, observed, bad_neighbour) / step

    Q = smoothness_matrix(result.W, result.D, lambda1)
    Xf = X.reshape(n, -1)
    resid2 = float((Xf * (Q @ Xf)).sum())
    sigma = np.sqrt(max(resid2, 0.0) / max(2 * int(observed.sum()), 1))
    rays = cap.rays()
    depth_sd = sigma * np.sqrt(np.maximum(depth_variances(Q, rays, observed), 0.0))
    obs_sd = np.where(observed, depth_sd, np.nan)
    image_sd = np.full(n, np.nan)
    image_sd[seen] = np.nanmedian(obs_sd[seen], axis=1)
    with np.errstate(divide="ignore"):
        log_sd = np.log(image_sd)
    uncertain = outlying(log_sd, robust_stats(log_sd), image_sd) | ~seen

    typical_sd = float(np.nanmedian(obs_sd)) if seen.any() else np.inf
    inconsistent = bad_residual | bad_neighbour
    status = np.where(inconsistent, 2, np.where(uncertain, 1, 0))
    reason = np.full(n, "", dtype=object)
    med_res = np.nanmedian(residual) if seen.any() else np.nan
    med_sd = np.nanmedian(image_sd) if seen.any() else np.nan
    for i in np.flatnonzero(status):
        parts = []
        if bad_residual[i]:
            parts.append(f"reprojection residual {residual[i]:.3g} px (capture median "
                         f"{med_res:.3g} px)")
        if bad_neighbour[i]:
            parts.append(f"{deviation[i]:.3g} neighbour steps from its neighbours' prediction "
                         f"(capture median {stats[0]:.3g})")
        if not seen[i]:
            parts.append("every observation rejected as an outlier" if detected[i]
                         else "no observed point")
        elif uncertain[i]:
            parts.append(f"depth sd {image_sd[i]:.3g} (capture median {med_sd:.3g})")
        reason[i] = "; ".join(parts)
    supported = ~(~observed & (depth_sd > WEAK_POINT_RATIO * typical_sd)) & ~inconsistent[:, None]
    timings = {**result.timings, "assess": time.perf_counter() - started}
    return replace(result, image_status=np.array(STATUS)[status], status_reason=reason.astype(str),
                   residual_px=residual, neighbour_deviation=deviation, depth_sd=depth_sd,
                   supported=supported, timings=timings)
