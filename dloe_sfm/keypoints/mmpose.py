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

from .. import progress
from ..errors import InputError
from .base import (
    Keypoints,
    Layout,
    as_int,
    as_points,
    brief,
    expect,
    file_key,
    get_layout,
    index_pairs,
    json_files,
    known_layout,
    quoted,
    read_json,
    shown,
    stack_people,
)


def _instance(inst, source: str) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(inst, dict) or "keypoints" not in inst:
        raise InputError(f"{shown(source)}: an instance without 'keypoints'")
    num = len(expect(inst["keypoints"], list, f"{shown(source)}: 'keypoints'"))
    xy = as_points(inst["keypoints"], num, source, columns=2, nested=True)
    scores = inst.get("keypoint_scores", [1.0] * num)
    scores = as_points(scores, num, source, columns=1)[:, 0]
    return xy, scores


def _meta_layout(meta, num_points: int, file: Path) -> Layout | None:
    """The layout of ``meta_info`` when it names every point 0..num_points - 1 (the known
    layout of those names, ``base.known_layout``, e.g. HALPE_26 for halpe26), else None."""
    if not isinstance(meta, dict) or not isinstance(meta.get("keypoint_id2name"), dict):
        return None
    where = f"{shown(file)}: meta_info"
    id2name = {}
    for k, v in meta["keypoint_id2name"].items():
        index = as_int(k)
        if index is None:
            raise InputError(f"{where} 'keypoint_id2name' key {brief(k)} is not an integer")
        id2name[index] = str(expect(v, (str, int, float), f"{where} 'keypoint_id2name' value"))
    if sorted(id2name) != list(range(num_points)):
        return None
    name = meta.get("dataset_name", "mmpose")
    layout = Layout(
        name=str(name) if isinstance(name, (str, int, float)) else "mmpose",
        point_names=[id2name[i] for i in range(num_points)],
        edges=index_pairs(meta.get("skeleton_links", []), num_points,
                          f"{where} 'skeleton_links'"),
        symmetric_pairs=[(a, b) for a, b in index_pairs(meta.get("flip_pairs", []), num_points,
                                                         f"{where} 'flip_pairs'") if a != b],
    )
    return known_layout(layout.point_names) or layout


def _frames(data, key: str, frame_offset: int, file: Path) -> tuple[dict[str, list], object]:
    """{key: instances} of one file and its meta_info (or None)."""
    meta = None
    if isinstance(data, dict) and "instance_info" in data:
        meta, data = data.get("meta_info"), data["instance_info"]
    if not isinstance(data, list):
        raise InputError(f"{shown(file)}: not MMPose predictions (expected a list of instances)")
    if data and all(isinstance(d, dict) and "frame_id" in d for d in data):
        frames = {}
        for d in data:
            k = as_int(d["frame_id"])
            if k is None:
                raise InputError(f"{shown(file)}: 'frame_id' must be an integer, got "
                                 f"{brief(d['frame_id'])}")
            if not isinstance(d.get("instances"), list):
                raise InputError(f"{shown(file)}: frame {k} has no 'instances' list")
            if f"{key}/{k + frame_offset}" in frames:
                raise InputError(f"{shown(file)}: frame_id {k} appears twice")
            frames[f"{key}/{k + frame_offset}"] = d["instances"]
        return frames, meta
    return {key: data}, meta


def read(path: Path, *, layout: str | Layout | None = None, frame_offset: int = 0) -> Keypoints:
    """Read MMPose prediction file(s); ``layout`` overrides the names in ``meta_info``;
    ``frame_offset`` is added to video frame ids (e.g. 1 for frames extracted from 1)."""
    files = json_files(path)
    root = path if path.is_dir() else path.parent
    raw: dict[str, tuple[str, list]] = {}
    meta, meta_file = None, path
    for file in progress.bar(files, desc="mmpose", unit="file", leave=False):
        frames, file_meta = _frames(read_json(file), file_key(file, root), frame_offset, file)
        if meta is None and file_meta:
            meta, meta_file = file_meta, file
        for key, instances in frames.items():
            if key in raw:
                raise InputError(f"{shown(file)}: image key {quoted(key)} appears twice")
            raw[key] = (str(file), instances)
    parsed = {
        key: [_instance(inst, f"{file} {quoted(key)} instance {i}")
              for i, inst in enumerate(insts)]
        for key, (file, insts) in raw.items()
    }
    sizes = {len(xy) for people in parsed.values() for xy, _ in people}
    if not sizes:
        raise InputError(f"{shown(path)}: no instance in any of {len(files)} file(s)")
    if len(sizes) > 1:
        raise InputError(f"{shown(path)}: instances have different keypoint counts "
                         f"({', '.join(map(str, sorted(sizes)[:5]))})")
    num_points = sizes.pop()
    if layout is None:
        layout = _meta_layout(meta, num_points, meta_file)
    layout = get_layout(layout, num_points, path)
    points = {
        key: stack_people([np.column_stack([xy, s]) for xy, s in people], num_points)
        for key, people in parsed.items()
    }
    return Keypoints(layout=layout, points=points, source=path)
