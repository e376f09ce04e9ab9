"""Every stream's time offset and rate from a ``reconstruct`` output's ``report.json`` (its
``sync`` entry, docs/interfaces.md, "Synchronisation"): a table per event, and JSON for other
tools."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from ..core.sync import (
    RATE_CHECK_DRIFT,
    RATE_CHECK_SD,
    Fps,
    largest_disagreement,
    rate_check,
    stream_fps,
)
from ..errors import InputError
from ..io import atomic_path, check_not_input
from ..mocap_export import whole_factor

JSON_KIND = "dloe-sfm sync"
"""The ``kind`` of the JSON file written (an earlier one may be replaced with ``--overwrite``)."""


def parse_fps(values: list[str] | None) -> Fps:
    """``--fps`` values: one number for every stream or ``STREAM=FPS`` pairs (stream ids as in
    report.json's ``sync``); a one-line InputError for anything else."""
    if not values:
        return None

    def rate(text: str) -> float:
        try:
            return positive_rate(text)
        except ValueError as e:
            raise InputError(f"option --fps: {e}") from None

    if len(values) == 1 and "=" not in values[0]:
        return rate(values[0])
    out = {}
    for item in values:
        stream, sep, value = item.partition("=")
        if not sep:
            raise InputError(f"option --fps: expected one FPS or STREAM=FPS pairs, got {item!r}")
        try:
            key = int(stream)
        except ValueError:
            raise InputError(f"option --fps: unknown stream {stream!r} (streams are numbered "
                             "as in report.json's sync)") from None
        if key in out:
            raise InputError(f"option --fps: stream {key} given twice")
        out[key] = rate(value)
    return out


def positive_rate(text: str) -> float:
    """A frame or sample rate given on the command line: a positive finite number (ValueError
    "must be a positive number, got ..." otherwise)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"must be a positive number, got {text!r}")
    return value


def add_fps_option(parser: argparse.ArgumentParser, *, solves: bool = False) -> None:
    """``--fps`` (``parse_fps``) on ``parser``; ``solves``: the command solves with it."""
    parser.add_argument("--fps", nargs="+", metavar="FPS|STREAM=FPS",
                        help="frame rate of every stream, or per stream (e.g. 0=30 1=29.97), "
                             "as the frame numbers in the image names count: a video's own rate "
                             "even when only every k-th frame is kept; times in seconds and "
                             "offsets in ms"
                             + (", trajectories.trc / .c3d in Hz; the clocks keep the rates' "
                                "ratios once the detections' offsets are out" if solves else ""))


def read_report(folder: Path) -> dict:
    """The ``sync`` entry of ``folder/report.json``; a one-line InputError when it is missing or
    malformed."""
    path = Path(folder) / "report.json"
    try:
        with open(path, encoding="utf-8") as f:
            report = json.load(f)
    except FileNotFoundError:
        raise InputError(f"{folder}: not a reconstruct output folder (no report.json)") from None
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:
        raise InputError(f"{path}: cannot read it ({type(e).__name__})") from None
    sync = report.get("sync") if isinstance(report, dict) else None
    events = sync.get("events") if isinstance(sync, dict) else None
    if not isinstance(events, list) or not all(
            isinstance(e, dict) and isinstance(e.get("streams"), dict)
            and all(_valid_clock(c) for c in e["streams"].values()) for e in events):
        raise InputError(f"{path}: no valid 'sync' entry (written by dloe-sfm >= the sync "
                         "command's version?)")
    return sync


def _valid_clock(clock: object) -> bool:
    """A stream's entry of a report's ``sync``: its offset and rate numbers, and where present
    a positive ``fps`` and a ``frame_span`` of at least 0."""
    if not isinstance(clock, dict):
        return False

    def number(key: str) -> bool:
        return isinstance(clock.get(key), (int, float))

    return (all(number(k) for k in ("offset_frames", "offset_sd_frames", "rate", "rate_sd"))
            and ("fps" not in clock or number("fps") and clock["fps"] > 0)
            and ("frame_span" not in clock or number("frame_span") and clock["frame_span"] >= 0))


def stream_table(sync: dict, fps: Fps = None) -> dict:
    """The JSON written by ``--json``: per event its ``reference_stream``, ``reference_fps`` and
    ``streams`` (``offset_frames``, ``offset_sd_frames``, ``rate``, ``rate_sd``, ``rate_held``
    (the report's: the rate held at the known frame rates' ratio), ``images``,
    with the reference's fps ``offset_s``, ``offset_sd_s``, ``implied_fps``, with the stream's
    own ``fps`` and the check against it, ``core.sync.rate_check``; where the event's clocks
    were dropped for its points, ``clocks_dropped``, ``clock_disagreement_frames`` and ``_s``);
    ``fps`` (as
    ``parse_fps``) replaces the report's rates. The event with the most images also at the top
    level."""
    events = []
    for event in sync["events"]:
        ref = event.get("reference_stream")
        ref_fps = stream_fps(fps, ref) if fps is not None else event.get("reference_fps")
        streams = {}
        for name, c in event["streams"].items():
            frames, sd = c["offset_frames"], c["offset_sd_frames"]
            entry = {"offset_frames": frames, "offset_sd_frames": sd, "rate": c["rate"],
                     "rate_sd": c["rate_sd"], "rate_held": bool(c.get("rate_held")),
                     "images": c.get("images")}
            apart = c.get("clock_disagreement_frames")
            if isinstance(apart, (int, float)):
                entry["clock_disagreement_frames"] = apart
            if ref_fps is not None:
                entry.update(offset_s=frames / ref_fps, offset_sd_s=sd / ref_fps,
                             implied_fps=ref_fps / c["rate"])
                if "clock_disagreement_frames" in entry:
                    entry["clock_disagreement_s"] = apart / ref_fps
            own = stream_fps(fps, int(name)) if fps is not None else c.get("fps")
            if own is not None:
                entry["fps"] = own
                if "frame_span" in c:  # reports before the check have none
                    entry.update(rate_check(c, ref_fps, own))
            streams[name] = entry
        events.append({"event": event.get("event"), "base": event.get("base"),
                       "clocks_dropped": bool(event.get("clocks_dropped")),
                       "reference_stream": ref, "reference_fps": ref_fps, "streams": streams})
    main = max(events, key=lambda e: sum(c["images"] or 0 for c in e["streams"].values()),
               default={"reference_stream": None, "reference_fps": None, "streams": {}})
    return {"kind": JSON_KIND, "reference_stream": main["reference_stream"],
            "reference_fps": main["reference_fps"], "streams": main["streams"], "events": events}


def format_table(table: dict) -> str:
    """The printed table: per event, one line per stream."""
    lines = []
    for event in table["events"]:
        fps = event["reference_fps"]
        lines.append(f"event {event['event']} (base {event['base']}, reference stream "
                     f"{event['reference_stream']}" + (f" at {fps:g} fps)" if fps else ")"))
        lines.append(f"  {'stream':>6} {'offset ms':>20} {'offset frames':>22} {'rate':>18}"
                     f" {'images':>6}")
        for name, c in event["streams"].items():
            ms = (f"{1000 * c['offset_s']:+9.3f} ± {1000 * c['offset_sd_s']:7.3f}"
                  if "offset_s" in c else "-")
            rate_sd = "   held  " if c["rate_held"] else f"± {c['rate_sd']:7.1e}"
            lines.append(f"  {name:>6} {ms:>20} {c['offset_frames']:+11.4f} ± "
                         f"{c['offset_sd_frames']:8.4f} {c['rate']:8.6f} {rate_sd}"
                         f" {c['images'] or 0:>6}" + ("  !" if c.get("fps_consistent") is False
                                                      else ""))
        if event["clocks_dropped"]:
            lines.append("  ~ the streams' fitted clocks predicted held-out detections worse "
                         "than DLOE's graph, which gives the points: the offsets are the clocks', "
                         "and the uncertainty includes their disagreement with the graph's time "
                         f"line (up to {largest_disagreement(event):.2f} frames)")
    if any(c.get("fps_consistent") is False for e in table["events"]
           for c in e["streams"].values()):
        lines.append(f"! the clock's rate is more than {RATE_CHECK_SD:g} standard uncertainties "
                     f"from the known frame rates, {RATE_CHECK_DRIFT:g} frame or more over the "
                     "stream: the fit may have settled on wrong rates, its offset and times are "
                     "not to be trusted")
    lines += [f"! stream {name}: {whole_factor(c, name)}" for e in table["events"]
              for name, c in e["streams"].items()
              if c.get("fps_consistent") is False and whole_factor(c, name)]
    return "\n".join(lines)


def write_json(path: Path, table: dict, *, inputs: list[Path], overwrite: bool) -> Path:
    """``table`` to ``path`` atomically; an existing file only replaced with ``overwrite`` and
    when it is an earlier output of this command; never an input."""
    path = Path(path)
    check_not_input(path, inputs, "input")
    if path.is_dir():
        raise InputError(f"{path}: exists and is a folder; choose another --json file")
    if path.exists():
        try:
            kind = json.loads(path.read_text(encoding="utf-8")).get("kind")
        except (OSError, UnicodeDecodeError, ValueError, AttributeError):
            kind = None
        if kind != JSON_KIND:
            raise InputError(f"{path}: exists and is not a dloe-sfm sync file, never replaced; "
                             "choose another --json file")
        if not overwrite:
            raise InputError(f"{path}: output file exists (use --overwrite to replace it)")
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(table, indent=2) + "\n")
    return path


def main(folder: Path, *, fps: Fps = None, json_out: Path | None = None,
         overwrite: bool = False) -> dict:
    """Read ``folder``'s sync entry, print its table, write ``json_out``; returns the table."""
    folder = Path(folder)
    sync = read_report(folder)
    table = stream_table(sync, fps)
    if json_out is not None:
        write_json(json_out, table, inputs=[folder / "report.json"], overwrite=overwrite)
    print(format_table(table))
    return table


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", type=Path, help="a reconstruct output folder")
    add_fps_option(parser)
    parser.add_argument("--json", dest="json_out", type=Path, metavar="FILE",
                        help="also write the offsets and rates as JSON")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier --json file of this command")


def run(args: argparse.Namespace) -> int:
    main(args.out, fps=parse_fps(args.fps), json_out=args.json_out, overwrite=args.overwrite)
    return 0


if __name__ == "__main__":
    from ..cli import run_stage

    sys.exit(run_stage(__name__))
