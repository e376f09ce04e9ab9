"""The paper's motion-capture protocol (docs/method.md, "Evaluation protocol"): a ring of
unsynchronised cameras.

Four static 1000 x 1000 px cameras (f = 1000, principal point (500, 500)) on a ring around the
motion centre (yaw +-45 deg, +-135 deg, looking inward). Each stream samples the motion at the same
rate with start offsets 0, 1/4, 1/2, 3/4 of a period, so no two images share an instant; or, as
field captures do, each at its own rate (``rates``) from a random start (``random_offsets``), the
motion interpolated at the true instants. Points are projected without clipping to the image
bounds (as in the paper's experiments), with Gaussian noise or a detector error model
(``detector``, :mod:`dloe_sfm.synth.detector`).
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import numbers
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from ..core.capture import Capture, project
from ..core.options import shown
from ..errors import InputError
from ..io import read_mocap
from ..truth import GroundTruth, Simulated
from .detector import DETECTORS, DetectorModel, detect


@dataclass(kw_only=True)
class MocapSequence:
    """A motion: ``positions`` (T, J, 3) metres at ``fps`` Hz; ``parents`` (J,), -1 = root."""

    positions: np.ndarray
    fps: float
    parents: np.ndarray
    name: str = "motion"

    @property
    def edges(self) -> list[tuple[int, int]]:
        return [(int(j), int(p)) for j, p in enumerate(self.parents) if p >= 0]


def symmetric_pairs(parents: np.ndarray) -> np.ndarray:
    """(K, 2) left/right joint pairs of a skeleton tree: the joints of sibling subtrees of the
    same shape (two legs under the pelvis, two arms under the chest), matched depth first."""
    parents = np.asarray(parents)
    children = [np.flatnonzero(parents == j).tolist() for j in range(parents.size)]

    def shape(j: int) -> tuple:
        return tuple(sorted(shape(c) for c in children[j]))

    def preorder(j: int) -> list[int]:
        return [j] + [i for c in sorted(children[j], key=shape) for i in preorder(c)]

    pairs = []
    for kids in children:
        by_shape: dict[tuple, list[int]] = {}
        for c in kids:
            by_shape.setdefault(shape(c), []).append(c)
        for twins in by_shape.values():
            if len(twins) == 2:
                pairs += zip(preorder(twins[0]), preorder(twins[1]), strict=True)
    return np.array(sorted(pairs), dtype=np.int64).reshape(-1, 2)


def load_mocap(path: Path | str) -> MocapSequence:
    """Read a shared mocap ``.npz`` (positions, fps, parents) and drop glitched leading frames.

    Some sequences start with a frame whose joints jump by tens of centimetres to the next one
    (an artefact of the forward kinematics): leading frames whose step exceeds 5 x the 99th
    percentile step are removed.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such mocap file")
    positions, fps, parents = read_mocap(path)
    if parents is None:
        parents = np.full(positions.shape[1], -1)
    step = np.linalg.norm(np.diff(positions, axis=0), axis=2).max(axis=1)
    limit = 5 * np.percentile(step, 99)
    start = 0
    while start < step.size and step[start] > limit:
        start += 1
    return MocapSequence(positions=positions[start:], fps=fps, parents=parents, name=path.stem)


def pipeline_parser(script: str, doc: str | None, name: str) -> argparse.ArgumentParser:
    """The command line the repository's mocap pipelines (``pipelines/*/pipeline.py``, at
    ``script``) start from: ``doc`` as help, ``--data`` (default the shared CMU clips beside the
    repository, ``../shared/data/mocap``) and ``--out`` (default ``outputs/<name>`` in it)."""
    repo = Path(script).resolve().parents[2]
    parser = argparse.ArgumentParser(allow_abbrev=False, description=doc,
                                     formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--data", type=Path, default=repo.parent / "shared" / "data" / "mocap",
                        help="folder of mocap .npz clips")
    parser.add_argument("--out", type=Path, default=repo / "outputs" / name)
    return parser


