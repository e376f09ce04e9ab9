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
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cholesky_banded
from scipy.sparse.csgraph import reverse_cuthill_mckee

from .capture import Capture
from .result import Result
from .robust import predicted, residuals_px
from .steps import smoothness_matrix, temporal_ends

Z_FLAG = 6.0
"""Robust z-score (against median / 1.4826 MAD over images) beyond which a statistic flags."""
RATIO_FLAG = 3.0
"""...and the factor above the images' median it must also exceed (a MAD near 0 flags nothing)."""
WEAK_POINT_RATIO = 10.0
"""An unobserved point whose position sd exceeds this many times the median depth sd of the
observed points has no support (NaN in the exports)."""
BLOCK = 8
"""Smallest block (rows) of the selected inversion of a banded factor."""
CHUNK = 1 << 20
"""Entries of the (blocks, factors, s, s) arrays formed at once by the selected inversion."""
STATUS = ("ok", "uncertain", "inconsistent")


def band_factor(H: sp.spmatrix) -> tuple[np.ndarray, np.ndarray] | None:
    """``(perm, U)``: H (sparse symmetric positive definite) reordered into a band by reverse
    Cuthill-McKee, ``H[perm][:, perm] = U^T U``, U in LAPACK upper band storage ((b + 1, m) for
    bandwidth b); O(m b^2). None when H is numerically singular."""
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
        return perm, cholesky_banded(ab)
    except np.linalg.LinAlgError:
        return None


