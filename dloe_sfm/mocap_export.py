"""Motion-capture exports of the points: TRC (OpenSim, Pose2Sim), C3D (ezc3d) and a wide CSV.

Time. Every image's time is first counted in frames of its event's reference stream (the
event's video with the most images: its frame numbers, as in the file names), by the most
faithful base the result holds, per event: ``clock`` (the streams' fitted affine clocks,
``Result.clock``, or those the held-out check dropped for the points,
``Result.clock_dropped``), ``burst clock`` (the same of an event of bursts and lone photos
alone: its bursts' clocks, ``core.clocked.burst_times``), ``affine
embedding`` (the embedding is the streams' affine clocks: every stream's images lie on a line
in their frame numbers), else ``rank`` (the reference stream's images at their frames, the
others between them evenly by estimated order; an event without a video: one frame per image).
Events are never bridged: a later event keeps its gap to the previous one when both are timed
by the same stream, else it is placed two of its frames after it.

TRC and C3D hold the points on a uniform time grid (default: the fastest stream's rate),
linearly interpolated between a point's observations that are at most 1.5 image periods of the
event's slowest stream apart (its frame period times its median step in frame numbers: a stream
that keeps every 4th frame samples every 4 periods), empty elsewhere. Where the frame rate of
every event's reference stream is known and the same (``--fps``: the rate of its frame numbers),
the three files are in seconds: time over that rate, TRC ``DataRate`` / ``CameraRate`` and C3D
``POINT:RATE`` in Hz (the grid's samples per frame times it); else in reference frames, rates in
samples per frame. Positions are in mm, taken from the model's units as metres (the calibration
import and the simulator work in metres), in the model's frame as it is (not rotated to
OpenSim's y-up)."""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path

import ezc3d
import numpy as np

from .core.capture import Capture
from .core.clocked import filmed
from .core.clocks import rank_times, reference_stream
from .core.result import Result
from .core.sync import Fps, stream_fps
from .errors import InputError

logger = logging.getLogger("dloe_sfm")

MM_PER_UNIT = 1000.0
"""Millimetres per model unit (the model's units are taken as metres)."""
MAX_GAP_PERIODS = 1.5
"""Longest interpolated gap between two observations of a point, in image periods of the
event's slowest stream (frame period times median frame step)."""
EVENT_GAP_FRAMES = 2.0
"""Separation of events whose relative timing is unknown, in reference frames."""
MAX_POINT_SAMPLES = 10**7
"""Largest grid (samples x points) written: a guard against a mistaken ``--export-rate``."""
AFFINE_TOLERANCE = 1e-6
"""Largest deviation of a stream's images from a line in their frame numbers (relative to the
span) for the embedding to count as the streams' affine clocks."""


WHOLE_FACTOR_TOLERANCE = 0.1
"""How near a whole factor (2, 3, ... or its inverse) a clock's rate over the stream's stated
frame rate must be for the rate check to name it: frame numbers counted at another rate."""


def whole_factor(clock: dict, stream: int | str) -> str:
    """Where a stream's clock (``core.sync.sync_report``, with ``implied_fps`` and ``fps``)
    runs at a whole factor (or its inverse) of the stated frame rate: the factor and the
    ``--fps`` the clock implies, for a warning; else empty."""
    factor = clock["implied_fps"] / clock["fps"]
    whole = round(max(factor, 1.0 / factor))
    if whole < 2 or abs(max(factor, 1.0 / factor) / whole - 1.0) > WHOLE_FACTOR_TOLERANCE:
        return ""
    meant, about = ((clock["fps"] * whole, f"{whole}") if factor > 1 else
                    (clock["fps"] / whole, f"1/{whole}"))
    return (f"its clock runs {factor:.3g} x the rate --fps gives it (about {about}), as when "
            "its frame numbers count frames at another rate than the images': "
            f"--fps {stream}={meant:g} if they count frames at that rate")


def frame_steps(capture: Capture) -> dict[int, int]:
    """Per stream of three or more frames: the largest step dividing every step between its
    frame numbers (4 when a video's frames are named at its rate and every 4th is kept)."""
    steps = {}
    for s in np.unique(capture.stream_ids):
        frames = np.unique(capture.frame[capture.stream_ids == s])
        if frames.size >= 3:
            steps[int(s)] = int(np.gcd.reduce(np.diff(frames)))
    return steps


