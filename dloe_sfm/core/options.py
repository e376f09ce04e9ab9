"""Solver options: the paper's and the authors' defaults, documented with their units."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields
from enum import Enum

import numpy as np

from ..errors import InputError


class Embedding(str, Enum):
    """Line embedding used to turn a distance matrix into an order."""

    SPECTRAL = "spectral"  # Fiedler vector of the Laplacian of affinity 1 / distance
    MDS = "mds"  # leading eigenvector of classical MDS
    SHP = "shp"  # approximate shortest Hamiltonian path (nearest neighbour + 2-opt)
    AFFINE = "affine"  # constant-rate streams: per-stream offset and rate from DTW (else SHP)


class Distance(str, Enum):
    """Distance between images used for sequencing."""

    ARC = "arc"  # in-stream path length + order-preserving DTW across streams
    EUCLIDEAN = "euclidean"  # plain distance between 3D shapes


class RobustLoss(str, Enum):
    """Robust loss on the ray term, applied by iterative reweighting."""

    CAUCHY = "cauchy"  # weight 1 / (1 + (r / c)^2)
    HUBER = "huber"  # weight min(1, c / r)
    NONE = "none"  # plain least squares


class Clocks(str, Enum):
    """When the images are placed on the streams' fitted clocks (``Options.stream_clocks``)."""

    AUTO = "auto"  # fitted, kept where they predict held-out detections (decisions.clock_verdict)
    ON = "on"
    OFF = "off"

    @classmethod
    def _missing_(cls, value: object) -> Clocks | None:
        """``true`` / ``false`` (and their spellings) for ``on`` / ``off``."""
        key = str(value).lower()
        if key in ("true", "1", "yes"):
            return cls.ON
        if key in ("false", "0", "no"):
            return cls.OFF
        return None


AUTO = "auto"
AUTO_WINDOW = 10_000
"""Images per window of ``window_images`` = auto (beyond twice as many)."""
"""``noise_px`` estimated from the data by the solver (``core.noise``)."""

RAY_WEIGHT_SCALE = 4e-8
"""Calibrated on the mocap protocol (pipelines/targets): 2 px at f = 1000 gives lambda2 = 1e-2.
It is the squared scale, in normalised units, of what the smoothness rows cannot explain."""

MAX_COUNT = 10**6
"""Upper bound of the iteration counts: generous, but a typo cannot run for ever."""
MAX_CANDIDATES = 10**4
"""Upper bound of ``num_candidates`` (the solver clamps it to N - 1 anyway): a typo cannot
allocate an (N, k) array that exhausts memory."""


def shown(value: object, limit: int = 60) -> str:
    """``repr(value)`` on one line, escaped and cut to about ``limit`` characters."""
    try:
        text = " ".join(repr(value).split())
    except Exception:  # a message must not fail (the repr of an int of 5000 digits raises)
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


@dataclass(frozen=True)
class Number:
    """Allowed values of a numeric option: an interval (an open ``inf`` end excludes inf, NaN is
    never inside), integers only with ``integer``, None too with ``optional``, and the word
    ``auto`` too with ``auto``."""

    lo: float
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = True
    integer: bool = False
    optional: bool = False
    auto: bool = False

    def describe(self) -> str:
        kind = "an integer" if self.integer else "a number"
        if math.isinf(self.hi):
            if not self.integer and self.hi_open:
                kind = "a finite number"
            text = f"{kind} {'>' if self.lo_open else '>='} {self.lo:g}"
            if not self.hi_open:
                text += " (inf allowed)"
        else:
            hi = str(int(self.hi)) if self.integer else f"{self.hi:g}"
            left, right = "(" if self.lo_open else "[", ")" if self.hi_open else "]"
            text = f"{kind} in {left}{self.lo:g}, {hi}{right}"
        text = f"None or {text}" if self.optional else text
        return f"auto or {text}" if self.auto else text

    def check(self, value: object) -> int | float | str | None:
        if value is None and self.optional:
            return None
        if self.auto and isinstance(value, str) and value.lower() == AUTO:
            return AUTO
        kind = numbers.Integral if self.integer else numbers.Real
        if isinstance(value, bool) or not isinstance(value, kind):
            raise ValueError
        try:
            number = int(value) if self.integer else float(value)
        except OverflowError:  # an int beyond float's range
            raise ValueError from None
        above = number > self.lo if self.lo_open else number >= self.lo
        below = number < self.hi if self.hi_open else number <= self.hi
        if not (above and below):
            raise ValueError
        return number


