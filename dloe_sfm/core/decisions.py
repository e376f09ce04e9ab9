"""The solver's decisions: every choice between two models that the data make, in one place
(docs/method.md, "Where the decisions are").

Two choices a user cannot make (are the detections exact? do the videos' clocks help?) are asked
of the data: each candidate predicts detections it was not given (``core.heldout``: folds of
observations or of whole images, on at most ``heldout.CHECK_IMAGES`` images) and the better one
is kept. The other rules read residuals or counts the solve has anyway. Each function answers
one question; the thresholds are this module's constants.

====================  ===================  ============================  ========================
decision              function             evidence                      called from
====================  ===================  ============================  ========================
how many people       subject_count        detections per image          multitarget.associate
cluster is a person   subject_support      its images and streams        multitarget.associate
hard phase done       HardRaysSettled      prediction px over sweeps     pipeline.solve_event
soft or hard rays     soft_rays_kept       held-out px, obs. folds       pipeline.solve_event
robust round kept     robust_round_undone  residual vs the plain solve   pipeline.robust_rounds
image mispredicted    spare_mispredicted   share of it rejected          pipeline.robust_rounds
soft rays on clocks   soft_rays_on_clocks  held-out px, image folds      clocked.placements
clocks checked        clocks_checked       option, how far fit moved     clocked.verdicts
clock refit kept      fit_trusted          how far the fit moved         clocked.robust_on_clocks
clocks or graph       clock_verdict        held-out px, image folds      clocked.verdicts
offsets taken out     offsets_kept         px of frames held out         clocked.clock_offsets
====================  ===================  ============================  ========================

The held-out rules: :func:`soft_wins` (soft rays, :data:`SOFT_MARGIN`), :func:`clocks_hold` and
:func:`clocks_time` (clocks kept, or timing their event: :data:`HOLD_MARGIN`,
:data:`TIMING_MARGIN`). Not here: where the events of lone photos are joined
(``events.join_touching``): a rule inside the event segmentation, which the solves this module's
checks run call, so it stays below them in ``events.py``.
"""

from __future__ import annotations

import logging
from enum import Enum

import numpy as np
import scipy.sparse as sp

from .alternation import Best, Search, soft_ray_weight
from .capture import Capture
from .clocks import REACH
from .heldout import held_out_px, middle_window
from .noise import estimate_noise_px
from .options import Clocks, Options
from .problem import Normalised
from .robust import predicted, residuals_px

logger = logging.getLogger("dloe_sfm")

