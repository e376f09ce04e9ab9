"""Run the whole chain on the bundled demo workspace (or, with ``--crowd``, the bundled crowd
workspace) and score it against the known truth."""

from __future__ import annotations

import argparse
import importlib.resources
import logging
import time
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..evaluate import evaluate_output
from .reconstruct import main as reconstruct_main

logger = logging.getLogger("dloe_sfm")

DEMO = Path(str(importlib.resources.files("dloe_sfm") / "assets" / "demo"))  # package data
# Lone photos and short bursts from cameras all around (pipelines/make_demo_assets, crowd mode)
CROWD = Path(str(importlib.resources.files("dloe_sfm") / "assets" / "crowd"))


def main(
    out: Path = Path("outputs/demo"),
    *,
    workspace: Path = DEMO,
    overwrite: bool = True,
    plots: bool = True,
) -> dict[str, float]:
    """``dloe-sfm reconstruct`` on ``workspace`` (default: assets/demo) into ``out``; scores.

    The demo replaces its own previous output at ``out`` unless ``overwrite=False``; a folder
    that dloe-sfm did not write is never replaced (``io.check_output``).
    """
    if not (workspace / "keypoints.csv").exists():
        raise InputError(f"{workspace}: not a demo workspace (no keypoints.csv)")
    tic = time.perf_counter()
    reconstruct_main(
        workspace, workspace / "keypoints.csv", "csv", out, overwrite=overwrite, plots=plots
    )
    scores = evaluate_output(out, workspace / "ground_truth.npz")
    scores["seconds"] = time.perf_counter() - tic
    return scores


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out",
        type=Path,
        help="output folder (default: outputs/demo, with --crowd outputs/demo_crowd; the demo's "
        "previous output there is replaced, any other folder is refused)",
    )
    parser.add_argument(
        "--crowd",
        action="store_true",
        help="the crowd workspace: lone photos and short bursts of many handheld cameras",
    )
    parser.add_argument("--workspace", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--no-plots", dest="plots", action="store_false", help="skip plots/")


def run(args: argparse.Namespace) -> int:
    workspace = args.workspace or (CROWD if args.crowd else DEMO)
    out = args.out or Path("outputs/demo_crowd" if args.crowd else "outputs/demo")
    s = main(out, workspace=workspace, plots=args.plots)
    with np.load(workspace / "ground_truth.npz") as truth:
        images = np.unique(truth["stream"], return_counts=True)[1]
    cameras = (
        f"{images.size} handheld cameras ({(images == 1).sum()} lone photos, "
        f"{(images > 1).sum()} bursts)"
        if args.crowd
        else f"{images.size} unsynchronised cameras"
    )
    print(f"demo: {s['images']} images from {cameras}, 8 moving markers, {s['seconds']:.1f} s")
    print(
        f"  3D error vs. truth: mean {s['error_mm']:.2f} mm, median {s['error_median_mm']:.2f} mm;"
        f" |Kendall tau| of the recovered order: {s['kendall_tau']:.4f}"
    )
    print(f"  point clouds: {out / 'frames'}/  (open3d / MeshLab)")
    print(f"  trajectories: {out / 'trajectories.npz'}, .csv, _wide.csv; "
          f"OpenSim / C3D: {out / 'trajectories.trc'}, .c3d")
    print(f"  plots:        {out / 'plots'}/  report: {out / 'report.json'}")
    return 0


if __name__ == "__main__":
    import sys

    from ..cli import run_stage

    sys.exit(run_stage(__name__))
