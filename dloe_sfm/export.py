"""Workspace outputs (docs/interfaces.md, "Reconstruct outputs"): point clouds, skeletons,
trajectories, report.

Everything is written into a temporary sibling of the output folder and renamed when complete, so a
failed export never leaves a half-written folder behind. open3d is used here and nowhere else.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d

from . import progress
from .columns import (
    column_edges,
    column_ids,
    column_labels,
    frame_file_stem,
    point_colors,
    solved_capture,
)
from .core.bias import per_stream
from .core.capture import Capture, project
from .core.multitarget import detection_confidence
from .core.result import Result
from .core.sync import (
    Fps,
    capture_fps,
    check_fps,
    largest_disagreement,
    stream_clocks,
    sync_report,
    times_in_unit,
)
from .errors import InputError
from .io import atomic_path, check_output, save_npz
from .mocap_export import warn_stepped_frames, whole_factor, write_mocap

if TYPE_CHECKING:
    from .colmap import Workspace
    from .keypoints.base import Layout

logger = logging.getLogger("dloe_sfm")


def reprojection_errors(capture: Capture, X: np.ndarray) -> np.ndarray:
    """Pixel distance between observed and reprojected points.

    X (N, P, 3) world points -> (N, P) float pixels under the capture's pinhole ``K R (X - C)``;
    NaN where the point is not observed (``capture.visible``) or X is not finite.
    """
    reproj = project(X, capture.K, capture.R, capture.C)
    err = np.linalg.norm(reproj - capture.x, axis=2)
    err[~capture.visible] = np.nan
    return err


def error_stats(errors: np.ndarray) -> dict[str, float | int | None]:
    """Summary of pixel errors (any shape, NaN ignored): count, mean, rms, median, p90, max."""
    e = np.asarray(errors, dtype=np.float64).ravel()
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"count": 0, "mean": None, "rms": None, "median": None, "p90": None, "max": None}
    return {
        "count": int(e.size),
        "mean": float(e.mean()),
        "rms": float(np.sqrt(np.mean(e**2))),
        "median": float(np.median(e)),
        "p90": float(np.percentile(e, 90)),
        "max": float(e.max()),
    }


def detection_subjects(capture: Capture, result: Result
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """(N, M') subject of each detection of every image, in the order of the image's keypoint
    list up to its last detection used (-1: not used, e.g. too few points or a stray), from
    ``result.assignment``, and how surely (``multitarget.detection_confidence``; NaN: not
    used); None for one subject. ``capture`` is the solver's input: without
    ``image_ids["detection_index"]`` (``observations.build_capture``) its slot order is the
    list's."""
    if result.assignment is None:
        return None
    confidence = detection_confidence(capture, result.assignment, result)
    index = capture.image_ids.get("detection_index")
    if index is None or index.shape != result.assignment.shape:
        return result.assignment.astype(np.int64), confidence
    out = np.full((len(index), int(index.max()) + 1), -1, dtype=np.int64)
    sure = np.full(out.shape, np.nan)
    rows, slots = np.nonzero(index >= 0)
    out[rows, index[rows, slots]] = result.assignment[rows, slots]
    sure[rows, index[rows, slots]] = confidence[rows, slots]
    return out, sure


def write_point_cloud(path: Path, xyz: np.ndarray, *, colors: np.ndarray | None = None,
                      attributes: dict[str, np.ndarray] | None = None) -> Path:
    """Binary PLY of points xyz (M, 3) float64, colors (M, 3) uint8, and extra per-point
    attributes (M,) int32 / float32 / uint8 (custom PLY vertex properties; open3d reads them)."""
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(xyz, dtype=np.float64)))
    if colors is not None:
        cloud.point.colors = o3d.core.Tensor(np.ascontiguousarray(colors, dtype=np.uint8))
    for name, values in (attributes or {}).items():
        cloud.point[name] = o3d.core.Tensor(np.ascontiguousarray(values)[:, None])
    with atomic_path(path) as tmp:
        if not o3d.t.io.write_point_cloud(str(tmp), cloud, write_ascii=False):
            raise OSError(f"{path}: open3d could not write the point cloud")
    return path