SUBJECT_IMAGES = 8
"""Fewest images whose detections make a subject; also how many images must hold k detections
for the capture to be taken as showing k people (one image with an extra detection, a person
split into two partial skeletons, is no extra person)."""
SUBJECT_VIEWS = 3
"""Fewest streams that must see a subject (all the capture's, when it has fewer): with two, no
view checks what the other two triangulate (a still bystander at the edge of two cameras' views,
a reflection)."""
SUBJECT_MISFIT = 10.0
"""Most times farther than the detections of all subjects (median) a subject's detections may
be predicted when each is held out (``heldout.held_out_subjects``, median) for it to be a
person: false detections (reflections, misplaced skeletons) that a subject gathers from
scattered instants and cameras follow no motion, and held out they are predicted hundreds of
pixels off (25-199 times the median on the simulated crowd case and the exact and detector-model
tests; people 0.7-3.6 times, Shelf's four 0.8-1.6: docs/method.md, "Several people")."""
SETTLED_GAIN = 0.01
"""The hard-ray phase stops once the graph's prediction of the detections (median residual)
fell by less than this share over the last :data:`SETTLED_CHECKS` checks
(:class:`HardRaysSettled`)."""
SETTLED_CHECKS = 2
"""Checks (one every ``Options.resequence_every`` sweeps) over which the prediction must still
improve by :data:`SETTLED_GAIN` for the hard-ray phase to go on."""
EXACT_PX = 0.5
"""Median prediction residual (pixels) below which detections are taken as exact: there the
hard-ray solve is the answer and runs to convergence (``Options.tolerance``,
``Options.cost_tolerance``), however slowly its prediction still improves."""
SOFT_MARGIN = 0.95
"""Soft rays are taken when their median held-out residual is below this fraction of hard
rays' (a tie keeps the detections exact)."""
ROUND_GAIN = 0.95
"""The robust rounds' first re-solve is kept when the median residual of the observations it
used, less the floor the detection noise leaves, is at most this share of the plain solve's
(:func:`robust_round_undone`)."""
NOISY_ROUNDS = 1
"""Robust re-solves at most (``Options.robust_iterations`` if fewer) while the last solve still
found detection noise (:data:`NOISE_KEPT`): there every round's loss scale, taken from a fit
that left out the last round's rejects, is tighter, and the rejected set grows round after
round without settling (docs/method.md, "Wrong detections (robust rounds)")."""
NOISE_KEPT = 0.5
"""The noise a re-solve estimates is still the detectors' when it is at least this share of the
solve before's (and not 0). Swapped or wrong detections look like noise to the plain solve:
once a round fixed some, the level falls far (1.34 -> 0.25 px on simulated swaps) and the
rounds go on, where the detectors' own noise barely moves (Shelf: 6.3 -> 4.5 px)."""
MOST_OF_AN_IMAGE = 0.5
"""Share of an image's observations beyond which the robust rounds take a misprediction for the
graph's, not the detector's: none of that image's observations is dropped
(:func:`spare_mispredicted`; docs/method.md, "Lone photos")."""
CHAIN_MIN_PX = 1.0
"""Soft rays along the stream clocks (:func:`soft_rays_on_clocks`) are tried from this level up.
Below a pixel, the level the graph's fit leaves is the SfM cameras' error and the fit's own,
which soft rays trade in ways held-out images cannot judge: the demo at 0.58 px predicts them
0.70 x as far off, yet its error goes 6.11 -> 7.24 mm; detectors' noise is several pixels
(docs/method.md, "Held-out checks")."""
HOLD_MARGIN = 1.05
"""The clocks are kept when their median held-out residual is at most this many times the graph's
(:func:`clocks_hold`)."""
TIMING_MARGIN = 1.5
"""Clocks dropped for the points still time their event when their median held-out residual is
at most this many times the graph's (:func:`clocks_time`)."""
OFFSET_GAIN = 0.9
"""The offsets are kept when, estimated on one half of each stream's frames, they bring the
median residual of the other half to at most this share of what it is without them."""


def subject_count(source: np.ndarray) -> int:
    """The number of people a capture shows: the most detections that at least
    :data:`SUBJECT_IMAGES` images hold (all its images, when it has fewer); ``source`` (N',):
    each detection's image."""
    held = np.sort(np.bincount(source)[np.unique(source)])[::-1]
    return int(held[min(SUBJECT_IMAGES, held.size) - 1])


def subject_support(streams: int) -> tuple[int, int]:
    """(images, streams) a cluster of detections needs to be a subject, in a capture of
    ``streams`` streams: :data:`SUBJECT_IMAGES`, and :data:`SUBJECT_VIEWS` or all the capture's
    when it has fewer (docs/method.md, "Several people")."""
    return SUBJECT_IMAGES, min(SUBJECT_VIEWS, streams)