@dataclass(frozen=True)
class Flag:
    """A boolean option: True or False (numpy booleans too), nothing else."""

    def describe(self) -> str:
        return "true or false"

    def check(self, value: object) -> bool:
        if not isinstance(value, bool | np.bool_):
            raise ValueError
        return bool(value)


@dataclass(frozen=True)
class Choice:
    """An enum option: a member of ``enum`` or its value as a string (any case)."""

    enum: type[Enum]

    def describe(self) -> str:
        names = ", ".join(m.value for m in self.enum)
        return f"one of {names}" + (" (or true / false)" if self.enum is Clocks else "")

    def check(self, value: object) -> Enum:
        if isinstance(value, self.enum):
            return value
        if isinstance(value, str):
            return self.enum(value.lower())
        if isinstance(value, bool) and self.enum is Clocks:
            return Clocks.ON if value else Clocks.OFF
        raise ValueError


def _count(lo: int, hi: int = MAX_COUNT) -> Number:
    return Number(lo, hi, hi_open=False, integer=True)


RULES: dict[str, Number | Flag | Choice] = {
    "lambda1": Number(0.0),
    "lambda2": Number(0.0, lo_open=True, hi_open=False, optional=True),
    "noise_px": Number(0.0, auto=True),
    "lambda3": Number(0.0),
    "ridge": Number(0.0),
    "prior_weight": Number(0.0, 1.0, hi_open=False),
    "degree_floor": Number(0.0, 1.0, hi_open=False),
    "fixed_degree": Flag(),
    "end_degree": Number(0.0, 1.0, hi_open=False),
    "num_candidates": _count(2, MAX_CANDIDATES),
    "min_ray_angle": Number(0.0, 90.0),
    "spectral_prior": Flag(),
    "omega": Number(0.0, 2.0, lo_open=True),
    "resequence_every": _count(1),
    "distance": Choice(Distance),
    "embedding": Choice(Embedding),
    "max_iterations": _count(1),
    "soft_iterations": _count(0),
    "tolerance": Number(0.0),
    "cost_tolerance": Number(0.0),
    "stream_clocks": Choice(Clocks),
    "shared_rate": Flag(),
    "stream_offsets": Flag(),
    "robust_loss": Choice(RobustLoss),
    "robust_scale_px": Number(0.0, lo_open=True, optional=True),
    "robust_iterations": _count(0),
    "fix_swaps": Flag(),
    "segment_events": Flag(),
    "workers": Number(1, MAX_COUNT, hi_open=False, integer=True, auto=True),
    "window_images": Number(0, MAX_COUNT, hi_open=False, integer=True, auto=True),
}
"""The allowed values of every option (``Options`` checks each assignment against them)."""


def check_option(name: str, value: object) -> object:
    """``value`` as option ``name`` holds it (ints as int, numbers as float, enums as members);
    InputError naming the option, the allowed values and ``value`` otherwise."""
    rule = RULES.get(name)
    if rule is None:
        raise InputError(f"unknown option {shown(name)} (known: {', '.join(RULES)})")
    try:
        return rule.check(value)
    except ValueError:
        raise InputError(
            f"option '{name}' must be {rule.describe()}, got {shown(value)}"
        ) from None


