"""The data every solve starts from: initial shapes, the normalised frame and problem, and the
assembly of sparse graphs from per-event parts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import InputError
from .capture import Capture
from .init import fill_missing, pseudo_triangulate
from .options import Options
from .steps import Problem, chain_matrix

SparseParts = list[tuple[np.ndarray, np.ndarray, np.ndarray]]
"""(data, rows, cols) triplets of the pieces of one sparse matrix."""


def known_rates(capture: Capture) -> np.ndarray | None:
    """(N,) every image's stream's frame rate where ``capture`` knows them all
    (``Capture.fps``), else None."""
    fps = capture.fps
    return fps if fps is not None and np.isfinite(fps).all() else None


def initialise(capture: Capture, options: Options) -> np.ndarray:
    """Pseudo-triangulated (N, P, 3) shapes in world units (unobserved points interpolated)."""
    rays = capture.rays()
    rays[capture.weights <= 0] = np.nan
    depths, _ = pseudo_triangulate(
        rays, capture.C, capture.stream_ids, capture.frame, min_angle=options.min_ray_angle
    )
    X0 = capture.C[:, None, :] + depths[..., None] * rays
    if not np.isfinite(depths).any():
        raise InputError(
            f"no two images of different streams see a point at least {options.min_ray_angle:g} "
            "degrees from (anti)parallel (option 'min_ray_angle'): nothing to triangulate"
        )
    return fill_missing(X0, capture.stream_ids, capture.frame)


def normalisation(capture: Capture, X0: np.ndarray) -> tuple[np.ndarray, float]:
    """Origin and scale of the normalised frame: scene centroid, median camera-to-point distance."""
    origin = np.nanmean(X0.reshape(-1, 3), axis=0)
    dist = np.linalg.norm(X0 - capture.C[:, None, :], axis=2)
    scale = float(np.nanmedian(dist))
    return origin, scale if np.isfinite(scale) and scale > 0 else 1.0


def build_problem(capture: Capture, options: Options, origin: np.ndarray, scale: float) -> Problem:
    """The fixed data of a solve in normalised units."""
    rays = capture.rays()
    weights = capture.weights
    rays[weights <= 0] = np.nan
    streams = capture.stream_ids
    view = np.nansum(rays, axis=1)
    blind = ~np.isfinite(rays).all(axis=2).any(axis=1)
    view[blind] = capture.R[blind, 2]  # no observation left (all rejected): the optical axis
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    chain = chain_matrix(streams, capture.frame)
    has_chain = np.asarray(chain.sum(axis=1)).ravel() > 0
    return Problem(
        rays=rays,
        C=(capture.C - origin) / scale,
        weights=weights,
        streams=streams,
        view_dirs=view,
        chain=chain,
        prior=np.where(has_chain, options.prior_weight, 0.0),
        rates=known_rates(capture),
        subjects=capture.subjects,
    )


@dataclass(frozen=True)
class Normalised:
    """A capture's problem in the normalised frame of shapes ``X_world`` (:func:`normalise`):
    world = normal * ``scale`` + ``origin``."""

    origin: np.ndarray  # (3,)
    scale: float
    problem: Problem

    def to_normal(self, X_world: np.ndarray) -> np.ndarray:
        """(..., 3) world points in normalised units."""
        return (X_world - self.origin) / self.scale

    def to_world(self, X: np.ndarray) -> np.ndarray:
        """(..., 3) normalised points in world units."""
        return X * self.scale + self.origin


def normalise(capture: Capture, options: Options, X_world: np.ndarray) -> Normalised:
    """The normalised frame of shapes ``X_world`` (N, P, 3) and the capture's problem in it."""
    origin, scale = normalisation(capture, X_world)
    return Normalised(origin, scale, build_problem(capture, options, origin, scale))


def parts(M: sp.spmatrix, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(data, rows, cols) of the entries of ``M``, an event's block, at images ``idx``."""
    coo = M.tocoo()
    return coo.data, idx[coo.row], idx[coo.col]


def assemble(pieces: SparseParts, n: int) -> sp.csr_matrix:
    """The (n, n) CSR matrix of the entries of all ``pieces`` ((data, rows, cols) each)."""
    data, rows, cols = (np.concatenate(v) for v in zip(*pieces, strict=True))
    return sp.csr_matrix((data, (rows, cols)), shape=(n, n))