class HardRaysSettled:
    """The hard-ray phase's stop (``alternation.Phase.settled``) for ``capture``: called with the
    best iterate's W and normalised X every ``Options.resequence_every`` sweeps, it returns why
    the phase is done, or None (and keeps it as ``reason``). Done when the median residual of
    the detections against the graph's prediction (``W X``) fell by less than
    :data:`SETTLED_GAIN` over the last :data:`SETTLED_CHECKS` calls and is above
    :data:`EXACT_PX`: under detection noise the cost keeps falling by a fraction of a percent
    every ten sweeps for hundreds of sweeps as W fits the noise, while the prediction the noise
    level is read from, and the soft rays start from, has stopped changing. The soft rays then
    refine; where the held-out check keeps hard rays instead (:func:`soft_rays_kept`: exact
    detections of fast motion at coarse sampling also leave residuals), the hard-ray phase is
    resumed to its own end (``pipeline.solve_event``; docs/method.md, "Stopping")."""

    def __init__(self, capture: Capture, options: Options, norm: Normalised) -> None:
        self.capture, self.norm = capture, norm
        self.sweeps = SETTLED_CHECKS * options.resequence_every
        self.history: list[float] = []
        self.reason: str | None = None

    def __call__(self, W: sp.csr_matrix, X: np.ndarray) -> str | None:
        X_pred = predicted(W, self.norm.to_world(X))
        self.history.append(float(np.nanmedian(residuals_px(self.capture, X_pred))))
        now = self.history[-1]
        if len(self.history) <= SETTLED_CHECKS or now < EXACT_PX:
            return None
        before = self.history[-SETTLED_CHECKS - 1]
        if now > (1.0 - SETTLED_GAIN) * before:
            self.reason = (f"converged: the graph's prediction of the detections settled at "
                           f"{now:.2f} px (median; {before:.2f} px {self.sweeps} sweeps before)")
        return self.reason


def soft_rays_kept(
    capture: Capture, options: Options, norm: Normalised, hard: Best, st: Search
) -> bool:
    """Whether the soft-ray solution ``st.best`` (at ``options.noise_px``, the estimate of
    ``auto``) predicts held-out detections better than the hard-ray one ``hard``
    (:func:`soft_wins`; observation folds, each model's folds started from its own solution,
    on at most ``heldout.CHECK_IMAGES`` images in the middle of the time line), logged."""
    window, sub = middle_window(capture, st.f)
    hard_px = held_out_px(sub, options.replace(noise_px=0.0), norm.to_world(hard.X)[window],
                          hard.D[window], np.inf)
    soft_px = held_out_px(sub, options, norm.to_world(st.best.X)[window], st.best.D[window],
                          soft_ray_weight(capture, options))
    wins = soft_wins(hard_px, soft_px)
    logger.info("held-out detections, median residual: hard rays %.2f px, soft rays at %.2f px "
                "noise %.2f px: %s", np.nanmedian(hard_px), options.noise_px,
                np.nanmedian(soft_px), "soft rays kept" if wins else "hard rays kept")
    return wins


def soft_wins(hard_px: np.ndarray, soft_px: np.ndarray) -> bool:
    """Whether soft rays predicted the held-out detections better: median residual below
    ``SOFT_MARGIN`` times hard rays' (both (M,) pixels over the same observations, NaN ignored)."""
    return bool(np.nanmedian(soft_px) < SOFT_MARGIN * np.nanmedian(hard_px))


def robust_round_undone(fit_px: float, expected_px: float, floor_px: float) -> bool:
    """Whether the robust rounds' first re-solve is undone: the median residual ``fit_px`` of
    the observations it used did not tighten to :data:`ROUND_GAIN` of the plain solve's
    ``expected_px`` beyond the floor ``floor_px`` the detection noise leaves
    (``noise.residual_floor_px``). Real outliers bend the graph, so removing them tightens the
    fit; at coarse sampling the largest residuals are the graph's own interpolation errors
    (docs/method.md, "Wrong detections (robust rounds)")."""
    return fit_px - floor_px > ROUND_GAIN * (expected_px - floor_px)


def spare_mispredicted(
    weights: np.ndarray, visible: np.ndarray, share: float
) -> tuple[np.ndarray, np.ndarray]:
    """(weights with every observation of a mispredicted image back at 1, (N,) those images):
    an image is mispredicted where more than ``share`` of its visible observations weigh below
    1/2. A detector gets joints wrong, not a whole person: there the graph's prediction failed
    (a wrong link), and dropping the detections would leave the image to float on that link."""
    mispredicted = (weights < 0.5).sum(axis=1) > share * visible.sum(axis=1)
    return np.where(mispredicted[:, None], 1.0, weights), mispredicted


