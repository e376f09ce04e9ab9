"""Sub-frame synchronisation: every stream's affine clock ``time = offset + rate frame`` with
standard uncertainties (docs/interfaces.md, "Synchronisation").

Time is counted in frames of each event's reference stream (``mocap_export.image_times``: its
video with the most images, at its own frames), so the reference has offset 0 and rate 1
exactly, and every other stream's offset and rate are relative to it.

Uncertainty. When the times are the streams' affine clocks (base ``clock`` or ``affine
embedding``) a line through them fits exactly, so its scatter says nothing. The uncertainty then
comes from the clock fit's own problem (``core.clocks``, ``core.splines``: every point's
trajectory a cubic B-spline in time, the residual each observation's distance to its ray, the
spline eliminated), with ``J`` the Kaufman Jacobian of the residuals in the non-reference
streams' offsets and rates, averaged over the fit's knot spacings: the Gauss-Newton covariance
``s^2 (J^T J)^-1`` (``s^2`` the residual variance per degree of freedom: the rays' noise) plus
the outer product of the Gauss-Newton step each spacing alone would take from the estimate (the
spline model's own error, which dominates on clean data). It is local: a fit caught in a wrong
minimum keeps a small one. Where the clock fit held the rates at the known frame rates' ratios,
``J`` is in the offsets alone and the rates carry no uncertainty (``rate_held``). With base
``burst clock`` (an event of bursts and lone photos on its bursts' clocks) the same from that
fit's own problem, its prior included (``clocks.burst_covariance``). With base
``rank`` the times are not on lines: ordinary least squares of the times on the frames. Their
uncertainty (:func:`_rank_sd`) adds two variances of the times: the residual variance pooled
over the event's streams (a burst of two or three frames has no scatter of its own, or one
degree of freedom of it), and how far times drawn at random over the event fall from the even
places the rank base gives them (order statistics); an offset or rate relative to the
reference carries the reference line's uncertainty too.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import InputError
from .capture import Capture
from .clocks import SPACINGS, burst_covariance, reference_stream, sampling_interval
from .splines import ray_equations, spline_residuals

Fps = float | dict[int, float] | None
"""Frame rates: one for every stream, per stream id, or unknown."""

RATE_CHECK_SD = 3.0
"""A stream's fitted rate further than this many of its standard uncertainties from the ratio
of the known frame rates, and drifting :data:`RATE_CHECK_DRIFT` or more from it, does not match
them (``fps_consistent``, :func:`rate_check`)."""
RATE_CHECK_DRIFT = 0.1
"""Reference frames of drift from the known frame rates' ratio over a stream's frames below
which its clock matches them whatever the uncertainty (a miss too small to matter)."""


def _lines(t: np.ndarray, streams: np.ndarray, frames: np.ndarray,
           videos: list[int]) -> dict[int, tuple[float, float, float, np.ndarray]]:
    """Per stream: the OLS line of ``t`` on its frames, ``(offset, rate, residual sum of
    squares, (A^T A)^-1 A^T)`` (A the design matrix, columns 1 and the frames; the last maps
    the stream's times, in index order, to its offset and rate)."""
    lines = {}
    for s in videos:
        m = streams == s
        A = np.stack([np.ones(int(m.sum())), frames[m].astype(np.float64)], axis=1)
        fit = np.linalg.pinv(A)
        coef = fit @ t[m]
        lines[s] = (float(coef[0]), float(coef[1]), float(((t[m] - A @ coef) ** 2).sum()), fit)
    return lines


def _rank_sd(lines: dict, t: np.ndarray, streams: np.ndarray,
             ref: int) -> dict[int, tuple[float, float]]:
    """Per stream of ``lines`` (:func:`_lines` of the rank base's times ``t``,
    ``clocks.rank_times``) but ``ref``: (offset_sd, rate_sd) of its line relative to the
    reference's, from two variances of the times (module docstring): the lines' residual
    variance pooled over all the lines (at least that of a time rounded to the step between
    consecutive times, step^2 / 12), and where times drawn at random fall about the even places
    the rank base gives them (:func:`_placement_variance`)."""
    rss = sum(line[2] for line in lines.values())
    dof = sum(int((streams == s).sum()) - 2 for s in lines)
    step = float(np.median(np.diff(np.sort(t)))) if t.size > 1 else 0.0
    var = max(rss / dof if dof else 0.0, step * step / 12.0)
    order = np.argsort(t, kind="stable")
    rank = np.empty(t.size, dtype=np.int64)
    rank[order] = np.arange(t.size)
    at_ref = np.flatnonzero(streams[order] == ref)
    ref_fit = lines[ref][3]
    out = {}
    for s, (_, rate, _, fit) in lines.items():
        if s != ref:
            sd = [np.sqrt(var * float(w @ w + own @ own)
                          + _placement_variance(rank[streams == s], w, at_ref, t[order][at_ref]))
                  for w, own in ((fit[0], ref_fit[0]), (fit[1], rate * ref_fit[1]))]
            out[s] = (float(sd[0]), float(sd[1]))
    return out


def _placement_variance(rank: np.ndarray, w: np.ndarray, at_ref: np.ndarray,
                        ref_time: np.ndarray) -> float:
    """Variance of ``w . (true - even times)`` of images at ``rank`` (in the order of ``w``)
    where the rank base puts the reference's images (ranks ``at_ref``) at their times
    ``ref_time`` and the others evenly in between, if every other image was taken at a random
    instant (a Poisson process): the m images between two reference frames L apart are m
    uniform times there (covariance L^2 (min(p_a, p_b) - p_a p_b) / (m + 2), p = j / (m + 1)
    for the j-th); beyond the first or last frame the rank base steps on by the reference
    span's mean step s over its K ranks, so the j-th image out is j steps of exponential length
    s away (covariance s^2 min(j_a, j_b)) and the step itself is off by about s / sqrt(K), for
    every image out at once (covariance +-j_a j_b s^2 / K, the sign + on the same side)."""
    gap = np.searchsorted(at_ref, rank)  # 0: before the first reference frame
    span = int(at_ref[-1] - at_ref[0])
    step = float(ref_time[-1] - ref_time[0]) / span
    total, outward = 0.0, 0.0
    for g in np.unique(gap):
        mine = gap == g
        if g == 0 or g == at_ref.size:
            x = np.abs(rank[mine] - at_ref[0 if g == 0 else -1]).astype(np.float64)
            scale, centred = step * step, 0.0
            outward += (1.0 if g else -1.0) * float(w[mine] @ x)
        else:
            m = at_ref[g] - at_ref[g - 1] - 1
            x = (rank[mine] - at_ref[g - 1]) / (m + 1.0)
            scale = (ref_time[g] - ref_time[g - 1]) ** 2 / (m + 2.0)
            centred = float(w[mine] @ x) ** 2
        # sum over pairs of w_a w_b min(x_a, x_b): increments of x times the squared tail sums
        k = np.argsort(x)
        tail = np.cumsum(w[mine][k][::-1])[::-1]
        total += scale * (float(np.diff(x[k], prepend=0.0) @ tail**2) - centred)
    return total + step * step / span * outward**2


def _ray_covariance(capture: Capture, t: np.ndarray, streams: np.ndarray, frames: np.ndarray,
                    free: list[int], *, held: bool = False) -> np.ndarray:
    """(2q, 2q) covariance of the offsets then rates of the ``free`` streams (module docstring);
    ``t`` the event's times, on every stream's line. With ``held`` (the rates were held at
    known ratios) (q, q), of the offsets alone."""
    f = frames.astype(np.float64)
    onehot = (streams[:, None] == np.array(free)[None, :]).astype(np.float64)
    dt = onehot if held else np.concatenate([onehot, onehot * f[:, None]], axis=1)
    E, rhs = ray_equations(capture.rays(), capture.C, capture.weights)
    visible = capture.visible
    interval = sampling_interval(t)
    img, pt = np.nonzero(visible)
    cov = 0.0
    for h in SPACINGS:
        spacing = h * interval * (1.5 if len(free) == 1 else 1.0)
        start = float(t.min()) - 3.0 - spacing
        r, J = spline_residuals(t, E, rhs, visible, spacing, start, dt)
        nb = int(np.floor((t.max() - start) / spacing)) + 4
        first = np.floor((t[img] - start) / spacing).astype(np.int64)
        spline = np.unique((pt * nb + first)[:, None] + np.arange(4)).size * 3
        inv = np.linalg.pinv(J.T @ J)
        step = inv @ (J.T @ r)
        # the rays' noise, plus how far this knot spacing alone would move the clocks
        cov = cov + (float(r @ r) / max(r.size - spline - dt.shape[1], 1) * inv
                     + np.outer(step, step)) / len(SPACINGS)
    return cov


def stream_clocks(capture: Capture, labels: np.ndarray, time: np.ndarray,
                  events: list[dict], graph: np.ndarray | None = None) -> list[dict]:
    """Every stream's clock with uncertainty, per event (module docstring).

    ``capture`` as from ``columns.solved_capture``; ``labels`` (N,) the images' events;
    ``time`` (N,) and ``events`` (per event: ``event``, ``base``, ``clocks_dropped``,
    ``reference_stream``) from ``mocap_export.image_times``. Returns per event its ``event``,
    ``base``, ``reference_stream``, ``clocks_dropped`` and ``streams``: stream id ->
    ``offset``, ``offset_sd`` (reference frames at the stream's frame 0, relative to the
    reference's frame 0), ``rate``, ``rate_sd`` (reference frames per own frame; 0 where
    ``rate_held``: the clock fit held the rates at the ratios of the capture's frame rates, and
    the offsets' uncertainty is then theirs alone), ``base`` (the event's), ``images``,
    ``frame_span`` (its last frame less its first); streams with fewer than two frames are left
    out.

    ``graph`` (N,): DLOE's own time line (``Result.embedding``). An event timed by clocks the
    held-out check dropped for its points (``clocks_dropped``: the points are DLOE's graph's)
    has two timings the data could not tell apart: every stream also gets
    ``clock_disagreement`` (the graph's offset less the clocks', reference frames), which joins
    ``offset_sd`` in quadrature.
    """
    stream_ids = capture.stream_ids
    out = []
    for summary in events:
        idx = np.flatnonzero(labels == summary["event"])
        streams, frames, t = stream_ids[idx], capture.frame[idx], time[idx]
        ref = summary["reference_stream"]
        videos, _ = reference_stream(streams, frames)
        other = None
        if graph is not None and summary["clocks_dropped"]:
            other = _lines(graph[idx], streams, frames, videos)
        entry = {"event": int(summary["event"]), "base": summary["base"],
                 "reference_stream": ref, "clocks_dropped": other is not None, "streams": {}}
        out.append(entry)
        if ref is None:
            continue
        lines = _lines(t, streams, frames, videos)
        a_ref = lines[ref][0]
        free = [s for s in videos if s != ref]
        sd = {}
        held = _held(capture, idx, lines, ref, free)
        if summary["base"] == "rank":
            sd = _rank_sd(lines, t, streams, ref)
        elif summary["base"] == "burst clock":
            burst = np.isin(streams, videos)
            sub = capture.subset(idx[burst])
            E, rhs = ray_equations(sub.rays(), sub.C, sub.weights)
            bursts, cov = burst_covariance(t[burst], streams[burst], frames[burst], E, rhs,
                                           sub.visible, ref)
            var = np.sqrt(np.maximum(np.diag(cov), 0.0))
            sd = {int(s): (float(var[k]), float(var[bursts.size + k]))
                  for k, s in enumerate(bursts)}
        elif free:
            cov = _ray_covariance(capture.subset(idx), t, streams, frames, free, held=held)
            var = np.sqrt(np.maximum(np.diag(cov), 0.0))
            sd = {s: (float(var[k]), 0.0 if held else float(var[len(free) + k]))
                  for k, s in enumerate(free)}
        for s in videos:
            a, b = lines[s][:2]
            a_sd, b_sd = sd.get(s, (0.0, 0.0))
            clock = {"offset": a - a_ref, "offset_sd": a_sd, "rate": b, "rate_sd": b_sd,
                     "rate_held": held and s != ref, "base": summary["base"],
                     "images": int((streams == s).sum()),
                     "frame_span": int(np.ptp(frames[streams == s]))}
            if other is not None:
                # the graph's time line in the reference's frames, as the exported times count
                a_o, b_o = other[ref][:2]
                apart = (other[s][0] - a_o) / b_o - (a - a_ref)
                clock["clock_disagreement"] = apart
                clock["offset_sd"] = float(np.hypot(clock["offset_sd"], apart))
            entry["streams"][s] = clock
    return out


def _held(capture: Capture, idx: np.ndarray, lines: dict, ref: int, free: list[int]) -> bool:
    """Whether every ``free`` stream's clock (``lines``) runs at the ratio of its frame rate
    to the reference's (``Capture.fps`` of the images ``idx``), to rounding: the clock fit
    held them there (``problem.known_rates``), and their rates are known, not estimated."""
    if capture.fps is None or not free:
        return False
    stream, fps = capture.stream_ids[idx], capture.fps[idx]
    rate = {s: fps[stream == s][0] for s in (ref, *free)}
    return all(np.isfinite(rate[s]) and abs(lines[s][1] * rate[s] / rate[ref] - 1.0) < 1e-9
               for s in free)


def capture_fps(capture: Capture) -> Fps:
    """The frame rates ``capture`` knows (``Capture.fps``), per stream id, or None."""
    if capture.fps is None:
        return None
    ids = capture.stream_ids
    known = np.isfinite(capture.fps)
    return {int(s): float(capture.fps[ids == s][0]) for s in np.unique(ids[known])} or None


def with_fps(capture: Capture, fps: Fps) -> Capture:
    """``capture`` with the frame rates of ``fps`` (one for every stream or per stream id,
    checked by :func:`check_fps`) replacing its own for those streams; lone photos have
    none."""
    if fps is None:
        return capture
    ids = capture.stream_ids
    known = np.full(ids.size, np.nan) if capture.fps is None else capture.fps.copy()
    for s in np.unique(ids[capture.stream >= 0]):
        rate = stream_fps(fps, int(s))
        if rate is not None:
            known[ids == s] = rate
    return replace(capture, fps=known)


def check_fps(fps: Fps, streams: np.ndarray) -> None:
    """One-line InputError for a non-positive or non-finite frame rate or a stream id that is
    not among ``streams``."""
    values = fps.items() if isinstance(fps, dict) else [] if fps is None else [(None, fps)]
    known = {int(s) for s in np.unique(streams)}
    for s, v in values:
        if not (np.isfinite(v) and v > 0):
            raise InputError(f"option --fps: must be a positive number, got {v!r}"
                             + ("" if s is None else f" for stream {s}"))
        if s is not None and s not in known:
            raise InputError(f"option --fps: unknown stream {s} (streams: "
                             f"{', '.join(map(str, sorted(known)))})")


def stream_fps(fps: Fps, stream: int | None) -> float | None:
    """The frame rate of ``stream`` from ``fps`` (None when unknown)."""
    if fps is None or stream is None:
        return None
    return fps.get(stream) if isinstance(fps, dict) else float(fps)


def sync_report(clocks: list[dict], fps: Fps) -> dict:
    """``report.json``'s ``sync`` entry from :func:`stream_clocks` and the known frame rates:
    ``time_unit`` (``s`` when every event's reference stream has a frame rate, else
    ``frame``) and per event the clocks: ``offset`` / ``offset_sd`` in ``time_unit``,
    ``offset_frames`` / ``offset_sd_frames`` in reference frames, where the reference's rate is
    known ``offset_ms`` / ``offset_sd_ms`` and ``implied_fps`` (the reference's rate over
    ``rate``), and where the stream's own is known ``fps`` (given). Where both are known and the
    rate has an uncertainty (not the reference), the check of the clock against them
    (:func:`rate_check`): the uncertainty is local (:func:`stream_clocks`), a clock fit caught
    in a wrong minimum keeps a small one, and the known frame rates are what shows it."""
    refs = [stream_fps(fps, c["reference_stream"]) for c in clocks]
    seconds = bool(refs) and all(r is not None for r in refs)
    events = []
    for c, ref_fps in zip(clocks, refs, strict=True):
        streams = {}
        for s, clock in c["streams"].items():
            entry = {**clock, "offset_frames": clock["offset"],
                     "offset_sd_frames": clock["offset_sd"]}
            apart = entry.pop("clock_disagreement", None)
            if apart is not None:
                entry["clock_disagreement_frames"] = apart
            if seconds:
                entry.update(offset=clock["offset"] / ref_fps,
                             offset_sd=clock["offset_sd"] / ref_fps)
            if ref_fps is not None:
                entry["offset_ms"] = 1000.0 * clock["offset"] / ref_fps
                entry["offset_sd_ms"] = 1000.0 * clock["offset_sd"] / ref_fps
                entry["implied_fps"] = ref_fps / clock["rate"]
                if apart is not None:
                    entry["clock_disagreement_ms"] = 1000.0 * apart / ref_fps
            own = stream_fps(fps, s)
            if own is not None:
                entry["fps"] = own
                entry.update(rate_check(clock, ref_fps, own))
            streams[str(s)] = entry
        events.append({**c, "reference_fps": ref_fps, "streams": streams})
    return {"time_unit": "s" if seconds else "frame", "events": events}


def largest_disagreement(event: dict) -> float:
    """The largest ``clock_disagreement_frames`` (absolute) of a ``sync`` event's streams (0
    where its clocks were not dropped)."""
    return max((abs(c.get("clock_disagreement_frames", 0.0)) for c in event["streams"].values()),
               default=0.0)


def rate_check(clock: dict, ref_fps: float | None, fps: float) -> dict:
    """A stream's fitted clock (``rate`` ± ``rate_sd`` reference frames per own frame over
    ``frame_span`` frames) against its known frame rate ``fps`` and the reference's ``ref_fps``:
    ``fps_deviation`` (the rate the clock implies over ``fps``, less 1), ``fps_deviation_sd``
    (the rate's distance from the rates' ratio in ``rate_sd``), ``fps_drift_frames`` (how far
    the clock drifts from that ratio over the stream's frames, in reference frames) and
    ``fps_consistent`` (:data:`RATE_CHECK_SD`, :data:`RATE_CHECK_DRIFT`); empty where
    ``ref_fps`` is unknown or ``rate_sd`` is 0 (the reference stream, a rate held)."""
    if ref_fps is None or not clock["rate_sd"] > 0:
        return {}
    miss = clock["rate"] - ref_fps / fps
    sigmas, drift = abs(miss) / clock["rate_sd"], miss * clock["frame_span"]
    return {"fps_deviation": ref_fps / clock["rate"] / fps - 1.0, "fps_deviation_sd": sigmas,
            "fps_drift_frames": drift,
            "fps_consistent": bool(sigmas <= RATE_CHECK_SD or abs(drift) < RATE_CHECK_DRIFT)}


def times_in_unit(time: np.ndarray, labels: np.ndarray, report: dict, fps: Fps) -> np.ndarray:
    """``time`` (N,) in reference frames in the unit of ``report`` (:func:`sync_report`):
    seconds (each event's frames over its reference's rate) or frames as they are."""
    if report["time_unit"] != "s":
        return time
    out = np.array(time, dtype=np.float64)
    for event in report["events"]:
        m = labels == event["event"]
        out[m] = time[m] / stream_fps(fps, event["reference_stream"])
    return out
