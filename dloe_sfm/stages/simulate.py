"""Simulate an unsynchronised multi-camera capture of a mocap sequence (the paper's protocol).

Several sequences: ``--mix events`` films them one after another with the same cameras,
``--mix people`` puts one person per sequence side by side in the same images (detections
shuffled per image). ``--outliers`` / ``--swaps`` then corrupt the detections. The truth needed
by ``dloe-sfm evaluate`` rides along in the capture file.
"""

from __future__ import annotations

import argparse
import logging
import math
from dataclasses import fields
from pathlib import Path

from ..errors import InputError
from ..io import check_not_input, save_capture
from ..synth import SimulationSettings, load_mocap, simulate
from ..synth.detector import DETECTORS
from ..synth.mocap import symmetric_pairs
from ..synth.scenarios import (
    add_outliers,
    simulate_events,
    simulate_people,
    swap_symmetric,
)

logger = logging.getLogger("dloe_sfm")

MIXES = ("events", "people")


def _check_fraction_or_distance(name: str, value: float, high: float) -> None:
    """``--gap`` / ``--spacing`` (>= 0) and ``--outliers`` / ``--swaps`` (in [0, 1]): one
    line naming the option; the capture's own settings check themselves
    (``SimulationSettings``)."""
    if not (isinstance(value, int | float) and math.isfinite(value) and 0 <= value <= high):
        bound = "a finite number >= 0" if high == math.inf else f"in [0, {high:g}]"
        raise InputError(f"--{name} must be {bound}, got {value!r}")


def main(
    mocap: Path | list[Path],
    out: Path,
    settings: SimulationSettings | None = None,
    *,
    mix: str = "events",
    gap: float = 2.0,
    spacing: float = 2.0,
    outliers: float = 0.0,
    swaps: float = 0.0,
) -> Path:
    """Write ``out`` (capture.npz with ``X_true`` / ``t_true`` ground truth) from mocap .npz
    file(s): one sequence, or several mixed as ``mix`` (``events``: ``gap`` seconds apart;
    ``people``: ``spacing`` metres apart); then ``outliers`` of the observations moved 20-100 px
    and ``swaps`` of the left/right pairs exchanged."""
    paths = [mocap] if isinstance(mocap, str | Path) else list(mocap)
    for name, value, high in (("gap", gap, math.inf), ("spacing", spacing, math.inf),
                              ("outliers", outliers, 1.0), ("swaps", swaps, 1.0)):
        _check_fraction_or_distance(name, value, high)
    if (outliers > 0 or swaps > 0) and settings is not None and settings.detector is not None:
        raise InputError("--outliers / --swaps cannot be combined with --detector (the detector "
                         "model makes its own outliers and swaps)")
    check_not_input(out, paths, "input mocap file")
    seqs = [load_mocap(p) for p in paths]
    if len(seqs) == 1:
        capture, truth = simulate(seqs[0], settings)
    elif mix == "events":
        capture, truth = simulate_events(seqs, settings, gap=gap)
    elif mix == "people":
        capture, truth = simulate_people(seqs, settings, spacing=spacing)
    else:
        raise InputError(f"unknown mix '{mix}' (known: {', '.join(MIXES)})")
    seed = (settings or SimulationSettings()).seed
    if outliers > 0:
        capture, truth = add_outliers(capture, truth, outliers, seed=seed + 1)
    if swaps > 0:
        capture, truth = swap_symmetric(capture, truth, symmetric_pairs(seqs[0].parents), swaps,
                                        seed=seed + 2)
    save_capture(out, capture, truth)
    logger.info("%s: %d images x %d points from %s", out, capture.num_images,
                capture.num_points, ", ".join(s.name for s in seqs))
    return Path(out)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mocap", type=Path, nargs="+",
                        help="mocap .npz (positions (T, J, 3) metres, fps); several: see --mix")
    parser.add_argument("--out", type=Path, required=True, help="capture.npz to write")
    parser.add_argument("--mix", choices=MIXES, default="events",
                        help="several sequences: one after another (events, default) or side "
                             "by side in the same images (people)")
    parser.add_argument("--gap", type=float, default=2.0, help="seconds between events")
    parser.add_argument("--spacing", type=float, default=2.0, help="metres between people")
    parser.add_argument("--outliers", type=float, default=0.0,
                        help="fraction of observations moved 20-100 px (wrong detections)")
    parser.add_argument("--swaps", type=float, default=0.0,
                        help="fraction of left/right pairs swapped in each image")
    special = {
        "rates": {"type": float, "nargs": "+", "metavar": "FPS",
                  "help": "frames per second of each stream (one per --num-streams, e.g. "
                          "24 25 29.97 30), overriding --rate"},
        "random_offsets": {"action": "store_true",
                           "help": "start each stream at a random time within its first period"},
        "detector": {"metavar": "NAME",
                     "help": "detector error model replacing --noise, calibrated on real "
                             f"detections ({', '.join(DETECTORS)})"},
    }
    defaults = SimulationSettings()
    for f in fields(SimulationSettings):
        value = getattr(defaults, f.name)
        kind = int if f.type == "int" else float  # every count: --lone-photos, --bursts too
        parser.add_argument(
            f"--{f.name.replace('_', '-')}",
            dest=f.name,
            default=value,
            **special.get(f.name, {"type": kind, "help": f"default: {value}"}),
        )


def run(args: argparse.Namespace) -> int:
    values = {f.name: getattr(args, f.name) for f in fields(SimulationSettings)}
    if values["rates"] is not None:
        values["rates"] = tuple(values["rates"])
    settings = SimulationSettings(**values)
    main(args.mocap, args.out, settings, mix=args.mix, gap=args.gap, spacing=args.spacing,
         outliers=args.outliers, swaps=args.swaps)
    return 0


if __name__ == "__main__":
    import sys

    from ..cli import run_stage

    sys.exit(run_stage(__name__))