def soft_rays_on_clocks(
    capture: Capture, options: Options, X_world: np.ndarray, D: np.ndarray, W_graph: sp.spmatrix,
    t: np.ndarray
) -> tuple[float, np.ndarray | None]:
    """The detection noise (pixels) of one event placed on its clocks ``t`` whose graph solve
    kept hard rays: the level the graph's fit ``W_graph`` leaves (``noise.estimate_noise_px``),
    if it is at least :data:`CHAIN_MIN_PX` and soft rays at it predict held-out images,
    chained along the clocks, better than hard rays (:func:`soft_wins`); else 0. With it, the
    held-out residuals of the rays kept (None when the level was not tried). Logged when tried.

    The graph's own check (:func:`soft_rays_kept`) holds out single detections: the
    image's other points fix its shape, and the depth error along the camera's rays that hard
    rays keep from noisy detections does not show. A held-out image is predicted from other
    cameras' images, and their depth errors show in it (docs/method.md, "Held-out checks")."""
    candidate = estimate_noise_px(residuals_px(capture, predicted(W_graph, X_world)))
    if candidate < CHAIN_MIN_PX:
        return 0.0, None
    window, sub = middle_window(capture, t)
    soft = options.replace(noise_px=candidate)
    hard_px = held_out_px(sub, options, X_world[window], D[window],
                          soft_ray_weight(capture, options), times=t[window], images=True)
    soft_px = held_out_px(sub, soft, X_world[window], D[window], soft_ray_weight(capture, soft),
                          times=t[window], images=True)
    wins = soft_wins(hard_px, soft_px)
    logger.info("held-out images along the stream clocks, median residual: hard rays %.2f px, "
                "soft rays at %.2f px noise %.2f px: %s", np.nanmedian(hard_px), candidate,
                np.nanmedian(soft_px), "soft rays kept" if wins else "hard rays kept")
    return (candidate, soft_px) if wins else (0.0, hard_px)


def clocks_checked(options: Options, moved: float) -> bool:
    """Whether an event's clocks face the held-out check (:func:`clock_verdict`): always with
    ``stream_clocks`` = ``auto``; with ``on`` only when the fit is not trusted
    (:func:`fit_trusted`), else they are kept."""
    return options.stream_clocks is Clocks.AUTO or not fit_trusted(moved)


def fit_trusted(moved: float) -> bool:
    """Whether a clock fit moved no stream ``clocks.REACH`` frame periods or more from its first
    guess (``moved``: ``clocks.moved_periods``): beyond, the rays may not pin its clocks, or the
    first guess was that far off (docs/method.md, "Stream clocks")."""
    return moved < REACH


class Verdict(Enum):
    """What the held-out check (:func:`clock_verdict`) makes of one event's clocks."""

    KEPT = "kept"  # the points are placed on them
    TIMING = "timing"  # DLOE's graph gives the points, the clocks the order and times
    REJECTED = "rejected"  # DLOE's graph gives both


def clock_verdict(
    capture: Capture, options: Options, X_world: np.ndarray, D: np.ndarray, t: np.ndarray,
    noise_px: float | None = None, clock: np.ndarray | None = None
) -> Verdict:
    """The verdict on one event's clocks ``t``: kept when, with the rays of ``noise_px``
    (default the graph's, ``options.noise_px``; 0: hard rays), they predict held-out images'
    detections about as well as DLOE's graph with its own (:func:`clocks_hold`;
    ``heldout.held_out_px`` on at most ``heldout.CHECK_IMAGES`` images in the middle of the
    clocks' time line); else timing when they lost narrowly (:func:`clocks_time`); else
    rejected. Logged. ``clock``: the clocks' held-out residuals, when :func:`soft_rays_on_clocks`
    has them. Rejected, and logged, where no held-out detection is predicted by both (a
    capture of a few images)."""
    window, sub = middle_window(capture, t)
    graph = held_out_px(sub, options, X_world[window], D[window],
                        soft_ray_weight(capture, options), images=True)
    if clock is None:
        ticked = options if noise_px is None else options.replace(noise_px=noise_px)
        clock = held_out_px(sub, ticked, X_world[window], D[window],
                            soft_ray_weight(capture, ticked), times=t[window], images=True)
    if not (np.isfinite(graph) & np.isfinite(clock)).any():
        logger.info("held-out detections: none that both models predict; DLOE's graph is kept")
        return Verdict.REJECTED
    verdict = (Verdict.KEPT if clocks_hold(graph, clock)
               else Verdict.TIMING if clocks_time(graph, clock) else Verdict.REJECTED)
    said = {Verdict.KEPT: "clocks kept",
            Verdict.TIMING: "the clocks fail, DLOE's graph is kept for the points, the clocks "
                            "time the images",
            Verdict.REJECTED: "the clocks fail clearly, DLOE's graph is kept"}
    logger.info("held-out detections, median residual: DLOE's graph %.2f px, stream clocks %.2f "
                "px, at least as good on %.0f %% of them: %s", np.nanmedian(graph),
                np.nanmedian(clock), 100 * as_good_share(graph, clock), said[verdict])
    return verdict


