"""Calibrations made outside COLMAP (Qualisys ``.qca.txt``, anipose / Pose2Sim ``.toml``, OpenCV
YAML / XML, EasyMocap's ``intri.yml`` + ``extri.yml``) as a COLMAP model, so rigs of calibrated
video cameras can feed ``build_capture`` like any workspace.

Intrinsics of every format are in OpenCV's pixel convention ((0, 0) = centre of the top-left
pixel); COLMAP's principal point is half a pixel larger.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import sys
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from .colmap import CameraSpec, ImageSpec, write_model
from .errors import InputError
from .images import IMAGE_SUFFIXES, list_images, natural_key
from .keypoints import read_keypoints

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

logger = logging.getLogger("dloe_sfm")

FORMATS = ("qualisys", "anipose", "pose2sim", "opencv")


@dataclass(kw_only=True)
class CameraCalibration:
    """One calibrated camera.

    K (3, 3) in OpenCV's pixel convention; dist (k,) OpenCV order k1, k2, p1, p2[, k3[, k4, k5,
    k6]], or k1..k4 when ``fisheye``; R (3, 3) world-to-camera; t (3,) so that
    ``x_cam = R X + t``. ``width`` / ``height`` are None when the file does not say (EasyMocap
    may not): the images tell them.
    """

    name: str
    width: int | None
    height: int | None
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
        K, dist = np.asarray(self.K, dtype=np.float64), np.asarray(self.dist, dtype=np.float64)
        what = f"camera '{self.name}'"
        if self.width is None or self.height is None:
            raise InputError(f"{what}: image size unknown (not in the calibration, no image)")
        if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]):
            raise InputError(f"{what}: skew {K[0, 1]} has no COLMAP camera model")
        if K[1, 0] != 0 or np.any(K[2] != [0, 0, 1]) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(f"{what}: K is not [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], f > 0")
        pinhole = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]
        if self.fisheye:
            if dist.size > 4:
                raise InputError(f"{what}: fisheye needs <= 4 distortions, got {dist.size}")
            model, extra = "OPENCV_FISHEYE", np.pad(dist, (0, 4 - dist.size))
        elif np.any(dist[8:] != 0):
            # thin prism s1..s4 and sensor tilt: no COLMAP model has them
            raise InputError(f"{what}: distortions beyond k6 (thin prism, tilt) are not zero")
        elif np.any(dist[4:8] != 0):
            model, extra = "FULL_OPENCV", np.pad(dist[:8], (0, 8 - min(dist.size, 8)))
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
    t = -R T / 1000 (as Pose2Sim's ``read_qca`` + ``calib_qca_fun``). The distortions k1, k2,
    k3 (radialDistortion1..3), p1, p2 are taken as printed; Pose2Sim divides them by 64 as
    well and drops k3 (the bundled capture triangulates alike both ways, so it cannot tell).
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


def _checked(value: object, key: str, shapes: Sequence[tuple[int, ...]], path: Path,
             name: str) -> np.ndarray:
    """``value`` as a finite float array of one of ``shapes`` (none given: any shape)."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{path}: camera '{name}' field '{key}' is not numeric") from None
    if shapes and arr.shape not in shapes:
        raise InputError(f"{path}: camera '{name}' field '{key}' has shape {arr.shape}, "
                         f"expected {' or '.join(map(str, shapes))}")
    if not np.isfinite(arr).all():
        raise InputError(f"{path}: camera '{name}' field '{key}' has NaN or infinite values")
    return arr


ROTATION_SHAPES = ((3,), (3, 1), (1, 3), (3, 3))
VECTOR_SHAPES = ((3,), (3, 1), (1, 3))


def _rotation(arr: np.ndarray, key: str, path: Path, name: str) -> np.ndarray:
    """(3, 3) world-to-camera rotation from a Rodrigues vector or a rotation matrix."""
    if arr.shape != (3, 3):
        return Rotation.from_rotvec(arr.ravel()).as_matrix()
    if np.abs(arr @ arr.T - np.eye(3)).max() > 1e-6 or np.linalg.det(arr) < 0:
        raise InputError(f"{path}: camera '{name}' field '{key}' is not a rotation matrix")
    return Rotation.from_matrix(arr).as_matrix()


def _size(arr: np.ndarray, key: str, path: Path, name: str) -> int:
    if np.any(arr < 1) or np.any(arr != np.round(arr)):
        raise InputError(f"{path}: camera '{name}' field '{key}' {arr.ravel().tolist()} is not "
                         "a positive whole number of pixels")
    return int(arr)


