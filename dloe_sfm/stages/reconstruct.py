"""Reconstruct moving points from keypoint files on the images of a COLMAP workspace."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from .. import __version__, progress
from ..colmap import load_workspace
from ..config import load_options
from ..core.options import Options
from ..core.solver import reconstruct
from ..core.sync import Fps, capture_fps, check_fps, with_fps
from ..errors import InputError
from ..io import check_output
from ..keypoints import FORMATS, Layout, load_layout, read_keypoints
from ..observations import PERSON_MODES, build_capture, observed_layout
from ..resources import check_solve_memory
from .sync import add_fps_option, parse_fps, positive_rate

logger = logging.getLogger("dloe_sfm")


def _person(value: str) -> str | int:
    """``--person``: ``largest``, ``all``, ``auto`` or a detection index (0 = first in a file)."""
    if value in PERSON_MODES:
        return value
    try:
        index = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected {', '.join(PERSON_MODES)} or an index, got {value!r}"
        ) from None
    if index < 0:
        raise argparse.ArgumentTypeError(f"person index must be >= 0, got {index}")
    return index


def _positive_rate(value: str) -> float:
    """``--export-rate``: a positive finite number."""
    try:
        return positive_rate(value)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def main(workspace: Path, keypoints: Path | None, fmt: str, out: Path, *,
         stream_pattern: str | None = None, min_score: float = 0.0,
         person: str | int = "auto", layout: str | Path | Layout | None = None,
         aruco_dict: str | None = None,
         config: Path | None = None, overrides: list[str] | None = None,
         options: Options | None = None, overwrite: bool = False, plots: bool = True,
         export_rate: float | None = None, fps: Fps = None) -> Path:
    """Workspace + keypoints -> capture -> DLOE -> ``out`` (docs/interfaces.md, "Reconstruct
    outputs").

    ``keypoints`` may be None for ``aruco`` (markers detected in the workspace's images).
    ``layout`` (names, skeleton, left/right pairs of the points; ``keypoints.load_layout``: a
    ``Layout``, a name or a JSON file) replaces the format's own; not for ``aruco``.
    ``aruco_dict``: the ``aruco`` format's predefined ``cv2.aruco`` dictionary (default
    DICT_4X4_50); only for ``aruco``.
    ``export_rate``: samples per reference-stream frame of ``trajectories.trc`` / ``.c3d``
    (``mocap_export``; default the fastest stream's rate).
    ``fps``: the streams' frame rates, one for all or per stream id (``core.sync``), replacing
    the capture's own: the rates of the frame numbers in the image names (a video's, also when
    every k-th frame is kept; ``mocap_export.warn_stepped_frames``); times in seconds, offsets
    in ms, the TRC / C3D in Hz.
    ``plots``: ``plots/``; the overlays need the image files, which are checked before the
    solve (``viz.readable_images``: one warning names the images without a readable file;
    keypoints and a calibration without image files are normal input).
    ``out`` is checked first (``io.check_output``: never an input, an existing folder only
    replaced with ``overwrite`` and when dloe-sfm wrote it, writable) and written atomically:
    on any error nothing is left at ``out``. Returns ``out``.
    """
    out = Path(out)
    if aruco_dict is not None and fmt.lower() != "aruco":
        raise InputError(f"--aruco-dict is only for --format aruco, not {fmt!r}")
    options = load_options(config, overrides, base=options)
    timings: dict[str, float] = {}

    tic = time.perf_counter()
    ws = load_workspace(workspace)
    timings["load_workspace"] = time.perf_counter() - tic
    check_output(out, overwrite=overwrite, protected=[
        ws.model_dir, ws.image_dir, keypoints, config,
        layout if isinstance(layout, (str, Path)) else None,
    ])

    tic = time.perf_counter()
    kp = read_keypoints(fmt, keypoints, workspace=ws,
                        **({} if layout is None else {"layout": load_layout(layout)}),
                        **({} if aruco_dict is None else {"dictionary": aruco_dict}))
    timings["read_keypoints"] = time.perf_counter() - tic

    tic = time.perf_counter()
    capture, skipped, unobserved = build_capture(ws, kp, stream_pattern=stream_pattern,
                                                 min_score=min_score, person=person)
    timings["build_capture"] = time.perf_counter() - tic
    check_fps(fps, capture.stream_ids)
    capture = with_fps(capture, fps)
    overlays = None
    if plots:  # before the solve: missing or empty image files only lose the overlays
        from ..viz import readable_images  # matplotlib / cv2 only when plotting

        overlays = readable_images(ws, capture.image_names.tolist())

    tic = time.perf_counter()
    check_solve_memory(capture, options, workspace)
    with progress.solver_bar() as on_sweep:
        result = reconstruct(capture, options, progress=on_sweep)
    timings["solve"] = time.perf_counter() - tic
    logger.info("DLOE: %s (%d iterations, %.2f s, %d event(s))", result.message, result.nit,
                result.seconds, np.unique(result.events).size)
    flagged = result.image_status != "ok"
    if flagged.any():
        logger.warning("%d image(s) flagged (%d inconsistent: their points NaN in the exports): "
                       "see report.json image_checks", int(flagged.sum()),
                       int((result.image_status == "inconsistent").sum()))

    report = {
        "dloe_sfm_version": __version__,
        "inputs": {
            "workspace": str(Path(workspace).resolve()),
            "model": str(ws.model_dir),
            "keypoints": None if keypoints is None else str(Path(keypoints).resolve()),
            "format": fmt,
            "stream_pattern": stream_pattern,
            "min_score": min_score,
            "person": person,
            "unregistered_images": list(ws.unregistered),
            "skipped_images": list(skipped),
            "unobserved_points": [kp.layout.point_names[j] for j in unobserved],
            "fps": capture_fps(capture),
        },
        "parameters": options.to_dict(),
        "timings": timings,
    }
    layout = observed_layout(kp.layout, unobserved)
    from ..export import export_outputs  # open3d is slow to import: only when writing

    export_outputs(out, capture, result, workspace=ws, layout=layout, report=report,
                   overwrite=overwrite, plots=plots, export_rate=export_rate,
                   overlay_images=overlays)
    return out


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("workspace", type=Path,
                        help="COLMAP workspace (images/ and sparse/0 or sparse/)")
    parser.add_argument("--keypoints", type=Path,
                        help="keypoint file or folder (per the format); aruco: default images/")
    parser.add_argument("--format", dest="fmt", required=True, choices=list(FORMATS),
                        help="keypoint format")
    parser.add_argument("--out", type=Path, required=True,
                        help="output folder (must not exist, see --overwrite); never inside the "
                             "workspace's images or model")
    parser.add_argument("--stream-pattern", metavar="REGEX",
                        help="regex with named groups (?P<stream>...) and (?P<frame>...) "
                             "searched in image names; default: one stream per COLMAP camera")
    parser.add_argument("--min-score", type=float, default=0.0,
                        help="ignore detections with a lower score (default 0)")
    parser.add_argument("--person", type=_person, default="auto", metavar="{largest,all,auto,N}",
                        help="detections per image: 'largest' (bounding box) or index N (one "
                             "person), 'all' (every detection with >= 1/4 of the points, "
                             "several subjects), 'auto' (default: 'all' when >= 10%% of the "
                             "images have several such detections, else 'largest')")
    parser.add_argument("--layout", metavar="NAME|FILE.json",
                        help="keypoint layout: a known name (BODY_25, BODY_25B, COCO_18, "
                             "COCO_17, HALPE_26, COCO_WHOLEBODY, MEDIAPIPE_33) or a JSON file "
                             "with point_names, edges, symmetric_pairs "
                             "(default: the format's own)")
    parser.add_argument("--aruco-dict", metavar="NAME",
                        help="--format aruco: the cv2.aruco predefined dictionary of the markers "
                             "(default DICT_4X4_50; e.g. DICT_5X5_100, DICT_APRILTAG_36H11)")
    parser.add_argument("--config", type=Path, help="TOML file of solver options")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override one solver option (repeatable)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing output folder written by dloe-sfm (it holds "
                             "a .dloe_sfm file); any other folder is refused")
    parser.add_argument("--no-plots", dest="plots", action="store_false", help="skip plots/")
    parser.add_argument("--export-rate", type=_positive_rate, metavar="RATE",
                        help="samples per reference-stream frame of trajectories.trc / .c3d "
                             "(default: the fastest stream's rate); with --fps the files' rate "
                             "is RATE x fps, in Hz")
    add_fps_option(parser, solves=True)
    parser.add_argument("--progress", action="store_true",
                        help="show progress bars (default: only on a terminal)")


def run(args: argparse.Namespace) -> int:
    out = main(args.workspace, args.keypoints, args.fmt, args.out,
               stream_pattern=args.stream_pattern, min_score=args.min_score, person=args.person,
               layout=args.layout, aruco_dict=args.aruco_dict, config=args.config,
               overrides=args.overrides,
               options=Options(),
               overwrite=args.overwrite, plots=args.plots, export_rate=args.export_rate,
               fps=parse_fps(args.fps))
    print(f"reconstruction written to {out}")
    return 0


if __name__ == "__main__":
    from ..cli import run_stage

    sys.exit(run_stage(__name__))