def clocks_hold(graph_px: np.ndarray, clock_px: np.ndarray) -> bool:
    """Whether the clocks predict held-out images' detections about as well as DLOE's graph: a
    median residual at most :data:`HOLD_MARGIN` times the graph's, or at least half of the
    detections predicted at least as well. ``graph_px``, ``clock_px``: the same detections'
    residuals, pixels, NaN ignored (``heldout.held_out_px``). Near-ties go to the clocks, a
    few numbers per stream where the graph has weights for every image: on exact data both
    models predict at the floor the cameras leave, where the medians alone decide by chance,
    and under detector noise the graph's many neighbours average the held-out detections' noise
    better than the chain's two, while the timing hardly shows (docs/method.md, "Far fits and
    near-ties")."""
    return bool(np.nanmedian(clock_px) <= HOLD_MARGIN * np.nanmedian(graph_px)
                or as_good_share(graph_px, clock_px) >= 0.5)


def clocks_time(graph_px: np.ndarray, clock_px: np.ndarray) -> bool:
    """Whether clocks that do not hold (:func:`clocks_hold`) lost narrowly enough to still time
    their event: a median held-out residual at most :data:`TIMING_MARGIN` times the graph's
    (arguments as :func:`clocks_hold`). Within it the loss is what the graph's many neighbours
    gain by averaging the detections' noise, which a frame of timing hardly moves; a clock fit
    that failed loses by twice and more (docs/method.md, "Times from dropped clocks")."""
    return bool(np.nanmedian(clock_px) <= TIMING_MARGIN * np.nanmedian(graph_px))


def as_good_share(graph_px: np.ndarray, clock_px: np.ndarray) -> float:
    """Share of the detections with both residuals (pixels) that the clocks predict at least as
    well as the graph (0 with none)."""
    both = np.isfinite(graph_px) & np.isfinite(clock_px)
    return float(np.mean(clock_px[both] <= graph_px[both])) if both.any() else 0.0


def burst_clocks_time(rank_px: np.ndarray, clock_px: np.ndarray) -> bool:
    """Whether an event of bursts and lone photos takes its times from its bursts' clocks:
    every detection predicted from the graph's points of its image's neighbours along each
    timing (``clocks.chain_predicted``), the clocks' median residual (pixels) below the rank
    base's. On the bundled crowd, 6 bursts among 16 lone photos, the clocks lose (1.57 against
    1.41 px) and order the images worse; on crowd workspaces of 25-33 bursts they win
    (docs/method.md, "Clocks of bursts")."""
    return bool(np.nanmedian(clock_px) < np.nanmedian(rank_px))


def offsets_kept(before: float, after: float) -> bool:
    """Whether the streams' offsets of the detections are taken out: estimated on one half of
    each stream's frames, they bring the median residual of the other half from ``before`` to
    ``after`` (pixels, ``bias.stream_offsets``), at most :data:`OFFSET_GAIN` of it."""
    return bool(after <= OFFSET_GAIN * before)
