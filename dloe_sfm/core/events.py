"""Event segmentation: temporally disjoint events = weakly linked parts of the estimated graph.

Images of one event are linked by the graph's rows; images of two events that nothing ties
together fall into different connected components. A video stream runs on within an event, so
the graph is first contracted to stream runs (cut where the video stops or jumps). When a few
stray links join two events (similar poses in both), a component is split spectrally: at the
best normalised cut along its Fiedler vector, when that cut is tiny.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

SHORT_RUN = 5
"""Stream runs of at most this many images (lone photos, bursts) cannot show by stopping that
an event ended: events made of them alone are split only where the shapes jump
(:func:`join_touching`)."""
TOUCH_STEPS = 3.0
"""Two such events whose closest shapes are within this many typical steps (median distance of
an image to its nearest shape) of each other are one motion: they are joined."""
JUNCTION_IMAGES = 10
"""Images at either side of a junction between two solved events of lone photos compared by
:func:`runs_on`..."""
RUN_ON_FACTOR = 3.4
"""...and the factor on ``log2 n`` median steps within which their closest shapes lie where
the motion runs on across it (docs/method.md, "Events of lone photos"): solved false cuts of
one motion needed up to 2.74, time gaps in which the motion went on at least 4.14; this is
their geometric middle."""


def without_videos(streams: np.ndarray) -> bool:
    """True when fewer than two streams (ids >= 0 per camera) hold more than ``SHORT_RUN``
    images: lone photos and bursts, whose order and events only the shapes can tell."""
    return bool((np.bincount(streams) > SHORT_RUN).sum() < 2)


def symmetrised(A: sp.spmatrix) -> sp.csr_matrix:
    """|A| + |A|^T without the diagonal: the undirected graph of an affinity."""
    G = sp.csr_matrix(abs(A) + abs(A).T)
    G.setdiag(0.0)
    G.eliminate_zeros()
    return G


def _leading_eigenvectors(A: sp.spmatrix, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, k) leading eigenvectors of the normalised adjacency D^-1/2 G D^-1/2 of ``A``'s
    undirected graph G (largest first), and D^-1/2.

    Solved per connected component (the matrix is block diagonal): every component has
    eigenvalue 1, and Lanczos on the whole matrix would find one copy of a repeated eigenvalue.
    """
    G = symmetrised(A)
    n = G.shape[0]
    deg = np.asarray(G.sum(axis=1)).ravel()
    inv = 1.0 / np.sqrt(np.maximum(deg, 1e-12))
    M = sp.csr_matrix(sp.diags(inv) @ G @ sp.diags(inv))
    _, comp = connected_components(G, directed=False)
    vals, vecs = [], []
    for c in range(comp.max() + 1):
        idx = np.flatnonzero(comp == c)
        m, kc = idx.size, min(k, idx.size)
        block = M[idx][:, idx]
        if m <= 1500 or kc >= m - 1:
            w, v = sla.eigh(block.toarray(), subset_by_index=[m - kc, m - 1])
        else:
            w, v = spla.eigsh(block, k=kc, which="LA", v0=np.sqrt(deg[idx] + 1e-12), tol=1e-8)
        full = np.zeros((n, kc))
        full[idx] = v
        vals.append(w)
        vecs.append(full)
    vals, vecs = np.concatenate(vals), np.concatenate(vecs, axis=1)
    top = np.argsort(-vals, kind="stable")[:k]
    return vecs[:, top], inv


def spectral_coordinates(A: sp.spmatrix, dim: int = 2) -> np.ndarray:
    """(N, dim) spectral embedding of the undirected graph of ``A``: the eigenvectors after the
    leading one of the normalised adjacency, scaled by D^-1/2 (random-walk coordinates).

    Images of different components (or weakly linked parts) get clearly separated coordinates.
    """
    n = A.shape[0]
    k = min(dim + 1, n - 1)
    vecs, inv = _leading_eigenvectors(A, k)
    out = np.zeros((n, dim))
    out[:, : k - 1] = vecs[:, 1:k] * inv[:, None]
    return out