def load_pipeline(pipelines: Path, name: str) -> ModuleType:
    """``<pipelines>/<name>/pipeline.py`` as the module ``pipeline_<name>``, executed once:
    registered in ``sys.modules`` (dataclasses look their module up there), every later call
    returns that module."""
    key = f"pipeline_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, pipelines / name / "pipeline.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module
        spec.loader.exec_module(module)
    return sys.modules[key]


def sibling_pipeline(script: str, name: str) -> ModuleType:
    """``pipelines/<name>/pipeline.py`` beside the pipeline at ``script`` (:func:`load_pipeline`):
    one pipeline's scores, cases or renderer used by another."""
    return load_pipeline(Path(script).resolve().parents[1], name)


def resolve_motion(data: Path, name: str) -> Path:
    """The mocap file of ``name``: a path, ``data/<name>``, ``data/<name>.npz`` (the bundled
    clips) or ``data/li2018_train_<name>.npz`` (the CMU set's file names)."""
    for path in (Path(name), data / name, data / f"{name}.npz", data / f"li2018_train_{name}.npz"):
        if path.is_file():
            return path
    raise InputError(f"motion '{name}' not found in {data}")

@dataclass(kw_only=True)
class SimulationSettings:
    """The protocol's knobs; defaults are the paper's base setting (4 x 30 Hz, no noise)."""

    rate: float = 30.0
    """Frames per second of every stream."""
    rates: tuple[float, ...] | None = None
    """Frames per second of each stream (``num_streams`` of them), overriding ``rate``."""
    random_offsets: bool = False
    """Start each stream at a uniform random time within its first period (else streams start
    k / num_streams of a period apart)."""
    num_streams: int = 4
    lone_photos: int = 0
    """Lone photos besides the streams (``num_streams`` may then be 0): each its own handheld
    camera anywhere around the motion (``crowd_cameras``), at a uniform random instant."""
    bursts: int = 0
    """Short bursts besides the streams: handheld cameras placed as lone photos, each taking 2-5
    frames at 1-10 Hz from a random instant (short streams, frame order known)."""
    noise: float = 0.0
    """Std of Gaussian 2D noise, pixels."""
    detector: str | None = None
    """Name of a bundled detector error model (``openpose``) replacing ``noise``."""
    missing: float = 0.0
    """Fraction of (image, point) observations removed at random."""
    drop: float = 0.0
    """Fraction of images dropped at random (non-uniform density)."""
    duration: float | None = None
    """Seconds of motion to use from ``start`` (None = all)."""
    start: float = 0.0
    radius: float | None = None
    """Camera ring radius around the motion centre, metres; None = 3 m, or the motion's horizontal
    extent + 2 m when it travels further (so nobody walks through the ring)."""
    focal: float = 1000.0
    image_size: int = 1000
    seed: int = 0

    def __post_init__(self) -> None:
        """Every knob in its range (one-line InputError naming it, e.g. ``--rate``)."""
        def check(name: str, ok: bool, what: str) -> None:
            if not ok:
                raise InputError(f"--{name.replace('_', '-')} must be {what}, "
                                 f"got {shown(getattr(self, name))}")

        def is_finite(value: object) -> bool:
            try:
                return isinstance(value, numbers.Real) and math.isfinite(value)
            except OverflowError:  # an int beyond float's range
                return False

        values = asdict(self)
        finite = {k: is_finite(v) for k, v in values.items()}
        integral = {k: isinstance(v, numbers.Integral) for k, v in values.items()}
        check("rate", finite["rate"] and 0 < self.rate <= 1000, "in (0, 1000] frames/s")
        check("num_streams", integral["num_streams"] and 0 <= self.num_streams <= 64,
              "an integer in [0, 64]")
        check("lone_photos", integral["lone_photos"] and 0 <= self.lone_photos <= 100000,
              "an integer in [0, 100000]")
        check("bursts", integral["bursts"] and 0 <= self.bursts <= 10000,
              "an integer in [0, 10000]")
        check("num_streams", self.num_streams + self.lone_photos + self.bursts > 0,
              "at least 1 when there are no --lone-photos or --bursts")
        check("rates", self.rates is None or (
            isinstance(self.rates, tuple | list) and len(self.rates) == self.num_streams
            and all(is_finite(r) and 0 < r <= 1000 for r in self.rates)),
            f"{shown(self.num_streams)} rates (--num-streams) in (0, 1000] frames/s")
        check("random_offsets", isinstance(self.random_offsets, bool), "true or false")
        check("noise", finite["noise"] and self.noise >= 0, "a finite number >= 0 px")
        check("detector", self.detector is None or self.detector in DETECTORS,
              f"one of {', '.join(DETECTORS)}")
        check("detector", self.detector is None or self.noise == 0,
              "left unset when --noise is given (the detector model replaces it)")
        check("missing", finite["missing"] and 0 <= self.missing < 1, "in [0, 1)")
        check("drop", finite["drop"] and 0 <= self.drop < 1, "in [0, 1)")
        check("duration", self.duration is None or (finite["duration"] and self.duration > 0),
              "a number of seconds > 0")
        check("start", finite["start"] and self.start >= 0, "a number of seconds >= 0")
        check("radius", self.radius is None or (finite["radius"] and self.radius > 0),
              "a distance > 0 m")
        check("focal", finite["focal"] and self.focal > 0, "a focal length > 0 px")
        check("image_size", integral["image_size"] and 16 <= self.image_size <= 100000,
              "an integer in [16, 100000] px")
        check("seed", integral["seed"] and self.seed >= 0, "an integer >= 0")


