"""Lone photos and bursts placed on the time line by their own rays (docs/method.md, "Lone
photos placed by their rays").

The shapes' line (``embedding.shape_embedding``) orders images by their solved shapes alone; a
lone photo's shape carries its detections' noise, and where the motion comes back near a pose
its nearest shapes may lie at another time. Here the shapes, in the line's order, are smoothed
into a curve (local linear regression with Gaussian weights of ``CURVE_WIDTH`` places), and
every lone photo is put where the curve best explains its own observed rays: the angle between
each ray and the direction from the camera to the curve's point, over the point's typical
angle at the images' own places, capped (a wrong detection weighs no more than ``ANGLE_CAP``
typical angles), squared and summed. An image is never placed by its own shape: near it, the
curve is left without it. A lone photo whose best place elsewhere on the line (beyond
``FAR_PLACES``) fits within ``AMBIGUOUS_MARGIN`` of its best is ambiguous: the data cannot tell
which of the two times it was taken at, so it keeps its place and is reported. A burst moves
as a whole, its frames to the increasing places whose misfits sum least; videos keep their
places.

Sparse in N: the curve is searched on at most ``CURVE_NODES`` nodes, then around the best node
at every place.
"""

from __future__ import annotations

import numpy as np

CURVE_WIDTH = 3.0
"""Standard deviation (in places) of the Gaussian that smooths the shapes into the curve."""
ANGLE_CAP = 3.0
"""A ray's misfit is capped at this many of its point's typical angles."""
AMBIGUOUS_MARGIN = 4.0
"""A photo is ambiguous when a far place fits within this of its best."""
FAR_PLACES = 0.05
"""Places farther than this share of the line (and 10 curve widths) are another time."""
CURVE_NODES = 512
"""Nodes of the coarse search along the curve."""
_BLOCK = 1 << 21
"""Ray-node pairs evaluated at once."""


class _Curve:
    """The shapes ``F`` (N, d) smoothed along their places ``place`` (N,): at every place the
    intercept of a straight line fitted to the shapes around it, weighted by a Gaussian of
    ``width`` places (local linear regression: unlike a weighted mean it is not pulled inwards
    at the line's ends). Kept as its sums, so that the curve can be left without any one
    image."""

    def __init__(self, F: np.ndarray, place: np.ndarray, width: float):
        self.F, self.place, self.width = F, place, width
        self.reach = int(3 * width) + 1
        n = F.shape[0]
        ordered = np.empty_like(F)
        ordered[place] = F
        self.s = np.zeros((3, n))  # sums of w, w d, w d^2 over the shapes d places away
        self.t = np.zeros((2, *F.shape))  # sums of w F, w d F
        for d in range(-self.reach, self.reach + 1):
            w = float(self.kernel(np.array(d)))
            lo, hi = max(0, -d), min(n, n - d)
            if lo < hi:
                self.s[:, lo:hi] += w * np.array([1.0, d, d * d])[:, None]
                self.t[0, lo:hi] += w * ordered[lo + d : hi + d]
                self.t[1, lo:hi] += w * d * ordered[lo + d : hi + d]

    def kernel(self, d: np.ndarray) -> np.ndarray:
        """The weight of a shape ``d`` places away."""
        return np.where(np.abs(d) <= self.reach, np.exp(-0.5 * (d / self.width) ** 2), 0.0)

    @staticmethod
    def _intercept(s0, s1, s2, t0, t1) -> np.ndarray:
        det = s0 * s2 - s1 * s1
        ok = det > 1e-9 * s0 * s0
        with np.errstate(divide="ignore", invalid="ignore"):
            line = (s2[..., None] * t0 - s1[..., None] * t1) / det[..., None]
            mean = t0 / s0[..., None]
        return np.where(ok[..., None], line, mean)

    def at(self, places: np.ndarray) -> np.ndarray:
        """(M, d) the curve at ``places`` (M,)."""
        s0, s1, s2 = self.s[:, places]
        return self._intercept(s0, s1, s2, self.t[0, places], self.t[1, places])

    def without(self, i: np.ndarray, places: np.ndarray) -> np.ndarray:
        """(len(i), M, d) the curve at ``places`` (len(i), M) left without image ``i``'s shape."""
        d = (self.place[i][:, None] - places).astype(np.float64)
        w = self.kernel(d)
        s0, s1, s2 = (self.s[k, places] - w * d**k for k in range(3))
        Fi = self.F[i][:, None, :]
        t0 = self.t[0, places] - w[..., None] * Fi
        t1 = self.t[1, places] - (w * d)[..., None] * Fi
        return self._intercept(np.maximum(s0, 1e-300), s1, s2, t0, t1)