def stream_runs(streams: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(N,) run labels: every stream cut into runs of consecutive frames where the video stopped.

    A stop is a gap of more than four times the stream's median frame step and of at least
    three frames (dropped frames leave shorter gaps). Shapes are no guide here: a fast jump
    after a still pose moves the body much further between two frames than the median step.
    Lone photos (stream < 0) are runs of their own.
    """
    n = streams.size
    order = np.lexsort((frames, streams))
    s, f = streams[order], frames[order]
    same = (s[1:] == s[:-1]) & (s[1:] >= 0)
    gap = np.diff(f).astype(np.float64)
    cont = same.copy()
    for sid in np.unique(s[1:][same]):
        links = np.flatnonzero(same & (s[1:] == sid))
        cont[links] &= gap[links] <= max(3.0, 4.0 * np.median(gap[links]))
    new = np.ones(n, dtype=bool)
    new[1:] = ~cont
    runs = np.empty(n, dtype=np.int64)
    runs[order] = np.cumsum(new) - 1
    return runs


def _normalised_cut(G: sp.csr_matrix, size: np.ndarray) -> np.ndarray | None:
    """Boolean side of the best normalised cut of connected ``G`` (nodes: runs of ``size``
    images) along its Fiedler vector, or None when no cut is weak.

    Between runs, weak is a cut under 5 % of the smaller side's volume: one event's runs are
    linked all along their length, two events of similar poses far less. When every run is a
    lone photo (one image), an event is a long chain whose every cut is cheap relative to
    volume, so there a weak cut is under 1 % of the volume and also carries under 0.5 % of the
    median weight crossing the line's cuts. The measurements behind both thresholds:
    docs/method.md, "Events".
    """
    n = G.shape[0]
    if n < 2:
        return None
    f = spectral_coordinates(G, 1)[:, 0]
    order = np.argsort(f, kind="stable")
    deg = np.asarray(G.sum(axis=1)).ravel()[order]
    pos = np.empty(n, dtype=np.int64)
    pos[order] = np.arange(n)
    coo = sp.triu(G, k=1).tocoo()
    lo = np.minimum(pos[coo.row], pos[coo.col])
    hi = np.maximum(pos[coo.row], pos[coo.col])
    # cut k separates positions <= k from > k; an edge crosses cuts lo..hi-1
    cross = np.cumsum(np.bincount(lo, coo.data, n) - np.bincount(hi, coo.data, n))[:-1]
    vol = np.cumsum(deg)[:-1]
    ncut = cross / np.maximum(np.minimum(vol, deg.sum() - vol), 1e-300)
    k = int(np.argmin(ncut))
    if (size > 1).any():
        weak = ncut[k] < 0.05
    else:
        weak = ncut[k] < 0.01 and cross[k] < 0.005 * np.median(cross)
    return pos <= k if weak else None


def join_touching(labels: np.ndarray, runs: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``labels`` with the events of short runs only (``SHORT_RUN``) joined where their shapes
    ``X`` (N, ...) touch: the closest pair across two events no farther apart than
    ``TOUCH_STEPS`` x the larger of the two events' typical steps (each image's distance to its
    nearest shape, median). A time gap leaves a jump in shape; a graph cut through a continuous
    motion does not, e.g. where a still pose ends (docs/method.md, "Events of lone photos").
    Nearest neighbours by k-d trees: no N x N table."""
    n = labels.size
    short = np.bincount(runs)[runs] <= SHORT_RUN
    F = X.reshape(n, -1)
    while True:
        events = [e for e in np.unique(labels) if short[labels == e].all()
                  and (labels == e).sum() >= 2]
        if len(events) < 2:
            return labels
        step = {e: float(np.median(cKDTree(F[labels == e]).query(F[labels == e], 2)[0][:, 1]))
                for e in events}
        joined = False
        for a in events:
            mine = labels == a
            others = np.isin(labels, events) & ~mine
            gap, j = cKDTree(F[others]).query(F[mine])
            b = labels[np.flatnonzero(others)[j[np.argmin(gap)]]]
            if gap.min() <= TOUCH_STEPS * max(step[a], step[b]):
                labels = np.where(labels == b, a, labels)
                joined = True
                break
        if not joined:
            return labels


def runs_on(X: np.ndarray, before: np.ndarray, after: np.ndarray, n: int) -> bool:
    """Whether the motion runs on from the images ``before`` (indices, in time order) to the
    images ``after`` (ditto), two events of lone photos and bursts solved apart: the closest
    shapes ``X`` (N, ...) across the junction no farther apart than the steps between
    consecutive shapes at the two ends allow when a continuous motion is photographed at ``n``
    random instants.

    At ``n`` random instants the largest of the spacings is about ln n mean spacings and their
    median ln 2 of one; :data:`RUN_ON_FACTOR` times that ratio allows for the largest spacing's
    tail, the motion's speed changing across the junction, and the solved shapes at an event's
    ends, which bunch up and leave the junction wider than the motion's step. A cut through a
    continuous motion (where a fast part leaves a wide step) stays within it; a time gap in
    which the motion went on does not (docs/method.md, "Events of lone photos").
    """
    return junction_factor(X, before, after, n) <= RUN_ON_FACTOR


def junction_factor(X: np.ndarray, before: np.ndarray, after: np.ndarray, n: int) -> float:
    """The closest shapes ``X`` across the junction of the images ``before`` and ``after``
    (:func:`runs_on`) apart in ``log2 n`` median steps between consecutive shapes there: the
    least factor that would join them (inf with no step to measure)."""
    F = X.reshape(X.shape[0], -1)
    a, b = F[before[-JUNCTION_IMAGES:]], F[after[:JUNCTION_IMAGES]]
    steps = np.concatenate([np.linalg.norm(np.diff(a, axis=0), axis=1),
                            np.linalg.norm(np.diff(b, axis=0), axis=1)])
    if not steps.size:
        return np.inf
    gap = float(np.sqrt(((a[:, None] - b[None]) ** 2).sum(axis=2).min()))
    unit = np.log2(max(n, 2)) * float(np.median(steps))
    return 0.0 if gap == 0 else gap / unit if unit > 0 else np.inf


def segment_events(
    A: sp.spmatrix,
    streams: np.ndarray | None = None,
    frames: np.ndarray | None = None,
    *,
    min_size: int = 8,
    shapes: np.ndarray | None = None,
) -> np.ndarray:
    """(N,) event labels 0..E-1 of the images linked by affinity ``A``.

    With ``streams`` / ``frames`` the nodes are stream runs (``stream_runs``): a video keeps
    one event while it runs on, whatever its images' rows link to. Runs linked by less than 5 %
    of the smaller run's size are not linked; the connected components of what remains are cut
    further while a weak normalised cut exists (``_normalised_cut``: stray links). Labels
    are numbered by the event's first image; events of fewer than ``min_size`` images join the
    largest. With ``shapes`` (N, ...), events of lone photos and bursts whose shapes touch are
    joined (:func:`join_touching`).
    """
    n = A.shape[0]
    runs = np.arange(n) if streams is None else stream_runs(streams, frames)
    size = np.bincount(runs).astype(np.float64)
    to_run = sp.csr_matrix((np.ones(n), (np.arange(n), runs)), shape=(n, size.size))
    R = symmetrised(to_run.T @ symmetrised(A) @ to_run)
    R.data[R.data < 0.05 * np.minimum(size[R.nonzero()[0]], size[R.nonzero()[1]])] = 0.0
    R.eliminate_zeros()
    _, comp = connected_components(R, directed=False)
    pending = [np.flatnonzero(comp == c) for c in range(comp.max() + 1)]
    parts = []
    while pending:
        idx = pending.pop()
        side = _normalised_cut(R[idx][:, idx], size[idx])
        if side is None:
            parts.append(idx)
        else:
            pending += [idx[side], idx[~side]]
    run_label = np.empty(size.size, dtype=np.int64)
    for c, idx in enumerate(parts):
        run_label[idx] = c
    labels = run_label[runs]
    if shapes is not None:
        labels = join_touching(labels, runs, shapes)
    sizes = np.bincount(labels)
    small = sizes < min_size
    if small.any() and not small.all():
        labels[small[labels]] = np.argmax(sizes)
    return numbered_by_first_image(labels)


def numbered_by_first_image(labels: np.ndarray) -> np.ndarray:
    """``labels`` (N,) renumbered 0..E-1 in the order of each event's first image."""
    _, first = np.unique(labels, return_index=True)
    remap = np.empty(labels.max() + 1, dtype=np.int64)
    remap[labels[np.sort(first)]] = np.arange(first.size)
    return remap[labels]
