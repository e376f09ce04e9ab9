"""SEDL-style self-expressive reconstruction (after Zheng et al., ICCV 2015 / TPAMI 2017).

Bi-convex alternation between the shapes X (observed points on their rays) and a self-expressive
coefficient matrix C (each shape a sparse combination of others), with the properties the DLOE
paper names as SEDL's: uniform weighting of all shapes (no degrees D, no compactness or ray
terms) and symmetric coefficients; only partial (intra-stream) sequencing is used.

Simplifications (stated plainly, this is not the authors' code):
- The coefficient step solves, per image, the simplex-constrained self-expression QP over its k
  nearest other-stream shapes (DLOE's W-step with the compactness and ray terms switched off);
  the simplex replaces SEDL's l1 penalty as the sparsity device.
- Symmetry is imposed on the support: the QP is solved a second time over the symmetrised
  neighbourhoods (j may express i whenever i chose j or j chose i). The coefficient *values* are
  not forced to be symmetric: forcing them (symmetric Sinkhorn scaling of ``(C + C^T) / 2``) kept
  the error at the pseudo-triangulation level on smooth synthetic motion, far above symmetric
  support alone (docs/method.md, "Baselines"), so this baseline is the stronger of the two
  readings.
- Partial sequencing enters as in DLOE's intra-stream prior: each row mixes a weight
  ``stream_weight`` of the previous / next frame of the same stream.
- No dictionary learning beyond the shapes themselves; the alternation stops on a small change
  in X or after ``max_iterations``.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp

from ..core.capture import Capture
from ..core.options import Options
from ..core.problem import build_problem, initialise, normalisation
from ..core.steps import full_weights
from ..core.wstep import select_candidates, w_step
from ..core.xstep import x_step

logger = logging.getLogger("dloe_sfm")


def symmetric_candidates(W: sp.spmatrix) -> np.ndarray:
    """Candidate lists of the symmetrised support of W (N, N): (N, k') int, -1 = pad."""
    S = sp.csr_matrix(abs(W) + abs(W).T)
    n = S.shape[0]
    counts = np.diff(S.indptr)
    rows = np.repeat(np.arange(n), counts)
    cand = np.full((n, max(int(counts.max()), 1)), -1)
    cand[rows, np.arange(S.nnz) - S.indptr[rows]] = S.indices
    return cand


def sedl(capture: Capture, *, num_candidates: int = 8, stream_weight: float = 0.1,
         ridge: float = 1e-9, max_iterations: int = 30, tolerance: float = 1e-6,
         options: Options | None = None) -> np.ndarray:
    """SEDL-style reconstruction, (N, P, 3) world units.

    Parameters
    ----------
    capture : Capture
        Needs streams with known frame order for the partial sequencing.
    num_candidates : int
        k: the other-stream shapes (nearest in the current X) each shape may combine.
    stream_weight : float
        Weight of the previous / next frame of the same stream in every coefficient row.
    ridge : float
        Ridge on the coefficients (normalised length^2) making each row's QP strictly convex.
    max_iterations, tolerance
        Stop after this many sweeps or when the RMS change of X (normalised units) is smaller.
    options : Options, optional
        Source of the pseudo-triangulated start and the ray-angle admissibility rule
        (``min_ray_angle``); ``Options()`` by default.
    """
    options = (options or Options()).replace(prior_weight=stream_weight)
    X0 = initialise(capture, options)
    origin, scale = normalisation(capture, X0)
    prob = build_problem(capture, options, origin, scale)
    n = capture.num_images
    X = (X0 - origin) / scale
    ones = np.ones(n)
    W_var = None
    for it in range(max_iterations):
        cand = select_candidates(X.reshape(n, -1), prob, num_candidates,
                                 min_angle=options.min_ray_angle, keep=W_var)
        W_var = w_step(X, ones, cand, prob, lambda1=0.0, lambda3=0.0, ridge=ridge)
        W_var = w_step(X, ones, symmetric_candidates(W_var), prob, lambda1=0.0, lambda3=0.0,
                       ridge=ridge)
        C = full_weights(W_var, prob)
        X_new = x_step(C, ones, prob, lambda1=0.0, lambda2=np.inf, X_prev=X)
        change = float(np.sqrt(np.mean((X_new - X) ** 2)))
        X = X_new
        logger.debug("SEDL sweep %d: rms change %.3e", it, change)
        if change < tolerance:
            break
    return X * scale + origin