def write_line_set(path: Path, xyz: np.ndarray, lines: np.ndarray, colors: np.ndarray) -> Path:
    """Binary PLY line set: vertices xyz (M, 3), lines (L, 2) indices, colors (L, 3) uint8."""
    line_set = o3d.geometry.LineSet(
        o3d.utility.Vector3dVector(np.asarray(xyz, dtype=np.float64)),
        o3d.utility.Vector2iVector(np.asarray(lines, dtype=np.int32)),
    )
    line_set.colors = o3d.utility.Vector3dVector(np.asarray(colors, dtype=np.float64) / 255.0)
    with atomic_path(path) as tmp:
        if not o3d.io.write_line_set(str(tmp), line_set, write_ascii=False):
            raise OSError(f"{path}: open3d could not write the line set")
    return path


def _json_ready(value):
    """Numbers, arrays and paths as plain JSON values; NaN / inf become null."""
    if isinstance(value, dict):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_ready(value.tolist())
    if isinstance(value, np.generic):
        return _json_ready(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    return value


def _event_summaries(capture: Capture, result: Result, errors: np.ndarray) -> list[dict]:
    rank = result.rank
    summaries = []
    for event in np.unique(result.events):
        members = np.flatnonzero(result.events == event)
        members = members[np.argsort(rank[members])]
        centroid = np.nanmean(result.X[members], axis=1)
        steps = np.linalg.norm(np.diff(centroid, axis=0), axis=1)
        pts = result.X[members].reshape(-1, 3)
        extent = np.nanmax(pts, axis=0) - np.nanmin(pts, axis=0)
        summaries.append({
            "event": int(event),
            "num_images": int(members.size),
            "streams": sorted({int(s) for s in capture.stream_ids[members]}),
            "first_image": str(capture.image_names[members[0]]),
            "last_image": str(capture.image_names[members[-1]]),
            "ranks": [int(rank[members[0]]), int(rank[members[-1]])],
            "centroid_path_length": float(np.nansum(steps)),
            "extent": extent.tolist(),
            "reprojection_error_px": error_stats(errors[members]),
        })
    return summaries


def _subject_summaries(capture: Capture, result: Result, errors: np.ndarray,
                       subject_id: np.ndarray) -> list[dict]:
    visible = capture.visible
    summaries = []
    for subject in np.unique(subject_id):
        columns = subject_id == subject
        seen = result.order[visible[result.order][:, columns].any(axis=1)]
        summaries.append({
            "subject_id": int(subject),
            "num_images_seen": int(seen.size),
            "images_seen": capture.image_names[seen].tolist(),
            "observed_fraction": float(visible[:, columns].mean()),
            "reprojection_error_px": error_stats(errors[:, columns]),
        })
    return summaries


def _left_out_report(capture: Capture, result: Result) -> dict:
    """``detections_left_out`` of a several-detection solve: the detections of the solver's
    input ``capture`` no subject took (``multitarget.associate``: they support none), their
    count and images; {} otherwise."""
    if result.assignment is None or capture.x.ndim != 4:
        return {}
    img, _ = np.nonzero(capture.visible.any(axis=2) & (result.assignment < 0))
    return {"detections_left_out": {"count": int(img.size),
                                    "images": capture.image_names[np.unique(img)].tolist()}}


def _robust_report(capture: Capture, result: Result, subject_id: np.ndarray,
                   point_id: np.ndarray, point_names: list[str]) -> dict:
    """Observations the robust loss down-weighted and left/right swaps it fixed, by name."""
    names = capture.image_names
    outliers = [
        {"image": str(names[i]), "point": point_names[point_id[k]],
         "subject_id": int(subject_id[k]), "residual_px": float(residual)}
        for (i, k), residual in zip(result.outliers, result.outlier_residual_px, strict=True)
    ]
    swaps = [
        {"image": str(names[i]), "points": [point_names[point_id[a]], point_names[point_id[b]]],
         "subject_id": int(subject_id[a])}
        for i, a, b in result.swaps
    ]
    return {"downweighted": {"count": len(outliers), "observations": outliers},
            "swaps_fixed": {"count": len(swaps), "swaps": swaps}}


def _offset_report(capture: Capture, result: Result, subject_id: np.ndarray,
                   point_id: np.ndarray, point_names: list[str]) -> dict:
    """Each stream's pixel offset of each point taken out of its detections
    (``Result.offset_px``, ``core.bias``), by name; empty when none was."""
    offsets = []
    if result.offset_px is not None:
        for s, shift in zip(*per_stream(result.offset_px, capture.stream_ids), strict=True):
            for k in np.flatnonzero(np.abs(shift).sum(axis=1) > 0):
                offsets.append({"stream": int(s), "point": point_names[point_id[k]],
                                "subject_id": int(subject_id[k]),
                                "offset_px": [float(shift[k, 0]), float(shift[k, 1])]})
    size = [float(np.hypot(*o["offset_px"])) for o in offsets]
    return {"stream_offsets": {"count": len(offsets),
                               "median_px": float(np.median(size)) if size else None,
                               "offsets": offsets}}


def supported_points(result: Result) -> np.ndarray:
    """(N, P) X with NaN where the data do not support a point (``Result.supported``: unobserved
    and weakly determined, or in an ``inconsistent`` image); X as is without the check."""
    if result.supported is None:
        return result.X
    return np.where(result.supported[..., None], result.X, np.nan)


def _image_report(capture: Capture, result: Result) -> dict:
    """report.json's per-image checks (``core.assess``): ``image_status`` and ``image_checks``."""
    if result.image_status is None:
        return {}
    names = capture.image_names
    sd = np.where(capture.visible, result.depth_sd, np.nan)
    ambiguous = (np.zeros(result.order.size, dtype=bool) if result.order_ambiguous is None
                 else result.order_ambiguous)
    images = {}
    for i in result.order:
        row = sd[i][np.isfinite(sd[i])]
        images[str(names[i])] = {
            "status": str(result.image_status[i]),
            "reason": str(result.status_reason[i]),
            "residual_px": float(result.residual_px[i]),
            "neighbour_deviation": float(result.neighbour_deviation[i]),
            "depth_sd_median": float(np.median(row)) if row.size else None,
            "unsupported_points": int((~result.supported[i]).sum()),
            "order_ambiguous": bool(ambiguous[i]),
        }
    status, counts = np.unique(result.image_status, return_counts=True)
    flagged = result.image_status != "ok"
    return {"image_status": {"counts": dict(zip(status.tolist(), counts.tolist(), strict=True)),
                             "flagged": [str(names[i]) for i in result.order if flagged[i]],
                             "unsupported_points": int((~result.supported).sum()),
                             "order_ambiguous": [str(names[i]) for i in result.order
                                                 if ambiguous[i]]},
            "image_checks": images}


def _check_shapes(capture: Capture, result: Result) -> None:
    """``capture`` as from ``solved_capture``."""
    n, p = capture.num_images, capture.num_points
    if capture.x.ndim != 3:
        raise InputError(f"result: field 'solved' is missing for the {capture.x.shape} "
                         "several-subject capture")
    if result.X.shape != (n, p, 3):
        raise InputError(f"result: field 'X' must have shape ({n}, {p}, 3), got {result.X.shape}")
    if sorted(result.order.tolist()) != list(range(n)):
        raise InputError(f"result: field 'order' is not a permutation of the {n} images")
    if result.events.shape != (n,):
        raise InputError(
            f"result: field 'events' must have shape ({n},), got {result.events.shape}"
        )
    if (result.subject_id is None) != (result.point_id is None):
        raise InputError("result: fields 'subject_id' and 'point_id' must be given together")
    for name in ("subject_id", "point_id"):
        ids = getattr(result, name)
        if ids is not None and (ids.shape != (p,) or (ids < 0).any()):
            raise InputError(f"result: field '{name}' must be ({p},) ids >= 0, got {ids.shape}")
    for name, width in (("outliers", 2), ("swaps", 3)):
        rows = np.asarray(getattr(result, name)).reshape(-1, width)
        if (rows < 0).any() or (rows[:, 0] >= n).any() or (rows[:, 1:] >= p).any():
            raise InputError(f"result: field '{name}' indexes an image or column out of range")
    if result.offset_px is not None and result.offset_px.shape != (n, p, 2):
        raise InputError(f"result: field 'offset_px' must have shape ({n}, {p}, 2), got "
                         f"{result.offset_px.shape}")
    if result.outlier_residual_px.shape != (len(result.outliers),):
        raise InputError(f"result: field 'outlier_residual_px' must have shape "
                         f"({len(result.outliers)},), got {result.outlier_residual_px.shape}")


def write_outputs(folder: Path, capture: Capture, result: Result, *,
                  static_xyz: np.ndarray | None = None, static_rgb: np.ndarray | None = None,
                  layout: Layout | None = None, report: dict | None = None,
                  export_rate: float | None = None, fps: Fps = None) -> dict:
    """Write the section-4 files into the existing folder ``folder`` (not atomic on its own).

    ``capture`` is the solver's input; the observations written and scored are those of
    ``solved_capture``. With several subjects, column k of X is point ``result.point_id[k]`` of
    subject ``result.subject_id[k]``: frames carry both ids, skeletons repeat per subject, and
    trajectories.npz has ``detection_subject`` and ``detection_confidence``
    (``detection_subjects``). static_xyz (M, 3)
    float, static_rgb (M, 3) uint8: COLMAP's static points. ``report`` entries (inputs,
    parameters, stage timings, ...) are merged into ``report.json``. TRC / C3D / wide CSV:
    ``mocap_export.write_mocap`` (``export_rate`` samples per reference frame; markers
    ``s<subject>_<name>`` with several subjects). ``fps``: the streams' frame rates (one for
    all or per stream id; ``core.sync``; default the capture's own, ``Capture.fps``), for
    ``sequence.csv``'s times in seconds, the TRC / C3D / wide CSV's in seconds and Hz, and the
    report's ``sync``. Returns the report.
    """
    detection_subject = detection_subjects(capture, result)
    left_out = _left_out_report(capture, result)
    capture = solved_capture(capture, result)
    _check_shapes(capture, result)
    folder = Path(folder)
    n, p = capture.num_images, capture.num_points
    names = capture.image_names
    rank = result.rank
    visible = capture.visible
    errors = reprojection_errors(capture, result.X)
    X = supported_points(result)
    subject_id, point_id = column_ids(result)
    num_layout = int(point_id.max()) + 1
    layout_names = (list(layout.point_names) if layout is not None
                    else [str(i) for i in range(num_layout)])
    if len(layout_names) != num_layout:
        raise InputError(f"keypoint layout '{layout.name}' names {len(layout_names)} points, "
                         f"the capture has {num_layout}")
    point_names = [layout_names[j] for j in point_id]
    colors = point_colors(num_layout)[point_id]
    subjects = result.subject_id is not None
    edges = column_edges(list(layout.edges) if layout is not None else [], subject_id, point_id)

    (folder / "frames").mkdir()
    if edges.size:
        (folder / "skeleton").mkdir()
    for i in progress.bar(result.order, desc="export frames", unit="image", leave=False):
        stem = frame_file_stem(int(rank[i]), str(names[i]), n)
        finite = np.isfinite(X[i]).all(axis=1)
        if not finite.any():
            logger.warning("image %s: no finite 3D point the data support, no frame file "
                           "written", names[i])
            continue
        attributes = {"point_id": point_id[finite].astype(np.int32)}
        if subjects:
            attributes["subject_id"] = subject_id[finite].astype(np.int32)
        attributes["observed"] = visible[i, finite].astype(np.uint8)
        attributes["event"] = np.full(int(finite.sum()), result.events[i], dtype=np.int32)
        if capture.confidence is not None:
            conf = np.nan_to_num(capture.confidence[i], nan=0.0).astype(np.float32)
            attributes["confidence"] = conf[finite]
        write_point_cloud(folder / "frames" / f"{stem}.ply", X[i, finite],
                          colors=colors[finite], attributes=attributes)
        if edges.size:
            ok = finite[edges].all(axis=1)
            if ok.any():
                write_line_set(folder / "skeleton" / f"{stem}.ply", X[i], edges[ok],
                               colors[edges[ok, 0]])

    if static_xyz is not None and len(static_xyz):
        rgb = None if static_rgb is None else np.asarray(static_rgb, dtype=np.uint8)
        write_point_cloud(folder / "static.ply", np.asarray(static_xyz, dtype=np.float64),
                          colors=rgb)

    # point_names and edges are per column of X (a skeleton per subject)
    save_npz(folder / "trajectories.npz", X=X, order=result.order.astype(np.int64),
             image_names=names.astype(str), events=result.events.astype(np.int64),
             rank=rank.astype(np.int64), observed=visible, point_names=np.array(point_names),
             edges=edges, embedding=result.embedding, reprojection_error=errors,
             **({} if result.supported is None else
                {"supported": result.supported, "depth_sd": result.depth_sd,
                 "image_status": result.image_status.astype(str)}),
             **({"subject_id": subject_id, "point_id": point_id} if subjects else {}),
             **({} if detection_subject is None else
                {"detection_subject": detection_subject[0],
                 "detection_confidence": detection_subject[1]}))

    with open(folder / "trajectories.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["rank", "image", "point_id", "x", "y", "z", "observed", "subject_id"])
        for i in result.order:
            for k in range(p):
                x, y, z = X[i, k]
                writer.writerow([int(rank[i]), names[i], int(point_id[k]), repr(float(x)),
                                 repr(float(y)), repr(float(z)), int(visible[i, k]),
                                 int(subject_id[k])])

    check_fps(fps, capture.stream_ids)
    fps = capture_fps(capture) if fps is None else fps
    warn_stepped_frames(capture, fps)
    times, mocap = write_mocap(folder, capture, replace(result, X=X),
                               column_labels(result, layout_names), export_rate=export_rate,
                               fps=fps)
    sync = sync_report(stream_clocks(capture, result.events, times, mocap["events"],
                                     result.embedding), fps)
    for event in sync["events"]:
        for s, clock in event["streams"].items():
            if clock.get("fps_consistent") is False:
                factor = whole_factor(clock, s)
                logger.warning(
                    "event %d, stream %s: its clock runs at %.3f fps where its frame rate is %g "
                    "(%+.1f %%, %.0f standard uncertainties): the clock fit may have settled on "
                    "wrong rates, its offset and times are not to be trusted%s", event["event"],
                    s, clock["implied_fps"], clock["fps"], 100 * clock["fps_deviation"],
                    clock["fps_deviation_sd"], f"; {factor}" if factor else "")
        if event["clocks_dropped"]:
            logger.warning(
                "event %d: the streams' fitted clocks predicted held-out detections worse than "
                "DLOE's graph, which gives the points; the times and offsets are the clocks', "
                "uncertain by their disagreement with the graph's time line (up to %.2f frames, "
                "report.json sync: clock_disagreement_frames)", event["event"],
                largest_disagreement(event))
    times = times_in_unit(times, result.events, sync, fps)

    with open(folder / "sequence.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["rank", "image", "event", "stream", "frame", "time"])
        for i in result.order:
            writer.writerow([int(rank[i]), names[i], int(result.events[i]), int(capture.stream[i]),
                             int(capture.frame[i]), repr(float(times[i]))])

    per_point = [{"point_id": int(point_id[k]), "subject_id": int(subject_id[k]),
                  "name": point_names[k], **error_stats(errors[:, k])} for k in range(p)]
    robust = _robust_report(capture, result, subject_id, point_id, layout_names)
    offsets = _offset_report(capture, result, subject_id, point_id, layout_names)
    full_report = {
        "images": n,
        "points": num_layout,
        "subjects": int(np.unique(subject_id).size),
        "streams": int(np.unique(capture.stream_ids).size),
        "observations": int(visible.sum()),
        "events": int(np.unique(result.events).size),
        "layout": None if layout is None else layout.name,
        **(report or {}),
        "solver": {
            "message": result.message,
            "success": bool(result.success),
            "iterations": int(result.nit),
            "seconds": float(result.seconds),
            "timings": dict(result.timings),
            "scale": float(result.scale),
            "noise_px": float(result.noise_px),
            "cost_history": np.asarray(result.cost_history, dtype=np.float64),
            "change_history": np.asarray(result.change_history, dtype=np.float64),
        },
        "reprojection_error_px": {
            "all": error_stats(errors),
            "per_image": {str(names[i]): error_stats(errors[i]) for i in result.order},
            "per_point": per_point,
        },
        **_image_report(capture, result),
        "event_summaries": _event_summaries(capture, result, errors),
        "subject_summaries": _subject_summaries(capture, result, errors, subject_id),
        "mocap_export": mocap,
        "time_unit": sync["time_unit"],
        "sync": sync,
        **left_out,
        **robust,
        **offsets,
    }
    full_report = _json_ready(full_report)
    with open(folder / "report.json", "w") as f:
        json.dump(full_report, f, indent=2)
    return full_report


def export_outputs(out: Path | str, capture: Capture, result: Result, *,
                   workspace: Workspace | None = None, static_xyz: np.ndarray | None = None,
                   static_rgb: np.ndarray | None = None, layout: Layout | None = None,
                   report: dict | None = None, overwrite: bool = False, plots: bool = True,
                   export_rate: float | None = None, fps: Fps = None,
                   overlay_images: Sequence[str] | None = None) -> dict:
    """Write the outputs of docs/interfaces.md ("Reconstruct outputs") of a solved capture to
    ``out`` atomically (``write_outputs``, and ``plots/`` unless ``plots=False``:
    ``viz.write_plots``); returns the report written to ``report.json``.

    ``workspace``: the COLMAP workspace of the capture, whose folders ``out`` must not be in;
    its static points go to the animation and, unless ``static_xyz`` (M, 3) / ``static_rgb``
    (M, 3) uint8 are given, to ``static.ply``; its images to the overlays. An existing ``out``
    is refused (InputError) unless ``overwrite`` and dloe-sfm wrote it (``io.check_output``),
    in which case it is replaced only once the new folder is complete. ``export_rate``, ``fps``:
    as :func:`write_outputs`. ``overlay_images``: the images with a readable file, when
    checked already (``viz.readable_images``).
    """
    out = Path(out)
    target = check_output(out, overwrite=overwrite, protected=[] if workspace is None else
                          [workspace.model_dir, workspace.image_dir])
    if workspace is not None and static_xyz is None:
        static_xyz, static_rgb = workspace.static_xyz, workspace.static_rgb
    tic = time.perf_counter()
    with atomic_path(target, mark=True) as tmp:
        tmp.mkdir()
        summary = write_outputs(tmp, capture, result, static_xyz=static_xyz,
                                static_rgb=static_rgb, layout=layout, report=report,
                                export_rate=export_rate, fps=fps)
        if plots:
            from . import viz  # matplotlib / cv2 only when plotting

            viz.write_plots(tmp / "plots", capture, result, workspace=workspace,
                            edges=None if layout is None else
                            np.asarray(layout.edges, dtype=np.int64).reshape(-1, 2),
                            point_names=None if layout is None else list(layout.point_names),
                            overlay_images=overlay_images)
    logger.info("outputs written in %.1f s: %s (frames/, trajectories.npz / .trc / .c3d, "
                "report.json%s)",
                time.perf_counter() - tic, out, ", plots/" if plots else "")
    error = summary["reprojection_error_px"]["all"]
    if error["mean"] is not None:
        logger.info("mean reprojection error %.3f px (median %.3f) over %d observations",
                    error["mean"], error["median"], error["count"])
    left_out = summary.get("detections_left_out", {}).get("count", 0)
    logger.info("%d subject(s)%s; robust loss: %d observation(s) down-weighted, %d left/right "
                "swap(s) fixed (report.json)", summary["subjects"],
                f", {left_out} detection(s) supporting none left out" if left_out else "",
                summary["downweighted"]["count"], summary["swaps_fixed"]["count"])
    if summary["stream_offsets"]["count"]:
        logger.info("detector offsets taken out: %d (stream, point) pairs, median %.2f px "
                    "(report.json: stream_offsets)", summary["stream_offsets"]["count"],
                    summary["stream_offsets"]["median_px"])
    return summary
