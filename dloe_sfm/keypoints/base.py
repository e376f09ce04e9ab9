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

from ..errors import InputError
from ..images import IMAGE_SUFFIXES, natural_key

if TYPE_CHECKING:
    from ..colmap import Workspace

logger = logging.getLogger("dloe_sfm")

# Most points per detection: far above any skeleton or marker board, it keeps a file's ids
# (e.g. a CSV point_id of 1e9) from sizing an array.
MAX_POINTS = 100_000
# Control characters (line breaks included) shown escaped, so a message naming them is one line.
_ESCAPES = {c: repr(chr(c))[1:-1] for c in (*range(0x20), *range(0x7F, 0xA0), 0x2028, 0x2029)}
_KINDS = {dict: "an object", list: "a list", str: "a string", int: "an integer", float: "a number"}


def shown(text: object) -> str:
    """``text`` for a message: control characters escaped (``\\n``), so it stays one line."""
    return str(text).translate(_ESCAPES)


def quoted(name: object) -> str:
    """A name (image, key) quoted for a message, control characters escaped."""
    return repr(str(name))


def brief(value: object, limit: int = 40) -> str:
    """A short one-line rendering of a parsed value for messages: scalars as repr, else the
    JSON type ("a list")."""
    if isinstance(value, (str, int, float)) or value is None:
        try:
            text = repr(value)
        except ValueError:  # an integer too long to print
            return "a huge integer"
        return shown(text if len(text) <= limit else text[:limit] + "...")
    return _KINDS.get(type(value), type(value).__name__)


def expect(value, kind: type | tuple[type, ...], where: str):
    """``value`` when it is of JSON type ``kind`` (bools are not numbers); else InputError
    "``where`` must be <kind>, got <value>"."""
    if isinstance(value, kind) and not isinstance(value, bool):
        return value
    kinds = kind if isinstance(kind, tuple) else (kind,)
    raise InputError(f"{where} must be {' or '.join(_KINDS[k] for k in kinds)}, "
                     f"got {brief(value)}")


