"""Run DLOE on a capture file and write a result file."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from .. import progress
from ..config import load_options
from ..core.options import Options
from ..core.result import Result
from ..core.solver import reconstruct
from ..io import check_output, load_capture, save_result, without_empty_images
from ..resources import check_solve_memory

logger = logging.getLogger("dloe_sfm")


def main(
    capture: Path,
    out: Path,
    *,
    config: Path | None = None,
    overrides: list[str] | None = None,
    options: Options | None = None,
    overwrite: bool = False,
) -> Result:
    """Solve ``capture`` (capture.npz) and write ``out`` (result.npz); returns the result.

    Images that observe no point (the detector found nobody) are left out with a warning and
    named in the result file (``skipped_images``); its rows are the capture's other images.
    ``out`` is checked first (``io.check_output``): never an input; an existing file is only
    replaced with ``overwrite`` and when it is a result file.
    """
    out = Path(out)
    target = check_output(out, protected=[capture, config], overwrite=overwrite, kind="file")
    options = load_options(config, overrides, base=options)
    full = load_capture(capture, validate=False).validate(str(capture), empty_images=True)
    cap, kept = without_empty_images(full, capture)
    skipped = np.delete(full.image_names, kept).tolist()
    logger.info(
        "solving %s: %d images, %d points, %d streams",
        capture,
        cap.num_images,
        cap.num_points,
        len(set(cap.stream_ids.tolist())),
    )
    check_solve_memory(cap, options, capture)
    with progress.solver_bar() as on_sweep:
        result = reconstruct(cap, options, progress=on_sweep)
    save_result(target, result, skipped_images=skipped)
    logger.info(
        "%s: %s after %d iterations, %.2f s, %d event(s)",
        out,
        result.message,
        result.nit,
        result.seconds,
        int(result.events.max()) + 1,
    )
    return result


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", type=Path, help="capture.npz (docs/interfaces.md)")
    parser.add_argument("--out", type=Path, required=True, help="result.npz to write")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing result file (any other file is refused)")
    parser.add_argument("--config", type=Path, help="TOML file of solver options")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one solver option (repeatable)",
    )
    parser.add_argument("--progress", action="store_true",
                        help="show progress bars (default: only on a terminal)")


def run(args: argparse.Namespace) -> int:
    base = Options()
    main(args.capture, args.out, config=args.config, overrides=args.overrides, options=base,
         overwrite=args.overwrite)
    return 0


if __name__ == "__main__":
    import sys

    from ..cli import run_stage

    sys.exit(run_stage(__name__))