# Pose2Sim's tables that are not cameras (``common.retrieve_calib_params``)
TOML_OTHER_TABLES = ("metadata", "capture_volume", "charuco", "checkerboard")


def _toml_camera(section: Mapping, name: str, path: Path) -> CameraCalibration:
    def field(key: str, shapes: Sequence[tuple[int, ...]]) -> np.ndarray:
        if key not in section:
            raise InputError(f"{path}: camera '{name}' lacks '{key}'")
        return _checked(section[key], key, shapes, path, name)

    width, height = field("size", [(2,)])
    fisheye = section.get("fisheye", False)
    if not isinstance(fisheye, bool):
        raise InputError(f"{path}: camera '{name}' field 'fisheye' is not true or false")
    return CameraCalibration(
        name=name, width=_size(width, "size", path, name),
        height=_size(height, "size", path, name), K=field("matrix", [(3, 3)]),
        dist=field("distortions", []).ravel(),
        R=_rotation(field("rotation", ROTATION_SHAPES), "rotation", path, name),
        t=field("translation", VECTOR_SHAPES).ravel(), fisheye=fisheye,
    )


def read_toml(path: Path | str) -> list[CameraCalibration]:
    """Cameras of an anipose / aniposelib ``calibration.toml`` or a Pose2Sim ``Calib_*.toml``
    (the same layout; Pose2Sim's ``toml_write`` gives 4 distortions and ``fisheye = false``):
    one table per camera with ``name`` (default: the table's key), ``size`` [w, h],
    ``matrix``, ``distortions``, ``rotation`` (Rodrigues, world-to-camera), ``translation``
    (the file's units; Pose2Sim: metres) and optional ``fisheye``; tables nested as
    ``[cameras.<key>]`` are read too."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: malformed TOML ({e})") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e})") from None
    tables = data["cameras"] if isinstance(data.get("cameras"), dict) else data
    cameras = [_toml_camera(section, str(section.get("name", key)), path)
               for key, section in tables.items()
               if key not in TOML_OTHER_TABLES and isinstance(section, dict)]
    if not cameras:
        raise InputError(f"{path}: no camera table in the calibration")
    return cameras


def _open_storage(path: Path) -> cv2.FileStorage:
    if not path.is_file():
        raise InputError(f"{path}: no such calibration file")
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:
        # the binding raises SystemError with OpenCV's parsing error as its cause
        detail = str(e.__cause__ or e).strip().split("error: ", 1)[-1]
        raise InputError(f"{path}: not an OpenCV YAML / XML / JSON file ({detail})") from None
    if not storage.isOpened():
        raise InputError(f"{path}: cannot read as an OpenCV YAML / XML / JSON file")
    return storage


def _node_value(node: cv2.FileNode, key: str, path: Path, name: str) -> object:
    """A node's numbers: an OpenCV matrix, a number or a (nested) sequence of numbers."""
    if node.isMap():
        try:
            return node.mat()
        except cv2.error:
            raise InputError(f"{path}: camera '{name}' field '{key}' is not a matrix") from None
    if node.isSeq():
        return [_node_value(node.at(i), key, path, name) for i in range(node.size())]
    if node.isInt() or node.isReal():
        return node.real()
    raise InputError(f"{path}: camera '{name}' field '{key}' is not numeric")


Storages = Sequence[tuple[Path, cv2.FileStorage]]


def _storage_field(storages: Storages, keys: Sequence[str], name: str,
                   shapes: Sequence[tuple[int, ...]], *, required: bool = True
                   ) -> tuple[np.ndarray, str, Path] | None:
    """The first of ``keys`` found in the files, as (array, key, file); None when absent and
    not ``required``."""
    for key in keys:
        for path, storage in storages:
            node = storage.getNode(key)
            if not node.isNone():
                value = _node_value(node, key, path, name)
                return _checked(value, key, shapes, path, name), key, path
    if required:
        raise InputError(f"{storages[0][0]}: camera '{name}' lacks "
                         f"{' / '.join(repr(k) for k in keys)}")
    return None


