"""Common types of the keypoint adapters: layouts (joint names, skeleton), keypoints, name matching.

Pixel convention of every adapter: (0, 0) = centre of the top-left pixel (OpenPose, COCO,
MMPose, OpenCV); COLMAP's is (0.5, 0.5), the half pixel is added in ``observations``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING

import numpy as np

from ..colmap import IMAGE_SUFFIXES, natural_key
from ..errors import InputError

if TYPE_CHECKING:
    from ..colmap import Workspace

logger = logging.getLogger("dloe_sfm")


@dataclass
class Layout:
    """Named points and their skeleton: ``edges`` and left/right ``symmetric_pairs`` index
    ``point_names``."""

    name: str
    point_names: list[str]
    edges: list[tuple[int, int]] = field(default_factory=list)
    symmetric_pairs: list[tuple[int, int]] = field(default_factory=list)

    @property
    def num_points(self) -> int:
        return len(self.point_names)

    def __post_init__(self) -> None:
        p = len(self.point_names)
        for kind, pairs in (("edge", self.edges), ("symmetric pair", self.symmetric_pairs)):
            for a, b in pairs:
                if not (0 <= a < p and 0 <= b < p):
                    raise InputError(
                        f"layout {self.name}: {kind} ({a}, {b}) out of range 0..{p - 1}"
                    )


@dataclass
class Keypoints:
    """2D points per image.

    ``points[image_name]`` is (M, P, 3) float64: x, y, score of M detected people (or marker
    sets), pixel convention (0, 0) = centre of the top-left pixel; NaN or score 0 = missing.
    Keys are workspace image names once matched (see ``match_names``), else the adapter's keys.
    """

    layout: Layout
    points: dict[str, np.ndarray]
    source: Path | None = None

    @property
    def num_points(self) -> int:
        return self.layout.num_points


def generic_layout(num_points: int, name: str = "points") -> Layout:
    """A layout of ``num_points`` points named p0, p1, ... without a skeleton."""
    return Layout(name=name, point_names=[f"p{i}" for i in range(num_points)])


def _mirror_pairs(names: list[str], left: str, right: str) -> list[tuple[int, int]]:
    index = {n: i for i, n in enumerate(names)}
    pairs = []
    for i, n in enumerate(names):
        if n.startswith(left) and n.replace(left, right, 1) in index:
            pairs.append((i, index[n.replace(left, right, 1)]))
    return pairs


def _layout(name: str, names: list[str], edges: list[tuple[int, int]], left: str, right: str
            ) -> Layout:
    return Layout(name=name, point_names=names, edges=edges,
                  symmetric_pairs=_mirror_pairs(names, left, right))


_BODY_25 = [
    "Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "MidHip",
    "RHip", "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar",
    "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel",
]
_BODY_25B = [
    "Nose", "LEye", "REye", "LEar", "REar", "LShoulder", "RShoulder", "LElbow", "RElbow",
    "LWrist", "RWrist", "LHip", "RHip", "LKnee", "RKnee", "LAnkle", "RAnkle", "UpperNeck",
    "HeadTop", "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel",
]
_COCO_18 = [
    "Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "RHip",
    "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar",
]
_COCO_17 = [
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip",
    "left_knee", "right_knee", "left_ankle", "right_ankle",
]
# skeleton edges as OpenPose / COCO render them
_COCO_17_EDGES = [
    (15, 13), (13, 11), (16, 14), (14, 12), (11, 12), (5, 11), (6, 12), (5, 6), (5, 7), (6, 8),
    (7, 9), (8, 10), (1, 2), (0, 1), (0, 2), (1, 3), (2, 4), (3, 5), (4, 6),
]

LAYOUTS: dict[str, Layout] = {
    "BODY_25": _layout("BODY_25", _BODY_25, [
        (1, 8), (1, 2), (1, 5), (2, 3), (3, 4), (5, 6), (6, 7), (8, 9), (9, 10), (10, 11),
        (8, 12), (12, 13), (13, 14), (1, 0), (0, 15), (15, 17), (0, 16), (16, 18), (14, 19),
        (19, 20), (14, 21), (11, 22), (22, 23), (11, 24),
    ], "L", "R"),
    "BODY_25B": _layout("BODY_25B", _BODY_25B, [
        (0, 1), (0, 2), (1, 3), (2, 4), (5, 7), (6, 8), (7, 9), (8, 10), (5, 11), (6, 12),
        (11, 13), (12, 14), (13, 15), (14, 16), (15, 19), (19, 20), (15, 21), (16, 22),
        (22, 23), (16, 24), (5, 17), (6, 17), (17, 18), (11, 12), (0, 17),
    ], "L", "R"),
    "COCO_18": _layout("COCO_18", _COCO_18, [
        (1, 2), (1, 5), (2, 3), (3, 4), (5, 6), (6, 7), (1, 8), (8, 9), (9, 10), (1, 11),
        (11, 12), (12, 13), (1, 0), (0, 14), (14, 16), (0, 15), (15, 17),
    ], "L", "R"),
    "COCO_17": _layout("COCO_17", _COCO_17, _COCO_17_EDGES, "left_", "right_"),
}


def named_layout(name: str, source: Path | str) -> Layout:
    """A layout of ``LAYOUTS`` by name (case and '-' / '_' insensitive)."""
    key = name.upper().replace("-", "_")
    if key not in LAYOUTS:
        raise InputError(f"{source}: unknown layout '{name}' (known: {', '.join(LAYOUTS)})")
    return LAYOUTS[key]


def load_layout(spec: str | Path | Layout) -> Layout:
    """A layout as given, from a JSON file (``*.json``: ``{"name": ..., "point_names": [...],
    "edges": [[a, b], ...], "symmetric_pairs": [[a, b], ...]}``, indices into point_names,
    edges and pairs optional) or by name (``LAYOUTS``)."""
    if isinstance(spec, Layout):
        return spec
    if Path(spec).suffix.lower() != ".json":
        return named_layout(str(spec), "layout")
    data = read_json(Path(spec))
    names = data.get("point_names") if isinstance(data, dict) else None
    if not isinstance(names, list) or not names:
        raise InputError(f"{spec}: a layout needs a non-empty 'point_names' list")
    try:
        pairs = {key: [(int(a), int(b)) for a, b in data.get(key, [])]
                 for key in ("edges", "symmetric_pairs")}
    except (TypeError, ValueError):
        raise InputError(f"{spec}: 'edges' and 'symmetric_pairs' must be lists of index "
                         "pairs") from None
    return Layout(name=str(data.get("name", Path(spec).stem)),
                  point_names=[str(n) for n in names], **pairs)


def get_layout(layout: str | Layout | None, num_points: int, source: Path | str) -> Layout:
    """A layout by name (``LAYOUTS``), as given, or generic; its size must be ``num_points``."""
    if layout is None:
        return generic_layout(num_points)
    if isinstance(layout, str):
        layout = named_layout(layout, source)
    if layout.num_points != num_points:
        raise InputError(
            f"{source}: layout {layout.name} has {layout.num_points} points, the data {num_points}"
        )
    return layout


def read_json(path: Path):
    """Parsed JSON; malformed or unreadable -> InputError naming the file (and line)."""
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: malformed JSON at line {e.lineno} ({e.msg})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read ({e})") from None


def json_files(path: Path) -> list[Path]:
    """``path`` itself, or every ``*.json`` below the folder ``path`` (sorted)."""
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise InputError(f"{path}: no such file or folder")
    files = sorted(path.rglob("*.json"))
    if not files:
        raise InputError(f"{path}: no .json files in the folder")
    return files


def file_key(file: Path, root: Path) -> str:
    """Key of a per-image keypoint file: POSIX path relative to ``root`` without the suffix and
    a trailing ``_keypoints`` (OpenPose), e.g. ``cam01_json/cam01.0012``."""
    rel = file.relative_to(root) if file != root else PurePosixPath(file.name)
    key = PurePosixPath(rel).with_suffix("").as_posix()
    return key.removesuffix("_keypoints")


def as_points(values, num_points: int, source: str, *, columns: int = 3) -> np.ndarray:
    """A flat or nested list of numbers as (num_points, columns) float64; NaN/inf and wrong sizes
    raise InputError naming ``source``."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{source}: keypoints are not a list of numbers") from None
    if arr.size != num_points * columns:
        raise InputError(
            f"{source}: expected {num_points} x {columns} keypoint values, got {arr.size}"
        )
    arr = arr.reshape(num_points, columns)
    if not np.isfinite(arr).all():
        raise InputError(f"{source}: keypoint coordinates or scores are NaN or infinite")
    return arr


