"""Solver options: the paper's and the authors' defaults, documented with their units."""

from __future__ import annotations

from dataclasses import dataclass, fields
from enum import Enum


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

    AUTO = "auto"  # with hard rays: noise_px = 0 and no lambda2
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


RAY_WEIGHT_SCALE = 4e-8
"""Calibrated on the mocap protocol (pipelines/targets): 2 px at f = 1000 gives lambda2 = 1e-2.
It is the squared scale, in normalised units, of what the smoothness rows cannot explain."""


@dataclass(kw_only=True)
class Options:
    """Options of :func:`dloe_sfm.reconstruct`.

    Lengths are in *normalised scene units*: the solver divides the world by the median
    camera-to-scene distance (so a camera ring of radius 3 m becomes radius 1) and multiplies
    back at the end. All cost terms are divided by N * P (as in the authors' code).
    """

    lambda1: float = 1e-5
    """Compactness weight (T term) on ``D_ii W_ij |X_i - X_j|^2``; normalised length^2."""
    lambda2: float | None = None
    """Ray weight (O term); ``inf`` pins observed points to their rays and solves for depths.
    None: derived from ``noise_px`` (``inf`` for exact detections)."""
    noise_px: float = 0.0
    """Expected std of the 2D detections, pixels. With lambda2 = None it sets the ray weight
    ``lambda2 = RAY_WEIGHT_SCALE (f / noise_px)^2`` (f: median focal length in pixels): solve with
    hard rays, then refine ``soft_iterations`` sweeps with soft ones."""
    lambda3: float = 1e-7
    """Ray-convergence weight (R term): ``sum_ijp (D_ii W_ij r_ip . r_jp)^2``, unit-free."""
    ridge: float = 1e-9
    """Ridge on W rows (normalised length^2): makes every row's QP strictly convex."""
    prior_weight: float = 0.1
    """Intra-stream chain prior: ``W = (1 - a) W_var + a W_chain`` (authors: 0.1); 0 = off."""
    degree_floor: float = 0.5
    """D-step: ``D = c diag(q) + (1 - c) I`` with ``sum q = N``, i.e. ``D_ii >= 1 - c``."""
    fixed_degree: bool = True
    """Keep D = I (skip the D-step): measured more accurate than the D-step (see the README)."""
    end_degree: float = 0.1
    """D_ii of the images at the two ends of the estimated time line (no neighbour on one side)."""
    num_candidates: int = 8
    """k: W row i may only use k admissible other-stream images (plus its previous support):
    half before and half after it on the time line (spectral prior), else the k nearest shapes."""
    min_ray_angle: float = 15.0
    """Degrees: image pairs whose rays are closer than this to (anti)parallel are not neighbours."""
    spectral_prior: bool = True
    """Pick W candidates on the time line (the sequencing embedding, or the streams' affine clocks)
    and use its ``(f_i - f_j)^2`` in T during the W- and D-steps; else shape-space distances."""
    omega: float = 1.9
    """Over-relaxation of the X update (1 = plain alternation); cost-raising steps are undone."""
    resequence_every: int = 10
    """Recompute the time line (prior, end images) every this many iterations."""
    distance: Distance = Distance.ARC
    """Distances for sequencing: arc (in-stream path length + DTW) or Euclidean."""
    embedding: Embedding = Embedding.AFFINE
    """Final order: the streams' affine clocks (SHP without two multi-image streams), or a line
    embedding of the distances (spectral ranking, classical MDS, shortest Hamiltonian path)."""
    max_iterations: int = 200
    """Sweeps with hard rays; a finite ray weight (lambda2 or noise_px) then adds soft ones."""
    soft_iterations: int = 60
    """With a finite ray weight: at most this many sweeps with soft rays after the hard-ray solve
    (0 = keep the hard-ray solve). With the weight from ``noise_px`` they stop as soon as the
    points' median reprojection residual is down to that of the noise, ``noise_px sqrt(2 ln 2)``
    (the discrepancy principle): a few sweeps at 1-2 px, tens at 5 px."""
    tolerance: float = 1e-6
    """Stop when the RMS change of X in one sweep falls below this (normalised units)..."""
    cost_tolerance: float = 1e-5
    """...or when the cost fell by less than this fraction over ``resequence_every`` sweeps."""
    stream_clocks: Clocks = Clocks.AUTO
    """Every event filmed by videos (two or more streams of three or more frames) is finally
    placed on its streams' fitted affine clocks (``core.clocks``): the points by the X-step on
    the chain along the clocks, the order from them. ``auto``: with hard rays (``noise_px`` = 0,
    no ``lambda2``). There the motion alone pins the clocks (sparse walking: 0.6 ms median, the
    error 25.5 -> 7.4 mm). With noisy rays, slow motion leaves them 9-21 ms off (soccer at
    2 / 5 px) and DLOE's graph does better (soccer, 2 px: 3.8 mm, 6.9 with the fitted clocks,
    4.1 with the true ones). ``on`` / ``off``: always / never (``off``: the paper's method)."""
    shared_rate: bool = False
    """With ``stream_clocks``: all streams run at one frame rate (True); else each stream's rate
    is fitted too, starting from the fit with one shared rate."""
    robust_loss: RobustLoss = RobustLoss.CAUCHY
    """Loss on every observation's residual r: its pixel distance from what the solved graph
    predicts there (``W X``) without it. Observations are reweighted and the capture re-solved."""
    robust_scale_px: float | None = None
    """Scale c of the robust loss, pixels; None: from the residuals, 4 sigma (sigma: their median
    / 1.18, a 2D Gaussian's) but at least 3 px. Observations weighted below 1/2 (r > c for
    Cauchy) are reported, and dropped with hard rays."""
    robust_iterations: int = 5
    """At most this many reweighted re-solves (stops earlier when nothing changes; swaps fixed in
    one round let the next find those that were hidden behind them: 3 rounds found 93 % of 10 %
    swaps on walking, 5 found 98 %)."""
    fix_swaps: bool = True
    """Exchange left/right detections of the capture's ``symmetric_pairs`` that fit the graph's
    prediction far better swapped."""
    segment_events: bool = True
    """Find temporally disjoint events first (components of a shape-space W on the initial
    shapes) and solve each on its own."""
    progress: bool = False
    """Show a tqdm bar over the outer iterations."""

    def ray_weight(self, focal_px: float) -> float:
        """The lambda2 in force for cameras of focal length ``focal_px``."""
        if self.lambda2 is not None:
            return self.lambda2
        if self.noise_px <= 0:
            return float("inf")
        return RAY_WEIGHT_SCALE * (focal_px / self.noise_px) ** 2

    def __post_init__(self) -> None:
        self.distance = Distance(self.distance)
        self.embedding = Embedding(self.embedding)
        self.robust_loss = RobustLoss(self.robust_loss)
        self.stream_clocks = Clocks(self.stream_clocks)

    @property
    def clocks_on(self) -> bool:
        """Whether stream clocks are fitted (``stream_clocks``: ``on``, or ``auto`` with hard
        rays)."""
        if self.stream_clocks is Clocks.AUTO:
            return self.ray_weight(1.0) == float("inf")
        return self.stream_clocks is Clocks.ON

    def replace(self, **changes) -> Options:
        """A copy with some options changed (unknown names raise ValueError)."""
        known = {f.name for f in fields(self)}
        unknown = set(changes) - known
        if unknown:
            raise ValueError(f"unknown option(s): {', '.join(sorted(unknown))}")
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
