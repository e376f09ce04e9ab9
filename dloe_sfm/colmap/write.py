"""Write a COLMAP model of posed images (no 3D points) from plain values."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ..errors import InputError
from ..io import atomic_path
from .common import quiet_colmap

logger = logging.getLogger("dloe_sfm")


@dataclass(kw_only=True)
class CameraSpec:
    """A camera as plain values: COLMAP model name, size in pixels, params in COLMAP's order
    and pixel convention (e.g. OPENCV: fx, fy, cx, cy, k1, k2, p1, p2)."""

    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass(kw_only=True)
class ImageSpec:
    """A posed image as plain values: ``camera`` indexes the camera list; R (3, 3)
    world-to-camera, C (3,) centre."""

    name: str
    camera: int
    R: np.ndarray
    C: np.ndarray


def _make_camera(i: int, spec: CameraSpec) -> pycolmap.Camera:
    if spec.model not in pycolmap.CameraModelId.__members__ or spec.model == "INVALID":
        raise InputError(f"camera {i}: unknown COLMAP camera model '{spec.model}'")
    params = np.asarray(spec.params, dtype=np.float64)
    if not np.isfinite(params).all():
        raise InputError(f"camera {i}: params are not finite")
    cam = pycolmap.Camera(
        model=spec.model, width=int(spec.width), height=int(spec.height),
        params=params.tolist(), camera_id=i + 1,
    )
    if not cam.verify_params():
        raise InputError(
            f"camera {i}: model {spec.model} needs params ({cam.params_info}), got {params.size}"
        )
    return cam


def write_model(
    path: Path | str,
    cameras: Sequence[CameraSpec],
    images: Sequence[ImageSpec],
    *,
    text: bool = False,
    overwrite: bool = False,
) -> Path:
    """Write a COLMAP model (binary, or text) of posed images without 3D points; returns ``path``.

    Camera ``i`` gets COLMAP camera id ``i + 1`` (and a rig of its own); each image a frame of
    its own. A folder that is not empty is only replaced (whole) with ``overwrite=True``.
    """
    path = Path(path)
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise InputError(f"{path}: folder is not empty (pass overwrite=True to replace it)")
    quiet_colmap()
    rec = pycolmap.Reconstruction()
    for i, spec in enumerate(cameras):
        rec.add_camera_with_trivial_rig(_make_camera(i, spec))
    names = set()
    for j, im in enumerate(images):
        if im.name in names:
            raise InputError(f"image '{im.name}': name used twice")
        names.add(im.name)
        if not 0 <= im.camera < len(cameras):
            raise InputError(f"image '{im.name}': camera index {im.camera} out of range")
        R = np.asarray(im.R, dtype=np.float64)
        C = np.asarray(im.C, dtype=np.float64)
        if not (np.isfinite(R).all() and np.isfinite(C).all()):
            raise InputError(f"image '{im.name}': pose is not finite")
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or abs(np.linalg.det(R) - 1) > 1e-6:
            raise InputError(f"image '{im.name}': R is not a rotation matrix")
        cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ C)
        image = pycolmap.Image(name=im.name, camera_id=im.camera + 1, image_id=j + 1)
        rec.add_image_with_trivial_frame(image, cam_from_world)
    with atomic_path(path, mark=True) as tmp:
        tmp.mkdir()
        if text:
            rec.write_text(str(tmp))
        else:
            rec.write(str(tmp))
    logger.info("%s: wrote a COLMAP model, %d cameras, %d images", path, len(cameras), len(images))
    return path
