"""OpenPose JSON: one ``*_keypoints.json`` per image, or Pose2Sim folders ``camXX_json/*.json``.

Each file holds ``{"people": [{"pose_keypoints_2d": [x0, y0, c0, x1, ...]}, ...]}``; a joint
at 0, 0, 0 (score 0) is missing. Keys are file paths relative to the given folder without
``.json`` and ``_keypoints`` (``cam01_json/cam01.0012``), matched to images by
``base.match_names``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .. import progress
from ..errors import InputError
from .base import (
    LAYOUTS,
    Keypoints,
    Layout,
    as_points,
    file_key,
    get_layout,
    json_files,
    quoted,
    read_json,
    shown,
    stack_people,
)

logger = logging.getLogger("dloe_sfm")

# layout by joint count: OpenPose's two 25-joint models share a size (``body_25_or_25b`` tells
# them apart from the data, else BODY_25, OpenPose's default); RTMPose / AlphaPose / MediaPipe
# results converted to OpenPose JSON (as Pose2Sim reads them)
DEFAULT_LAYOUTS = {25: "BODY_25", 18: "COCO_18", 26: "HALPE_26", 133: "COCO_WHOLEBODY",
                   33: "MEDIAPIPE_33"}
# BODY_25's Neck (1) and MidHip (8) are trained on the midpoints of its shoulders (2, 5) and
# hips (9, 12): on BODY_25 detections each lies 0.01-0.08 of its pair's distance from the
# pair's midpoint (two OpenPose 1.2 / 1.3 outputs quoted in public code); on BODY_25B's the same
# indices (LEye vs REye and LShoulder, RElbow vs RWrist and RHip) give 0.3-1.3 (the Pose2Sim
# trial: median 0.53 over both pairs)
MIDPOINT_PAIRS = ((1, 2, 5), (8, 9, 12))
MIDPOINT_TOLERANCE = 0.2
# BODY_25B's first five points are the head (nose, eyes, ears): their spread is a small part
# of the person's (0.09 on the Pose2Sim trial); BODY_25's are nose, neck and the right arm
# (0.36 on the same detections in BODY_25's order)
HEAD_SPREAD_TOLERANCE = 0.2
MIN_DETECTIONS = 5  # detections with the points a test needs, for its median to count


def _midpoint_residual(people: np.ndarray) -> float:
    """Median over ``people`` (D, 25, 3), NaN = missing, and both ``MIDPOINT_PAIRS`` of
    |x_a - (x_b + x_c) / 2| / |x_b - x_c| (NaN with under ``MIN_DETECTIONS`` values)."""
    xy = people[..., :2]
    a, b, c = (xy[:, list(k)] for k in zip(*MIDPOINT_PAIRS, strict=True))
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.linalg.norm(a - (b + c) / 2, axis=-1) / np.linalg.norm(b - c, axis=-1)
    ratio = ratio[np.isfinite(ratio)]
    return float(np.median(ratio)) if ratio.size >= MIN_DETECTIONS else np.nan


def _head_spread(people: np.ndarray) -> float:
    """Median over ``people`` of the extent of points 0-4 over the person's extent (both the
    larger side of their bounding boxes), of detections with all five points."""
    xy = people[..., :2]
    whole = xy[np.isfinite(xy[:, :5]).all(axis=(1, 2))]
    if len(whole) < MIN_DETECTIONS:
        return np.nan
    head = np.ptp(whole[:, :5], axis=1).max(axis=1)
    body = (np.nanmax(whole, axis=1) - np.nanmin(whole, axis=1)).max(axis=1)
    return float(np.median(head / body))


def body_25_or_25b(people: np.ndarray) -> tuple[str | None, str]:
    """Which of OpenPose's two 25-point models detections ``people`` (D, 25, 3), NaN =
    missing, are in: ("BODY_25" or "BODY_25B", the evidence), or (None, why the data cannot
    tell)."""
    midpoint, head = _midpoint_residual(people), _head_spread(people)
    evidence = (f"points 1 and 8 from the midpoints of 2, 5 and 9, 12: {midpoint:.2f} of their "
                f"distance, points 0-4 spread over {head:.2f} of the person (median)")
    body_25 = midpoint < MIDPOINT_TOLERANCE
    body_25b = midpoint >= MIDPOINT_TOLERANCE and head < HEAD_SPREAD_TOLERANCE
    if body_25 == body_25b:  # neither (or too few detections: NaN fails both tests)
        return None, evidence
    return ("BODY_25" if body_25 else "BODY_25B"), evidence


def _default_layout(points: dict[str, np.ndarray], num_points: int, path: Path) -> str | None:
    """The layout of ``num_points`` joints (``DEFAULT_LAYOUTS``, BODY_25 / BODY_25B from the
    data), logged with the other layouts of that size and how to choose one."""
    same_size = [name for name, lay in LAYOUTS.items()
                 if num_points in (lay.num_points, lay.source_points)]
    choose = "--layout NAME|FILE.json to choose"
    name = DEFAULT_LAYOUTS.get(num_points)
    others = ", ".join(n for n in same_size if n != name) or "none"
    if name is None:
        logger.info("%s: %d joints per detection, no layout taken: points p0, p1, ... (known "
                    "layouts of %d joints: %s; %s)", shown(path), num_points, num_points,
                    others, choose)
        return None
    if num_points != 25:
        logger.info("%s: %d joints per detection: read as %s (other known layouts of %d "
                    "joints: %s; %s)", shown(path), num_points, name, num_points, others, choose)
        return name
    found, evidence = body_25_or_25b(np.concatenate([*points.values(), np.zeros((0, 25, 3))]))
    if found is None:
        logger.warning("%s: 25 joints per detection, BODY_25 or BODY_25B (Pose2Sim's default): "
                       "the data does not tell (%s); read as BODY_25, --layout BODY_25B if it "
                       "is that", shown(path), evidence)
        return name
    other = "BODY_25B" if found == "BODY_25" else "BODY_25"
    logger.info("%s: 25 joints per detection, read as %s, not %s, from the data (%s; --layout "
                "NAME to choose)", shown(path), found, other, evidence)
    return found


def _people(data, file: Path) -> list[list[float]]:
    if not isinstance(data, dict) or not isinstance(data.get("people"), list):
        raise InputError(f"{shown(file)}: not OpenPose output (no 'people' list)")
    flat = []
    for i, person in enumerate(data["people"]):
        values = person.get("pose_keypoints_2d") if isinstance(person, dict) else None
        if not isinstance(values, list):
            raise InputError(f"{shown(file)}: person {i} has no 'pose_keypoints_2d' list")
        flat.append(values)
    return flat


def read(path: Path, *, layout: str | Layout | None = None) -> Keypoints:
    """Read an OpenPose file or folder; ``layout`` names the model (BODY_25, BODY_25B, COCO_18,
    ...), default by joint count (``DEFAULT_LAYOUTS``: 25 -> BODY_25 or BODY_25B as the data
    tells, ``body_25_or_25b``, 18 -> COCO_18, 26 -> HALPE_26, 133 -> COCO_WHOLEBODY (body and
    feet kept), 33 -> MEDIAPIPE_33), logged with the other layouts of that size."""
    files = json_files(path)
    root = path if path.is_dir() else path.parent
    raw: dict[str, tuple[Path, list[list[float]]]] = {}
    for file in progress.bar(files, desc="openpose", unit="file", leave=False):
        key = file_key(file, root)
        if key in raw:
            raise InputError(f"{shown(file)}: same image key {quoted(key)} as "
                             f"{shown(raw[key][0])}")
        raw[key] = (file, _people(read_json(file), file))
    sizes = {len(v) for _, people in raw.values() for v in people}
    if not sizes:
        raise InputError(f"{shown(path)}: no person detected in any of {len(files)} file(s)")
    if len(sizes) > 1 or next(iter(sizes)) % 3:
        raise InputError(f"{shown(path)}: 'pose_keypoints_2d' lengths differ or are not "
                         f"3 x joints ({', '.join(map(str, sorted(sizes)[:5]))})")
    num_points = next(iter(sizes)) // 3
    points = {
        key: stack_people(
            [as_points(v, num_points, f"{file} person {i}") for i, v in enumerate(people)],
            num_points,
        )
        for key, (file, people) in raw.items()
    }
    if layout is None:
        layout = _default_layout(points, num_points, path)
    return Keypoints(layout=get_layout(layout, num_points, path), points=points, source=path)
