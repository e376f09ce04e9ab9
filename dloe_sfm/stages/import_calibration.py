"""Write a COLMAP model of a calibration made elsewhere (Qualisys, anipose, Pose2Sim, OpenCV)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from ..calibration import FORMATS, import_calibration
from ..io import check_output
from ..keypoints import FORMATS as KEYPOINT_FORMATS


def main(
    calib: Path | Sequence[Path],
    fmt: str,
    out: Path,
    *,
    images_dir: Path | None = None,
    keypoints: Path | None = None,
    keypoint_format: str = "openpose",
    overwrite: bool = False,
) -> Path:
    """Calibration file(s) ``calib`` in ``fmt`` -> COLMAP model folder ``out`` (cameras, images,
    points3D .bin), which ``reconstruct`` reads as a workspace (or as ``WS/sparse/0`` beside
    ``WS/images``). Images: those below ``images_dir`` whose first folder or file name starts
    with a camera's name, else one per file of ``keypoints`` (in ``keypoint_format``) named
    after its camera in the same way (``cam01_json/cam01.0012.json`` -> image
    ``cam01_json/cam01.0012.jpg``; no image files needed), else one ``<camera>.jpg`` per
    camera. ``out`` must not exist unless ``overwrite``; it is written atomically. Returns
    ``out``."""
    sources = [calib] if isinstance(calib, (str, Path)) else list(calib)
    out = check_output(out, protected=[*sources, images_dir, keypoints], overwrite=overwrite)
    return import_calibration(calib, out, fmt=fmt, image_dir=images_dir, keypoints=keypoints,
                              keypoint_format=keypoint_format, overwrite=overwrite)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("calib", type=Path, nargs="+", metavar="CALIB",
                        help="calibration file (opencv: one file per camera, EasyMocap's "
                             "intri.yml [extri.yml], or a folder holding both)")
    parser.add_argument("--format", dest="fmt", required=True, choices=FORMATS,
                        help="qualisys (.qca.txt), anipose or pose2sim (.toml), opencv "
                             "(cv2.FileStorage .yml / .xml / .json, EasyMocap)")
    parser.add_argument("--out", type=Path, required=True,
                        help="COLMAP model folder to write (must not exist)")
    parser.add_argument("--images-dir", type=Path,
                        help="images, in one folder per camera or named after their camera "
                             "(default: one image <camera>.jpg per camera)")
    parser.add_argument("--keypoints", type=Path,
                        help="instead of image files: one image per keypoint file, in one "
                             "folder per camera or named after their camera (Pose2Sim's "
                             "pose/ with camXX_json/camXX.NNNN.json); reconstruct then reads "
                             "the same keypoints, no image file needed")
    parser.add_argument("--keypoint-format", default="openpose",
                        choices=[f for f in KEYPOINT_FORMATS if f != "aruco"],
                        help="format of --keypoints (default openpose)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing output folder")


def run(args: argparse.Namespace) -> int:
    calib = args.calib[0] if len(args.calib) == 1 else args.calib
    out = main(calib, args.fmt, args.out, images_dir=args.images_dir, keypoints=args.keypoints,
               keypoint_format=args.keypoint_format, overwrite=args.overwrite)
    print(f"COLMAP model written to {out}")
    return 0


if __name__ == "__main__":
    import sys

    from ..cli import run_stage

    sys.exit(run_stage(__name__))