@dataclass(kw_only=True)
class Options:
    """Options of :func:`dloe_sfm.reconstruct`.

    Lengths are in *normalised scene units*: the solver divides the world by the median
    camera-to-scene distance (so a camera ring of radius 3 m becomes radius 1) and multiplies
    back at the end. All cost terms are divided by N * P (as in the authors' code).

    Every value is checked when it is set (``RULES``: the range each docstring states; counts
    are at most 1e6): a bad one raises InputError (a ValueError) naming the option, its allowed
    values and the value given.
    """

    lambda1: float = 1e-5
    """Compactness weight (T term) on ``D_ii W_ij |X_i - X_j|^2``; normalised length^2; >= 0."""
    lambda2: float | None = None
    """Ray weight (O term); ``inf`` pins observed points to their rays and solves for depths.
    None: derived from ``noise_px`` (``inf`` for exact detections). None or > 0, inf allowed."""
    noise_px: float | str = AUTO
    """Expected std of the 2D detections, pixels. With lambda2 = None it sets the ray weight
    ``lambda2 = RAY_WEIGHT_SCALE (f / noise_px)^2`` (f: median focal length in pixels): solve with
    hard rays, then refine ``soft_iterations`` sweeps with soft ones. ``auto``: every event
    estimates it from its hard-ray solution (``core.noise``; 0, i.e. hard rays only, unless the
    residuals are noise that every point shares). ``auto``, or finite and >= 0."""
    lambda3: float = 1e-7
    """Ray-convergence weight (R term): ``sum_ijp (D_ii W_ij r_ip . r_jp)^2``, unit-free; >= 0."""
    ridge: float = 1e-9
    """Ridge on W rows (normalised length^2): makes every row's QP strictly convex; >= 0."""
    prior_weight: float = 0.1
    """Intra-stream chain prior: ``W = (1 - a) W_var + a W_chain`` (authors: 0.1); 0 = off.
    In [0, 1]."""
    degree_floor: float = 0.5
    """D-step: ``D = c diag(q) + (1 - c) I`` with ``sum q = N``, i.e. ``D_ii >= 1 - c``.
    In [0, 1]."""
    fixed_degree: bool = True
    """Keep D = I (skip the D-step): in a prototype the D-step's floor set the smoothness weight
    and a fixed D did better at high noise (docs/method.md, "Departures from the paper")."""
    end_degree: float = 0.1
    """D_ii of the images at the two ends of the estimated time line (no neighbour on one side);
    in [0, 1]."""
    num_candidates: int = 8
    """k: W row i may only use k admissible other-stream images (plus its previous support):
    half before and half after it on the time line (spectral prior), else the k nearest shapes.
    In [2, 10000] (one before and one after); more than N - 1 (N: images) is taken as N - 1."""
    min_ray_angle: float = 15.0
    """Degrees: image pairs whose rays are closer than this to (anti)parallel are not neighbours;
    in [0, 90)."""
    spectral_prior: bool = True
    """Pick W candidates on the time line (the sequencing embedding, or the streams' affine clocks)
    and use its ``(f_i - f_j)^2`` in T during the W- and D-steps; else shape-space distances."""
    omega: float = 1.9
    """Over-relaxation of the X update (1 = plain alternation); cost-raising steps are undone.
    In (0, 2)."""
    resequence_every: int = 10
    """Recompute the time line (prior, end images) every this many iterations; >= 1."""
    distance: Distance = Distance.ARC
    """Distances for sequencing: arc (in-stream path length + DTW) or Euclidean."""
    embedding: Embedding = Embedding.AFFINE
    """Final order: the streams' affine clocks (SHP without two multi-image streams), or a line
    embedding of the distances (spectral ranking, classical MDS, shortest Hamiltonian path)."""
    max_iterations: int = 200
    """Most sweeps with hard rays (>= 1); a finite ray weight (lambda2 or noise_px) then adds
    soft ones. Where soft ones may follow (also with ``noise_px`` auto), the hard ones stop
    once the graph's prediction settles (``decisions.HardRaysSettled``)."""
    soft_iterations: int = 60
    """With a finite ray weight: at most this many sweeps with soft rays after the hard-ray solve
    (0 = keep the hard-ray solve). With the weight from ``noise_px`` they stop as soon as the
    points' median reprojection residual is down to that of the noise, ``noise_px sqrt(2 ln 2)``
    (the discrepancy principle; how many sweeps that takes: docs/method.md, "The steps as
    implemented"). >= 0."""
    tolerance: float = 1e-6
    """Stop when the RMS change of X in one sweep falls below this (normalised units; >= 0)..."""
    cost_tolerance: float = 1e-5
    """...or when the cost fell by less than this fraction (>= 0) over ``resequence_every``
    sweeps."""
    stream_clocks: Clocks = Clocks.AUTO
    """Every event filmed by videos (two or more streams of three or more frames) is finally
    placed on its streams' fitted affine clocks (``core.clocks``): the points by the X-step on
    the chain along the clocks, the order from them. ``auto``: fitted for every such event and
    kept where they predict held-out images' detections about as well as DLOE's graph
    (``decisions.clock_verdict``): few frames per stream, or slow motion under noise, leave the
    clocks unpinned and the graph does better (docs/method.md, "Held-out checks").
    ``on`` / ``off``: always (but a fit that moved a stream ``clocks.REACH`` frame periods
    from DLOE's placement faces the same check) / never (``off``: the paper's method)."""
    shared_rate: bool = False
    """With ``stream_clocks``: all streams run at one frame rate (True); else each stream's rate
    is fitted too, starting from the fit with one shared rate."""
    stream_offsets: bool = True
    """With ``stream_clocks``: each stream's constant offset of each point's detections (a
    detector's bias in that view) is estimated on the events placed on clocks and taken out
    before the clocks are fitted again, where it predicts the frames it was not estimated on
    (``core.bias``); False: the detections as they are."""
    robust_loss: RobustLoss = RobustLoss.CAUCHY
    """Loss on every observation's residual r: its pixel distance from what the solved graph
    predicts there (``W X``) without it. Observations are reweighted and the capture re-solved."""
    robust_scale_px: float | None = None
    """Scale c of the robust loss, pixels; None: from the residuals, 5 sigma (sigma: their median
    / 1.18, a 2D Gaussian's) but at least 3 px. Observations weighted below 1/2 (r > c for
    Cauchy) are reported, and dropped with hard rays; a round that would drop more than half
    of the observations is not run. None or > 0, finite."""
    robust_iterations: int = 5
    """At most this many reweighted re-solves (stops earlier when nothing changes; swaps fixed in
    one round let the next find those that were hidden behind them; while the last solve still
    found detection noise, at most ``decisions.NOISY_ROUNDS``: docs/method.md, "Wrong detections
    (robust rounds)"). >= 0."""
    fix_swaps: bool = True
    """Exchange left/right detections of the capture's ``symmetric_pairs`` that fit the graph's
    prediction far better swapped."""
    segment_events: bool = True
    """Find temporally disjoint events first (components of a shape-space W on the initial
    shapes) and solve each on its own."""
    workers: int | str = AUTO
    """Processes that solve a capture's events (or windows) and place them on their stream
    clocks in parallel (``core.parallel``: one BLAS thread each, kept through one solve).
    ``auto``: one per core (at most one per event) from 25 000 (image, point) slots; 1: all in
    this process. ``auto`` or an integer >= 1."""
    window_images: int | str = AUTO
    """A capture of more images is solved in overlapping time windows of this many (a tenth of
    them shared with the next window), stitched (``core.windows``). ``auto``: windows of
    10 000 images beyond 20 000; 0: one solve, whatever the size. One subject only; needs two
    or more video streams. ``auto`` or an integer >= 0."""

    def window_size(self, num_images: int) -> int:
        """Images per window for a capture of ``num_images`` (0: one solve)."""
        if self.window_images == AUTO:
            return AUTO_WINDOW if num_images > 2 * AUTO_WINDOW else 0
        return self.window_images if num_images > self.window_images > 0 else 0

    def ray_weight(self, focal_px: float) -> float:
        """The lambda2 in force for cameras of focal length ``focal_px`` (hard rays, inf, with
        ``noise_px`` = ``auto``: the solver replaces it by its estimate)."""
        if self.lambda2 is not None:
            return self.lambda2
        if self.noise_px == AUTO or self.noise_px <= 0:
            return float("inf")
        ratio = focal_px / self.noise_px
        return RAY_WEIGHT_SCALE * ratio * ratio  # inf, not OverflowError, for a tiny noise_px

    def __setattr__(self, name: str, value: object) -> None:
        """Every assignment, the constructor's included, is checked against ``RULES`` (InputError,
        a ValueError, naming the option and its allowed values) and stored normalised."""
        super().__setattr__(name, check_option(name, value))

    def replace(self, **changes) -> Options:
        """A copy with some options changed (unknown names and bad values raise InputError)."""
        unknown = [name for name in changes if name not in RULES]
        if unknown:
            raise InputError(f"unknown option(s): {', '.join(shown(n) for n in unknown)} "
                             f"(known: {', '.join(RULES)})")
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values.update(changes)
        return Options(**values)

    def to_dict(self) -> dict:
        return {
            f.name: (
                getattr(self, f.name).value
                if isinstance(getattr(self, f.name), Enum)
                else getattr(self, f.name)
            )
            for f in fields(self)
        }
