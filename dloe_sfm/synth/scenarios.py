"""Harder captures built from the mocap protocol: several events, several people, detector errors.

- :func:`simulate_events`: clips of different motions filmed one after another by the same
  streams (frame numbers run on through the gaps between clips).
- :func:`simulate_people`: several people in the same images, the detections of every image in
  a random order (a detector knows no identities).
- :func:`add_outliers` and :func:`swap_symmetric`: wrong detections and left/right swaps.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..core.capture import Capture
from ..errors import InputError
from ..truth import GroundTruth, Simulated
from .mocap import (
    MocapSequence,
    SimulationSettings,
    _interpolate,
    _render,
    _ring_radius,
    _stream_samples,
    _window,
)


def _centred(pos: np.ndarray, at: np.ndarray) -> np.ndarray:
    """``pos`` moved horizontally (x, z) so its mean sits at ``at`` (height kept)."""
    shift = at - pos.reshape(-1, 3).mean(axis=0)
    shift[1] = 0.0
    return pos + shift


def _turned(pos: np.ndarray, angle: float) -> np.ndarray:
    """``pos`` (T, J, 3) turned by ``angle`` radians about the vertical (y) through its mean."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    centre = pos.reshape(-1, 3).mean(axis=0)
    return (pos - centre) @ rot.T + centre


def _same_rate(seqs: list[MocapSequence]) -> float:
    fps = {s.fps for s in seqs}
    joints = {s.positions.shape[1] for s in seqs}
    if len(fps) != 1 or len(joints) != 1:
        raise InputError("sequences to mix need the same frame rate and number of joints")
    return fps.pop()


def simulate_events(
    seqs: list[MocapSequence], settings: SimulationSettings | None = None, *, gap: float = 2.0
) -> Simulated:
    """The clips of ``seqs`` one after another, ``gap`` seconds apart, seen by one camera ring.

    Each clip is moved to the ring's centre. Truth as :func:`simulate` plus ``events`` (N,) the
    clip of every image.
    """
    s = settings or SimulationSettings()
    rng = np.random.default_rng(s.seed)
    fps = _same_rate(seqs)
    clips = [_centred(_window(q, s), np.zeros(3)) for q in seqs]
    starts = np.cumsum([0.0] + [c.shape[0] + gap * fps for c in clips[:-1]])
    span = starts[-1] + clips[-1].shape[0] - 1
    t, stream, frame, camera = _stream_samples(span, fps, s, rng)
    event = np.full(t.size, -1)
    X = np.empty((t.size, clips[0].shape[1], 3))
    for k, (clip, t0) in enumerate(zip(clips, starts, strict=True)):
        inside = (t >= t0) & (t <= t0 + clip.shape[0] - 1)
        event[inside] = k
        X[inside] = _interpolate(clip, t[inside] - t0)
    keep = event >= 0
    X, t, stream, frame, camera, event = (
        a[keep] for a in (X, t, stream, frame, camera, event))
    everything = np.concatenate([c.reshape(-1, 3) for c in clips])
    radius = _ring_radius(s, everything, np.zeros(3))
    return _render(X, stream, frame, camera, np.zeros(3), radius, s, rng, t / fps,
                   seqs[0].parents, event)


def simulate_people(
    seqs: list[MocapSequence],
    settings: SimulationSettings | None = None,
    *,
    spacing: float = 2.0,
    shuffle: bool = True,
    turns: tuple[float, ...] | None = None,
) -> Simulated:
    """One person per sequence, side by side ``spacing`` metres apart along x, in every image.
    ``turns``: each person's motion first turned by this many radians about the vertical through
    its centre (pi: a walk along z comes back the other way, so two walkers cross).

    Returns a several-subject capture: ``x`` (N, S, P, 2) with the detections of every image in a
    random order (``shuffle``; confidence and the detector's outliers / swaps follow the slots).
    Truth: ``X`` (N, S, P, 3) by person, ``subjects`` (N, S) the person of every detection slot,
    ``t`` (N,) seconds.
    """
    s = settings or SimulationSettings()
    rng = np.random.default_rng(s.seed)
    fps = _same_rate(seqs)
    clips = [_window(q, s) for q in seqs]
    if turns is not None:
        if len(turns) != len(seqs):
            raise InputError(f"{len(turns)} turns for {len(seqs)} people")
        clips = [_turned(c, a) for c, a in zip(clips, turns, strict=True)]
    length = min(c.shape[0] for c in clips)
    offsets = (np.arange(len(seqs)) - (len(seqs) - 1) / 2) * spacing
    clips = [
        _centred(c[:length], np.array([dx, 0.0, 0.0])) for c, dx in zip(clips, offsets, strict=True)
    ]
    t, stream, frame, camera = _stream_samples(length - 1, fps, s, rng)
    X = np.stack([_interpolate(c, t) for c in clips], axis=1)
    everything = np.concatenate([c.reshape(-1, 3) for c in clips])
    radius = _ring_radius(s, everything, np.zeros(3))
    capture, truth = _render(X, stream, frame, camera, np.zeros(3), radius, s, rng, t / fps,
                             seqs[0].parents)
    slots = np.tile(np.arange(len(seqs)), (t.size, 1))
    if shuffle:
        slots = rng.permuted(slots, axis=1)

    def by_slot(a: np.ndarray | None) -> np.ndarray | None:
        """(N, S, ...) ``a`` with the slots of every image in the shuffled order."""
        if a is None:
            return None
        return np.take_along_axis(a, slots.reshape(*slots.shape, *(1,) * (a.ndim - 2)), axis=1)

    capture = replace(capture, x=by_slot(capture.x), confidence=by_slot(capture.confidence))
    truth = replace(truth, x_clean=by_slot(truth.x_clean), outliers=by_slot(truth.outliers),
                    swaps=by_slot(truth.swaps), subjects=slots)
    return Simulated(capture, truth)


