"""Event segmentation: temporally disjoint events = weakly linked parts of the estimated graph."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components


def segment_events(A: sp.spmatrix, *, min_size: int = 2) -> np.ndarray:
    """(N,) event labels 0..E-1: connected components of the symmetrised affinity.

    Labels are numbered by the component's first image; components smaller than ``min_size`` are
    merged into the component they link to most (or the largest one if isolated).
    """
    A.shape[0]
    G = sp.csr_matrix(abs(A) + abs(A).T)
    _, labels = connected_components(G, directed=False)
    sizes = np.bincount(labels)
    small = np.flatnonzero(sizes < min_size)
    if small.size and small.size < sizes.size:
        big = int(np.argmax(sizes))
        for c in small:
            labels[labels == c] = big
    _, first = np.unique(labels, return_index=True)
    remap = np.empty(labels.max() + 1, dtype=np.int64)
    remap[labels[np.sort(first)]] = np.arange(first.size)
    return remap[labels]