def banded_inverse_diagonals(factors: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Diagonal of ``(U^T U)^-1`` for each banded Cholesky factor U (LAPACK upper band storage).

    Selected inversion (Takahashi / Erisman-Tinney) on diagonal blocks of ``s = max(b, BLOCK)``
    rows, b the largest bandwidth: U is then block upper bidiagonal, and the diagonal blocks of
    ``Z = (U^T U)^-1`` follow ``Z_k = (U_kk^T U_kk)^-1 + V_k Z_(k+1) V_k^T``, ``V_k = U_kk^-1
    U_k,k+1``, from the last block to the first: O(m s^2) time and O(m s) memory for m rows.
    The factors run in lockstep, each padded in front to the longest with identity rows (which
    leave the rest of its inverse unchanged).
    """
    width = max(f.shape[0] for f in factors) - 1
    size = max(width, BLOCK)
    blocks = -(-max(f.shape[1] for f in factors) // size)
    total = blocks * size
    # one block of zeros past the end: the last block's (empty) coupling to the next
    full = np.zeros((len(factors), width + 1, total + size))
    for k, f in enumerate(factors):
        b, m = f.shape[0] - 1, f.shape[1]
        d, c = np.indices(f.shape)
        # LAPACK leaves the entries above the first row of U unset
        full[k, width - b :, total - m : total] = np.where(d + c >= b, f, 0.0)
        full[k, width, : total - m] = 1.0
    i, j = np.indices((size, size))
    # U[r, c] = full[width - (c - r), c] for 0 <= c - r <= width
    diag_offset, next_offset = j - i, size + j - i
    in_diag = (diag_offset >= 0) & (diag_offset <= width)
    in_next = next_offset <= width
    diag_row = width - np.clip(diag_offset, 0, width)
    next_row = width - np.clip(next_offset, 0, width)
    out = np.empty((blocks, len(factors), size))
    chunk = max(1, CHUNK // (len(factors) * size * size))
    Z = np.zeros((len(factors), size, size))
    for hi in range(blocks, 0, -chunk):
        lo = max(hi - chunk, 0)
        first = size * np.arange(lo, hi)[:, None, None]
        U_diag = np.where(in_diag, full[:, diag_row, first + j], 0.0).swapaxes(0, 1)
        U_next = np.where(in_next, full[:, next_row, first + size + j], 0.0).swapaxes(0, 1)
        U_inv = np.linalg.inv(U_diag)  # triangular: the solves are back-substitutions
        D = U_inv @ U_inv.swapaxes(2, 3)
        V = U_inv @ U_next
        for k in range(hi - lo - 1, -1, -1):
            Z = D[k] + V[k] @ Z @ V[k].swapaxes(1, 2)
            out[lo + k] = Z.diagonal(axis1=1, axis2=2)
    flat = out.transpose(1, 0, 2).reshape(len(factors), total)
    return [row[total - f.shape[1] :] for row, f in zip(flat, factors, strict=True)]


def inverse_diagonals(matrices: Sequence[sp.spmatrix]) -> list[np.ndarray]:
    """Exact diagonal of ``H^-1`` for each H (sparse symmetric positive definite): reordered into
    a band (:func:`band_factor`), then selected inversion of the banded factors
    (:func:`banded_inverse_diagonals`): O(m b^2) time and O(m b) memory for m unknowns and
    bandwidth b, never the dense inverse. Inf when H is numerically singular (nothing
    determines the unknowns)."""
    factored = [band_factor(H) for H in matrices]
    solved = [f for f in factored if f is not None]
    inner = iter(banded_inverse_diagonals([f[1] for f in solved]) if solved else [])
    out = []
    for H, f in zip(matrices, factored, strict=True):
        diag = np.full(H.shape[0], np.inf)
        if f is not None:
            diag[f[0]] = next(inner)
        out.append(diag)
    return out


def depth_variances(Q: sp.csr_matrix, rays: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """(N, P) diagonal of the inverse of each point's hard-ray system, up to the residual scale.

    Point p: ``X_p = c + B z`` with one depth column ``r_np`` per observed image and three unit
    columns per unobserved one (as ``xstep.x_step`` with ``lambda2 = inf``); the system is
    ``B^T (Q kron I3) B``. Observed entries: the depth's variance factor; unobserved: the trace
    of the position's 3 x 3 block.
    """
    n, p = observed.shape
    Q3 = sp.kron(Q, sp.identity(3), format="csr")
    reg = 1e-10 * max(Q.diagonal().mean(), 1e-300)
    r0 = np.nan_to_num(rays)
    systems = []
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
        systems.append(B.T @ Q3 @ B + reg * sp.identity(B.shape[1]))
    out = np.empty((n, p))
    for j, diag in enumerate(inverse_diagonals(systems)):
        seen, miss = np.flatnonzero(observed[:, j]), np.flatnonzero(~observed[:, j])
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
                        excluded: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """RMS distance of each of the images ``rows``' observed points (all when none) from the
    prediction of its graph row with the ``excluded`` images' columns dropped (row
    renormalised); NaN for an image with no neighbour left. Each row's value depends on its
    own row of W only."""
    Wk = sp.csr_matrix(W[rows] @ sp.diags((~excluded).astype(np.float64)))
    sums = np.asarray(Wk.sum(axis=1)).ravel()
    with np.errstate(divide="ignore"):
        Wk = sp.csr_matrix(sp.diags(np.where(sums > 0, 1.0 / sums, 0.0)) @ Wk)
    shape = (len(rows), *X.shape[1:])
    d2 = ((X[rows] - np.asarray(Wk @ X.reshape(X.shape[0], -1)).reshape(shape)) ** 2).sum(axis=2)
    seen = observed[rows]
    pick = np.where(seen.any(axis=1)[:, None], seen, True)
    dev = np.sqrt((d2 * pick).sum(axis=1) / pick.sum(axis=1))
    dev[sums <= 0] = np.nan
    return dev


def _row_means(W: sp.csr_matrix, values) -> tuple[np.ndarray, np.ndarray]:
    """(N,) every row's W-weighted mean of ``values(rows, cols)`` over its entries (0 where the
    row has none) and (N,) whether it has any."""
    coo = W.tocoo()
    n = W.shape[0]
    sums = np.bincount(coo.row, coo.data, minlength=n).astype(np.float64)
    means = np.bincount(coo.row, coo.data * values(coo.row, coo.col),
                        minlength=n).astype(np.float64)
    has = sums > 0
    means[has] /= sums[has]
    return means, has


def typical_step(X: np.ndarray, W: sp.csr_matrix) -> float:
    """Median over images of the W-weighted RMS distance to their neighbours' shapes (1 when
    nothing moves)."""
    step, has = _row_means(W, lambda r, c: np.sqrt(((X[r] - X[c]) ** 2).sum(axis=2).mean(axis=1)))
    typical = float(np.median(step[has])) if has.any() else 0.0
    return typical if typical > 0 else 1.0


def gap_ratio(f: np.ndarray, W: sp.csr_matrix) -> np.ndarray:
    """(N,) every image's W-weighted time gap to its neighbours along ``f``, over the median of
    those gaps (1 without neighbours): how much farther than usual its row has to reach."""
    gap, has = _row_means(W, lambda r, c: np.abs(f[r] - f[c]))
    typical = float(np.median(gap[has])) if has.any() else 0.0
    return np.where(has & (typical > 0), gap / max(typical, 1e-300), 1.0)


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

    # the time line's ends can only extrapolate (by up to about a step): measured in steps twice
    # as long, or as many times as an end's row reaches farther in time than rows usually do; the
    # spread at least half a step (docs/method.md, "Per-image status and reconstructability")
    step = typical_step(X, result.W) * np.where(
        temporal_ends(result.embedding, cap.stream_ids),
        np.maximum(2.0, gap_ratio(result.embedding, result.W)), 1.0)
    W = sp.csr_matrix(result.W)
    by_column = sp.csc_matrix(W)
    bad_neighbour = np.zeros(n, dtype=bool)
    deviation = neighbour_deviation(X, W, observed, bad_neighbour, np.arange(n)) / step
    stats = robust_stats(deviation, 0.5)
    while True:
        # flag the worst image, then re-predict the images it predicts without it
        fresh = outlying(deviation, stats, deviation) & ~bad_neighbour
        if not fresh.any():
            break
        worst = np.flatnonzero(fresh)[np.argmax(deviation[fresh])]
        bad_neighbour[worst] = True
        rows = by_column.indices[by_column.indptr[worst] : by_column.indptr[worst + 1]]
        deviation[rows] = neighbour_deviation(X, W, observed, bad_neighbour, rows) / step[rows]

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