def warn_stepped_frames(capture: Capture, fps: Fps) -> None:
    """Warn where streams of a known frame rate number their frames in steps of k > 1: the
    rate (``--fps``) counts frame numbers, so the images are k times rarer; a rate meant as the
    images' own makes every time k times too long."""
    groups: dict[tuple[int, float], list[int]] = {}
    for s, k in frame_steps(capture).items():
        rate = stream_fps(fps, s)
        if k > 1 and rate is not None:
            groups.setdefault((k, rate), []).append(s)
    for (k, rate), streams in groups.items():
        every = len(streams) == np.unique(capture.stream[capture.stream >= 0]).size
        fix = f"{rate * k:g}" if every else " ".join(f"{s}={rate * k:g}" for s in streams)
        logger.warning("stream(s) %s: the frame numbers in the image names step by %d, so at "
                       "%g fps (the rate of those numbers, --fps) the images are %g per second; "
                       "if %g fps is the images' own rate, the numbers run at %g: give --fps %s",
                       ", ".join(map(str, streams)), k, rate, rate / k, rate, rate * k, fix)


@dataclass(frozen=True, kw_only=True)
class Timeline:
    """Estimated time of every image (module docstring).

    time : (N,) float, in ``unit``; events : per event (in estimated order) its label, time
    ``base``, ``clocks_dropped`` (the times are the clocks of ``Result.clock_dropped``, the
    points DLOE's graph's), ``reference_stream`` (None without a video), ``start`` / ``end`` time,
    ``offset_known`` (its gap to the previous event is measured, not set) and ``max_gap``;
    rate : the fastest stream's sampling rate, samples per ``unit``.
    """

    time: np.ndarray
    unit: str
    events: list[dict]
    rate: float


def _affine_times(u: np.ndarray, streams: np.ndarray, frames: np.ndarray,
                  ref: int) -> np.ndarray | None:
    """``u`` mapped to the reference stream's frames when every stream's images lie on a line
    ``u = a + b frame`` (b > 0) and one stream has three or more images; else None."""
    tol = AFFINE_TOLERANCE * max(float(np.ptp(u)), 1e-300)
    lines = {}
    for s in np.unique(streams):
        m = streams == s
        if np.unique(frames[m]).size < 2:
            continue
        b, a = np.polyfit(frames[m].astype(np.float64), u[m], 1)
        if b <= 0 or np.abs(u[m] - (a + b * frames[m])).max() > tol:
            return None
        lines[int(s)] = (a, b, int(m.sum()))
    if max(size for _, _, size in lines.values()) < 3:
        return None
    a, b, _ = lines[ref]
    # the reference stream's images at their frames exactly (not a rounding off them)
    return np.where(streams == ref, frames, (u - a) / b)


def _event_times(times: np.ndarray | None, idx: np.ndarray) -> np.ndarray | None:
    """``times`` of the event's images ``idx`` when it has them all (a ``Result`` clock)."""
    return times[idx] if times is not None and np.isfinite(times[idx]).all() else None


def image_times(capture: Capture, result: Result) -> Timeline:
    """Every image's time in reference frames and the export's default rate (module docstring).

    ``capture`` is the one ``result.X`` refers to (``columns.solved_capture``).
    """
    n = capture.num_images
    rank = result.rank
    stream_ids = capture.stream_ids
    time = np.empty(n)
    periods = []
    summaries = []
    prev = None
    firsts = [int(rank[result.events == e].min()) for e in np.unique(result.events)]
    for e in np.unique(result.events)[np.argsort(firsts)]:
        idx = np.flatnonzero(result.events == e)
        idx = idx[np.argsort(rank[idx])]
        streams, frames = stream_ids[idx], capture.frame[idx]
        videos, ref = reference_stream(streams, frames)
        t, base = None, "rank"
        kept = _event_times(result.clock, idx)
        clocks = _event_times(result.clock_dropped, idx) if kept is None else kept
        if ref is not None:
            u = result.embedding[idx] if clocks is None else clocks
            t = _affine_times(u, streams, frames, ref)
            if t is not None and (np.diff(t) >= -AFFINE_TOLERANCE * np.ptp(t)).all():
                base = ("affine embedding" if clocks is None
                        else "clock" if filmed(streams) else "burst clock")
            else:
                t = rank_times(streams, frames, ref)
        if t is None:
            t, ref = np.arange(idx.size, dtype=np.float64), None
            event_periods, steps = [1.0], [1.0]
        else:
            slopes = [float(np.polyfit(frames[streams == s], t[streams == s], 1)[0])
                      for s in videos]
            event_periods = [p for p in slopes if p > 0] or [1.0]
            # a stream that keeps every k-th frame samples the motion every k frame periods
            steps = [p * float(np.median(np.diff(np.sort(frames[streams == s]))))
                     for s, p in zip(videos, slopes, strict=True) if p > 0] or [1.0]
        offset_known = (prev is not None and ref is not None and ref == prev["reference_stream"]
                        and t.min() > prev["end"])
        if prev is not None and not offset_known:
            t = t - t.min() + prev["end"] + EVENT_GAP_FRAMES
        time[idx] = t
        periods += event_periods
        prev = {"event": int(e), "base": base, "clocks_dropped": base == "clock" and kept is None,
                "reference_stream": None if ref is None else int(ref),
                "start": float(t.min()), "end": float(t.max()),
                "offset_known": bool(offset_known),
                "max_gap": MAX_GAP_PERIODS * max(steps)}
        summaries.append(prev)
    rate = 1.0 / min(periods)
    # streams within 1 % of the reference's rate: sample on the reference's frames
    return Timeline(time=time, unit="frame", events=summaries,
                    rate=1.0 if abs(rate - 1.0) < 0.01 else rate)


