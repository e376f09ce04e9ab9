"""Keypoint adapters, one per input format, chosen by name with ``read_keypoints``."""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import InputError
from .base import (
    LAYOUTS,
    Keypoints,
    Layout,
    load_layout,
    match_names,
    quoted,
    rename_to_workspace,
    shown,
)
from .detect import KINDS, looks_like

if TYPE_CHECKING:
    from ..colmap import Workspace

# format name -> module with ``read(path, **options) -> Keypoints`` (imported on use: cv2 is
# only loaded for aruco)
FORMATS = {
    "openpose": "dloe_sfm.keypoints.openpose",
    "coco": "dloe_sfm.keypoints.coco",
    "mmpose": "dloe_sfm.keypoints.mmpose",
    "csv": "dloe_sfm.keypoints.csv",
    "aruco": "dloe_sfm.keypoints.aruco",
}

__all__ = ["FORMATS", "LAYOUTS", "Keypoints", "Layout", "load_layout", "match_names",
           "read_keypoints"]


def read_keypoints(
    fmt: str, path: Path | str | None, *, workspace: Workspace | None = None, **options
) -> Keypoints:
    """Read keypoints of format ``fmt`` (one of ``FORMATS``) from ``path``.

    With a ``workspace``, keys are matched to its image names (``base.match_names``); keys that
    match no image stay as they are (``observations.build_capture`` rejects them). For
    ``aruco``, ``path`` may be None: the workspace's image folder.
    """
    module_name = FORMATS.get(fmt.lower())
    if module_name is None:
        raise InputError(f"unknown keypoint format {quoted(fmt)} (known: {', '.join(FORMATS)})")
    reader = importlib.import_module(module_name).read
    allowed = [p for p in inspect.signature(reader).parameters if p != "path"]
    unknown = [k for k in options if k not in allowed]
    if unknown:
        raise InputError(
            f"keypoint format '{fmt}' has no option {shown(', '.join(unknown))} "
            f"(options: {', '.join(allowed) or 'none'})"
        )
    if path is None:
        if fmt.lower() != "aruco" or workspace is None or workspace.image_dir is None:
            raise InputError(f"keypoint format '{fmt}': no keypoint path given")
        path = workspace.image_dir
    path = Path(path)
    if not path.exists():
        raise InputError(f"{shown(path)}: no such keypoint file or folder")
    try:
        keypoints = reader(path, **options)
    except InputError:
        guess = looks_like(path)
        if guess is None or guess == fmt.lower():
            raise
        raise InputError(f"{shown(path)}: looks like {KINDS[guess]}, not {fmt} keypoints: "
                         f"use --format {guess}") from None
    return rename_to_workspace(keypoints, workspace) if workspace is not None else keypoints
