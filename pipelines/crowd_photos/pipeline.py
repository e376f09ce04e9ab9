"""Crowd photos: pictures -> COLMAP SfM -> keypoints -> DLOE -> point clouds, trajectories, report.

Any folder of images (loose photos, or one sub-folder per video) with one keypoint file per image
(OpenPose, COCO, MMPose, CSV) or visible ArUco markers:

    python pipelines/crowd_photos/pipeline.py --images path/to/images \\
        --keypoints path/to/openpose_json --format openpose --out outputs/crowd

writes ``OUT/workspace`` (the COLMAP workspace: database.db, sparse/<k>, images -> a link to
the pictures) and ``OUT/reconstruction`` (docs/interfaces.md, "Reconstruct outputs", plots
included). The SfM step is skipped when ``OUT/workspace`` already holds a model
(``--redo-sfm`` recomputes it); an existing reconstruction is only replaced with ``--overwrite``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import dloe_sfm.stages.reconstruct as stage
from dloe_sfm.colmap import SFM_CAMERA_MODES, find_model, run_sfm
from dloe_sfm.errors import InputError
from dloe_sfm.keypoints import FORMATS

logger = logging.getLogger("dloe_sfm")


def run(images: Path, keypoints: Path | None, fmt: str, out: Path, *,
        camera_mode: str | None = None, camera_model: str = "SIMPLE_RADIAL",
        mapper: str = "global", stream_pattern: str | None = None, min_score: float = 0.0,
        person: str | int = "largest", overrides: list[str] | None = None,
        redo_sfm: bool = False, overwrite: bool = False, plots: bool = True) -> Path:
    """SfM (unless already done) then the ``reconstruct`` stage; returns the reconstruction."""
    out = Path(out)
    workspace, reconstruction = out / "workspace", out / "reconstruction"
    if reconstruction.exists() and not overwrite:
        raise InputError(f"{reconstruction}: exists (use --overwrite to replace it)")
    if redo_sfm or not workspace.exists():
        tic = time.perf_counter()
        run_sfm(images, workspace, camera_mode=camera_mode, camera_model=camera_model,
                mapper=mapper, overwrite=redo_sfm)
        logger.info("SfM done in %.1f s: %s", time.perf_counter() - tic, workspace)
    else:
        logger.info("using the existing workspace %s (model %s; --redo-sfm to recompute)",
                    workspace, find_model(workspace))
    return stage.main(workspace, keypoints, fmt, reconstruction, stream_pattern=stream_pattern,
                      min_score=min_score, person=person, overrides=overrides,
                      overwrite=overwrite, plots=plots)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=Path, required=True, help="folder of images")
    parser.add_argument("--keypoints", type=Path,
                        help="keypoint file or folder (aruco: default, the images)")
    parser.add_argument("--format", dest="fmt", required=True, choices=list(FORMATS))
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--camera-mode", choices=SFM_CAMERA_MODES,
                        help="COLMAP cameras: per_folder (videos in sub-folders; default then), "
                             "per_image (loose photos; default otherwise) or single")
    parser.add_argument("--camera-model", default="SIMPLE_RADIAL", help="COLMAP camera model")
    parser.add_argument("--mapper", choices=("global", "incremental"), default="global")
    parser.add_argument("--stream-pattern", metavar="REGEX",
                        help="named groups (?P<stream>..) (?P<frame>..) on image names")
    parser.add_argument("--min-score", type=float, default=0.0)
    parser.add_argument("--person", default="largest", help="'largest' or a detection index")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="override one solver option (repeatable)")
    parser.add_argument("--redo-sfm", action="store_true", help="recompute the COLMAP model")
    parser.add_argument("--overwrite", action="store_true", help="replace the reconstruction")
    parser.add_argument("--no-plots", dest="plots", action="store_false")
    args = parser.parse_args(argv)
    person = int(args.person) if args.person.isdigit() else args.person
    try:
        out = run(args.images, args.keypoints, args.fmt, args.out, camera_mode=args.camera_mode,
                  camera_model=args.camera_model, mapper=args.mapper,
                  stream_pattern=args.stream_pattern, min_score=args.min_score, person=person,
                  overrides=args.overrides, redo_sfm=args.redo_sfm, overwrite=args.overwrite,
                  plots=args.plots)
    except InputError as e:
        parser.exit(2, f"{parser.prog}: error: {e}\n")
    print(f"reconstruction written to {out}")
    return 0


if __name__ == "__main__":
    from dloe_sfm.cli import setup_logging

    setup_logging()
    sys.exit(main())
