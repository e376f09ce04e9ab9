"""Workspace + keypoints -> ``Capture``: undistorted observations of ideal pinhole cameras.

Each registered image with keypoints becomes one capture image. Keypoints ((0, 0) = centre of
the top-left pixel) are shifted by half a pixel into COLMAP's convention, undistorted with the
image's COLMAP camera, and re-expressed in the ideal pinhole ``K = ws.pinhole(name)``, so
``Capture.rays()`` equals ``Workspace.rays`` of the original keypoints.
"""

from __future__ import annotations

import logging
import re
from pathlib import PurePosixPath
from typing import NamedTuple

import numpy as np

from . import progress
from .colmap import Workspace
from .core.capture import Capture
from .errors import InputError
from .images import natural_key
from .keypoints.base import Keypoints, Layout, quoted, shown

logger = logging.getLogger("dloe_sfm")

PERSON_MODES = ("largest", "all", "auto")


def _some(names: list[str], limit: int = 5) -> str:
    listed = ", ".join(quoted(n) for n in names[:limit])
    return listed + (f" and {len(names) - limit} more" if len(names) > limit else "")


def _usable(pts: np.ndarray, min_score: float) -> np.ndarray:
    """(..., P) bool: finite points with a positive score >= ``min_score``; pts (..., P, 3)."""
    score = np.nan_to_num(pts[..., 2], nan=0.0)
    return np.isfinite(pts[..., :2]).all(axis=-1) & (score > 0) & (score >= min_score)


def usable_people(people: np.ndarray, min_score: float) -> np.ndarray:
    """(M',) int: indices of the detections of (M, P, 3) ``people`` with at least a quarter of
    the points usable (score >= ``min_score``), largest bounding box first."""
    p = people.shape[1]
    keep = [m for m, pts in enumerate(people) if 4 * _usable(pts, min_score).sum() >= p]
    keep.sort(key=lambda m: -_box_area(people[m], min_score))
    return np.array(keep, dtype=np.int64)


def _box_area(pts: np.ndarray, min_score: float) -> float:
    ok = _usable(pts, min_score)
    if not ok.any():
        return -1.0
    with np.errstate(over="ignore"):  # absurd pixels (1e308) give an infinite box
        extent = pts[ok, :2].max(axis=0) - pts[ok, :2].min(axis=0)
        return float(extent[0] * extent[1])


def person_index(people: np.ndarray, person: str | int, min_score: float) -> int | None:
    """Index in (M, P, 3) ``people`` of index ``person`` or of the ``"largest"`` bounding box of
    points with score >= ``min_score``; None when there is no such person."""
    if isinstance(person, int):
        return person if person < len(people) else None
    areas = [_box_area(pts, min_score) for pts in people]
    return int(np.argmax(areas)) if areas and max(areas) >= 0 else None


def select_person(people: np.ndarray, person: str | int, min_score: float) -> np.ndarray | None:
    """One person's (P, 3) points from (M, P, 3), chosen as by ``person_index``."""
    m = person_index(people, person, min_score)
    return None if m is None else people[m]


def _parse_person(person: str | int) -> str | int:
    if isinstance(person, str) and person.strip().isdigit():
        person = int(person)
    if person in PERSON_MODES or (isinstance(person, int) and person >= 0):
        return person
    raise InputError(f"person must be 'largest', 'all', 'auto' or an index >= 0, got {person!r}")


def _auto_person(kp: Keypoints, names: list[str], min_score: float) -> str:
    """``"all"`` when >= 10 % of the images with a usable detection have several, else
    ``"largest"`` (a stray second detection now and then is a false positive, not a subject)."""
    counts = np.array([len(usable_people(kp.points[n], min_score)) for n in names
                       if len(kp.points[n])], dtype=np.int64)
    with_any, several = int((counts >= 1).sum()), int((counts >= 2).sum())
    mode = "all" if with_any and several >= 0.1 * with_any else "largest"
    logger.info("person=auto: %d of %d image(s) with a usable detection have several -> %s",
                several, with_any, mode)
    return mode


