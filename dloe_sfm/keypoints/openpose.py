"""OpenPose JSON: one ``*_keypoints.json`` per image, or Pose2Sim folders ``camXX_json/*.json``.

Each file holds ``{"people": [{"pose_keypoints_2d": [x0, y0, c0, x1, ...]}, ...]}``; a joint
at 0, 0, 0 (score 0) is missing. Keys are file paths relative to the given folder without
``.json`` and ``_keypoints`` (``cam01_json/cam01.0012``), matched to images by
``base.match_names``.
"""

from __future__ import annotations

from pathlib import Path

from .. import progress
from ..errors import InputError
from .base import (
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

# layout by joint count: OpenPose's two 25-joint models share a size, BODY_25 is its default;
# RTMPose / AlphaPose / MediaPipe results converted to OpenPose JSON (as Pose2Sim reads them)
DEFAULT_LAYOUTS = {25: "BODY_25", 18: "COCO_18", 26: "HALPE_26", 133: "COCO_WHOLEBODY",
                   33: "MEDIAPIPE_33"}


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
    ...), default by joint count (``DEFAULT_LAYOUTS``: 25 -> BODY_25, 18 -> COCO_18,
    26 -> HALPE_26, 133 -> COCO_WHOLEBODY (body and feet kept), 33 -> MEDIAPIPE_33)."""
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
    layout = get_layout(layout if layout is not None else DEFAULT_LAYOUTS.get(num_points),
                        num_points, path)
    points = {
        key: stack_people(
            [as_points(v, num_points, f"{file} person {i}") for i, v in enumerate(people)],
            num_points,
        )
        for key, (file, people) in raw.items()
    }
    return Keypoints(layout=layout, points=points, source=path)
