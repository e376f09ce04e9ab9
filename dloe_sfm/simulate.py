"""Simulate an unsynchronised multi-camera capture of a mocap sequence (the paper's protocol)."""

from __future__ import annotations

import argparse
import logging
from dataclasses import fields
from pathlib import Path

from .io import save_capture
from .synth import SimulationSettings, load_mocap, simulate

logger = logging.getLogger("dloe_sfm")


def main(mocap: Path, out: Path, settings: SimulationSettings | None = None) -> Path:
    """Write ``out`` (capture.npz with ``X_true`` / ``t_true`` ground truth) from a mocap .npz."""
    seq = load_mocap(mocap)
    capture = simulate(seq, settings)
    save_capture(out, capture)
    logger.info(
        "%s: %d images x %d points from %s", out, capture.num_images, capture.num_points, seq.name
    )
    return Path(out)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mocap", type=Path, help="mocap .npz (positions (T, J, 3) metres, fps)")
    parser.add_argument("--out", type=Path, required=True, help="capture.npz to write")
    defaults = SimulationSettings()
    for f in fields(SimulationSettings):
        value = getattr(defaults, f.name)
        kind = int if f.name in ("num_streams", "image_size", "seed") else float
        parser.add_argument(
            f"--{f.name.replace('_', '-')}",
            dest=f.name,
            type=kind,
            default=value,
            help=f"default: {value}",
        )


def run(args: argparse.Namespace) -> int:
    settings = SimulationSettings(
        **{f.name: getattr(args, f.name) for f in fields(SimulationSettings)}
    )
    main(args.mocap, args.out, settings)
    return 0


if __name__ == "__main__":
    import sys

    from .cli import run_stage

    sys.exit(run_stage(__name__))