def _file_number(name: str) -> int | None:
    """The last digit run of an image's file name without suffix (``cam0/00012.jpg``: 12)."""
    digits = re.findall(r"\d+", PurePosixPath(name).stem)
    return int(digits[-1]) if digits else None


def assign_streams(
    ws: Workspace, names: list[str], stream_pattern: str | None
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) stream and (N,) frame of images ``names`` (natural name order).

    Default: images sharing a COLMAP camera id form a stream, in name order; frames are the
    last numbers of the file names (``cam0/00012.jpg``: 12) minus the stream's first when they
    rise with the name order (so a video that stopped and restarted keeps its gap, which
    separates events), else the ranks in name order. ``stream_pattern``: a regex searched in
    each name with named groups ``stream`` and ``frame`` (frame: its integer value when all
    digits, else its rank in name order). A stream of one image is a lone photo (-1).
    """
    if stream_pattern is None:
        labels: list[object] = [ws.camera_id(n) for n in names]
        frames_raw: list[str] = list(names)
    else:
        try:
            regex = re.compile(stream_pattern)
        except re.error as e:
            raise InputError(f"stream pattern {stream_pattern!r} is not a regex ({e})") from None
        if not {"stream", "frame"} <= set(regex.groupindex):
            raise InputError(
                f"stream pattern {stream_pattern!r} needs named groups (?P<stream>...) and "
                "(?P<frame>...)"
            )
        labels, frames_raw = [], []
        for n in names:
            m = regex.search(n)
            if m is None:
                raise InputError(f"image {quoted(n)}: does not match stream pattern "
                                 f"{stream_pattern!r}")
            labels.append(m.group("stream"))
            frames_raw.append(m.group("frame"))
    order = sorted(set(labels), key=lambda s: natural_key(str(s)))
    stream = np.array([order.index(s) for s in labels], dtype=np.int64)
    frame = np.zeros(len(names), dtype=np.int64)
    for s in range(len(order)):
        idx = np.flatnonzero(stream == s)
        values = [frames_raw[i] for i in idx]
        ranks = sorted(range(len(idx)), key=lambda k: natural_key(values[k]))
        numbers = [_file_number(values[k]) for k in ranks]
        if stream_pattern is not None and all(v.isdigit() for v in values):
            frame[idx] = [int(v) for v in values]
        elif (stream_pattern is None and None not in numbers
              and all(a < b for a, b in zip(numbers, numbers[1:], strict=False))):
            frame[idx[ranks]] = np.array(numbers) - numbers[0]
        else:
            frame[idx[ranks]] = np.arange(len(idx))
        if len(idx) == 1:
            stream[idx] = -1
    return stream, frame


def _undistorted(ws: Workspace, name: str, pts: np.ndarray, min_score: float
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """(P, 2) pixels in the ideal pinhole of image ``name`` and (P,) confidence of one
    detection pts (P, 3) ((0, 0) convention); NaN / 0 where missing; None when nothing is left."""
    ok = _usable(pts, min_score)
    pixels = np.where(ok[:, None], pts[:, :2] + 0.5, np.nan)  # to COLMAP's convention
    uv = ws.normalised(name, pixels)
    ok &= np.isfinite(uv).all(axis=1)
    if not ok.any():
        return None
    K = ws.pinhole(name)
    x = uv * np.diag(K)[:2] + K[:2, 2]
    ok &= np.isfinite(x).all(axis=1)  # absurd pixels (1e308) overflow here
    if not ok.any():
        return None
    x[~ok] = np.nan
    return x, np.where(ok, np.clip(np.nan_to_num(pts[:, 2], nan=0.0), 0.0, 1.0), 0.0)


class Observations(NamedTuple):
    """What :func:`build_capture` returns: the capture, the names of the registered images left
    out for want of a usable detection, and the layout indices of the points no image observes
    (left out of the capture)."""

    capture: Capture
    skipped_images: list[str]
    unobserved_points: list[int]


def observed_layout(layout: Layout, unobserved: list[int]) -> Layout:
    """``layout`` without the points ``build_capture`` left out because no image observes them
    (their indices: ``Observations.unobserved_points``), so it matches the capture."""
    if not unobserved:
        return layout
    return layout.subset([j for j in range(layout.num_points) if j not in set(unobserved)])


def build_capture(
    ws: Workspace,
    kp: Keypoints,
    *,
    stream_pattern: str | None = None,
    min_score: float = 0.0,
    person: str | int = "auto",
) -> Observations:
    """The capture of every registered image with keypoints (and what was left out of it).

    Keypoints naming images the model does not know raise InputError, unless they hold no
    detection (then they are only logged); unregistered images are logged and skipped. Images
    without a usable detection (the detector found nobody, or only points below
    ``min_score``) are left out with one warning and listed in ``skipped_images`` (a list of
    names); only when no image is left is it an error. Likewise points no image observes are
    left out of x (listed by layout index in ``unobserved_points``;
    :func:`observed_layout` is the layout of the rest); only when none is observed is it an
    error.

    ``person``: ``"largest"`` (bounding box) or an index: one detection per image, x (N, P, 2);
    an index beyond an image's detections leaves that image out (beyond every image's: an
    error);
    ``"all"``: every usable detection (a quarter of the points or more with score >=
    ``min_score``), largest first, x (N, M, P, 2) with M the most in any image, empty slots NaN;
    ``"auto"``: ``"all"`` when >= 10 % of the images with a usable detection have several,
    else ``"largest"``.

    x in the ideal pinhole ``ws.pinhole(name)`` (COLMAP pixel convention), NaN = missing
    (score below ``min_score``, or not undistortable); confidence (N, P) or (N, M, P) = score
    clipped to [0, 1], 0 where missing; streams as in ``assign_streams``; ``symmetric_pairs``
    from the layout. ``image_ids["detection_index"]`` (N, M) or (N,) int: the index of each
    detection in the image's keypoint list (-1 = empty slot). When a COLMAP rig frame holds
    several of the images, ``image_ids["colmap_frame_id"]`` (N,) marks those taken together.
    """
    source = shown(kp.source) if kp.source is not None else "keypoints"
    person = _parse_person(person)
    if not np.isfinite(min_score):
        raise InputError(f"min_score must be a finite number, got {min_score}")
    registered = set(ws.image_names)
    unregistered = set(ws.unregistered)
    unknown = [k for k in kp.points if k not in registered and k not in unregistered]
    empty_unknown = [k for k in unknown if kp.points[k].size == 0]
    if empty_unknown:
        logger.info("%s: %d keypoint file(s)/entries without detections match no image, "
                    "ignored: %s", source, len(empty_unknown), _some(empty_unknown))
    unknown = [k for k in unknown if kp.points[k].size]
    if unknown:
        raise InputError(
            f"{source}: keypoints for {len(unknown)} image(s) not in the COLMAP model "
            f"{ws.model_dir}: {_some(sorted(unknown, key=natural_key))}"
        )
    skipped = sorted((k for k in kp.points if k in unregistered), key=natural_key)
    if skipped:
        logger.info("%s: %d image(s) with keypoints are unregistered, skipped: %s",
                    source, len(skipped), _some(skipped))
    without = [n for n in ws.image_names if n not in kp.points]
    if without:
        logger.info("%d registered image(s) have no keypoints, skipped: %s",
                    len(without), _some(without))
    num_points = kp.num_points
    candidates = [n for n in ws.image_names if n in kp.points]
    for name in candidates:
        people = kp.points[name]
        if people.ndim != 3 or people.shape[1:] != (num_points, 3):
            raise InputError(f"{source}: keypoints of {quoted(name)} have shape {people.shape}, "
                             f"expected (M, {num_points}, 3)")
    if isinstance(person, int):
        most = max((len(kp.points[n]) for n in candidates), default=0)
        if person >= most:
            raise InputError(f"person index {person}: no image holds more than {most} "
                             "detection(s)")
    if person == "auto":
        person = _auto_person(kp, candidates, min_score)
    names, xs, Ks, Rs, Cs, confs, indices = [], [], [], [], [], [], []
    empty = []
    for name in progress.bar(candidates, desc="observations", unit="image", leave=False):
        people = kp.points[name]
        if person == "all":
            chosen = usable_people(people, min_score).tolist()
        else:
            m = person_index(people, person, min_score)
            chosen = [] if m is None else [m]
        detections = [(m, d) for m, d in ((m, _undistorted(ws, name, people[m], min_score))
                                          for m in chosen) if d is not None]
        if not detections:
            empty.append(name)
            continue
        names.append(name)
        xs.append(np.stack([x for _, (x, _) in detections]))
        confs.append(np.stack([c for _, (_, c) in detections]))
        indices.append([m for m, _ in detections])
        Ks.append(ws.pinhole(name))
        Rs.append(ws.rotation(name))
        Cs.append(ws.centre(name))
    if empty:
        logger.warning("%d image(s) without a usable detection (person=%s, min_score=%g), "
                       "skipped: %s", len(empty), person, min_score, _some(empty))
    if not names:
        raise InputError(f"{source}: no usable observation in any registered image")
    slots = max(len(x) for x in xs)
    x = np.full((len(names), slots, num_points, 2), np.nan)
    confidence = np.zeros((len(names), slots, num_points))
    detection = np.full((len(names), slots), -1, dtype=np.int64)
    for i, (xi, ci, mi) in enumerate(zip(xs, confs, indices, strict=True)):
        x[i, :len(xi)], confidence[i, :len(ci)], detection[i, :len(mi)] = xi, ci, mi
    if person != "all":
        x, confidence = x[:, 0], confidence[:, 0]
    seen = np.isfinite(x).all(axis=-1).reshape(len(names), -1, num_points)
    observed = seen.any(axis=(0, 1))
    if not observed.any():
        raise InputError(f"{source}: no point observed in any image")
    unobserved = np.flatnonzero(~observed).tolist()
    if unobserved:  # left out of the capture; ``observed_layout`` drops them from the layout
        logger.warning("%d point(s) observed in no image, left out of the reconstruction: %s",
                       len(unobserved), _some([kp.layout.point_names[j] for j in unobserved]))
        x, confidence = x[..., observed, :], confidence[..., observed]
        seen = seen[..., observed]
    stream, frame = assign_streams(ws, names, stream_pattern)
    image_ids = {"detection_index": detection if person == "all" else detection[:, 0]}
    if any(ws.frame_size(n) > 1 for n in names):
        image_ids["colmap_frame_id"] = np.array([ws.frame_id(n) for n in names], dtype=np.int64)
    pairs = np.asarray(observed_layout(kp.layout, unobserved).symmetric_pairs,
                       dtype=np.int64).reshape(-1, 2)
    capture = Capture(
        x=x, K=np.stack(Ks), R=np.stack(Rs), C=np.stack(Cs), stream=stream, frame=frame,
        confidence=confidence, image_names=np.array(names), image_ids=image_ids,
        symmetric_pairs=pairs if pairs.size else None,
    )
    n_streams = np.unique(capture.stream_ids).size
    if n_streams < 2:
        raise InputError(f"{source}: the {len(names)} image(s) with keypoints form one stream; "
                         "at least two cameras / streams are needed")
    logger.info("capture: %d images, %d points, %d streams (%d lone photos), %d observations%s",
                len(names), int(observed.sum()), n_streams, int((stream < 0).sum()),
                int(seen.sum()),
                f", up to {slots} detections per image" if person == "all" else "")
    return Observations(capture.validate(source), empty, unobserved)
