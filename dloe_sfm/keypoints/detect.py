"""Which keypoint format a file or folder looks like, from its content, to tell the user the
``--format`` to give when the one given does not read it."""

from __future__ import annotations

import json
from itertools import islice
from pathlib import Path

from ..images import IMAGE_SUFFIXES
from .csv import REQUIRED

# how a message names what each format's files are
KINDS = {"openpose": "OpenPose JSON", "coco": "a COCO keypoint file", "mmpose": "MMPose JSON",
         "csv": "CSV keypoints", "aruco": "images (markers are found in them)"}
_HEADER_CHARS = 4096  # a CSV header is read from this much of the file at most
# JSON files of a folder looked at before giving up (a Pose2Sim trial holds thousands)
_JSON_FILES_LOOKED_AT = 20


def _json_format(data: object) -> str | None:
    """The format of parsed JSON by its top-level keys (each format has its own), else None."""
    if isinstance(data, dict):
        if "people" in data:
            return "openpose"
        if "images" in data and "annotations" in data:
            return "coco"
        if "instance_info" in data:
            return "mmpose"
        return None
    first = data[0] if isinstance(data, list) and data else None
    if isinstance(first, dict) and ("keypoints" in first or "instances" in first):
        return "mmpose"
    return None


def _file_format(file: Path) -> str | None:
    if file.suffix.lower() in IMAGE_SUFFIXES:
        return "aruco"
    try:
        with open(file, encoding="utf-8-sig") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError):
        return None
    try:
        return _json_format(json.loads(text))
    except (ValueError, RecursionError):
        pass
    first_line = text[:_HEADER_CHARS].split("\n", 1)[0]
    header = {h.strip().strip('"').lower() for h in first_line.split(",")}
    return "csv" if set(REQUIRED) <= header else None


def looks_like(path: Path) -> str | None:
    """The keypoint format (a ``FORMATS`` name) that file or folder ``path`` looks like: a
    folder by its first decisive ``.json`` file below it, else ``aruco`` when it holds
    images; None when nothing tells."""
    if path.is_file():
        return _file_format(path)
    if not path.is_dir():
        return None
    for file in islice(sorted(path.rglob("*.json")), _JSON_FILES_LOOKED_AT):
        fmt = _file_format(file)
        if fmt is not None:
            return fmt
    images = (p for p in path.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    return "aruco" if next(images, None) is not None else None