# field -> its keys, the first found wins: single-camera files (OpenCV's calibration sample)
# and EasyMocap's (``{}``: the camera's name; ``R_`` is a Rodrigues vector, ``Rot_`` a matrix)
OPENCV_KEYS = {
    "K": ("camera_matrix", "K", "cameraMatrix"),
    "dist": ("distortion_coefficients", "dist", "dist_coeffs", "D"),
    "R": ("R", "rvec", "Rot"),
    "t": ("T", "tvec", "t"),
    "width": ("image_width",),
    "height": ("image_height",),
    "size": ("image_size",),
    "fisheye": ("fisheye_model", "fisheye"),
}
EASYMOCAP_KEYS = {
    "K": ("K_{}",),
    "dist": ("dist_{}", "D_{}"),
    "R": ("R_{}", "Rot_{}"),
    "t": ("T_{}",),
    "width": ("W_{}",),
    "height": ("H_{}",),
    "size": (),
    "fisheye": (),
}


def _opencv_camera(storages: Storages, name: str, keys: Mapping[str, Sequence[str]]
                   ) -> CameraCalibration:
    def field(what: str, shapes: Sequence[tuple[int, ...]], required: bool = True
              ) -> tuple[np.ndarray, str, Path] | None:
        return _storage_field(storages, [k.format(name) for k in keys[what]], name, shapes,
                              required=required)

    K, _, _ = field("K", [(3, 3)])
    dist, _, _ = field("dist", [])
    R, r_key, r_path = field("R", ROTATION_SHAPES)
    t, _, _ = field("t", VECTOR_SHAPES)
    width, height = field("width", [()], False), field("height", [()], False)
    if width is None or height is None:
        both = field("size", [(2,), (1, 2), (2, 1)], False)
        if both is not None:
            width, height = ((v, *both[1:]) for v in both[0].ravel())
    # EasyMocap writes -1 for a size it does not know
    width, height = (None if f is None or f[0] < 1 else _size(*f, name) for f in (width, height))
    fisheye = field("fisheye", [()], False)
    return CameraCalibration(
        name=name, width=width, height=height, K=K, dist=dist.ravel(),
        R=_rotation(R, r_key, r_path, name), t=t.ravel(),
        fisheye=fisheye is not None and bool(fisheye[0]),
    )


def _node_names(node: cv2.FileNode, path: Path) -> list[str]:
    names = []
    for i in range(node.size()):
        item = node.at(i)
        if item.isString():
            names.append(item.string())
        elif item.isInt():
            names.append(str(int(item.real())))
        else:
            raise InputError(f"{path}: 'names' entry {i} is not a camera name")
    return names


def _extrinsics_beside(path: Path) -> Path | None:
    """EasyMocap's ``extri.yml`` for ``intri.yml`` (``Intrinsic.yml``: ``Extrinsic.yml``)."""
    name = re.sub("([Ii])ntri", lambda m: "Extri" if m.group(1) == "I" else "extri", path.name)
    return path.with_name(name) if name != path.name and path.with_name(name).is_file() else None


def read_opencv(paths: Sequence[Path | str]) -> list[CameraCalibration]:
    """Cameras of OpenCV FileStorage files (YAML, XML or JSON as ``cv2.FileStorage`` writes).

    EasyMocap: ``intri.yml`` with ``names`` and per camera ``K_<name>``, ``dist_<name>`` (or
    ``D_``), optional ``W_<name>`` / ``H_<name>``; ``extri.yml`` with ``R_<name>`` (Rodrigues,
    world-to-camera; or the matrix ``Rot_<name>``) and ``T_<name>``. Given a folder: its
    ``intri.yml`` and ``extri.yml``; given the intrinsics file alone: the one beside it named
    with ``extri`` for ``intri``, if any. Otherwise one camera per file, named by
    ``camera_name`` or the file name up to its first dot: ``camera_matrix`` (or ``K``),
    ``distortion_coefficients`` (or ``dist``, ``D``), ``image_width`` / ``image_height`` (or
    ``image_size``), ``R`` (matrix or Rodrigues) or ``rvec``, ``T`` or ``tvec``
    (world-to-camera) and optional ``fisheye_model`` (the keys of OpenCV's camera calibration
    sample)."""
    files: list[Path] = []
    for path in map(Path, paths):
        if path.is_dir():
            pair = [path / "intri.yml", path / "extri.yml"]
            missing = [f.name for f in pair if not f.is_file()]
            if missing:
                raise InputError(f"{path}: no {missing[0]} (EasyMocap's intri.yml and extri.yml "
                                 "expected in a calibration folder)")
            files += pair
        else:
            files.append(path)
    storages = [(f, _open_storage(f)) for f in files]
    listed = [(f, s) for f, s in storages if not s.getNode("names").isNone()]
    if not listed:
        return [_opencv_camera([(f, s)], _storage_name(f, s), OPENCV_KEYS) for f, s in storages]
    if len(files) == 1 and (beside := _extrinsics_beside(files[0])) is not None:
        storages.append((beside, _open_storage(beside)))
    path, storage = listed[0]
    names = _node_names(storage.getNode("names"), path)
    if not names:
        raise InputError(f"{path}: 'names' lists no camera")
    return [_opencv_camera(storages, name, EASYMOCAP_KEYS) for name in names]


