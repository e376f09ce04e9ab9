"""ArUco markers detected in the images themselves (``cv2.aruco.ArucoDetector``).

Point ``4 * marker_id + k`` is corner k (0 top-left, then clockwise, in the marker's own frame)
of marker ``marker_id``; P = 4 * ``num_markers`` (default: largest id seen + 1). Corners are
refined to sub-pixel; OpenCV's pixel convention is (0, 0) = centre of the top-left pixel.
Keys are image paths relative to the image folder, matched by ``base.match_names``. An image's
size is read from its header first: images above ``MAX_IMAGE_PIXELS`` are refused before
anything is decoded.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from .. import progress
from ..errors import InputError
from ..images import list_images
from .base import MAX_POINTS, Keypoints, Layout, check_count, quoted, shown

logger = logging.getLogger("dloe_sfm")

# 150 megapixels (a 14000 x 10700 photo): the decoded grey image is at most 150 MB
MAX_IMAGE_PIXELS = 150_000_000


def marker_layout(num_markers: int, dictionary: str) -> Layout:
    """Four corner points per marker, the marker outlines as edges."""
    names = [f"marker{m}_corner{k}" for m in range(num_markers) for k in range(4)]
    edges = [(4 * m + k, 4 * m + (k + 1) % 4) for m in range(num_markers) for k in range(4)]
    return Layout(name=f"aruco_{dictionary}", point_names=names, edges=edges)


def dictionary_name(name: str) -> str:
    """The ``cv2.aruco`` predefined dictionary named ``name`` (e.g. DICT_5X5_100; case and the
    DICT_ prefix optional), in OpenCV's upper-case spelling; unknown -> InputError."""
    known = [n for n in dir(cv2.aruco) if n.startswith("DICT_") and n.isupper()]
    key = name.strip().upper()
    key = key if key.startswith("DICT_") else f"DICT_{key}"
    if key not in known or not isinstance(getattr(cv2.aruco, key), int):
        raise InputError(f"unknown ArUco dictionary {quoted(name)} (known: {', '.join(known)})")
    return key


def make_detector(dictionary: str) -> cv2.aruco.ArucoDetector:
    """An ArUco detector for a predefined dictionary (``dictionary_name``), sub-pixel corners."""
    dict_id = getattr(cv2.aruco, dictionary_name(dictionary))
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dict_id), params)


def _grey_image(file: Path) -> np.ndarray:
    """The image as 8-bit grey, its header checked against ``MAX_IMAGE_PIXELS`` first."""
    try:
        with warnings.catch_warnings():
            # PIL warns from 89 megapixels and raises from 179; the limit here is our own
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(file) as im:
                width, height = im.size
    except Image.DecompressionBombError:
        raise InputError(f"{shown(file)}: image larger than {MAX_IMAGE_PIXELS} pixels") from None
    except Image.UnidentifiedImageError:
        raise InputError(f"{shown(file)}: cannot read the image (unknown or damaged "
                         "format)") from None
    except Exception as e:  # PIL's format plugins raise assorted errors on corrupt headers
        raise InputError(f"{shown(file)}: cannot read the image ({shown(e)})") from None
    if width * height > MAX_IMAGE_PIXELS:
        raise InputError(f"{shown(file)}: image of {width} x {height} pixels, more than "
                         f"{MAX_IMAGE_PIXELS}")
    try:
        image = cv2.imread(str(file), cv2.IMREAD_GRAYSCALE)
    except cv2.error as e:
        raise InputError(f"{shown(file)}: cannot read the image ({shown(e.err)})") from None
    if image is None:
        raise InputError(f"{shown(file)}: cannot read the image")
    return image


def read(path: Path, *, dictionary: str = "DICT_4X4_50", num_markers: int | None = None
         ) -> Keypoints:
    """Detect markers of the predefined ``dictionary`` (``dictionary_name``) in an image file or
    every image below a folder."""
    dictionary = dictionary_name(dictionary)
    detector = make_detector(dictionary)
    if num_markers is not None:
        check_count(num_markers, "num_markers", MAX_POINTS // 4)
    if path.is_file():
        root, names = path.parent, [path.name]
    elif path.is_dir():
        root, names = path, list_images(path)
    else:
        raise InputError(f"{shown(path)}: not an image file or folder")
    if not names:
        raise InputError(f"{shown(path)}: no images in the folder")
    found: dict[str, dict[int, np.ndarray]] = {}
    for name in progress.bar(names, desc="aruco", unit="image", leave=False):
        corners, ids, _ = detector.detectMarkers(_grey_image(root / name))
        markers: dict[int, np.ndarray] = {}
        ids = [] if ids is None else ids.ravel().tolist()
        for marker_id, c in zip(ids, corners, strict=True):
            if marker_id in markers:
                logger.warning("%s: marker %d seen twice, both dropped", quoted(name),
                               marker_id)
                markers[marker_id] = np.full((4, 2), np.nan)
            else:
                markers[marker_id] = np.asarray(c, dtype=np.float64).reshape(4, 2)
        found[name] = markers
    seen = {m for markers in found.values() for m in markers}
    if num_markers is None:
        if not seen:
            raise InputError(f"{shown(path)}: no {dictionary} marker found in {len(names)} "
                             "image(s)")
        num_markers = max(seen) + 1
    ignored = sorted(m for m in seen if m >= num_markers)
    if ignored:
        logger.info("%s: marker ids %s >= num_markers=%d ignored", path, ignored, num_markers)
    points = {}
    for name, markers in found.items():
        arr = np.tile([np.nan, np.nan, 0.0], (1, 4 * num_markers, 1))
        for m, c in markers.items():
            if m < num_markers and np.isfinite(c).all():
                arr[0, 4 * m:4 * m + 4] = np.column_stack([c, np.ones(4)])
        points[name] = arr
    logger.info("%s: %d marker corner(s) detected in %d image(s)", path,
                int(sum(np.isfinite(a[0, :, 0]).sum() for a in points.values())), len(names))
    return Keypoints(layout=marker_layout(num_markers, dictionary), points=points, source=path)