def resample_uniform(t: np.ndarray, X: np.ndarray, valid: np.ndarray, rate: float, *,
                     segments: np.ndarray | None = None,
                     max_gap: float | np.ndarray = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Points on a uniform time grid, linear between samples, empty across unsupported gaps.

    t (M,) sample times, X (M, P, 3), valid (M, P) bool: the samples a point may be
    interpolated from (non-finite ones are never used); rate: grid samples per unit of t.
    ``segments`` (M,) int labels 0..S-1 (default: one): a point is never interpolated between
    samples of different segments, nor between two samples more than ``max_gap`` (a float or
    (S,) per segment) apart; at a grid instant equal to a lone sample's time it takes that
    sample (duplicates averaged). Returns the grid (K,), from ``t.min()`` through ``t.max()``,
    and Y (K, P, 3), NaN where no pair of samples supports the instant.
    """
    t = np.asarray(t, dtype=np.float64)
    segments = np.zeros(t.size, dtype=np.int64) if segments is None else np.asarray(segments)
    gaps = np.broadcast_to(np.asarray(max_gap, dtype=np.float64), (int(segments.max()) + 1,))
    count = int(np.floor((t.max() - t.min()) * rate * (1 + 1e-12))) + 1
    grid = t.min() + np.arange(count) / rate
    Y = np.full((count, X.shape[1], 3), np.nan)
    valid = np.asarray(valid, dtype=bool) & np.isfinite(X).all(axis=2)
    for s in np.unique(segments):
        for k in range(X.shape[1]):
            m = (segments == s) & valid[:, k]
            if not m.any():
                continue
            ts, inverse = np.unique(t[m], return_inverse=True)
            xs = np.zeros((ts.size, 3))
            np.add.at(xs, inverse, X[m, k])
            xs /= np.bincount(inverse, minlength=ts.size)[:, None]
            inside = np.flatnonzero((grid >= ts[0]) & (grid <= ts[-1]))
            g = grid[inside]
            right = np.searchsorted(ts, g, side="left")  # ts[right - 1] < g <= ts[right]
            exact = ts[right] == g
            left = np.maximum(right - 1, 0)
            span = ts[right] - ts[left]
            w = (g - ts[left]) / np.where(exact, 1.0, span)
            value = np.where(exact[:, None], xs[right],
                             xs[left] + w[:, None] * (xs[right] - xs[left]))
            ok = exact | (span <= gaps[s])
            Y[inside[ok], k] = value[ok]
    return grid, Y


def write_trc(path: Path, grid: np.ndarray, Y_mm: np.ndarray, names: list[str],
              rate: float) -> Path:
    """OpenSim / Pose2Sim TRC: grid (K,) times, Y_mm (K, P, 3) mm (NaN: empty fields)."""
    count, num = Y_mm.shape[:2]
    rate = float(rate)
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{Path(path).name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame"
        "\tOrigNumFrames",
        f"{rate!r}\t{rate!r}\t{count}\t{num}\tmm\t{rate!r}\t1\t{count}",
        "Frame#\tTime" + "".join(f"\t{name}\t\t" for name in names),
        "\t" + "".join(f"\tX{k}\tY{k}\tZ{k}" for k in range(1, num + 1)),
        "",
    ]
    for row, (time, values) in enumerate(zip(grid.tolist(), Y_mm.reshape(count, -1).tolist(),
                                             strict=True), start=1):
        cells = ("" if v != v else repr(v) for v in values)  # NaN: empty
        lines.append(f"{row}\t{time!r}\t" + "\t".join(cells))
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)


def write_c3d(path: Path, grid: np.ndarray, Y_mm: np.ndarray, names: list[str], rate: float,
              *, unit: str, note: str) -> Path:
    """C3D through ezc3d: points (K, P, 3) mm (NaN: invalid, residual -1 in the file),
    POINT:RATE ``rate`` per ``unit``; group DLOE_SFM holds TIME_UNIT, START_TIME, NOTE."""
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [float(rate)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = tuple(names)
    points = np.ones((4, Y_mm.shape[1], Y_mm.shape[0]))
    points[:3] = np.transpose(Y_mm, (2, 1, 0))
    points[:, ~np.isfinite(points[:3]).all(axis=0)] = np.nan
    c3d["data"]["points"] = points
    c3d.add_parameter("POINT", "UNITS", "mm")
    c3d.add_parameter("DLOE_SFM", "TIME_UNIT", unit)
    c3d.add_parameter("DLOE_SFM", "START_TIME", [float(grid[0])])
    c3d.add_parameter("DLOE_SFM", "NOTE", note)
    c3d.write(str(path))
    return Path(path)


def write_wide_csv(path: Path, capture: Capture, result: Result, time: np.ndarray,
                   names: list[str]) -> Path:
    """One row per image in estimated order: rank, image, event, stream, frame, time, then
    ``<name>_x, _y, _z`` per column of X in model units (empty where not finite)."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["rank", "image", "event", "stream", "frame", "time",
                         *(f"{name}_{axis}" for name in names for axis in "xyz")])
        for r, i in enumerate(result.order):
            writer.writerow([r, capture.image_names[i], int(result.events[i]),
                             int(capture.stream[i]), int(capture.frame[i]), repr(float(time[i])),
                             *("" if v != v else repr(v) for v in result.X[i].ravel().tolist())])
    return Path(path)


