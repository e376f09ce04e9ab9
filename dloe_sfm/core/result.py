"""The solver's result object."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp


@dataclass(kw_only=True)
class Result:
    """What :func:`dloe_sfm.reconstruct` returns (shapes: N images, P points).

    Attributes
    ----------
    X : (N, P, 3) float
        Reconstructed points of every image, also where the point was not observed.
    order : (N,) int
        Image indices sorted by estimated time (first = earliest; direction follows the streams).
    A : (N, N) scipy.sparse.csr_matrix
        Estimated affinity ``D W``.
    W : (N, N) csr_matrix
        Row-stochastic neighbour weights (chain prior included).
    D : (N,) float
        Degrees (diagonal of D).
    events : (N,) int
        Event (connected component) label of every image, 0..E-1.
    embedding : (N,) float
        Position of every image on the estimated time line (arc-length units within an event).
    cost_history, change_history : (iters,) float
        Total cost and relative change of X per outer iteration.
    nit : int
    success : bool
        Whether the stopping tolerance was reached.
    message : str
    seconds : float
        Wall time of the solve.
    timings : dict
        Seconds spent per stage (init, w_step, d_step, x_step, sequencing, ...).
    """

    X: np.ndarray
    order: np.ndarray
    A: sp.csr_matrix
    W: sp.csr_matrix
    D: np.ndarray
    events: np.ndarray
    embedding: np.ndarray
    cost_history: np.ndarray
    change_history: np.ndarray
    nit: int
    success: bool
    message: str
    seconds: float
    timings: dict = field(default_factory=dict)
    scale: float = 1.0

    @property
    def rank(self) -> np.ndarray:
        """(N,) int: position of every image in ``order``."""
        rank = np.empty_like(self.order)
        rank[self.order] = np.arange(self.order.size)
        return rank
