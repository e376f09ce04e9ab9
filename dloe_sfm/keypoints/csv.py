"""CSV keypoints: a header, then one row per observed point.

Columns (by header name, any order): ``image``, ``point_id``, ``x``, ``y`` and optionally
``score`` (default 1; 0 = missing) and ``person`` (default 0). ``image`` is matched to workspace
images by ``base.match_names`` (the exact COLMAP image name always works). Errors name the file
and line.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from .base import Keypoints, Layout, get_layout, named_layout, stack_people

REQUIRED = ("image", "point_id", "x", "y")


def _number(text: str, column: str, where: str, kind: type = float) -> float:
    try:
        value = kind(text)
    except ValueError:
        raise InputError(f"{where}: column '{column}' is not a number ({text!r})") from None
    if not math.isfinite(value):
        raise InputError(f"{where}: column '{column}' is NaN or infinite ({text!r})")
    return value


def read(path: Path, *, layout: str | Layout | None = None, num_points: int | None = None
         ) -> Keypoints:
    """Read a keypoint CSV; the number of points is ``num_points``, the layout's, or the largest
    point_id + 1."""
    if isinstance(layout, str):
        layout = named_layout(layout, path)
    if layout is not None and num_points is None:
        num_points = layout.num_points
    rows: dict[tuple[str, int, int], tuple[float, float, float]] = {}
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            header = [h.strip().lower() for h in next(reader, [])]
            missing = [c for c in REQUIRED if c not in header]
            if missing:
                raise InputError(f"{path}:1: header lacks column(s) {', '.join(missing)}")
            col = {name: header.index(name) for name in (*REQUIRED, "score", "person")
                   if name in header}
            for row in reader:
                where = f"{path}:{reader.line_num}"
                if not row or all(not c.strip() for c in row):
                    continue
                if len(row) != len(header):
                    raise InputError(f"{where}: {len(row)} fields, the header has {len(header)}")
                image = row[col["image"]].strip()
                if not image:
                    raise InputError(f"{where}: empty image name")
                pid = _number(row[col["point_id"]], "point_id", where, int)
                person = _number(row[col["person"]], "person", where, int) if "person" in col \
                    else 0
                if pid < 0 or (num_points is not None and pid >= num_points):
                    bound = f"0..{num_points - 1}" if num_points is not None else ">= 0"
                    raise InputError(f"{where}: point_id {pid} out of range {bound}")
                if person < 0:
                    raise InputError(f"{where}: person {person} is negative")
                x = _number(row[col["x"]], "x", where)
                y = _number(row[col["y"]], "y", where)
                score = _number(row[col["score"]], "score", where) if "score" in col else 1.0
                if (image, person, pid) in rows:
                    raise InputError(
                        f"{where}: point {pid} of person {person} in '{image}' given twice"
                    )
                rows[(image, person, pid)] = (x, y, score)
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not a UTF-8 text file ({e.reason})") from None
    except csv.Error as e:
        raise InputError(f"{path}: malformed CSV ({e})") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e})") from None
    if not rows:
        raise InputError(f"{path}: no keypoint rows")
    if num_points is None:
        num_points = max(pid for _, _, pid in rows) + 1
    layout = get_layout(layout, num_points, path)
    people: dict[str, dict[int, np.ndarray]] = {}
    for (image, person, pid), value in rows.items():
        per = people.setdefault(image, {})
        per.setdefault(person, np.tile([np.nan, np.nan, 0.0], (num_points, 1)))[pid] = value
    points = {
        image: stack_people([per.get(m, np.tile([np.nan, np.nan, 0.0], (num_points, 1)))
                             for m in range(max(per) + 1)], num_points)
        for image, per in people.items()
    }
    return Keypoints(layout=layout, points=points, source=path)