def _seconds_per_frame(events: list[dict], fps: Fps) -> float | None:
    """The frame rate every event's reference stream shares in ``fps``, else None (a video
    of unknown rate, an event without one, or references at different rates)."""
    rates = {stream_fps(fps, e["reference_stream"]) for e in events}
    return rates.pop() if len(rates) == 1 and None not in rates else None


def write_mocap(folder: Path, capture: Capture, result: Result, names: list[str], *,
                export_rate: float | None = None, fps: Fps = None) -> tuple[np.ndarray, dict]:
    """``trajectories.trc``, ``trajectories.c3d`` and ``trajectories_wide.csv`` in ``folder``.

    ``capture`` as from ``columns.solved_capture``, ``names`` (P',) the columns' marker names;
    ``export_rate``: grid samples per reference frame (default: the fastest stream's rate);
    ``fps``: the streams' frame rates (``core.sync``), the files in seconds and Hz when every
    event's reference stream has the same one (module docstring). Returns every image's time
    (N,) in reference frames and the report's ``mocap_export`` entry.
    """
    if export_rate is not None and not (np.isfinite(export_rate) and export_rate > 0):
        raise InputError(f"option --export-rate: must be a positive number, got {export_rate}")
    timeline = image_times(capture, result)
    rate = timeline.rate if export_rate is None else float(export_rate)
    samples = int(np.ptp(timeline.time) * rate) + 1
    if samples * result.X.shape[1] > MAX_POINT_SAMPLES:
        raise InputError(f"option --export-rate: {rate:g} samples per frame over "
                         f"{np.ptp(timeline.time):g} frames make {samples} samples of "
                         f"{result.X.shape[1]} points, more than {MAX_POINT_SAMPLES}; lower it")
    hz = _seconds_per_frame(timeline.events, fps)
    per_unit = 1.0 if hz is None else hz  # frames per unit of the files' time
    time = timeline.time / per_unit
    label = {summary["event"]: k for k, summary in enumerate(timeline.events)}
    grid, Y = resample_uniform(time, result.X, capture.visible, rate * per_unit,
                               segments=np.array([label[int(e)] for e in result.events]),
                               max_gap=np.array([s["max_gap"] for s in timeline.events]) / per_unit)
    Y_mm = Y * MM_PER_UNIT
    bases = sorted({s["base"] for s in timeline.events})
    unit = "frame" if hz is None else "s"
    when = ("frames of each event's reference stream" if hz is None else
            f"seconds (frames of each event's reference stream at {hz:g} fps)")
    note = (f"time in {when} (base: {', '.join(bases)}); "
            f"mm from model units as metres; model frame as is (not y-up)")
    write_trc(folder / "trajectories.trc", grid, Y_mm, names, rate * per_unit)
    write_c3d(folder / "trajectories.c3d", grid, Y_mm, names, rate * per_unit, unit=unit,
              note=note)
    write_wide_csv(folder / "trajectories_wide.csv", capture, result, time, names)
    report = {"time_unit": unit, "rate": rate * per_unit, "rate_per_frame": rate, "fps": hz,
              "samples": int(grid.size), "start_time": float(grid[0]), "units": "mm",
              "mm_per_model_unit": MM_PER_UNIT,
              "empty_fraction": float(np.isnan(Y[..., 0]).mean()), "note": note,
              "events": timeline.events}
    return timeline.time, report