def _tangents(rays: np.ndarray, visible: np.ndarray, C: np.ndarray,
              Y: np.ndarray) -> np.ndarray:
    """(n, P) tangent of the angle between every image's rays (n, P, 3) from ``C`` (n, 3) and
    the direction to its point of ``Y`` (n, P, 3); NaN where unobserved or behind."""
    V = Y - C[:, None, :]
    along = np.einsum("npk,npk->np", rays, V)
    across = np.sqrt(np.maximum(np.einsum("npk,npk->np", V, V) - along * along, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(visible & (along > 0), across / along, np.nan)


def _capped(along: np.ndarray, norm2: np.ndarray, visible: np.ndarray,
            scale: np.ndarray) -> np.ndarray:
    """(n, M) from a ray's component ``along`` the direction to its point and that direction's
    squared length ``norm2`` (both (P, n, M)): the tangent of their angle over the point's
    ``scale``, capped at ``ANGLE_CAP`` (behind the camera: capped), squared, summed over the
    image's ``visible`` points (n, P). ``norm2`` is overwritten."""
    cap2 = ANGLE_CAP * ANGLE_CAP
    along2 = along * along
    norm2 -= along2
    np.maximum(norm2, 0.0, out=norm2)
    along2 *= (scale * scale)[:, None, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        norm2 /= along2
    norm2[~(along > 0)] = cap2
    np.minimum(norm2, cap2, out=norm2)
    return np.einsum("pnm,np->nm", norm2, visible.astype(np.float64))


def _misfits(rays: np.ndarray, visible: np.ndarray, C: np.ndarray, Y: np.ndarray,
             scale: np.ndarray) -> np.ndarray:
    """(n, M) misfit (``_capped``) of every image's rays (n, P, 3, unit) from centres ``C``
    (n, 3) against its own curve points ``Y`` (n, M, P, 3)."""
    V = Y - C[:, None, None, :]
    return _capped(np.einsum("npk,nmpk->pnm", rays, V), np.einsum("nmpk,nmpk->pnm", V, V),
                   visible, scale)


def _misfits_shared(rays: np.ndarray, visible: np.ndarray, C: np.ndarray, Y: np.ndarray,
                    scale: np.ndarray) -> np.ndarray:
    """:func:`_misfits` against the same curve points ``Y`` (M, P, 3) for every image, by
    products of the rays and centres with the points (no (n, M, P, 3) array)."""
    Yp = Y.transpose(1, 2, 0)  # (P, 3, M)
    along = rays.transpose(1, 0, 2) @ Yp  # (P, n, M)
    along -= np.einsum("npk,nk->pn", rays, C)[:, :, None]
    norm2 = C @ Yp  # (P, n, M)
    norm2 *= -2.0
    norm2 += (Y * Y).sum(axis=2).T[:, None, :]
    norm2 += (C * C).sum(axis=1)[None, :, None]
    return _capped(along, norm2, visible, scale)


def _monotone(table: np.ndarray) -> np.ndarray:
    """(k,) strictly increasing columns of ``table`` (k, M), one per row, of the least total
    (dynamic programming: O(k M))."""
    k, m = table.shape
    if m < k:
        return np.minimum(np.arange(k), m - 1)
    cost = table[0].copy()
    back = np.zeros((k, m), dtype=np.int64)
    for j in range(1, k):
        arg = _running_argmin(cost)  # the best column up to each column
        earlier = np.full(m, np.inf)
        earlier[1:] = cost[arg[:-1]]
        back[j, 1:] = arg[:-1]
        cost = earlier + table[j]
    cols = np.empty(k, dtype=np.int64)
    cols[-1] = int(np.argmin(cost))
    for j in range(k - 1, 0, -1):
        cols[j - 1] = back[j, cols[j]]
    return cols


def _running_argmin(v: np.ndarray) -> np.ndarray:
    """(M,) index of the minimum of ``v[:m + 1]`` for every m."""
    run = np.minimum.accumulate(v)
    new = np.concatenate([[True], run[1:] < run[:-1]])
    return np.maximum.accumulate(np.where(new, np.arange(v.size), 0))


def _vertex(lo: np.ndarray, mid: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The offset of the lowest point of the parabola through (-1, ``lo``), (0, ``mid``),
    (1, ``hi``) where ``mid`` is the least, within 0.45 (0 where it is no valley)."""
    bend = lo - 2 * mid + hi
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(bend > 0, 0.5 * (lo - hi) / bend, 0.0)
    return np.clip(shift, -0.45, 0.45)


def place_by_rays(
    X: np.ndarray, rays: np.ndarray, C: np.ndarray, visible: np.ndarray, f: np.ndarray,
    lone: np.ndarray, bursts: list[np.ndarray] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """(embedding, ambiguous): ``f`` (N,) with the ``lone`` photos moved to where the curve of
    the shapes ``X`` (N, P, 3) in ``f``'s order best explains their ``rays`` (N, P, 3, unit,
    NaN = unobserved) from centres ``C`` (N, 3), and (N,) which lone photos fit as well at
    another time (left in place). Every burst of ``bursts`` (its images in frame order) moves
    as a whole: its frames to the increasing places that fit them best together (a burst with
    a frame that sees no point stays). The embedding keeps ``f``'s values, handed out in the
    new order."""
    n = X.shape[0]
    ambiguous = np.zeros(n, dtype=bool)
    observed = visible.any(axis=1)
    singles = np.flatnonzero(lone & observed)
    bursts = [b for b in bursts if b.size >= 2 and observed[b].all()]
    idx = np.concatenate([singles, *bursts]).astype(np.int64)
    if n < 3 or not idx.size:
        return f, ambiguous
    order = np.argsort(f, kind="stable")
    place = np.empty(n, dtype=np.int64)
    place[order] = np.arange(n)
    rays = np.nan_to_num(rays)
    F = X.reshape(n, -1)
    curve = _Curve(F, place, CURVE_WIDTH)
    own = _tangents(rays, visible, C,
                    curve.without(np.arange(n), place[:, None])[:, 0].reshape(X.shape))
    # every point's typical angle: its rays against the curve at their images' own places
    seen = np.isfinite(own).any(axis=0)
    scale = np.ones(X.shape[1])
    scale[seen] = np.nanmedian(own[:, seen], axis=0)
    scale[~(scale > 0)] = 1.0

    def misfits(rows: np.ndarray, at: np.ndarray) -> np.ndarray:
        """(len(rows), M) of images ``rows`` at places ``at`` (len(rows), M), the curve left
        without the image."""
        out = np.empty(at.shape)
        block = max(1, _BLOCK // (at.shape[1] * X.shape[1]))
        for b in range(0, rows.size, block):
            i = rows[b : b + block]
            Y = curve.without(i, at[b : b + block]).reshape((i.size, at.shape[1], *X.shape[1:]))
            out[b : b + block] = _misfits(rays[i], visible[i], C[i], Y, scale)
        return out

    # the whole curve on its nodes; near an image's own place, without the image
    stride = max(1, -(-n // CURVE_NODES))
    nodes = np.arange(0, n, stride)
    Y = curve.at(nodes).reshape((nodes.size, *X.shape[1:]))
    coarse = np.empty((idx.size, nodes.size))
    block = max(1, _BLOCK // (nodes.size * X.shape[1]))
    for b in range(0, idx.size, block):
        i = idx[b : b + block]
        coarse[b : b + block] = _misfits_shared(rays[i], visible[i], C[i], Y, scale)
    window = np.clip(place[idx][:, None] + np.arange(-curve.reach, curve.reach + 1), 0, n - 1)
    near_own = misfits(idx, window)
    rows, cols = np.nonzero(window % stride == 0)
    coarse[rows, window[rows, cols] // stride] = near_own[rows, cols]
    key = place.astype(np.float64)

    # a burst: its frames at the increasing nodes that fit them best together, each then
    # between its node's neighbours (a parabola through three, within half a node: in order)
    start = singles.size
    for b in bursts:
        table = coarse[start : start + b.size]
        cols = _monotone(table)
        rows = np.arange(b.size)
        inner = (cols > 0) & (cols < nodes.size - 1)
        lo = table[rows, np.maximum(cols - 1, 0)]
        hi = table[rows, np.minimum(cols + 1, nodes.size - 1)]
        key[b] = nodes[cols] + stride * np.where(inner, _vertex(lo, table[rows, cols], hi), 0.0)
        start += b.size

    # a lone photo: around its best node every place, then a parabola through three
    coarse = coarse[: singles.size]
    offsets = np.arange(-stride, stride + 1)
    near = np.clip(nodes[np.argmin(coarse, axis=1)][:, None] + offsets, 0, n - 1)
    fine = misfits(singles, near)
    j = np.argmin(fine, axis=1)
    rows = np.arange(singles.size)
    fit = fine[rows, j]
    inner = (j > 0) & (j < offsets.size - 1) & (near[rows, 0] < near[rows, -1])
    lo, hi = fine[rows, np.maximum(j - 1, 0)], fine[rows, np.minimum(j + 1, offsets.size - 1)]
    best = near[rows, j] + np.where(inner, _vertex(lo, fit, hi), 0.0)
    far = np.abs(nodes[None, :] - best[:, None]) > max(10 * curve.width, FAR_PLACES * n)
    rival = np.where(far, coarse, np.inf).min(axis=1)
    ambiguous[singles] = rival - fit < AMBIGUOUS_MARGIN
    key[singles[~ambiguous[singles]]] = best[~ambiguous[singles]]
    new_order = np.lexsort((place, key))
    out = np.empty(n)
    out[new_order] = f[order]
    return out, ambiguous