def _strip_image_suffix(name: str) -> str:
    p = PurePosixPath(name)
    return p.with_suffix("").as_posix() if p.suffix.lower() in IMAGE_SUFFIXES else name


def match_names(keys: list[str], names: list[str], source: Path | str) -> dict[str, str]:
    """Map keypoint keys to image names; unmatched keys map to themselves.

    Rules, first that matches wins (the suffix is dropped only when it is an image suffix):

    1. the image name, with or without its suffix, equals the key with or without its suffix
       (``cam01/0012`` -> ``cam01/0012.jpg``);
    2. the same with numbers compared by value (``video/12`` -> ``video/000012.png``);
    3. the image's file stem equals the key's last path component, also by value
       (``cam01_json/cam01.0012`` -> ``cam01/cam01.0012.png``).

    A key matching several images, or two keys matching one image, raises InputError.
    """
    tables: list[dict] = [{}, {}, {}]
    for n in names:
        bare = _strip_image_suffix(n)
        for k in (n, bare):
            tables[0].setdefault(k, set()).add(n)
            tables[1].setdefault(natural_key(k), set()).add(n)
        tables[2].setdefault(natural_key(PurePosixPath(bare).name), set()).add(n)
    # natural_key compares digit runs by value: 'f0012' == 'f12'
    lookups = (lambda c: c, natural_key, lambda c: natural_key(PurePosixPath(c).name))
    out: dict[str, str] = {}
    for key in keys:
        k = key.replace("\\", "/")
        candidates = (k, _strip_image_suffix(k))
        hits: set[str] = set()
        for table, lookup in zip(tables, lookups, strict=True):
            hits = set().union(*(table.get(lookup(c), set()) for c in candidates))
            if hits:
                break
        if len(hits) > 1:
            some = ", ".join(f"'{h}'" for h in sorted(hits)[:3])
            raise InputError(f"{source}: keypoints '{key}' match several images ({some})")
        out[key] = next(iter(hits)) if hits else key
    seen: dict[str, str] = {}
    for key, name in out.items():
        if name in seen:
            raise InputError(
                f"{source}: keypoints '{seen[name]}' and '{key}' both match image '{name}'"
            )
        seen[name] = key
    return out


def rename_to_workspace(kp: Keypoints, workspace: Workspace) -> Keypoints:
    """The same keypoints keyed by workspace image names (registered or not, see
    ``match_names``); keys matching no image are kept as they are."""
    names = list(workspace.image_names) + list(workspace.unregistered)
    mapping = match_names(list(kp.points), names, kp.source or "keypoints")
    matched = sum(1 for k, v in mapping.items() if k != v or v in names)
    logger.info("%s: keypoints of %d image(s), %d matched to workspace images",
                kp.source, len(mapping), matched)
    return Keypoints(layout=kp.layout, points={mapping[k]: v for k, v in kp.points.items()},
                     source=kp.source)


def stack_people(people: list[np.ndarray], num_points: int) -> np.ndarray:
    """(M, P, 3) from a list of (P, 3) arrays; scores <= 0 become missing (NaN x, y, score 0)."""
    arr = np.stack(people) if people else np.zeros((0, num_points, 3))
    missing = ~(arr[..., 2] > 0)
    arr[missing] = (np.nan, np.nan, 0.0)
    return arr