def _storage_name(path: Path, storage: cv2.FileStorage) -> str:
    node = storage.getNode("camera_name")
    return node.string() if node.isString() and node.string() else path.name.split(".")[0]


def _guess_format(path: Path) -> str:
    name = path.name.lower()
    if path.is_dir() or name.endswith((".yml", ".yaml", ".json")):
        return "opencv"
    if name.endswith(".toml"):
        return "anipose"
    if name.endswith((".qca.txt", ".qca")):
        return "qualisys"
    if name.endswith(".xml"):
        try:
            with open(path, "rb") as f:
                head = f.read(4096)
        except OSError as e:
            raise InputError(f"{path}: cannot read ({e.strerror or e})") from None
        return "opencv" if b"<opencv_storage" in head else "qualisys"
    raise InputError(f"{path}: unknown calibration format (expected .qca.txt, .toml, .yml, "
                     ".yaml, .xml or .json, or --format)")


def read_calibration(path: Path | str | Sequence[Path | str], fmt: str | None = None
                     ) -> list[CameraCalibration]:
    """Cameras of a calibration in ``fmt`` (one of ``FORMATS``), by default guessed from the
    name: ``.qca.txt`` / ``.qca`` Qualisys, ``.toml`` anipose / Pose2Sim, ``.yml`` / ``.yaml``
    / ``.json`` OpenCV, ``.xml`` OpenCV when its root is ``opencv_storage``, else Qualisys.
    ``path`` is one file; for ``opencv`` also several files or an EasyMocap folder."""
    paths = [Path(path)] if isinstance(path, str | Path) else [Path(p) for p in path]
    if not paths:
        raise InputError("no calibration file given")
    for p in paths:
        if not p.exists():
            raise InputError(f"{p}: no such calibration file")
    fmt = _guess_format(paths[0]) if fmt is None else fmt
    if fmt not in FORMATS:
        raise InputError(f"unknown calibration format '{fmt}' (known: {', '.join(FORMATS)})")
    if fmt == "opencv":
        cameras = read_opencv(paths)
    elif len(paths) > 1:
        raise InputError(f"{paths[1]}: the {fmt} format is one file, got {len(paths)}")
    elif not paths[0].is_file():
        raise InputError(f"{paths[0]}: not a file")
    else:
        cameras = read_qualisys(paths[0]) if fmt == "qualisys" else read_toml(paths[0])
    names = [c.name for c in cameras]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(f"{paths[0]}: camera name {twice[0]!r} used twice")
    return cameras


def _name_pattern(name: str) -> re.Pattern | None:
    """Matches a file or folder name that starts with the camera's name: case, separators and
    leading zeros ignored, ending where a word or number ends (``cam1`` is not ``cam10``)."""
    tokens = re.findall(r"[a-z]+|\d+", name.lower())
    if not tokens:
        return None
    parts = [f"0*{int(t)}" if t.isdigit() else re.escape(t) for t in tokens]
    end = r"(?!\d)" if tokens[-1].isdigit() else "(?![a-z])"
    return re.compile("^" + r"[\W_]*".join(parts) + end, re.IGNORECASE)


def names_per_camera(names: Sequence[str], camera_names: Sequence[str], source: Path | str
                     ) -> dict[str, list[str]]:
    """Image ``names`` (POSIX paths, kept in their order) by camera: a name belongs to the
    camera whose name starts its first folder (``cam01/0001.jpg``, ``cam_01_img/0001.jpg``)
    or, without a folder, its file name (``cam01_0001.jpg``); the longest such camera name
    wins. ``source`` (the folder they come from) names them in messages."""
    patterns = [(c, _name_pattern(c)) for c in camera_names]
    images: dict[str, list[str]] = {c: [] for c in camera_names}
    unmatched = []
    for image in names:
        parts = image.split("/")
        head = parts[0] if len(parts) > 1 else Path(image).stem
        matches = [(m.end(), c) for c, pattern in patterns
                   if pattern is not None and (m := pattern.match(head))]
        if not matches:
            unmatched.append(image)
            continue
        best = max(end for end, _ in matches)
        owners = [c for end, c in matches if end == best]
        if len(owners) > 1:
            raise InputError(f"{source}: image '{image}' could be of camera "
                             f"{' or '.join(map(repr, owners))}")
        images[owners[0]].append(image)
    if unmatched:
        logger.info("%s: %d image(s) named after no camera, left out (e.g. '%s')", source,
                    len(unmatched), unmatched[0])
    if not any(images.values()):
        raise InputError(f"{source}: no image in a folder or file named after a camera "
                         f"({', '.join(camera_names)})")
    for camera in (c for c, listed in images.items() if not listed):
        logger.warning("%s: no image of camera '%s'", source, camera)
    return images


