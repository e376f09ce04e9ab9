"""``dloe-sfm benchmark SUITE``: the paper's experiments with every baseline on simulated mocap
captures (:mod:`dloe_sfm.benchmark`).

Suites: ``noise``, ``rate``, ``missing``, ``density`` (3D error of every method while one
factor of the capture varies), ``kendall`` (|Kendall tau| of the sequencing orders),
``ablation`` (DLOE without the S, T or R term), ``runtime`` (time and memory against the number
of images), ``streams`` (the same for many cameras: 11 000 images from 16 streams, 10 000 from
64; ``--data`` with the CMU clips), ``lone`` (the same for lone photos: 300 under the detector
model, 300 to 4 000 clean). Each writes ``results.json``, ``table.md`` and
``<suite>.png`` to ``--out`` and prints the table.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ..benchmark import SUITES, main


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("suite", choices=SUITES, help="which benchmark to run")
    parser.add_argument("--quick", action="store_true",
                        help="reduced grid: 2 motions, 1 seed, 2 settings, 1 s clips")
    parser.add_argument("--out", type=Path, help="output folder (default outputs/benchmark/SUITE)")
    parser.add_argument("--data", type=Path,
                        help="folder of mocap .npz clips (default: the bundled walking_1, "
                             "jumping_1 and basketball_signal_1, enough for --quick); the full "
                             "suites need one with the CMU clips (MOTION.npz or "
                             "li2018_train_MOTION.npz)")
    parser.add_argument("--seeds", type=int, help="seeds per setting (default 3, quick 1)")
    parser.add_argument("--motions", nargs="+", help="motion names, e.g. walking_1 soccer_2")
    parser.add_argument("--jobs", type=int, default=1,
                        help="parallel worker processes, each single-threaded (default 1)")
    parser.add_argument("--duration", type=float, help="clip length, s (default 2.5, quick 1)")
    parser.add_argument("--sizes", type=int, nargs="+", help="runtime suite: numbers of images")
    parser.add_argument("--streams", type=int,
                        help="runtime suite: video streams (default 8); 10^4 images of the 26 s "
                             "basketball_signal_1 clip need 13 or more at 30 Hz")
    parser.add_argument("--rate", type=float,
                        help="runtime suite: the streams' frame rate, Hz (default 30)")


def run(args: argparse.Namespace) -> int:
    jobs = max(1, min(args.jobs, os.cpu_count() or 1))
    doc = main(args.suite, out=args.out, data=args.data, quick=args.quick, seeds=args.seeds,
               motions=args.motions, jobs=jobs, duration=args.duration, sizes=args.sizes,
               streams=args.streams, rate=args.rate)
    print(doc["table"])
    return 0


if __name__ == "__main__":
    from ..cli import run_stage

    sys.exit(run_stage(__name__))
