"""CSV keypoints: a header, then one row per observed point.

Columns (by header name, any order, case-insensitive): ``image``, ``point_id``, ``x``, ``y`` and
optionally ``score`` (default 1; 0 = missing) and ``person`` (the detection's index in its
image, default 0). UTF-8, with or without a byte order mark; any line ending; quoted fields may
hold commas and line breaks. ``image`` is matched to workspace images by ``base.match_names``
(the exact COLMAP image name always works). Errors name the file and line.

Ids size arrays, so they are bounded before anything is allocated: ``point_id`` < the layout's
points or ``source_points`` (or ``base.MAX_POINTS`` without a layout), ``person`` <
``MAX_PEOPLE``, and the dense (people x points) arrays at most ``SPARSITY`` entries per row of
the file (or ``MIN_ENTRIES``).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from .base import (
    MAX_POINTS,
    Keypoints,
    Layout,
    brief,
    check_count,
    get_layout,
    mark_missing,
    named_layout,
    quoted,
    shown,
)

REQUIRED = ("image", "point_id", "x", "y")
MAX_PEOPLE = 1000  # detections of one image
SPARSITY, MIN_ENTRIES = 100, 1_000_000


def _number(text: str, column: str, where: str, kind: type = float) -> float:
    try:
        value = kind(text)
    except ValueError:
        what = "an integer" if kind is int else "a number"
        raise InputError(f"{where}: column '{column}' is not {what} ({brief(text)})") from None
    if not math.isfinite(value):
        raise InputError(f"{where}: column '{column}' is NaN or infinite ({brief(text)})")
    return value


def _rows(path: Path, num_points: int | None
          ) -> dict[tuple[str, int, int], tuple[float, float, float]]:
    """{(image, person, point_id): (x, y, score)} of every row of the file."""
    bound = num_points if num_points is not None else MAX_POINTS
    where = shown(path)
    rows: dict[tuple[str, int, int], tuple[float, float, float]] = {}
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.reader(f)
        header = [h.strip().lower() for h in next(reader, [])]
        missing = [c for c in REQUIRED if c not in header]
        if missing:
            raise InputError(f"{where}:1: header lacks column(s) {', '.join(missing)}")
        col = {name: header.index(name) for name in (*REQUIRED, "score", "person")
               if name in header}
        twice = [name for name in col if header.count(name) > 1]
        if twice:
            raise InputError(f"{where}:1: header repeats column(s) {', '.join(twice)}")
        start = reader.line_num + 1  # a quoted line break makes a row span several lines
        for row in reader:
            line, start = f"{where}:{start}", reader.line_num + 1
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise InputError(f"{line}: {len(row)} fields, the header has {len(header)}")
            image = row[col["image"]].strip()
            if not image:
                raise InputError(f"{line}: empty image name")
            pid = _number(row[col["point_id"]], "point_id", line, int)
            person = _number(row[col["person"]], "person", line, int) if "person" in col else 0
            if not 0 <= pid < bound:
                raise InputError(f"{line}: point_id {pid} out of range 0..{bound - 1}")
            if not 0 <= person < MAX_PEOPLE:
                raise InputError(f"{line}: person {person} out of range 0..{MAX_PEOPLE - 1} "
                                 "(the index of the detection in its image)")
            x = _number(row[col["x"]], "x", line)
            y = _number(row[col["y"]], "y", line)
            score = _number(row[col["score"]], "score", line) if "score" in col else 1.0
            if (image, person, pid) in rows:
                raise InputError(
                    f"{line}: point {pid} of person {person} in {quoted(image)} given twice"
                )
            rows[(image, person, pid)] = (x, y, score)
    return rows


def read(path: Path, *, layout: str | Layout | None = None, num_points: int | None = None
         ) -> Keypoints:
    """Read a keypoint CSV; the number of points is ``num_points``, the layout's (its
    ``source_points`` when a point_id needs them), or the largest point_id + 1."""
    if num_points is not None:
        check_count(num_points, "num_points", MAX_POINTS)
    if isinstance(layout, str):
        layout = named_layout(layout, path)
    bound = num_points
    if layout is not None and num_points is None:
        bound = layout.source_points or layout.num_points
    try:
        rows = _rows(path, bound)
    except UnicodeDecodeError as e:
        raise InputError(f"{shown(path)}: not a UTF-8 text file ({e.reason} at byte "
                         f"{e.start})") from None
    except csv.Error as e:
        raise InputError(f"{shown(path)}: malformed CSV ({shown(e)})") from None
    except OSError as e:
        raise InputError(f"{shown(path)}: cannot read ({shown(e.strerror or e)})") from None
    if not rows:
        raise InputError(f"{shown(path)}: no keypoint rows")
    if num_points is None:
        num_points = max(pid for _, _, pid in rows) + 1
        if layout is not None:
            num_points = layout.num_points if num_points <= layout.num_points else bound
    layout = get_layout(layout, num_points, path)
    people: dict[str, int] = {}
    for image, person, _ in rows:
        people[image] = max(people.get(image, 0), person + 1)
    entries = sum(people.values()) * num_points
    if entries > max(MIN_ENTRIES, SPARSITY * len(rows)):
        raise InputError(
            f"{shown(path)}: {len(rows)} rows spread over {sum(people.values())} detections "
            f"of {num_points} points ({entries} entries, mostly empty); number points and "
            "people from 0 without gaps"
        )
    points = {image: np.tile([np.nan, np.nan, 0.0], (m, num_points, 1))
              for image, m in people.items()}
    for (image, person, pid), value in rows.items():
        points[image][person, pid] = value
    for arr in points.values():
        mark_missing(arr)
    return Keypoints(layout=layout, points=points, source=path)