def limit_presence(
    capture: Capture, truth: GroundTruth, person: int, start: float, end: float
) -> Simulated:
    """A copy of a several-subject capture (``simulate_people``) where ``person`` is detected
    only from ``start`` to ``end`` seconds (one who enters late and leaves early): its
    detections at other times are removed and their slots' truth ``subjects`` set to -1."""
    away = (truth.subjects == person) & ~((truth.t >= start) & (truth.t <= end))[:, None]
    x = np.where(away[..., None, None], np.nan, capture.x)
    confidence = None
    if capture.confidence is not None:
        confidence = np.where(away[..., None], 0.0, capture.confidence)
    return Simulated(replace(capture, x=x, confidence=confidence),
                     replace(truth, subjects=np.where(away, -1, truth.subjects)))


def add_false_detections(
    capture: Capture, truth: GroundTruth, fraction: float, *, low: float = 50.0,
    high: float = 200.0, seed: int = 0,
) -> Simulated:
    """A copy of a several-subject capture with one more detection slot, holding in
    ``fraction`` of the images a false detection: a person's detection from another image
    (another instant and camera), moved ``low``-``high`` pixels in a random direction, like a
    reflection or a misplaced skeleton that supports nobody. Its truth ``subjects`` is -1 and
    its ``x_clean`` NaN."""
    rng = np.random.default_rng(seed)
    n = capture.num_images
    held = np.argwhere(np.isfinite(capture.x).all(axis=-1).any(axis=-1))  # (image, slot)
    if np.unique(held[:, 0]).size < 2:
        raise ValueError("false detections are copied from other images: two need detections")
    hit = np.flatnonzero(rng.random(n) < fraction)
    source = held[rng.integers(0, len(held), hit.size)]
    while (same := source[:, 0] == hit).any():  # another image's, never the image's own
        source[same] = held[rng.integers(0, len(held), same.sum())]
    angle = rng.uniform(0, 2 * np.pi, hit.size)
    shift = rng.uniform(low, high, hit.size)[:, None] * np.stack([np.cos(angle), np.sin(angle)], 1)
    extra = np.full((n, 1, *capture.x.shape[2:]), np.nan)
    extra[hit, 0] = capture.x[source[:, 0], source[:, 1]] + shift[:, None]
    confidence = None
    if capture.confidence is not None:
        more = np.zeros((n, 1, capture.confidence.shape[2]))
        more[hit, 0] = capture.confidence[source[:, 0], source[:, 1]]
        confidence = np.concatenate([capture.confidence, more], axis=1)

    def padded(a: np.ndarray | None, fill: float | bool) -> np.ndarray | None:
        """``a`` (N, M, ...) with the new slot holding ``fill``."""
        if a is None:
            return None
        return np.concatenate([a, np.full((n, 1, *a.shape[2:]), fill, dtype=a.dtype)], axis=1)

    return Simulated(
        replace(capture, x=np.concatenate([capture.x, extra], axis=1), confidence=confidence),
        replace(truth, subjects=padded(truth.subjects, -1), x_clean=padded(truth.x_clean, np.nan),
                outliers=padded(truth.outliers, False), swaps=padded(truth.swaps, False)),
    )


def add_outliers(
    capture: Capture, truth: GroundTruth, fraction: float, *, low: float = 20.0,
    high: float = 100.0, seed: int = 0,
) -> Simulated:
    """A copy with ``fraction`` of the observations moved ``low``-``high`` pixels in a random
    direction (wrong detections); the truth's ``outliers`` marks them."""
    rng = np.random.default_rng(seed)
    x = capture.x.copy()
    seen = np.isfinite(x).all(axis=-1)
    hit = seen & (rng.random(seen.shape) < fraction)
    angle = rng.uniform(0, 2 * np.pi, hit.sum())
    length = rng.uniform(low, high, hit.sum())
    x[hit] += length[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    return Simulated(replace(capture, x=x), replace(truth, outliers=hit))


def swap_symmetric(
    capture: Capture, truth: GroundTruth, pairs: np.ndarray, fraction: float, *, seed: int = 0
) -> Simulated:
    """A copy where every (image, pair) of two observed points is swapped with probability
    ``fraction`` (a detector confusing left and right); the truth's ``swaps`` (N, K) marks
    them and ``symmetric_pairs`` is set."""
    rng = np.random.default_rng(seed)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    x = capture.x.copy()
    seen = np.isfinite(x).all(axis=-1)
    both = seen[..., pairs[:, 0]] & seen[..., pairs[:, 1]]
    hit = both & (rng.random(both.shape) < fraction)
    idx = np.nonzero(hit)
    a, b = pairs[idx[-1], 0], pairs[idx[-1], 1]
    head = idx[:-1]
    x[(*head, a)], x[(*head, b)] = capture.x[(*head, b)], capture.x[(*head, a)]
    return Simulated(replace(capture, x=x, symmetric_pairs=pairs), replace(truth, swaps=hit))
