"""The observation model: a capture (cameras + 2D points) and the viewing rays it implies."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError
from .sequencing import MDS_SAMPLE

if TYPE_CHECKING:
    from .options import Options

logger = logging.getLogger("dloe_sfm")

REQUIRED_KEYS = ("x", "K", "R", "C")
OPTIONAL_KEYS = ("stream", "frame", "fps", "confidence", "image_names", "symmetric_pairs")
ROTATION_TOLERANCE = 1e-3
"""Largest deviation of a rotation from orthonormal (``|R R^T - I|``, ``|det R - 1|``) that is
accepted and projected to SO(3); files written with single precision or rounded text are
1e-7 .. 1e-5 off."""
INDEX_LIMIT = 2**31 - 1
"""Largest magnitude of a ``stream`` or ``frame`` value."""
MIN_IMAGES = 3


def field_shapes(x_shape: tuple[int, ...]) -> dict[str, tuple[int, ...]]:
    """The shape every per-image field must have given the shape of ``x``."""
    n = x_shape[0]
    return {"K": (n, 3, 3), "R": (n, 3, 3), "C": (n, 3), "stream": (n,), "frame": (n,),
            "fps": (n,), "image_names": (n,), "confidence": tuple(x_shape[:-1])}


def rotation_deviation(R: np.ndarray) -> np.ndarray:
    """(...) deviation of (..., 3, 3) ``R`` from a rotation: ``max(|R R^T - I|, |det R - 1|)``."""
    ortho = np.abs(np.einsum("...ij,...kj->...ik", R, R) - np.eye(3)).max(axis=(-2, -1))
    return np.maximum(ortho, np.abs(np.linalg.det(R) - 1))


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation(s) nearest (..., 3, 3) ``R`` (by SVD); for R within ``ROTATION_TOLERANCE``
    of one."""
    u, _, vt = np.linalg.svd(R)
    return u @ vt


def _integers(values: np.ndarray) -> np.ndarray:
    """``values`` as int64 when they are all integers within ``INDEX_LIMIT``; otherwise float64,
    left for :meth:`Capture.validate` to report."""
    a = np.asarray(values)
    if np.issubdtype(a.dtype, np.integer) and (np.abs(a) <= INDEX_LIMIT).all():
        return a.astype(np.int64, copy=False)
    f = a.astype(np.float64)
    if np.isfinite(f).all() and (f == np.round(f)).all() and (np.abs(f) <= INDEX_LIMIT).all():
        return f.astype(np.int64)
    return f