def images_per_camera(image_dir: Path | str, camera_names: Sequence[str]
                      ) -> dict[str, list[str]]:
    """The images below ``image_dir`` (POSIX names relative to it, natural order) by camera
    (``names_per_camera``)."""
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise InputError(f"{image_dir}: no such image folder")
    return names_per_camera(list_images(image_dir), camera_names, image_dir)


def keypoint_image_names(keys: Sequence[str]) -> list[str]:
    """One image name per keypoint key, for a model without image files: the key itself
    (``cam01_json/cam01.0012`` -> ``cam01_json/cam01.0012.jpg``, ``.jpg`` added unless it ends
    in an image suffix), so the keypoints match their image exactly (``match_names`` rule 1)
    and its last number is the frame number (``observations.assign_streams``)."""
    names = (k if PurePosixPath(k).suffix.lower() in IMAGE_SUFFIXES else f"{k}.jpg"
             for k in (key.replace("\\", "/") for key in keys))
    return sorted(names, key=natural_key)


def keypoint_images_per_camera(keypoints: Path | str, camera_names: Sequence[str], *,
                               fmt: str = "openpose") -> dict[str, list[str]]:
    """One image per keypoint file (or entry) of ``keypoints`` in keypoint format ``fmt``
    (``keypoint_image_names``), by camera (``names_per_camera``): the frame list of a rig
    whose videos were never cut into image files (Pose2Sim's ``camXX_json/camXX.NNNN.json``)."""
    kp = read_keypoints(fmt, keypoints)
    return names_per_camera(keypoint_image_names(list(kp.points)), camera_names, keypoints)


def _image_size(path: Path) -> tuple[int, int]:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path}: cannot read the image (needed for its camera's size)")
    return image.shape[1], image.shape[0]


def import_calibration(
    calib_file: Path | str | Sequence[Path | str],
    out_model_dir: Path | str,
    image_names_per_camera: Mapping[str, Sequence[str]] | None = None,
    *,
    fmt: str | None = None,
    image_dir: Path | str | None = None,
    keypoints: Path | str | None = None,
    keypoint_format: str = "openpose",
    overwrite: bool = False,
) -> Path:
    """Write a COLMAP model of a calibration (``read_calibration``): one COLMAP camera per
    calibrated camera and its images, all at that camera's pose: ``image_names_per_camera``,
    else the images below ``image_dir`` (``images_per_camera``), else one image per file of
    ``keypoints`` in ``keypoint_format`` (``keypoint_images_per_camera``; no image files
    needed), else one image ``<camera name>.jpg`` per camera. A size the calibration lacks is
    read from the camera's first image in ``image_dir``. Returns the model folder."""
    if image_dir is not None and keypoints is not None:
        raise InputError(f"{keypoints}: the images come from the image folder {image_dir} or "
                         "from the keypoint files, not both")
    cameras = read_calibration(calib_file, fmt)
    names = [c.name for c in cameras]
    if image_names_per_camera is None:
        image_names_per_camera = (
            images_per_camera(image_dir, names) if image_dir is not None
            else keypoint_images_per_camera(keypoints, names, fmt=keypoint_format)
            if keypoints is not None
            else {c.name: [f"{c.name}.jpg"] for c in cameras})
    unknown = [k for k in image_names_per_camera if k not in names]
    if unknown:
        raise InputError(f"{calib_file}: no camera named {', '.join(map(repr, unknown))} "
                         f"(cameras: {', '.join(names)})")
    if image_dir is not None:
        cameras = [
            dataclasses.replace(c, **dict(zip(("width", "height"), _image_size(
                Path(image_dir) / image_names_per_camera[c.name][0]), strict=True)))
            if c.width is None and image_names_per_camera.get(c.name) else c
            for c in cameras
        ]
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
