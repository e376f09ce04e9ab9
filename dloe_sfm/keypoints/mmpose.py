"""MMPose predictions saved as JSON.

Accepted layouts of a file (``MMPoseInferencer(pred_out_dir=...)`` and the demo scripts'
``--save-predictions``):

- per image, ``IMAGE_STEM.json``: a list of instances, or ``{"meta_info": ...,
  "instance_info": [instances]}``; key = file path relative to the folder without ``.json``;
- per video, ``VIDEO.json``: a list of ``{"frame_id": k, "instances": [...]}`` (also under
  ``instance_info``); frame k gets the key ``VIDEO/<k + frame_offset>``, which
  ``base.match_names`` pairs with e.g. ``VIDEO/000012.jpg`` (numbers compare by value).

An instance is ``{"keypoints": [[x, y], ...], "keypoint_scores": [s, ...], ...}``; the joint
names and skeleton come from ``meta_info`` when present.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import InputError
from .base import (
    Keypoints,
    Layout,
    as_points,
    file_key,
    get_layout,
    json_files,
    read_json,
    stack_people,
)


def _instance(inst, source: str) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(inst, dict) or "keypoints" not in inst:
        raise InputError(f"{source}: an instance without 'keypoints'")
    num = len(inst["keypoints"]) if isinstance(inst["keypoints"], list) else 0
    xy = as_points(inst["keypoints"], num, source, columns=2)
    scores = inst.get("keypoint_scores", [1.0] * num)
    scores = as_points(scores, num, source, columns=1)[:, 0]
    return xy, scores


def _meta_layout(meta, num_points: int) -> Layout | None:
    if not isinstance(meta, dict) or not isinstance(meta.get("keypoint_id2name"), dict):
        return None
    id2name = {int(k): str(v) for k, v in meta["keypoint_id2name"].items()}
    if sorted(id2name) != list(range(num_points)):
        return None
    return Layout(
        name=str(meta.get("dataset_name", "mmpose")),
        point_names=[id2name[i] for i in range(num_points)],
        edges=[(int(a), int(b)) for a, b in meta.get("skeleton_links", [])],
        symmetric_pairs=[(int(a), int(b)) for a, b in meta.get("flip_pairs", [])],
    )


def _frames(data, key: str, frame_offset: int, file: Path) -> tuple[dict[str, list], object]:
    """{key: instances} of one file and its meta_info (or None)."""
    meta = None
    if isinstance(data, dict) and "instance_info" in data:
        meta, data = data.get("meta_info"), data["instance_info"]
    if not isinstance(data, list):
        raise InputError(f"{file}: not MMPose predictions (expected a list of instances)")
    if data and all(isinstance(d, dict) and "frame_id" in d for d in data):
        frames = {}
        for d in data:
            try:
                k = int(d["frame_id"]) + frame_offset
            except (TypeError, ValueError):
                raise InputError(f"{file}: frame_id {d['frame_id']!r} is not an integer") from None
            if not isinstance(d.get("instances"), list):
                raise InputError(f"{file}: frame {d['frame_id']} has no 'instances' list")
            frames[f"{key}/{k}"] = d["instances"]
        return frames, meta
    return {key: data}, meta


def read(path: Path, *, layout: str | Layout | None = None, frame_offset: int = 0) -> Keypoints:
    """Read MMPose prediction file(s); ``layout`` overrides the names in ``meta_info``;
    ``frame_offset`` is added to video frame ids (e.g. 1 for frames extracted from 1)."""
    files = json_files(path)
    root = path if path.is_dir() else path.parent
    raw: dict[str, tuple[str, list]] = {}
    meta = None
    for file in tqdm(files, desc="mmpose", unit="file", leave=False):
        frames, file_meta = _frames(read_json(file), file_key(file, root), frame_offset, file)
        meta = meta or file_meta
        for key, instances in frames.items():
            if key in raw:
                raise InputError(f"{file}: image key '{key}' appears twice")
            raw[key] = (str(file), instances)
    parsed = {
        key: [_instance(inst, f"{file} '{key}' instance {i}") for i, inst in enumerate(insts)]
        for key, (file, insts) in raw.items()
    }
    sizes = {len(xy) for people in parsed.values() for xy, _ in people}
    if not sizes:
        raise InputError(f"{path}: no instance in any of {len(files)} file(s)")
    if len(sizes) > 1:
        raise InputError(f"{path}: instances have different keypoint counts {sorted(sizes)}")
    num_points = sizes.pop()
    if layout is None:
        layout = _meta_layout(meta, num_points)
    layout = get_layout(layout, num_points, path)
    points = {
        key: stack_people([np.column_stack([xy, s]) for xy, s in people], num_points)
        for key, people in parsed.items()
    }
    return Keypoints(layout=layout, points=points, source=path)
