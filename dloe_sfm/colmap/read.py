"""Read a COLMAP workspace: find its model, check it (binary layout, cameras, poses), ``Workspace``.

Pixel convention here is COLMAP's: the centre of the top-left pixel is (0.5, 0.5). Keypoint
adapters use (0, 0) and add 0.5 before calling anything in this module.
"""

from __future__ import annotations

import functools
import logging
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..core.capture import ROTATION_TOLERANCE, nearest_rotation, rotation_deviation
from ..errors import InputError
from ..images import list_images, natural_key
from .common import quiet_colmap

logger = logging.getLogger("dloe_sfm")

MODEL_FILES = ("cameras", "images", "points3D")
# cam_from_img is iterative for distorted models; beyond the valid domain it returns a wrong
# point without complaint, so every result is checked by projecting it back (pixels).
UNDISTORT_TOLERANCE = 1e-2


def has_model(folder: Path) -> bool:
    """True when ``folder`` holds cameras, images and points3D as .bin or .txt."""
    return any(
        all((folder / f"{n}{ext}").is_file() for n in MODEL_FILES) for ext in (".bin", ".txt")
    )


class _BinaryFile:
    """Walks a COLMAP .bin file: every count is checked against the bytes that are left, so a
    truncated or corrupt file is refused before pycolmap allocates what it claims."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def _corrupt(self, what: str) -> InputError:
        return InputError(f"{self.path.parent}: cannot read the COLMAP model ({self.path.name} "
                          f"is truncated or corrupt: {what} at byte {self.pos} of "
                          f"{len(self.data)})")

    def take(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise self._corrupt("ends early")
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def count(self, fmt: str, min_size: int) -> int:
        """A count (struct ``fmt``) of entries of at least ``min_size`` bytes each."""
        (n,) = self.take(fmt)
        if n * min_size > len(self.data) - self.pos:
            raise self._corrupt(f"{n} entries declared")
        return n

    def skip(self, size: int) -> None:
        if self.pos + size > len(self.data):
            raise self._corrupt("ends early")
        self.pos += size

    def string(self) -> None:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise self._corrupt("unterminated name")
        self.pos = end + 1

    def finish(self) -> None:
        if self.pos != len(self.data):
            raise self._corrupt(f"{len(self.data) - self.pos} unexpected bytes")


@functools.cache
def _camera_num_params() -> dict[int, int]:
    """Number of parameters of every COLMAP camera model, by model id."""
    return {
        int(v): pycolmap.Camera.create_from_model_name(0, name, 1.0, 1, 1).params.size
        for name, v in pycolmap.CameraModelId.__members__.items() if name != "INVALID"
    }


def _check_binary_model(model_dir: Path) -> None:
    """Walk the structure of a binary model (reconstruction_io_binary.cc's layout)."""
    num_params = _camera_num_params()
    f = _BinaryFile(model_dir / "cameras.bin")
    for _ in range(f.count("Q", 24)):
        _, model_id, _, _ = f.take("iiQQ")
        if model_id not in num_params:
            raise f._corrupt(f"unknown camera model id {model_id}")
        f.skip(8 * num_params[model_id])
    f.finish()
    if (model_dir / "rigs.bin").is_file():
        f = _BinaryFile(model_dir / "rigs.bin")
        for _ in range(f.count("Q", 8)):
            f.take("I")
            sensors = f.count("I", 8)
            if sensors:
                f.skip(8)
            for _ in range(max(sensors - 1, 0)):
                _, _, has_pose = f.take("iIB")
                f.skip(56 if has_pose else 0)
        f.finish()
    if (model_dir / "frames.bin").is_file():
        f = _BinaryFile(model_dir / "frames.bin")
        for _ in range(f.count("Q", 68)):
            f.skip(64)
            f.skip(16 * f.count("I", 16))
        f.finish()
    f = _BinaryFile(model_dir / "images.bin")
    for _ in range(f.count("Q", 73)):
        f.skip(64)
        f.string()
        f.skip(24 * f.count("Q", 24))
    f.finish()
    f = _BinaryFile(model_dir / "points3D.bin")
    for _ in range(f.count("Q", 51)):
        f.skip(43)
        f.skip(8 * f.count("Q", 8))
    f.finish()


def _read_reconstruction(model_dir: Path) -> pycolmap.Reconstruction:
    quiet_colmap()
    try:
        if all((model_dir / f"{n}.bin").is_file() for n in MODEL_FILES):
            _check_binary_model(model_dir)
        rec = pycolmap.Reconstruction(str(model_dir))
        for image in rec.images.values():
            image.name.encode()  # names that are not UTF-8 fail here (UnicodeDecodeError)
        return rec
    except UnicodeDecodeError as e:
        raise InputError(f"{model_dir}: an image name in the COLMAP model is not UTF-8 ({e.reason} "
                         f"at byte {e.start})") from None
    except InputError:  # a ValueError: _check_binary_model's message stands
        raise
    except OSError as e:
        raise InputError(f"{model_dir}: cannot read the COLMAP model ({e.strerror or e})") from None
    except (ValueError, RuntimeError, IndexError, KeyError, OverflowError, MemoryError) as e:
        lines = str(e).strip().splitlines()
        detail = " ".join(lines[-1].split())[:200] if lines else type(e).__name__
        raise InputError(f"{model_dir}: cannot read the COLMAP model ({detail})") from None


def _check_camera(camera: pycolmap.Camera, model_dir: Path) -> None:
    """A camera the rays can come from: finite parameters, positive focal length(s)."""
    params = np.asarray(camera.params, dtype=np.float64)
    focal = params[list(camera.focal_length_idxs())]
    where = f"{model_dir}: camera {camera.camera_id} ({camera.model_name})"
    if not np.isfinite(params).all():
        raise InputError(f"{where} has parameters that are not finite: {params.tolist()}")
    if (focal <= 0).any():
        raise InputError(f"{where} has focal length {focal.tolist()}; it must be positive")
    if camera.width <= 0 or camera.height <= 0:
        raise InputError(f"{where} has size {camera.width} x {camera.height} pixels")


def _checked_poses(
    rec: pycolmap.Reconstruction, names: Sequence[str], model_dir: Path
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(R, t) world-to-camera of every registered image, R projected to SO(3) (SVD) when within
    ``ROTATION_TOLERANCE`` of it, else an InputError naming the image (COLMAP normalises
    quaternions only in models with frames)."""
    images = {im.name: im for im in rec.images.values() if im.has_pose}
    poses, worst, worst_name = {}, 0.0, ""
    for name in names:
        pose = images[name].cam_from_world()
        R = np.array(pose.rotation.matrix(), dtype=np.float64)
        t = np.array(pose.translation, dtype=np.float64)
        if not (np.isfinite(R).all() and np.isfinite(t).all()):
            raise InputError(f"{model_dir}: image {name!r} has a pose that is not finite")
        deviation = float(rotation_deviation(R))
        if deviation > ROTATION_TOLERANCE:
            raise InputError(
                f"{model_dir}: image {name!r} has a rotation {deviation:.2g} from orthonormal "
                f"(tolerance {ROTATION_TOLERANCE:g}; a quaternion that is not unit?)"
            )
        if deviation > worst:
            worst, worst_name = deviation, name
        poses[name] = (nearest_rotation(R), t)
    if worst > 1e-12:
        logger.info("%s: rotations projected to SO(3), largest deviation %.2g (image %r)",
                    model_dir, worst, worst_name)
    return poses


@dataclass
class Workspace:
    """A COLMAP workspace, read-only: registered images, their cameras and poses, static points.

    Attributes
    ----------
    root : Path
        The workspace folder.
    model_dir : Path
        The folder of the model that was read.
    image_dir : Path or None
        ``root/images`` when it exists.
    image_names : list of str
        Registered images (with a pose), in natural name order.
    unregistered : list of str
        Images in the model without a pose, and files in ``image_dir`` not in the model.
    static_xyz : (M, 3) float64
        The model's 3D points.
    static_rgb : (M, 3) uint8
        Their colours.
    reconstruction : pycolmap.Reconstruction
    """

    root: Path
    model_dir: Path
    image_dir: Path | None
    image_names: list[str]
    unregistered: list[str]
    static_xyz: np.ndarray
    static_rgb: np.ndarray
    reconstruction: pycolmap.Reconstruction = field(repr=False)
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = field(repr=False)
    """(R, t) world-to-camera of every registered image, R exactly a rotation."""
    _image_ids: dict[str, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._image_ids = {
            im.name: im_id for im_id, im in self.reconstruction.images.items() if im.has_pose
        }

    def _image(self, name: str) -> pycolmap.Image:
        image_id = self._image_ids.get(name)
        if image_id is None:
            raise InputError(f"{self.model_dir}: no registered image '{name}' in the model")
        return self.reconstruction.images[image_id]

    def _camera(self, name: str) -> pycolmap.Camera:
        return self.reconstruction.cameras[self._image(name).camera_id]

    def camera_id(self, name: str) -> int:
        """COLMAP camera id of an image (images of one video share it)."""
        return int(self._image(name).camera_id)

    def rig_id(self, name: str) -> int:
        """COLMAP rig id of an image (a rig is a set of cameras mounted together)."""
        return int(self._image(name).frame.rig_id)

    def frame_id(self, name: str) -> int:
        """COLMAP frame id of an image: images sharing one were taken at the same instant."""
        return int(self._image(name).frame_id)

    def frame_size(self, name: str) -> int:
        """Number of images in the COLMAP frame of an image (1 without a multi-camera rig)."""
        frame = self.reconstruction.frames[self._image(name).frame_id]
        return len(frame.data_ids)

    def image_size(self, name: str) -> tuple[int, int]:
        """(width, height) of an image's camera in pixels."""
        cam = self._camera(name)
        return int(cam.width), int(cam.height)

    def rotation(self, name: str) -> np.ndarray:
        """(3, 3) world-to-camera rotation."""
        self._image(name)
        return self.poses[name][0].copy()

    def centre(self, name: str) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        self._image(name)
        R, t = self.poses[name]
        return -R.T @ t

    def pinhole(self, name: str) -> np.ndarray:
        """(3, 3) K of the ideal undistorted pinhole with the camera's focal length(s) and
        principal point (COLMAP pixel convention)."""
        cam = self._camera(name)
        return np.array([
            [cam.focal_length_x, 0.0, cam.principal_point_x],
            [0.0, cam.focal_length_y, cam.principal_point_y],
            [0.0, 0.0, 1.0],
        ])

    def normalised(self, name: str, pixels: np.ndarray) -> np.ndarray:
        """Undistorted normalised camera coordinates of pixels.

        pixels (P, 2) float in COLMAP's convention, NaN allowed -> (P, 2) float, NaN where the
        input is NaN or outside the domain where the camera's distortion can be inverted.
        """
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        out = np.full_like(pixels, np.nan)
        ok = np.isfinite(pixels).all(axis=1)
        if not ok.any():
            return out
        cam = self._camera(name)
        uv = np.asarray(cam.cam_from_img(np.ascontiguousarray(pixels[ok])), dtype=np.float64)
        back = cam.img_from_cam(
            np.concatenate([uv, np.ones((len(uv), 1))], axis=1), check_cheirality=False
        )
        good = np.linalg.norm(np.asarray(back) - pixels[ok], axis=1) <= UNDISTORT_TOLERANCE
        if not good.all():
            logger.warning(
                "%s: %d pixel(s) outside the invertible range of camera %d (%s) set missing",
                name, int((~good).sum()), cam.camera_id, cam.model_name,
            )
        uv[~good] = np.nan
        out[ok] = uv
        return out

    def rays(self, name: str, pixels: np.ndarray) -> np.ndarray:
        """Unit world rays of pixels: (P, 2) COLMAP pixel convention -> (P, 3), NaN = invalid."""
        uv = self.normalised(name, pixels)
        cam = np.concatenate([uv, np.ones((len(uv), 1))], axis=1)
        world = cam @ self.rotation(name)  # R^T cam, row-wise
        return world / np.linalg.norm(world, axis=1, keepdims=True)

    def project(self, name: str, X: np.ndarray) -> np.ndarray:
        """Project world points with distortion: X (P, 3) -> (P, 2) COLMAP pixel coordinates,
        NaN behind the camera."""
        X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
        self._image(name)
        R, t = self.poses[name]
        cam = X @ R.T + t
        return np.asarray(self._camera(name).img_from_cam(np.ascontiguousarray(cam)),
                          dtype=np.float64)


def _numbered_models(sparse: Path) -> list[Path]:
    if not sparse.is_dir():
        return []
    dirs = [d for d in sparse.iterdir() if d.is_dir() and d.name.isdigit() and has_model(d)]
    return sorted(dirs, key=lambda d: int(d.name))


def find_model(path: Path) -> Path:
    """The model folder of a workspace: ``WS``, ``WS/sparse/<k>``, ``WS/sparse`` or
    ``WS/dense/0/sparse``, first found; among several ``sparse/<k>`` the one with most
    registered images."""
    if not path.is_dir():
        raise InputError(f"{path}: no such workspace folder")
    if has_model(path):
        return path
    numbered = _numbered_models(path / "sparse")
    if len(numbered) > 1:
        counts = [_read_reconstruction(d).num_reg_images() for d in numbered]
        best = numbered[int(np.argmax(counts))]
        logger.info(
            "%s: %d models (%s registered images); using %s",
            path / "sparse", len(numbered), ", ".join(map(str, counts)), best.name,
        )
        return best
    if numbered:
        return numbered[0]
    for candidate in (path / "sparse", path / "dense" / "0" / "sparse"):
        if has_model(candidate):
            return candidate
    raise InputError(
        f"{path}: no COLMAP model (cameras, images, points3D as .bin or .txt) in it, "
        "in sparse/<k>, sparse/ or dense/0/sparse"
    )


def _find_image_dir(root: Path, model_dir: Path) -> Path | None:
    candidates = [root / "images"]
    if model_dir.name == "sparse":
        candidates.append(model_dir.parent / "images")
    if model_dir.parent.name == "sparse":
        candidates.append(model_dir.parent.parent / "images")
    return next((d for d in candidates if d.is_dir()), None)


def load_workspace(path: Path | str, *, image_dir: Path | str | None = None) -> Workspace:
    """Read a COLMAP workspace (or a model folder) without modifying it.

    Images in the model without a pose and image files the model does not know are logged
    as unregistered and left out.
    """
    root = Path(path)
    model_dir = find_model(root)
    rec = _read_reconstruction(model_dir)
    registered = sorted((im.name for im in rec.images.values() if im.has_pose), key=natural_key)
    if not registered:
        raise InputError(f"{model_dir}: the COLMAP model has no registered images")
    for camera_id in sorted({im.camera_id for im in rec.images.values() if im.has_pose}):
        _check_camera(rec.cameras[camera_id], model_dir)
    poses = _checked_poses(rec, registered, model_dir)
    unposed = [im.name for im in rec.images.values() if not im.has_pose]
    img_dir = Path(image_dir) if image_dir is not None else _find_image_dir(root, model_dir)
    if img_dir is not None and not img_dir.is_dir():
        raise InputError(f"{img_dir}: no such image folder")
    known = {im.name for im in rec.images.values()}
    unknown = [n for n in list_images(img_dir) if n not in known] if img_dir else []
    unregistered = sorted(unposed + unknown, key=natural_key)
    if unregistered:
        logger.info(
            "%s: %d image(s) unregistered, skipped: %s", model_dir, len(unregistered),
            _some(unregistered),
        )
    points = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.uint8).reshape(-1, 3)
    logger.info(
        "%s: %d registered images, %d cameras, %d static points",
        model_dir, len(registered), rec.num_cameras(), len(points),
    )
    return Workspace(
        root=root, model_dir=model_dir, image_dir=img_dir, image_names=registered,
        unregistered=unregistered, static_xyz=xyz, static_rgb=rgb, reconstruction=rec,
        poses=poses,
    )


def _some(names: Sequence[str], limit: int = 5) -> str:
    shown = ", ".join(f"'{n}'" for n in names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")
