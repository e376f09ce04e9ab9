"""Small pure helpers shared by the export and the plots: the columns of a result's X (subject
and layout point ids, skeleton edges, colours), the observations X refers to, and the files
named after images."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .core.bias import without_offsets
from .core.capture import Capture
from .core.result import Result


def point_colors(num_points: int) -> np.ndarray:
    """(P, 3) uint8: one distinct, stable colour per point id (golden-ratio hues)."""
    hue = (np.arange(num_points) * 0.618033988749895) % 1.0
    # HSV -> RGB with s = 0.75, v = 0.95
    k = (np.array([5.0, 3.0, 1.0])[None, :] + hue[:, None] * 6.0) % 6.0
    rgb = 0.95 - 0.95 * 0.75 * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return np.round(rgb * 255).astype(np.uint8)


def frame_file_stem(rank: int, image_name: str, num_images: int) -> str:
    """``NNNNN_<stem>``: zero-padded rank, then the image name without extension, with ``/``
    and other characters unsafe in file names replaced by ``_`` (``cam01/0012.jpg`` ->
    ``cam01_0012``: a bare stem would collide across camera folders)."""
    width = max(5, len(str(max(num_images - 1, 0))))
    stem = str(Path(image_name).with_suffix("")).replace("\\", "/")
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", stem).strip("_") or "image"
    return f"{rank:0{width}d}_{stem}"


def solved_capture(capture: Capture, result: Result) -> Capture:
    """The (N, P', 2) observations ``result.X`` refers to: ``result.solved`` when the solver
    made one (subjects aggregated, left/right swaps undone, stream offsets taken out), else
    ``capture`` itself, less ``result.offset_px`` when a result file holds them."""
    if result.solved is not None:
        return result.solved
    if result.offset_px is not None and result.offset_px.shape == capture.x.shape:
        return without_offsets(capture, result.offset_px)
    return capture


def column_ids(result: Result) -> tuple[np.ndarray, np.ndarray]:
    """(P',) subject id and (P',) layout point id of every column of ``result.X``; one subject:
    subject 0 and the column index."""
    if result.subject_id is None:
        return (np.zeros(result.X.shape[1], dtype=np.int64),
                np.arange(result.X.shape[1], dtype=np.int64))
    return result.subject_id.astype(np.int64), result.point_id.astype(np.int64)


def column_labels(result: Result, point_names: list[str] | None) -> list[str]:
    """(P',) label of every column of ``result.X``: its layout point's name in ``point_names``
    (the point id without), ``s<subject>_`` before it with several subjects (one subject found
    among several people's detections keeps the plain names: OpenSim's marker set)."""
    subject_id, point_id = column_ids(result)
    names = [str(j) if point_names is None else point_names[j] for j in point_id]
    if result.subject_id is None or np.unique(subject_id).size < 2:
        return names
    return [f"s{k}_{name}" for k, name in zip(subject_id, names, strict=True)]


def column_edges(edges: np.ndarray, subject_id: np.ndarray, point_id: np.ndarray) -> np.ndarray:
    """(E', 2) skeleton edges between columns of X: the layout's (E, 2) edges between point ids,
    repeated for every subject (subject_id, point_id (P',) as from ``column_ids``)."""
    column = {(int(s), int(j)): k for k, (s, j) in enumerate(zip(subject_id, point_id,
                                                                   strict=True))}
    out = [(column[s, int(a)], column[s, int(b)])
           for s in np.unique(subject_id).tolist()
           for a, b in np.asarray(edges, dtype=np.int64).reshape(-1, 2)
           if (s, int(a)) in column and (s, int(b)) in column]
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)