def ring_cameras(
    centre: np.ndarray,
    *,
    num: int = 4,
    radius: float = 3.0,
    focal: float = 1000.0,
    image_size: int = 1000,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``num`` cameras on a horizontal ring (y up) looking at ``centre``.

    Returns K (num, 3, 3), R (num, 3, 3) world-to-camera, C (num, 3). Four cameras sit at yaw
    45, 135, 225, 315 degrees (the authors' layout); other counts are spread evenly from 45 degrees.
    """
    yaw = np.deg2rad(45.0 + 360.0 * np.arange(num) / num)
    C = centre + radius * np.stack([np.sin(yaw), np.zeros(num), np.cos(yaw)], axis=1)
    K = np.array([[focal, 0, image_size / 2], [0, focal, image_size / 2], [0, 0, 1.0]])
    R = np.empty((num, 3, 3))
    for i in range(num):
        z = centre - C[i]
        z /= np.linalg.norm(z)
        x = np.cross(np.array([0.0, -1.0, 0.0]), z)  # image y points down = world -y
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R[i] = np.stack([x, y, z])
    return np.repeat(K[None], num, axis=0), R, C


def _window(seq: MocapSequence, s: SimulationSettings) -> np.ndarray:
    """The (T, J, 3) frames of ``seq`` between ``s.start`` and ``s.start + s.duration``."""
    pos = seq.positions
    first = int(round(s.start * seq.fps))
    last = pos.shape[0] if s.duration is None else min(
        pos.shape[0], first + int(round(s.duration * seq.fps))
    )
    if last - first < 2:
        raise InputError(f"{seq.name}: the chosen window has fewer than 2 frames")
    return pos[first:last]


def _ring_radius(s: SimulationSettings, points: np.ndarray, centre: np.ndarray) -> float:
    if s.radius is not None:
        return s.radius
    return max(3.0, float(np.linalg.norm((points - centre)[:, [0, 2]], axis=1).max()) + 2.0)


def _rates(s: SimulationSettings) -> tuple[float, ...]:
    """Frames per second of every stream."""
    return s.rates or (s.rate,) * s.num_streams


def _stream_samples(
    span: float, fps: float, s: SimulationSettings, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t, stream, frame, camera) of streams sampling [0, ``span``] (mocap frames at ``fps``) at
    ``s.rate`` with start offsets k / num_streams of a period (or each at its own ``s.rates``
    from a random time in its first period: ``s.random_offsets``), minus ``s.drop`` of the
    images; then ``s.bursts`` short streams and ``s.lone_photos`` lone photos (stream -1) at
    random instants. ``camera`` indexes the ring's cameras, then one handheld camera per burst
    and per lone photo."""
    rates = _rates(s)
    times, streams, frames = [np.zeros(0)], [np.zeros(0)], [np.zeros(0)]
    for k in range(s.num_streams):
        period = fps / rates[k]
        start = rng.uniform(0, period) if s.random_offsets else k * period / s.num_streams
        t = start + period * np.arange(int(span / period) + 1)
        t = t[t <= span]
        times.append(t)
        streams.append(np.full(t.size, k))
        frames.append(np.arange(t.size))
    t, stream, frame = (np.concatenate(v).astype(d) for v, d in (
        (times, np.float64), (streams, np.int64), (frames, np.int64)))
    if s.drop > 0:
        keep = rng.random(t.size) >= s.drop
        t, stream, frame = t[keep], stream[keep], frame[keep]
    camera = stream.copy()
    if s.bursts or s.lone_photos:
        hand_t, hand_stream, hand_frame = [t], [stream], [frame]
        for b in range(s.bursts):
            period = fps / rng.uniform(1.0, 10.0)
            count = min(int(rng.integers(2, 6)), int(span / period) + 1)
            start = rng.uniform(0, span - (count - 1) * period)
            hand_t.append(start + period * np.arange(count))
            hand_stream.append(np.full(count, s.num_streams + b))
            hand_frame.append(np.arange(count))
        hand_t.append(rng.uniform(0, span, s.lone_photos))
        hand_stream.append(np.full(s.lone_photos, -1))
        hand_frame.append(np.zeros(s.lone_photos, dtype=np.int64))
        t, stream, frame = (np.concatenate(v) for v in (hand_t, hand_stream, hand_frame))
        camera = np.where(stream >= 0, stream,
                          s.num_streams + s.bursts + np.cumsum(stream < 0) - 1)
    return t, stream, frame, camera


def crowd_cameras(
    centre: np.ndarray,
    num: int,
    rng: np.random.Generator,
    *,
    radius: float = 3.0,
    focal: float = 1000.0,
    image_size: int = 1000,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``num`` handheld cameras anywhere around ``centre`` (y up): a uniform random direction,
    1 to 2.5 x ``radius`` away, held 0.6 m below to 0.8 m above it, aimed within about 0.2 m
    of it with up to 5 degrees of roll, the focal length scaled with the distance (0.8-1.25 x,
    so the subject fills about as much of the picture as in the ring's cameras).

    Returns K (num, 3, 3), R (num, 3, 3) world-to-camera, C (num, 3)."""
    yaw = rng.uniform(0, 2 * np.pi, num)
    dist = radius * rng.uniform(1.0, 2.5, num)
    C = centre + np.stack([dist * np.sin(yaw), rng.uniform(-0.6, 0.8, num),
                           dist * np.cos(yaw)], axis=1)
    target = centre + 0.2 * rng.standard_normal((num, 3))
    f = focal * dist / radius * rng.uniform(0.8, 1.25, num)
    roll = np.deg2rad(rng.uniform(-5.0, 5.0, num))
    K = np.zeros((num, 3, 3))
    K[:, 0, 0] = K[:, 1, 1] = f
    K[:, :2, 2] = image_size / 2
    K[:, 2, 2] = 1.0
    R = np.empty((num, 3, 3))
    for i in range(num):
        z = target[i] - C[i]
        z /= np.linalg.norm(z)
        x = np.cross(np.array([0.0, -1.0, 0.0]), z)
        x /= np.linalg.norm(x)
        c, sn = np.cos(roll[i]), np.sin(roll[i])
        spin = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        R[i] = spin @ np.stack([x, np.cross(z, x), z])
    return K, R, C


def _interpolate(pos: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear interpolation of (T, J, 3) at fractional frames ``t`` (rates not dividing fps)."""
    lo = np.clip(np.floor(t).astype(int), 0, pos.shape[0] - 1)
    hi = np.minimum(lo + 1, pos.shape[0] - 1)
    a = (t - lo)[:, None, None]
    return (1 - a) * pos[lo] + a * pos[hi]


def _render(
    X_true: np.ndarray,
    stream: np.ndarray,
    frame: np.ndarray,
    camera: np.ndarray,
    centre: np.ndarray,
    radius: float,
    s: SimulationSettings,
    rng: np.random.Generator,
    t: np.ndarray,
    parents: np.ndarray,
    events: np.ndarray | None = None,
) -> Simulated:
    """Project (N, ..., 3) points into the ring's cameras and the handheld ones of ``camera``
    (``_stream_samples``) with noise (or the detector model: confidences, true outliers and
    swaps) and missing points; ``t`` (N,) seconds, ``parents`` and ``events`` go to the truth."""
    K1, R1, C1 = ring_cameras(
        centre, num=s.num_streams, radius=radius, focal=s.focal, image_size=s.image_size
    )
    if s.bursts or s.lone_photos:
        hand = crowd_cameras(centre, s.bursts + s.lone_photos, rng, radius=radius,
                             focal=s.focal, image_size=s.image_size)
        K1, R1, C1 = (np.concatenate([a, b]) for a, b in zip((K1, R1, C1), hand, strict=True))
    K, R, C = K1[camera], R1[camera], C1[camera]
    n = X_true.shape[0]
    x_clean = project(X_true.reshape(n, -1, 3), K, R, C).reshape(*X_true.shape[:-1], 2)
    if s.detector is None:
        x = x_clean + s.noise * rng.standard_normal(x_clean.shape)
    else:
        x = x_clean.copy()
    if s.missing > 0:
        flat = x.reshape(n, -1, 2)
        p = flat.shape[1]
        gone = rng.random((n, p)) < s.missing
        gone[np.arange(n), rng.integers(0, p, n)] = False  # every image keeps a point
        gone[rng.integers(0, n, p), np.arange(p)] = False  # every point stays seen somewhere
        flat[gone] = np.nan
    confidence = pairs = outliers = swaps = None
    if s.detector is not None:
        pairs = symmetric_pairs(parents)
        x, confidence, outliers, swaps = detect(DetectorModel.load(s.detector), x_clean, camera,
                                                pairs, rng, np.isfinite(x).all(axis=-1))
    ring = (stream >= 0) & (stream < s.num_streams)
    names = np.array([f"cam{k}/{f:05d}" if r else f"burst{k - s.num_streams}/{f:05d}" if k >= 0
                      else f"photo{c - s.num_streams - s.bursts:05d}"
                      for r, k, f, c in zip(ring, stream, frame, camera, strict=True)])
    fps = np.full(n, np.nan)  # bursts and lone photos: no frame rate known
    fps[ring] = np.array(_rates(s))[stream[ring]]
    capture = Capture(
        x=x, K=K, R=R, C=C, stream=stream, frame=frame, fps=fps,
        image_names=names,
        confidence=confidence, symmetric_pairs=pairs,
    )
    truth = GroundTruth(X=X_true, t=t, x_clean=x_clean, events=events, outliers=outliers,
                        swaps=swaps, parents=parents, settings=np.array(str(asdict(s))))
    return Simulated(capture, truth)


def simulate(seq: MocapSequence, settings: SimulationSettings | None = None) -> Simulated:
    """Sample ``seq`` with unsynchronised streams: the capture and its ground truth.

    Images are stored stream by stream in frame order (as videos are), never in time order,
    with their stream's nominal frame rate as ``fps`` (as a video's file gives it). Truth:
    ``X`` (N, P, 3) metres, ``t`` (N,) seconds, ``x_clean`` (N, P, 2) pixels before noise
    and removal, ``parents``; with ``detector``, ``outliers`` (N, P) and ``swaps`` (N, K) of the
    capture's ``symmetric_pairs``, and the simulated scores as ``confidence``.
    """
    s = settings or SimulationSettings()
    rng = np.random.default_rng(s.seed)
    pos = _window(seq, s)
    centre = pos.reshape(-1, 3).mean(axis=0)
    radius = _ring_radius(s, pos.reshape(-1, 3), centre)
    t, stream, frame, camera = _stream_samples(pos.shape[0] - 1, seq.fps, s, rng)
    return _render(_interpolate(pos, t), stream, frame, camera, centre, radius, s, rng,
                   (t + round(s.start * seq.fps)) / seq.fps, seq.parents)
