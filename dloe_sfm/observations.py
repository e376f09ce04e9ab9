"""Workspace + keypoints -> ``Capture``: undistorted observations of ideal pinhole cameras.

Each registered image with keypoints becomes one capture image. Keypoints ((0, 0) = centre of
the top-left pixel) are shifted by half a pixel into COLMAP's convention, undistorted with the
image's COLMAP camera, and re-expressed in the ideal pinhole ``K = ws.pinhole(name)``, so
``Capture.rays()`` equals ``Workspace.rays`` of the original keypoints.
"""

from __future__ import annotations

import logging
import re

import numpy as np
from tqdm import tqdm

from .colmap import Workspace, natural_key
from .core.capture import Capture
from .errors import InputError
from .keypoints.base import Keypoints

logger = logging.getLogger("dloe_sfm")

PERSON_MODES = ("largest", "all", "auto")


def _some(names: list[str], limit: int = 5) -> str:
    shown = ", ".join(f"'{n}'" for n in names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def _usable(pts: np.ndarray, min_score: float) -> np.ndarray:
    """(..., P) bool: finite points with a positive score >= ``min_score``; pts (..., P, 3)."""
    score = np.nan_to_num(pts[..., 2], nan=0.0)
    return np.isfinite(pts[..., :2]).all(axis=-1) & (score > 0) & (score >= min_score)


def usable_people(people: np.ndarray, min_score: float) -> np.ndarray:
    """(M', P, 3): the detections of (M, P, 3) ``people`` with at least a quarter of the points
    usable (score >= ``min_score``), largest bounding box first."""
    p = people.shape[1]
    keep = [pts for pts in people if 4 * _usable(pts, min_score).sum() >= p]
    keep.sort(key=lambda pts: -_box_area(pts, min_score))
    return np.stack(keep) if keep else np.zeros((0, *people.shape[1:]))


def _box_area(pts: np.ndarray, min_score: float) -> float:
    ok = _usable(pts, min_score)
    if not ok.any():
        return -1.0
    extent = pts[ok, :2].max(axis=0) - pts[ok, :2].min(axis=0)
    return float(extent[0] * extent[1])


def select_person(people: np.ndarray, person: str | int, min_score: float) -> np.ndarray | None:
    """One person's (P, 3) points from (M, P, 3): index ``person`` or the ``"largest"`` bounding
    box of points with score >= ``min_score``; None when there is no such person."""
    if isinstance(person, int):
        return people[person] if person < len(people) else None
    best, best_area = None, -1.0
    for pts in people:
        area = _box_area(pts, min_score)
        if area > best_area:
            best, best_area = pts, area
    return best


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


def assign_streams(
    ws: Workspace, names: list[str], stream_pattern: str | None
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) stream and (N,) frame of images ``names`` (natural name order).

    Default: images sharing a COLMAP camera id form a stream, frames numbered in name order.
    ``stream_pattern``: a regex searched in each name with named groups ``stream`` and ``frame``
    (frame: its integer value when all digits, else its rank in name order). A stream of one
    image is a lone photo (-1).
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
                raise InputError(f"image '{n}': does not match stream pattern {stream_pattern!r}")
            labels.append(m.group("stream"))
            frames_raw.append(m.group("frame"))
    order = sorted(set(labels), key=lambda s: natural_key(str(s)))
    stream = np.array([order.index(s) for s in labels], dtype=np.int64)
    frame = np.zeros(len(names), dtype=np.int64)
    for s in range(len(order)):
        idx = np.flatnonzero(stream == s)
        values = [frames_raw[i] for i in idx]
        if stream_pattern is not None and all(v.isdigit() for v in values):
            frame[idx] = [int(v) for v in values]
        else:
            ranks = sorted(range(len(idx)), key=lambda k: natural_key(values[k]))
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
    x[~ok] = np.nan
    return x, np.where(ok, np.clip(np.nan_to_num(pts[:, 2], nan=0.0), 0.0, 1.0), 0.0)


def build_capture(
    ws: Workspace,
    kp: Keypoints,
    *,
    stream_pattern: str | None = None,
    min_score: float = 0.0,
    person: str | int = "auto",
) -> Capture:
    """The capture of every registered image with keypoints.

    Keypoints naming images the model does not know raise InputError, unless they hold no
    detection (then they are only logged); unregistered images are logged and skipped.

    ``person``: ``"largest"`` (bounding box) or an index: one detection per image, x (N, P, 2);
    ``"all"``: every usable detection (a quarter of the points or more with score >=
    ``min_score``), largest first, x (N, M, P, 2) with M the most in any image, empty slots NaN;
    ``"auto"``: ``"all"`` when >= 10 % of the images with a usable detection have several,
    else ``"largest"``.

    x in the ideal pinhole ``ws.pinhole(name)`` (COLMAP pixel convention), NaN = missing
    (score below ``min_score``, or not undistortable); confidence (N, P) or (N, M, P) = score
    clipped to [0, 1], 0 where missing; streams as in ``assign_streams``; ``symmetric_pairs``
    from the layout. When a COLMAP rig frame holds several of the images,
    ``extras["colmap_frame_id"]`` (N,) marks those taken together.
    """
    source = str(kp.source) if kp.source is not None else "keypoints"
    person = _parse_person(person)
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
            raise InputError(f"{source}: keypoints of '{name}' have shape {people.shape}, "
                             f"expected (M, {num_points}, 3)")
    if person == "auto":
        person = _auto_person(kp, candidates, min_score)
    names, xs, Ks, Rs, Cs, confs = [], [], [], [], [], []
    empty = []
    for name in tqdm(candidates, desc="observations", unit="image", leave=False):
        people = kp.points[name]
        if person == "all":
            chosen = list(usable_people(people, min_score))
        else:
            pts = select_person(people, person, min_score) if len(people) else None
            chosen = [] if pts is None else [pts]
        detections = [d for d in (_undistorted(ws, name, pts, min_score) for pts in chosen)
                      if d is not None]
        if not detections:
            empty.append(name)
            continue
        names.append(name)
        xs.append(np.stack([x for x, _ in detections]))
        confs.append(np.stack([c for _, c in detections]))
        Ks.append(ws.pinhole(name))
        Rs.append(ws.rotation(name))
        Cs.append(ws.centre(name))
    if empty:
        logger.info("%d image(s) without a usable detection (person=%s, min_score=%g), "
                    "skipped: %s", len(empty), person, min_score, _some(empty))
    if not names:
        raise InputError(f"{source}: no usable observation in any registered image")
    slots = max(len(x) for x in xs)
    x = np.full((len(names), slots, num_points, 2), np.nan)
    confidence = np.zeros((len(names), slots, num_points))
    for i, (xi, ci) in enumerate(zip(xs, confs, strict=True)):
        x[i, :len(xi)], confidence[i, :len(ci)] = xi, ci
    if person != "all":
        x, confidence = x[:, 0], confidence[:, 0]
    seen = np.isfinite(x).all(axis=-1).reshape(len(names), -1, num_points)
    never = np.flatnonzero(~seen.any(axis=(0, 1)))
    if never.size:
        missing = [kp.layout.point_names[i] for i in never]
        raise InputError(f"{source}: point(s) {_some(missing)} observed in no image "
                         "(lower min_score or use a layout without them)")
    stream, frame = assign_streams(ws, names, stream_pattern)
    extras = {}
    if any(ws.frame_size(n) > 1 for n in names):
        extras["colmap_frame_id"] = np.array([ws.frame_id(n) for n in names], dtype=np.int64)
    pairs = np.asarray(kp.layout.symmetric_pairs, dtype=np.int64).reshape(-1, 2)
    capture = Capture(
        x=x, K=np.stack(Ks), R=np.stack(Rs), C=np.stack(Cs), stream=stream, frame=frame,
        confidence=confidence, image_names=np.array(names), extras=extras,
        symmetric_pairs=pairs if pairs.size else None,
    )
    n_streams = np.unique(capture.stream_ids).size
    if n_streams < 2:
        raise InputError(f"{source}: the {len(names)} image(s) with keypoints form one stream; "
                         "at least two cameras / streams are needed")
    logger.info("capture: %d images, %d points, %d streams (%d lone photos), %d observations%s",
                len(names), num_points, n_streams, int((stream < 0).sum()), int(seen.sum()),
                f", up to {slots} detections per image" if person == "all" else "")
    return capture.validate(source)