def as_int(value) -> int | None:
    """An integer given as a JSON integer, an integral number or a string of digits, else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return int(value) if value.is_integer() else None
    if isinstance(value, str):
        try:
            return int(value)
        except ValueError:
            return None
    return None


def check_count(value, name: str, most: int) -> None:
    """InputError unless reader option ``name`` is an integer in 1..``most``."""
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= most:
        raise InputError(f"{name} must be an integer in 1..{most}, got {brief(value)}")


def index_pairs(value, num_points: int, where: str, *, base: int = 0, distinct: bool = False
                ) -> list[tuple[int, int]]:
    """A JSON list of ``[a, b]`` point indices (``base`` 1: COCO's 1-based skeleton) as 0-based
    pairs in 0..num_points - 1 (of two different points if ``distinct``); anything else raises
    InputError naming ``where``."""
    pairs = []
    for k, pair in enumerate(expect(value, list, where)):
        ab = [as_int(v) for v in pair] if isinstance(pair, list) and len(pair) == 2 else [None]
        if None in ab:
            raise InputError(f"{where}[{k}] must be a pair of point indices, got {brief(pair)}")
        a, b = (v - base for v in ab)
        if not (0 <= a < num_points and 0 <= b < num_points):
            raise InputError(f"{where}[{k}] ({a + base}, {b + base}) out of range "
                             f"{base}..{num_points - 1 + base}")
        if distinct and a == b:
            raise InputError(f"{where}[{k}] pairs point {a + base} with itself")
        pairs.append((a, b))
    return pairs


def point_names(value, where: str) -> list[str]:
    """A non-empty JSON list of point names (strings or numbers) of at most ``MAX_POINTS``."""
    names = expect(value, list, where)
    if not 1 <= len(names) <= MAX_POINTS:
        raise InputError(f"{where} must list 1..{MAX_POINTS} point names, got {len(names)}")
    for i, n in enumerate(names):
        expect(n, (str, int, float), f"{where}[{i}]")
    return [str(n) for n in names]


@dataclass
class Layout:
    """Named points and their skeleton: ``edges`` and left/right ``symmetric_pairs`` index
    ``point_names``.

    ``source_points``: files may also hold this many points per detection, of which the layout
    keeps the first ``num_points`` (``Keypoints`` drops the rest, described by ``dropped``):
    COCO-WholeBody's 133 points, of which body and feet come first.
    """

    name: str
    point_names: list[str]
    edges: list[tuple[int, int]] = field(default_factory=list)
    symmetric_pairs: list[tuple[int, int]] = field(default_factory=list)
    source_points: int | None = None
    dropped: str = "the other points"

    @property
    def num_points(self) -> int:
        return len(self.point_names)

    def __post_init__(self) -> None:
        p = len(self.point_names)
        if self.source_points is not None and self.source_points <= p:
            raise InputError(f"layout {shown(self.name)}: source_points {self.source_points} "
                             f"must exceed its {p} points")
        for kind, pairs in (("edge", self.edges), ("symmetric pair", self.symmetric_pairs)):
            for a, b in pairs:
                if not (0 <= a < p and 0 <= b < p):
                    raise InputError(
                        f"layout {shown(self.name)}: {kind} ({a}, {b}) out of range 0..{p - 1}"
                    )
        if any(a == b for a, b in self.symmetric_pairs):
            raise InputError(f"layout {shown(self.name)}: a symmetric pair joins a point to "
                             "itself")

    def subset(self, keep: list[int]) -> Layout:
        """The layout of the points ``keep`` (indices, in order), renumbered: edges and pairs
        between kept points only."""
        new = {int(j): k for k, j in enumerate(keep)}
        return Layout(
            name=self.name, point_names=[self.point_names[j] for j in new],
            edges=[(new[a], new[b]) for a, b in self.edges if a in new and b in new],
            symmetric_pairs=[(new[a], new[b]) for a, b in self.symmetric_pairs
                             if a in new and b in new],
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

    def __post_init__(self) -> None:
        """Detections of the layout's ``source_points`` keep only its first points."""
        full, p = self.layout.source_points, self.layout.num_points
        if full is None or not any(v.shape[-2] == full for v in self.points.values()):
            return
        self.points = {k: v[..., :p, :].copy() if v.shape[-2] == full else v
                       for k, v in self.points.items()}
        logger.info("%s: layout %s keeps the first %d of %d points per detection (%s "
                    "dropped)", shown(self.source or "keypoints"), self.layout.name, p, full,
                    self.layout.dropped)


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


def _layout(name: str, names: list[str], edges: list[tuple[int, int]], left: str, right: str,
            **extra) -> Layout:
    return Layout(name=name, point_names=names, edges=edges,
                  symmetric_pairs=_mirror_pairs(names, left, right), **extra)


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
# the 17 COCO points under Pose2Sim's marker names (its skeletons.py, HALPE_26 and COCO_133)
_COCO_BODY = [
    "Nose", "LEye", "REye", "LEar", "REar", "LShoulder", "RShoulder", "LElbow", "RElbow",
    "LWrist", "RWrist", "LHip", "RHip", "LKnee", "RKnee", "LAnkle", "RAnkle",
]
# AlphaPose / RTMPose body with feet (MMPose's halpe26 dataset; Pose2Sim's default)
_HALPE_26 = [
    *_COCO_BODY, "Head", "Neck", "Hip", "LBigToe", "RBigToe", "LSmallToe", "RSmallToe",
    "LHeel", "RHeel",
]
# MMPose's halpe26 skeleton_info
_HALPE_26_EDGES = [
    (15, 13), (13, 11), (11, 19), (16, 14), (14, 12), (12, 19), (17, 18), (18, 19), (18, 5),
    (5, 7), (7, 9), (18, 6), (6, 8), (8, 10), (1, 2), (0, 1), (0, 2), (1, 3), (2, 4), (3, 5),
    (4, 6), (15, 20), (15, 22), (15, 24), (16, 21), (16, 23), (16, 25),
]
# COCO-WholeBody's first 23 of 133 points: body, then the feet (face and hands follow)
_COCO_WHOLEBODY = [
    *_COCO_BODY, "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel",
]
_COCO_WHOLEBODY_EDGES = [
    *_COCO_17_EDGES, (15, 17), (15, 18), (15, 19), (16, 20), (16, 21), (16, 22),
]
# MediaPipe Pose (BlazePose): PoseLandmark in lower case, and POSE_CONNECTIONS (the face is
# not linked to the body)
_MEDIAPIPE_33 = [
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
    "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
    "right_heel", "left_foot_index", "right_foot_index",
]
_MEDIAPIPE_33_EDGES = [
    (0, 1), (1, 2), (2, 3), (3, 7), (0, 4), (4, 5), (5, 6), (6, 8), (9, 10), (11, 12),
    (11, 13), (13, 15), (15, 17), (15, 19), (15, 21), (17, 19), (12, 14), (14, 16), (16, 18),
    (16, 20), (16, 22), (18, 20), (11, 23), (12, 24), (23, 24), (23, 25), (24, 26), (25, 27),
    (26, 28), (27, 29), (28, 30), (29, 31), (30, 32), (27, 31), (28, 32),
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
    "HALPE_26": _layout("HALPE_26", _HALPE_26, _HALPE_26_EDGES, "L", "R"),
    "COCO_WHOLEBODY": _layout("COCO_WHOLEBODY", _COCO_WHOLEBODY, _COCO_WHOLEBODY_EDGES, "L", "R",
                              source_points=133, dropped="face and hands"),
    "MEDIAPIPE_33": Layout(
        "MEDIAPIPE_33", _MEDIAPIPE_33, _MEDIAPIPE_33_EDGES,
        _mirror_pairs(_MEDIAPIPE_33, "left_", "right_") + [(9, 10)],  # mouth_left, _right
    ),
}
# other names of LAYOUTS entries (Pose2Sim's)
ALIASES = {"COCO_133": "COCO_WHOLEBODY", "BLAZEPOSE": "MEDIAPIPE_33"}


def _name_key(name: str) -> str:
    """A point name compared across conventions: lower case, letters and digits only, a
    leading "left" / "right" shortened to "l" / "r" (MMPose's left_big_toe = LBigToe)."""
    key = "".join(c for c in name.lower() if c.isalnum())
    for side in ("left", "right"):
        if key.startswith(side):
            key = side[0] + key[len(side):]
    return key


def known_layout(names: list[str]) -> Layout | None:
    """The layout of ``LAYOUTS`` whose point names are ``names`` (all of them, or the first
    ones of its ``source_points``) by ``_name_key``, e.g. an MMPose halpe26 or
    coco_wholebody file's; else None."""
    keys = [_name_key(n) for n in names]
    for layout in LAYOUTS.values():
        p = layout.num_points
        if (len(keys) in (p, layout.source_points)
                and keys[:p] == [_name_key(n) for n in layout.point_names]):
            return layout
    return None


def named_layout(name: str, source: Path | str) -> Layout:
    """A layout of ``LAYOUTS`` or ``ALIASES`` by name (case and '-' / '_' insensitive)."""
    key = name.upper().replace("-", "_")
    key = ALIASES.get(key, key)
    if key not in LAYOUTS:
        raise InputError(f"{shown(source)}: unknown layout {brief(name)} "
                         f"(known: {', '.join(LAYOUTS)})")
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
    where = shown(spec)
    names = data.get("point_names") if isinstance(data, dict) else None
    if not isinstance(names, list) or not names:
        raise InputError(f"{where}: a layout needs a non-empty 'point_names' list")
    names = point_names(names, f"{where}: 'point_names'")
    pairs = {key: index_pairs(data.get(key, []), len(names), f"{where}: '{key}'",
                              distinct=key == "symmetric_pairs")
             for key in ("edges", "symmetric_pairs")}
    name = expect(data.get("name", Path(spec).stem), (str, int, float), f"{where}: 'name'")
    return Layout(name=str(name), point_names=names, **pairs)


def get_layout(layout: str | Layout | None, num_points: int, source: Path | str) -> Layout:
    """A layout by name (``LAYOUTS``), as given, or generic; its size (or its
    ``source_points``) must be ``num_points``."""
    if not 1 <= num_points <= MAX_POINTS:
        raise InputError(f"{shown(source)}: {num_points} points per detection "
                         f"(expected 1..{MAX_POINTS})")
    if layout is None:
        return generic_layout(num_points)
    if isinstance(layout, str):
        layout = named_layout(layout, source)
    if num_points not in (layout.num_points, layout.source_points):
        full = f" (or {layout.source_points})" if layout.source_points else ""
        raise InputError(f"{shown(source)}: layout {shown(layout.name)} has "
                         f"{layout.num_points}{full} points, the data {num_points}")
    return layout


def read_json(path: Path):
    """Parsed JSON (UTF-8, a byte order mark allowed); malformed, too deeply nested, not UTF-8 or
    unreadable -> InputError naming the file (and line). Callers check the types they read
    (``expect``)."""
    try:
        with open(path, encoding="utf-8-sig") as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        raise InputError(f"{shown(path)}: malformed JSON at line {e.lineno} ({e.msg})") from None
    except RecursionError:
        raise InputError(f"{shown(path)}: JSON nested too deeply") from None
    except UnicodeDecodeError as e:
        raise InputError(f"{shown(path)}: not a UTF-8 text file ({e.reason} at byte "
                         f"{e.start})") from None
    except ValueError as e:  # e.g. an integer literal of thousands of digits
        raise InputError(f"{shown(path)}: unreadable JSON ({shown(e).split(':')[0]})") from None
    except OSError as e:
        raise InputError(f"{shown(path)}: cannot read ({shown(e.strerror or e)})") from None


def json_files(path: Path) -> list[Path]:
    """``path`` itself, or every ``*.json`` below the folder ``path`` (sorted)."""
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise InputError(f"{shown(path)}: not a file or folder")
    files = sorted(p for p in path.rglob("*.json") if p.is_file())
    if not files:
        raise InputError(f"{shown(path)}: no .json files in the folder")
    return files


def file_key(file: Path, root: Path) -> str:
    """Key of a per-image keypoint file: POSIX path relative to ``root`` without the suffix and
    a trailing ``_keypoints`` (OpenPose), e.g. ``cam01_json/cam01.0012``."""
    rel = file.relative_to(root) if file != root else PurePosixPath(file.name)
    key = PurePosixPath(rel).with_suffix("").as_posix()
    return key.removesuffix("_keypoints")


def _holds_bool(values) -> bool:
    """Whether nested lists ``values`` hold a bool (numpy reads ``true`` as 1)."""
    stack = [values]
    while stack:
        value = stack.pop()
        if isinstance(value, bool):
            return True
        if isinstance(value, list):
            stack.extend(value)
    return False


def as_points(values, num_points: int, source: str, *, columns: int = 3, nested: bool = False
              ) -> np.ndarray:
    """(num_points, columns) float64 from a flat JSON list of num_points x columns numbers
    (``nested``: a list of num_points lists of ``columns`` numbers); anything else (strings,
    booleans, other shapes), NaN and inf raise InputError naming ``source``."""
    try:
        arr = np.asarray(values)
    except (TypeError, ValueError, OverflowError, RecursionError):
        arr = None
    if arr is None or arr.dtype.kind not in "iuf" or _holds_bool(values):
        raise InputError(f"{shown(source)}: keypoints are not a list of numbers")
    shape = (num_points, columns) if nested else (num_points * columns,)
    if arr.shape != shape:
        want = (f"{num_points} lists of {columns} numbers" if nested
                else f"a flat list of {num_points} x {columns} numbers")
        raise InputError(f"{shown(source)}: expected {want}, got shape {arr.shape}")
    arr = arr.astype(np.float64).reshape(num_points, columns)
    if not np.isfinite(arr).all():
        raise InputError(f"{shown(source)}: keypoint coordinates or scores are NaN or "
                         "infinite")
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
    3. the file stem of exactly one image equals the key's last path component, also by value
       (``cam01_json/cam01.0012`` -> ``cam01/cam01.0012.png``); a stem several images share
       (``cam9/003`` beside ``cam0/003.jpg`` and ``cam1/003.jpg``) matches none of them.

    A key matching several images by rule 1 or 2, or two keys matching one image, raises
    InputError.
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
        for rule, (table, lookup) in enumerate(zip(tables, lookups, strict=True)):
            hits = set().union(*(table.get(lookup(c), set()) for c in candidates))
            if len(hits) > 1 and rule == 2:
                hits = set()  # a shared stem says nothing: the key matches no image
            if hits:
                break
        if len(hits) > 1:
            some = ", ".join(quoted(h) for h in sorted(hits)[:3])
            raise InputError(f"{shown(source)}: keypoints {quoted(key)} match several images "
                             f"({some})")
        out[key] = next(iter(hits)) if hits else key
    seen: dict[str, str] = {}
    for key, name in out.items():
        if name in seen:
            raise InputError(f"{shown(source)}: keypoints {quoted(seen[name])} and {quoted(key)} "
                             f"both match image {quoted(name)}")
        seen[name] = key
    return out


def rename_to_workspace(kp: Keypoints, workspace: Workspace) -> Keypoints:
    """The same keypoints keyed by workspace image names (registered or not, see
    ``match_names``); keys matching no image are kept as they are."""
    names = list(workspace.image_names) + list(workspace.unregistered)
    mapping = match_names(list(kp.points), names, kp.source or "keypoints")
    matched = sum(1 for k, v in mapping.items() if k != v or v in names)
    logger.info("%s: keypoints of %d image(s), %d matched to workspace images",
                shown(kp.source), len(mapping), matched)
    return Keypoints(layout=kp.layout, points={mapping[k]: v for k, v in kp.points.items()},
                     source=kp.source)


def stack_people(people: list[np.ndarray], num_points: int) -> np.ndarray:
    """(M, P, 3) from a list of (P, 3) arrays; scores <= 0 become missing (NaN x, y, score 0)."""
    return mark_missing(np.stack(people) if people else np.zeros((0, num_points, 3)))


def mark_missing(arr: np.ndarray) -> np.ndarray:
    """(..., P, 3) ``arr`` with points of score <= 0 set missing (NaN x, y, score 0), in place."""
    arr[~(arr[..., 2] > 0)] = (np.nan, np.nan, 0.0)
    return arr
