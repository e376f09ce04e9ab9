"""ArUco markers detected in the images themselves (``cv2.aruco.ArucoDetector``).

Point ``4 * marker_id + k`` is corner k (0 top-left, then clockwise, in the marker's own frame)
of marker ``marker_id``; P = 4 * ``num_markers`` (default: largest id seen + 1). Corners are
refined to sub-pixel; OpenCV's pixel convention is (0, 0) = centre of the top-left pixel.
Keys are image paths relative to the image folder, matched by ``base.match_names``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..colmap import list_images
from ..errors import InputError
from .base import Keypoints, Layout

logger = logging.getLogger("dloe_sfm")


def marker_layout(num_markers: int, dictionary: str) -> Layout:
    """Four corner points per marker, the marker outlines as edges."""
    names = [f"marker{m}_corner{k}" for m in range(num_markers) for k in range(4)]
    edges = [(4 * m + k, 4 * m + (k + 1) % 4) for m in range(num_markers) for k in range(4)]
    return Layout(name=f"aruco_{dictionary}", point_names=names, edges=edges)


def make_detector(dictionary: str) -> cv2.aruco.ArucoDetector:
    """An ArUco detector for a predefined dictionary name (e.g. DICT_4X4_50), sub-pixel corners."""
    dict_id = getattr(cv2.aruco, dictionary, None) if dictionary.startswith("DICT_") else None
    if not isinstance(dict_id, int):
        known = ", ".join(n for n in dir(cv2.aruco) if n.startswith("DICT_") and n.isupper())
        raise InputError(f"unknown ArUco dictionary '{dictionary}' (known: {known})")
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dict_id), params)


def read(path: Path, *, dictionary: str = "DICT_4X4_50", num_markers: int | None = None
         ) -> Keypoints:
    """Detect markers in an image file or every image below a folder."""
    detector = make_detector(dictionary)
    if path.is_file():
        root, names = path.parent, [path.name]
    elif path.is_dir():
        root, names = path, list_images(path)
    else:
        raise InputError(f"{path}: no such image file or folder")
    if not names:
        raise InputError(f"{path}: no images in the folder")
    found: dict[str, dict[int, np.ndarray]] = {}
    for name in tqdm(names, desc="aruco", unit="image", leave=False):
        image = cv2.imread(str(root / name), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise InputError(f"{root / name}: cannot read the image")
        corners, ids, _ = detector.detectMarkers(image)
        markers: dict[int, np.ndarray] = {}
        ids = [] if ids is None else ids.ravel().tolist()
        for marker_id, c in zip(ids, corners, strict=True):
            if marker_id in markers:
                logger.warning("%s: marker %d seen twice, both dropped", name, marker_id)
                markers[marker_id] = np.full((4, 2), np.nan)
            else:
                markers[marker_id] = np.asarray(c, dtype=np.float64).reshape(4, 2)
        found[name] = markers
    seen = {m for markers in found.values() for m in markers}
    if num_markers is None:
        if not seen:
            raise InputError(f"{path}: no {dictionary} marker found in {len(names)} image(s)")
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