@dataclass(kw_only=True)
class Capture:
    """P dynamic points seen in N images, each image one camera at one unknown instant.

    With several subjects (people) per image, ``x`` is (N, M, P, 2): M detections per image in
    no particular order (NaN = absent), ``confidence`` (N, M, P); :func:`dloe_sfm.reconstruct`
    then associates the detections into subjects (``core.multitarget``).

    Projection: ``x ~ K R (X - C)`` with no half-pixel offset: pixels mean what ``K`` makes
    them (docs/interfaces.md, "Capture file").

    Attributes
    ----------
    x : (N, P, 2) or (N, M, P, 2) float
        Pixel coordinates; NaN = not observed.
    K : (N, 3, 3) float
        Pinhole intrinsics (pixels already undistorted).
    R : (N, 3, 3) float
        World-to-camera rotations.
    C : (N, 3) float
        Camera centres in world coordinates.
    stream : (N,) int
        Stream (video / camera) id; -1 = lone photo (each becomes a stream of its own).
    frame : (N,) int
        Frame index inside its stream (compared only within a stream).
    fps : (N,) float or None
        Frame rate of the image's stream (a video's nominal rate, from its file or ``--fps``),
        one value per stream; NaN = unknown. The exports count time in seconds with it
        (``core.sync``); the clock fit after the detections' offsets are taken out holds the
        streams' rates at its ratios (docs/method.md, "Known frame rates").
    confidence : (N, P) or (N, M, P) float or None
        Detector scores in [0, 1]; 0 / NaN = not observed. Used as observation weights.
    image_names : (N,) str
    symmetric_pairs : (K, 2) int or None
        Left/right point pairs (e.g. shoulders) a detector may swap; the solver checks them.
    subjects : int
        The people whose points the columns hold, P / subjects columns each, in turn
        (``multitarget.aggregate``); 1 for a capture as read.
    image_ids : dict of str to (N, ...) int
        Per-image ids passed through the solver untouched (``observations.build_capture``:
        ``detection_index``, ``colmap_frame_id``); restricted by :meth:`subset` like the fields.
    """

    x: np.ndarray
    K: np.ndarray
    R: np.ndarray
    C: np.ndarray
    stream: np.ndarray | None = None
    frame: np.ndarray | None = None
    fps: np.ndarray | None = None
    confidence: np.ndarray | None = None
    image_names: np.ndarray | None = None
    symmetric_pairs: np.ndarray | None = None
    subjects: int = 1
    image_ids: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.x = np.asarray(self.x, dtype=np.float64)
        self.K = np.asarray(self.K, dtype=np.float64)
        self.R = np.asarray(self.R, dtype=np.float64)
        self.C = np.asarray(self.C, dtype=np.float64)
        n = self.x.shape[0] if self.x.ndim in (3, 4) else 0
        if self.stream is None:
            self.stream = np.full(n, -1, dtype=np.int64)
        if self.frame is None:
            self.frame = np.zeros(n, dtype=np.int64)
        self.stream = _integers(self.stream)
        self.frame = _integers(self.frame)
        if self.fps is not None:
            self.fps = np.asarray(self.fps, dtype=np.float64)
        if self.confidence is not None:
            self.confidence = np.asarray(self.confidence, dtype=np.float64)
        if self.image_names is None:
            self.image_names = np.array([f"image_{i:05d}" for i in range(n)])
        self.image_names = np.asarray(self.image_names).astype(str)
        if self.symmetric_pairs is not None:
            self.symmetric_pairs = np.asarray(self.symmetric_pairs).astype(np.int64).reshape(-1, 2)
        self.image_ids = {k: np.asarray(v) for k, v in self.image_ids.items()}

    @property
    def num_images(self) -> int:
        return self.x.shape[0]

    @property
    def num_points(self) -> int:
        return self.x.shape[-2]

    @property
    def num_people(self) -> int:
        """M, the detections per image of a several-subject capture (1 for (N, P, 2) ``x``)."""
        return self.x.shape[1] if self.x.ndim == 4 else 1

    def validate(self, source: str = "capture", *, empty_images: bool = False) -> Capture:
        """Check shapes, values and solvability; raise InputError naming the field and image.

        ``empty_images``: images that observe no point pass (a reader then leaves them out,
        ``io.without_empty_images``); by default they are an error.

        Rotations within ``ROTATION_TOLERANCE`` of orthonormal are projected to SO(3): the
        returned capture carries the projected ones (the largest deviation is logged).
        """
        x, K, R, C = self.x, self.K, self.R, self.C
        if x.ndim not in (3, 4) or x.shape[-1] != 2:
            raise InputError(
                f"{source}: field 'x' must have shape (N, P, 2) or (N, M, P, 2), got {x.shape}"
            )
        n, p = x.shape[0], x.shape[-2]
        if n < MIN_IMAGES or p < 1:
            raise InputError(
                f"{source}: field 'x' needs at least {MIN_IMAGES} images and 1 point, "
                f"got {x.shape}"
            )
        shapes = field_shapes(x.shape)
        for name in ("K", "R", "C", "stream", "frame", "fps", "image_names", "confidence"):
            arr = getattr(self, name)
            if arr is not None and arr.shape != shapes[name]:
                raise InputError(
                    f"{source}: field '{name}' must have shape {shapes[name]}, got {arr.shape}"
                )
        for name, arr in self.image_ids.items():
            if arr.ndim < 1 or arr.shape[0] != n:
                raise InputError(
                    f"{source}: image ids '{name}' must have one entry per image ({n}), got "
                    f"shape {arr.shape}"
                )
        for name, arr in (("K", K), ("R", R), ("C", C)):
            bad = ~np.isfinite(arr.reshape(n, -1)).all(axis=1)
            if bad.any():
                raise InputError(
                    f"{source}: field '{name}' is not finite for image {self._name(np.argmax(bad))}"
                )
        if np.isinf(x).any():
            i = int(np.argwhere(np.isinf(x))[0, 0])
            raise InputError(
                f"{source}: field 'x' has an infinite coordinate in image {self._name(i)}"
            )
        self._check_intrinsics(source)
        for name in ("stream", "frame"):
            arr = getattr(self, name)
            if not np.issubdtype(arr.dtype, np.integer):
                bad = ~np.isfinite(arr) | (arr != np.round(arr)) | (np.abs(arr) > INDEX_LIMIT)
                i = int(np.argmax(bad))
                raise InputError(
                    f"{source}: field '{name}' must hold integers within +-{INDEX_LIMIT}, "
                    f"got {arr[i]} for image {self._name(i)}"
                )
        if not 1 <= self.subjects <= p or p % self.subjects:
            raise InputError(f"{source}: field 'subjects' must divide the {p} points, got "
                             f"{self.subjects}")
        pairs = self.symmetric_pairs
        if pairs is not None and pairs.size and (
            (pairs < 0).any() or (pairs >= p).any() or (pairs[:, 0] == pairs[:, 1]).any()
        ):
            raise InputError(
                f"{source}: field 'symmetric_pairs' must pair two different points in 0..{p - 1}"
            )
        visible = self.visible.reshape(n, -1, p)
        empty = ~visible.any(axis=(1, 2))
        if empty.any() and not empty_images:
            raise InputError(f"{source}: image {self._name(np.argmax(empty))} observes no point")
        never = ~visible.any(axis=(0, 1))
        if never.any():
            raise InputError(f"{source}: point {int(np.argmax(never))} is observed in no image")
        streams = self.stream_ids
        if np.unique(streams).size < 2:
            raise InputError(
                f"{source}: all {n} images belong to one stream; DLOE needs images from at least "
                "two cameras / streams to triangulate"
            )
        for s in np.unique(self.stream[self.stream >= 0]):
            frames = self.frame[self.stream == s]
            if np.unique(frames).size != frames.size:
                raise InputError(f"{source}: stream {s} has repeated values in field 'frame'")
        self._check_fps(source)
        return self._with_rotations(source)

    def _check_fps(self, source: str) -> None:
        """Every ``fps`` positive (or NaN, unknown) and one value per stream."""
        if self.fps is None:
            return
        fps = self.fps
        bad = ~(np.isnan(fps) | (np.isfinite(fps) & (fps > 0)))
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(f"{source}: field 'fps' must be a positive frame rate or NaN "
                             f"(unknown), got {fps[i]:g} for image {self._name(i)}")
        for s in np.unique(self.stream[self.stream >= 0]):
            rates = fps[self.stream == s]
            if not (np.array_equal(rates, np.full_like(rates, rates[0]), equal_nan=True)):
                raise InputError(f"{source}: field 'fps' holds several rates for stream {s} "
                                 f"({', '.join(f'{r:g}' for r in np.unique(rates))}); a "
                                 "stream has one")

    def _check_intrinsics(self, source: str) -> None:
        """Positive focal lengths and a (0, 0, 1) bottom row (pinhole K) in every image."""
        K = self.K
        focal = np.stack([K[:, 0, 0], K[:, 1, 1]], axis=1)
        bad = (focal <= 0).any(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(
                f"{source}: field 'K' has focal lengths ({focal[i, 0]:g}, {focal[i, 1]:g}) "
                f"for image {self._name(i)}; they must be positive"
            )
        bad = np.abs(K[:, 2] - np.array([0.0, 0.0, 1.0])).max(axis=1) > 1e-9
        if bad.any():
            raise InputError(
                f"{source}: field 'K' must have the bottom row (0, 0, 1) (a pinhole), got "
                f"{K[int(np.argmax(bad)), 2].tolist()} for image {self._name(np.argmax(bad))}"
            )
        bad = np.abs(np.linalg.det(K)) < 1e-12
        if bad.any():
            raise InputError(
                f"{source}: field 'K' is singular for image {self._name(np.argmax(bad))}"
            )

    def _with_rotations(self, source: str) -> Capture:
        """Self with R projected to SO(3) (nearest rotation, by SVD) when it deviates."""
        deviation = rotation_deviation(self.R)
        worst = int(np.argmax(deviation))
        if deviation[worst] > ROTATION_TOLERANCE:
            raise InputError(
                f"{source}: field 'R' is not a rotation for image {self._name(worst)} (deviates "
                f"{deviation[worst]:.2g} from orthonormal, tolerance {ROTATION_TOLERANCE:g})"
            )
        if deviation[worst] <= 1e-12:
            return self
        logger.info(
            "%s: rotations projected to SO(3), largest deviation %.2g (image %s)",
            source, deviation[worst], self._name(worst),
        )
        return replace(self, R=nearest_rotation(self.R))

    def memory_estimate(self, options: Options) -> int:
        """Bytes the solve of this capture needs at its peak, roughly (:func:`memory_estimate`)."""
        counts = np.unique(self.stream_ids, return_counts=True)[1]
        return memory_estimate(
            self.num_images, self.num_points, num_people=self.num_people,
            num_streams=counts.size, num_videos=int((counts >= 2).sum()),
            num_candidates=options.num_candidates,
        )

    def _name(self, i: int) -> str:
        return f"{int(i)} ({str(self.image_names[int(i)])!r})"

    @property
    def visible(self) -> np.ndarray:
        """(N, P) (or (N, M, P)) bool: observed, finite and with positive confidence."""
        vis = np.isfinite(self.x).all(axis=-1)
        if self.confidence is not None:
            conf = np.nan_to_num(self.confidence, nan=0.0)
            vis &= conf > 0
        return vis

    @property
    def weights(self) -> np.ndarray:
        """(N, P) (or (N, M, P)) observation weights: confidence where given, else 1; 0 = unseen."""
        w = self.visible.astype(np.float64)
        if self.confidence is not None:
            w *= np.clip(np.nan_to_num(self.confidence, nan=0.0), 0.0, 1.0)
        return w

    @property
    def stream_ids(self) -> np.ndarray:
        """(N,) int: stream ids with every lone photo (-1) given a stream id of its own."""
        ids = self.stream.copy()
        lone = ids < 0
        start = (ids.max() + 1) if (~lone).any() else 0
        ids[lone] = start + np.arange(lone.sum())
        return ids

    def rays(self) -> np.ndarray:
        """(N, P, 3) unit world viewing rays ``R^T K^-1 [x; 1]``; NaN = unobserved."""
        return pixel_rays(self.x, self.K, self.R)

    def subset(self, idx: np.ndarray) -> Capture:
        """The capture restricted to images ``idx`` (same points)."""
        idx = np.asarray(idx)
        return Capture(
            x=self.x[idx],
            K=self.K[idx],
            R=self.R[idx],
            C=self.C[idx],
            stream=self.stream[idx],
            frame=self.frame[idx],
            fps=None if self.fps is None else self.fps[idx],
            confidence=None if self.confidence is None else self.confidence[idx],
            image_names=self.image_names[idx],
            symmetric_pairs=self.symmetric_pairs,
            subjects=self.subjects,
            image_ids={k: v[idx] for k, v in self.image_ids.items()},
        )


def pixel_rays(x: np.ndarray, K: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Unit world rays of pixels.

    x (N, P, 2), K (N, 3, 3), R (N, 3, 3) world-to-camera -> (N, P, 3), NaN where x is NaN.
    """
    n, p = x.shape[:2]
    h = np.concatenate([x, np.ones((n, p, 1))], axis=2)
    cam = np.einsum("nij,npj->npi", np.linalg.inv(K), h)
    world = np.einsum("nji,npj->npi", R, cam)
    return world / np.linalg.norm(world, axis=2, keepdims=True)


def project(X: np.ndarray, K: np.ndarray, R: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Pinhole projection ``x ~ K R (X - C)``: X (N, P, 3) -> (N, P, 2)."""
    cam = np.einsum("nij,npj->npi", R, X - C[:, None, :])
    h = np.einsum("nij,npj->npi", K, cam)
    return h[..., :2] / h[..., 2:3]


def memory_estimate(
    num_images: int, num_points: int, *, num_people: int = 1, num_streams: int = 1,
    num_videos: int = 0, num_candidates: int = 8,
) -> int:
    """Bytes a solve needs at its peak beyond what is already loaded, roughly, on the high side.

    The dominant arrays: the dense (N', N') ones of sequencing (N' = N images, or with two or
    more videos, streams of 2+ images, at most ``sequencing.MDS_SAMPLE``: arc distances, the
    eigenproblem of an event), every image's place on every stream (streams x N), the pair
    scores of the initialisation (blocks of 64 images against all, (64, N, M P, 3); with videos
    3 partners per other video, a stream at a time), the W-step's candidate shapes
    (N, k, 3 M P) and the per-observation arrays (N, M P).
    """
    n = int(num_images)
    k = max(min(int(num_candidates), n - 1), 1)  # the solver clamps k to N - 1
    obs = n * int(num_people) * int(num_points)
    table = min(n, MDS_SAMPLE) if num_videos >= 2 else n
    dense = 8 * table * table + 2 * int(num_streams) * n
    pairs = (3 if num_videos >= 2 else min(n, 64)) * 17 * obs
    candidates = 6 * k * 3 * obs
    per_observation = 80 * obs
    return 8 * (dense + pairs + candidates + per_observation) + (64 << 20)
