"""Calibrations made outside COLMAP (Qualisys ``.qca.txt``, anipose / OpenCV ``.toml``) as a
COLMAP model, so rigs of calibrated video cameras can feed ``build_capture`` like any workspace.

Intrinsics of both formats are in OpenCV's pixel convention ((0, 0) = centre of the top-left
pixel); COLMAP's principal point is half a pixel larger.
"""

from __future__ import annotations

import logging
import sys
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from .colmap import CameraSpec, ImageSpec, write_model
from .errors import InputError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

logger = logging.getLogger("dloe_sfm")


@dataclass(kw_only=True)
class CameraCalibration:
    """One calibrated camera.

    K (3, 3) in OpenCV's pixel convention; dist (k,) OpenCV order k1, k2, p1, p2[, k3[, k4, k5,
    k6]], or k1..k4 when ``fisheye``; R (3, 3) world-to-camera; t (3,) so that
    ``x_cam = R X + t``.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    fisheye: bool = False

    @property
    def centre(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return -self.R.T @ self.t

    def colmap_camera(self) -> CameraSpec:
        """The COLMAP camera: OPENCV, FULL_OPENCV when k3..k6 are used, or OPENCV_FISHEYE."""
        K, dist = self.K, np.asarray(self.dist, dtype=np.float64)
        if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]):
            raise InputError(f"camera '{self.name}': skew {K[0, 1]} has no COLMAP camera model")
        pinhole = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]
        if self.fisheye:
            if dist.size > 4:
                raise InputError(f"camera '{self.name}': fisheye needs <= 4 distortions")
            model, extra = "OPENCV_FISHEYE", np.pad(dist, (0, 4 - dist.size))
        elif dist.size > 8:
            raise InputError(f"camera '{self.name}': {dist.size} distortions, at most 8 known")
        elif dist.size > 4 and np.any(dist[4:] != 0):
            model, extra = "FULL_OPENCV", np.pad(dist, (0, 8 - dist.size))
        else:
            model, extra = "OPENCV", np.pad(dist[:4], (0, 4 - min(dist.size, 4)))
        return CameraSpec(model=model, width=self.width, height=self.height,
                          params=np.concatenate([pinhole, extra]))


def _floats(element: ET.Element, keys: Sequence[str], path: Path, what: str) -> list[float]:
    try:
        values = [float(element.attrib[k]) for k in keys]
    except KeyError as e:
        raise InputError(f"{path}: {what} lacks attribute {e.args[0]}") from None
    except ValueError as e:
        raise InputError(f"{path}: {what} has a non-numeric attribute ({e})") from None
    if not np.isfinite(values).all():
        raise InputError(f"{path}: {what} has NaN or infinite values")
    return values


def read_qualisys(path: Path | str) -> list[CameraCalibration]:
    """Cameras of a Qualisys ``.qca.txt`` calibration (positions in mm -> metres).

    f = focalLength / 64, c = centerPoint / 64 - fov_video offset; world-to-camera
    R = diag(1, -1, -1) Rq^T with Rq = [[r11, r21, r31], [r12, r22, r32], [r13, r23, r33]],
    t = -R T / 1000.
    """
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise InputError(f"{path}: malformed XML ({e})") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e})") from None
    cameras = []
    for i, cam in enumerate(root.iter("camera")):
        name = cam.attrib.get("serial", f"camera{i}")
        what = f"camera '{name}'"
        if cam.attrib.get("active", "1") == "0":
            logger.info("%s: %s is inactive, skipped", path, what)
            continue
        if cam.attrib.get("viewrotation", "0") not in ("0", ""):
            raise InputError(f"{path}: {what} has viewrotation {cam.attrib['viewrotation']}, "
                             "only 0 is supported")
        fov, intr, tr = cam.find("fov_video"), cam.find("intrinsic"), cam.find("transform")
        if fov is None or intr is None or tr is None:
            raise InputError(f"{path}: {what} lacks fov_video, intrinsic or transform")
        left, top, right, bottom = _floats(fov, ("left", "top", "right", "bottom"), path, what)
        fu, fv, cu, cv = (v / 64 for v in _floats(
            intr, ("focalLengthU", "focalLengthV", "centerPointU", "centerPointV"), path, what))
        k1, k2, k3, p1, p2 = _floats(intr, (
            "radialDistortion1", "radialDistortion2", "radialDistortion3",
            "tangentalDistortion1", "tangentalDistortion2"), path, what)
        r = _floats(tr, [f"r{a}{b}" for a in "123" for b in "123"], path, what)
        T = np.array(_floats(tr, ("x", "y", "z"), path, what)) / 1000.0
        Rq = np.array(r).reshape(3, 3).T
        R = np.diag([1.0, -1.0, -1.0]) @ Rq.T
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6:
            raise InputError(f"{path}: {what} transform r11..r33 is not a rotation")
        R = Rotation.from_matrix(R).as_matrix()  # re-orthonormalise the printed digits
        cameras.append(CameraCalibration(
            name=name, width=int(right - left + 1), height=int(bottom - top + 1),
            K=np.array([[fu, 0.0, cu - left], [0.0, fv, cv - top], [0.0, 0.0, 1.0]]),
            dist=np.array([k1, k2, p1, p2, k3]), R=R, t=-R @ T,
        ))
    if not cameras:
        raise InputError(f"{path}: no active camera in the calibration")
    return cameras


def _array(section: Mapping, key: str, shape: tuple[int, ...], path: Path, name: str
           ) -> np.ndarray:
    try:
        arr = np.asarray(section[key], dtype=np.float64)
    except KeyError:
        raise InputError(f"{path}: camera '{name}' lacks '{key}'") from None
    except (TypeError, ValueError):
        raise InputError(f"{path}: camera '{name}' field '{key}' is not numeric") from None
    if shape and arr.shape != shape:
        raise InputError(f"{path}: camera '{name}' field '{key}' has shape {arr.shape}, "
                         f"expected {shape}")
    if not np.isfinite(arr).all():
        raise InputError(f"{path}: camera '{name}' field '{key}' has NaN or infinite values")
    return arr


def read_anipose_toml(path: Path | str) -> list[CameraCalibration]:
    """Cameras of an anipose / aniposelib ``calibration.toml``: one table per camera with
    ``name``, ``size`` [w, h], ``matrix``, ``distortions``, ``rotation`` (Rodrigues,
    world-to-camera), ``translation`` (the file's units) and optional ``fisheye``."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: malformed TOML ({e})") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e})") from None
    cameras = []
    for key, section in data.items():
        if key == "metadata" or not isinstance(section, dict):
            continue
        name = str(section.get("name", key))
        size = _array(section, "size", (2,), path, name)
        dist = _array(section, "distortions", (), path, name).ravel()
        R = Rotation.from_rotvec(_array(section, "rotation", (3,), path, name)).as_matrix()
        cameras.append(CameraCalibration(
            name=name, width=int(size[0]), height=int(size[1]),
            K=_array(section, "matrix", (3, 3), path, name), dist=dist, R=R,
            t=_array(section, "translation", (3,), path, name),
            fisheye=bool(section.get("fisheye", False)),
        ))
    if not cameras:
        raise InputError(f"{path}: no camera table in the calibration")
    return cameras


def read_calibration(path: Path | str) -> list[CameraCalibration]:
    """Cameras of a ``.qca.txt`` / ``.qca`` / ``.xml`` (Qualisys) or ``.toml`` (anipose) file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such calibration file")
    name = path.name.lower()
    if name.endswith(".toml"):
        return read_anipose_toml(path)
    if name.endswith((".qca.txt", ".qca", ".xml")):
        return read_qualisys(path)
    raise InputError(f"{path}: unknown calibration format (expected .qca.txt or .toml)")


def import_calibration(
    calib_file: Path | str,
    out_model_dir: Path | str,
    image_names_per_camera: Mapping[str, Sequence[str]] | None = None,
    *,
    overwrite: bool = False,
) -> Path:
    """Write a COLMAP model of a calibration: one COLMAP camera per calibrated camera and its
    images (default: one image ``<camera name>.jpg``) all at that camera's pose. Returns the
    model folder."""
    cameras = read_calibration(calib_file)
    names = [c.name for c in cameras]
    if image_names_per_camera is None:
        image_names_per_camera = {c.name: [f"{c.name}.jpg"] for c in cameras}
    unknown = [k for k in image_names_per_camera if k not in names]
    if unknown:
        raise InputError(f"{calib_file}: no camera named {', '.join(map(repr, unknown))} "
                         f"(cameras: {', '.join(names)})")
    images = [
        ImageSpec(name=image, camera=i, R=cam.R, C=cam.centre)
        for i, cam in enumerate(cameras)
        for image in image_names_per_camera.get(cam.name, [])
    ]
    specs = [cam.colmap_camera() for cam in cameras]
    logger.info("%s: %d cameras (%s), %d images", calib_file, len(cameras),
                ", ".join(f"{c.name}: {s.model}" for c, s in zip(cameras, specs, strict=True)),
                len(images))
    return write_model(out_model_dir, specs, images, overwrite=overwrite)
