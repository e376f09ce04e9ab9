"""Line embeddings of the images: of a distance table (classical MDS, spectral ranking, an
approximate shortest Hamiltonian path), and of the shapes alone (the backbone of their
nearest-neighbour graph and its geodesic line, for images with no stream order; docs/method.md,
"Lone photos"). The
distances and the streams' placements are in :mod:`.sequencing`.

Shapes: N images, P points, X (N, P, 3); Z (N, N) distances.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree, shortest_path
from scipy.spatial import cKDTree

from .options import Embedding

BACKBONE_NEIGHBOURS = 10
"""Nearest shapes every image is linked to in the graph whose spanning tree
:func:`backbone_embedding` follows (and whose shortest paths :func:`geodesic_embedding`)."""
GEODESIC_LANDMARKS = 60
"""Landmark images of :func:`geodesic_embedding` (shortest-path sweeps)."""


def neighbour_graph(F: np.ndarray, k: int) -> sp.csr_matrix:
    """(N, N) sparse symmetric graph linking every row of ``F`` (N, d) to its ``k`` nearest
    rows, weighted by their distance, with the closest pair between components added until it
    is connected."""
    n = F.shape[0]
    k = min(k, n - 1)
    dist, nb = cKDTree(F).query(F, k + 1)
    rows = np.repeat(np.arange(n), k)
    # a tiny floor keeps coincident shapes linked (csgraph reads an explicit 0 as no edge)
    G = sp.csr_matrix((np.maximum(dist[:, 1:].ravel(), 1e-300), (rows, nb[:, 1:].ravel())),
                      shape=(n, n))
    G = G.maximum(G.T).tolil()
    count, comp = connected_components(G, directed=False)
    while count > 1:
        inside = comp == np.argmin(np.bincount(comp))
        outside = np.flatnonzero(~inside)
        d, j = cKDTree(F[outside]).query(F[inside])
        i = int(np.argmin(d))
        a, b = int(np.flatnonzero(inside)[i]), int(outside[j[i]])
        G[a, b] = G[b, a] = max(float(d[i]), 1e-300)
        count, comp = connected_components(G, directed=False)
    return G.tocsr()


def backbone_embedding(X: np.ndarray, k: int = BACKBONE_NEIGHBOURS) -> np.ndarray:
    """Every image's place along the longest path of the minimum spanning tree of its shapes'
    ``k``-nearest-neighbour graph (X's units): the sequencing of images with no stream order.

    Shapes sampled along a motion leave a spanning tree that is the motion's path with short
    twigs where noise or a revisited pose branches off; its longest path (two sweeps from a
    node) is the path, and an image off it takes the place where its twig meets it. Sparse:
    O(N k) edges, no N x N table; where the motion comes back close to a pose, the tree may
    still take the shortcut (docs/method.md, "Lone photos").
    """
    n = X.shape[0]
    if n < 3:
        return np.arange(n, dtype=np.float64)
    return _backbone(neighbour_graph(X.reshape(n, -1), k))


def _backbone(G: sp.csr_matrix) -> np.ndarray:
    """:func:`backbone_embedding` of the shapes' neighbour graph ``G``."""
    n = G.shape[0]
    tree = minimum_spanning_tree(G)
    tree = tree + tree.T
    first = int(np.argmax(shortest_path(tree, directed=False, indices=0)))
    dist, pred = shortest_path(tree, directed=False, indices=first, return_predecessors=True)
    node = int(np.argmax(dist))
    on_path = np.zeros(n, dtype=bool)
    while node >= 0:
        on_path[node] = True
        node = pred[node]
    f = np.where(on_path, dist, 0.0)
    for i in np.argsort(dist, kind="stable"):  # a twig's nodes after the node it hangs from
        if not on_path[i]:
            f[i] = f[pred[i]]
    return f


def geodesic_embedding(X: np.ndarray, k: int = BACKBONE_NEIGHBOURS,
                       landmarks: int = GEODESIC_LANDMARKS) -> np.ndarray:
    """Every image's coordinate of landmark Isomap to one dimension (de Silva & Tenenbaum 2003):
    classical MDS of the shortest-path distances through the shapes' ``k``-nearest-neighbour
    graph from ``landmarks`` images (farthest-point sampled), every image placed from its
    distances to them (X's units). Sparse: ``landmarks`` shortest-path sweeps of O(N k) edges.

    The paths run along the middle of the noisy tube of shapes a motion leaves, where the
    spanning tree of :func:`backbone_embedding` zigzags across it; a motion that comes back
    near a pose folds it (the shortcut joins the ends of a loop)."""
    n = X.shape[0]
    if n < 3:
        return np.arange(n, dtype=np.float64)
    return _geodesic(neighbour_graph(X.reshape(n, -1), k), landmarks)


def _geodesic(G: sp.csr_matrix, landmarks: int = GEODESIC_LANDMARKS) -> np.ndarray:
    """:func:`geodesic_embedding` of the shapes' neighbour graph ``G``."""
    start = int(np.argmax(shortest_path(G, directed=False, indices=0)))  # an end of the motion
    chosen, rows = [start], [shortest_path(G, directed=False, indices=start)]
    nearest = rows[0]
    while len(chosen) < min(landmarks, G.shape[0]) and nearest.max() > 0:
        chosen.append(int(np.argmax(nearest)))
        rows.append(shortest_path(G, directed=False, indices=chosen[-1]))
        nearest = np.minimum(nearest, rows[-1])
    return _landmark_mds(np.array(rows) ** 2, np.array(chosen))


def _landmark_mds(sq: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """One-dimensional landmark MDS of squared distances ``sq`` (L, N) from the L ``landmarks``
    (image indices) to every image."""
    among = sq[:, landmarks]
    val, vec = _top_eigenpairs(
        -0.5 * (among - among.mean(axis=0) - among.mean(axis=1)[:, None] + among.mean()), 1)
    return -0.5 * (vec[:, 0] / np.sqrt(max(val[0], np.finfo(float).tiny))) @ (
        sq - among.mean(axis=1)[:, None])


def path_length(X: np.ndarray, f: np.ndarray) -> float:
    """Length of the path through the shapes X (N, P, 3) in the order of ``f`` (X's units)."""
    F = X.reshape(X.shape[0], -1)[np.argsort(f, kind="stable")]
    return float(np.linalg.norm(np.diff(F, axis=0), axis=1).sum())


def shape_embedding(X: np.ndarray) -> np.ndarray:
    """The sequencing of images with no stream order: of :func:`backbone_embedding` and
    :func:`geodesic_embedding`, the one whose order threads the shapes on the shorter path (the
    seriation criterion of the shortest Hamiltonian path). Both on one neighbour graph."""
    n = X.shape[0]
    if n < 3:
        return np.arange(n, dtype=np.float64)
    G = neighbour_graph(X.reshape(n, -1), BACKBONE_NEIGHBOURS)
    return min((_backbone(G), _geodesic(G)), key=lambda f: path_length(X, f))


def mds_embedding(Z: np.ndarray) -> np.ndarray:
    """Classical MDS to one dimension: the leading eigenvector of -1/2 J Z^2 J, in Z's units."""
    n = Z.shape[0]
    B = Z**2
    B = -0.5 * (B - B.mean(axis=0, keepdims=True) - B.mean(axis=1, keepdims=True) + B.mean())
    val, vec = _top_eigenpairs(B, 1)
    return vec[:, 0] * np.sqrt(max(val[0], 0.0)) if n > 1 else np.zeros(n)


def spectral_embedding(Z: np.ndarray) -> np.ndarray:
    """Spectral ranking: Fiedler vector of the Laplacian of the affinity 1 / distance."""
    n = Z.shape[0]
    with np.errstate(divide="ignore"):
        Aff = np.where(Z > 0, 1.0 / np.maximum(Z, 1e-300), 0.0)
    np.fill_diagonal(Aff, 0.0)
    Aff /= max(Aff.max(), 1e-300)
    deg = Aff.sum(axis=1)
    L = -Aff
    L[np.diag_indices(n)] = deg
    if n <= 200:
        return sla.eigh(L, subset_by_index=[1, 1])[1][:, 0]
    # smallest eigenvector orthogonal to the constant one (L's null vector), Jacobi-preconditioned
    x0 = np.linspace(-1.0, 1.0, n)[:, None]
    _, vec = spla.lobpcg(
        L, x0, Y=np.ones((n, 1)), M=sp.diags(1.0 / deg), largest=False, tol=1e-9, maxiter=2000
    )
    return vec[:, 0]


def _top_eigenpairs(M: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k largest eigenpairs of a symmetric matrix, in decreasing order (Lanczos when large)."""
    n = M.shape[0]
    if n <= 200:
        vals, vecs = sla.eigh(M, subset_by_index=[n - k, n - 1])
    else:
        vals, vecs = spla.eigsh(M, k=k, which="LA", v0=np.ones(n), tol=1e-10)
    order = np.argsort(-vals)
    return vals[order], vecs[:, order]


def shp_embedding(Z: np.ndarray, *, max_passes: int = 50) -> np.ndarray:
    """Approximate shortest Hamiltonian path (nearest-neighbour path, then 2-opt).

    Returns every image's distance from the path's start along the path (Z's units).
    """
    n = Z.shape[0]
    best_path, best_len = None, np.inf
    starts = {int(np.argmax(Z.sum(axis=1))), int(np.argmax(Z[int(np.argmax(Z.sum(axis=1)))]))}
    for start in starts:
        path = _nearest_neighbour_path(Z, start)
        path = _two_opt(Z, path, max_passes)
        length = Z[path[:-1], path[1:]].sum()
        if length < best_len:
            best_path, best_len = path, length
    f = np.empty(n)
    f[best_path] = np.concatenate([[0.0], np.cumsum(Z[best_path[:-1], best_path[1:]])])
    return f


def _nearest_neighbour_path(Z: np.ndarray, start: int) -> np.ndarray:
    n = Z.shape[0]
    seen = np.zeros(n, dtype=bool)
    path = [start]
    seen[start] = True
    for _ in range(n - 1):
        d = np.where(seen, np.inf, Z[path[-1]])
        nxt = int(np.argmin(d))
        path.append(nxt)
        seen[nxt] = True
    return np.array(path)


def _two_opt(Z: np.ndarray, path: np.ndarray, max_passes: int) -> np.ndarray:
    """Open-path 2-opt: reverse path[i+1..j] while that shortens the path."""
    n = path.size
    if n < 4:
        return path
    for _ in range(max_passes * n):
        P = path
        a, b = P[:-1], P[1:]  # edge i: (a_i, b_i)
        edge = Z[a, b]
        # reversing P[i+1..j] replaces edges (i, i+1) and (j, j+1) by (i, j) and (i+1, j+1);
        # j = n - 1 (reverse to the end) only removes edge i
        gain = edge[:, None] + np.append(edge, 0.0)[None, 1:] - Z[a[:, None], b[None, :]]
        gain[:, :-1] -= Z[b[:, None], b[None, 1:]]
        i_idx, j_idx = np.triu_indices(n - 1, k=1)
        g = gain[i_idx, j_idx]
        best = int(np.argmax(g))
        if g[best] <= 1e-12 * max(edge.sum(), 1e-300):
            break
        i, j = i_idx[best], j_idx[best] + 1
        path = np.concatenate([P[: i + 1], P[i + 1 : j + 1][::-1], P[j + 1 :]])
    return path


def line_embedding(Z: np.ndarray, kind: Embedding | str = Embedding.MDS) -> np.ndarray:
    """A line embedding of the distance matrix Z (N, N): MDS, spectral ranking or SHP."""
    kind = Embedding(kind)
    if kind is Embedding.MDS:
        return mds_embedding(Z)
    if kind is Embedding.SPECTRAL:
        return spectral_embedding(Z)
    if kind is Embedding.SHP:
        return shp_embedding(Z)
    raise ValueError(f"'{kind.value}' is not an embedding of a distance matrix (see affine_time)")
