"""Lab rig: a calibrated, synchronised 4-camera capture made asynchronous, DLOE vs. triangulation.

Data: the Pose2Sim single-trial sample (Qualisys calibration + OpenPose BODY_25B per frame).

1. calibration -> a COLMAP workspace whose model holds one image entry per kept frame per camera
   (``cam01/0012.jpg``; no image files needed);
2. asynchronous subsampling: camera k keeps frames f with ``f % step == k % step``, so no two
   kept images share an instant;
3. OpenPose JSON -> keypoints keyed by those image names -> capture -> DLOE -> section-4 outputs;
4. synchronised DLT triangulation of the same detections (all cameras at every frame, undistorted
   rays) and a comparison table: reprojection error in the views each method used, in views it
   did not use (held out), and the 3D distance between the two reconstructions;
5. DLOE's timing against the true frames (Kendall tau, per-stream offset errors, RMS time error)
   and issue 14's acceptance checks, at the package's default solver options.

    python pipelines/lab_rig/pipeline.py --data ../shared/data/pose2sim_single_trial \\
        --out outputs/lab_rig
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
import time
from pathlib import Path

import numpy as np

import dloe_sfm
from dloe_sfm.calibration import import_calibration, read_calibration
from dloe_sfm.colmap import Workspace, load_workspace
from dloe_sfm.columns import solved_capture
from dloe_sfm.config import load_options
from dloe_sfm.core.sequencing import kendall_tau
from dloe_sfm.errors import InputError
from dloe_sfm.export import error_stats, export_outputs, reprojection_errors
from dloe_sfm.io import atomic_path, check_output, save_npz
from dloe_sfm.keypoints import Keypoints, read_keypoints
from dloe_sfm.mocap_export import image_times
from dloe_sfm.observations import build_capture, select_person

logger = logging.getLogger("dloe_sfm")

LAYOUT = "BODY_25B"  # Pose2Sim's OpenPose model (same joint count as OpenPose's default BODY_25)
KEY = re.compile(r"^(cam\d+)_json/\1\.(\d+)$")  # cam01_json/cam01.0012
FPS = 60.0  # the sample's frame rate: an image's true time is its frame number
ACCEPT_TAU = 0.99  # issue 14's acceptance of the lab rig (see the README)
ACCEPT_OFFSET_STREAM_FRAMES = 0.25
ACCEPT_HELD_OUT_MEDIAN_PX = 14.0


def camera_folder(serial: str) -> str:
    """Qualisys serial ``cam_01`` -> Pose2Sim folder name ``cam01``."""
    return serial.replace("_", "")


def detections(kp: Keypoints, cameras: list[str]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Frames seen by every camera, and per camera the (M, P, 3) detections of each such frame."""
    per_camera: dict[str, dict[int, np.ndarray]] = {c: {} for c in cameras}
    ignored = []
    for key, people in kp.points.items():
        match = KEY.match(key)
        if match is None or match.group(1) not in per_camera:
            ignored.append(key)
            continue
        per_camera[match.group(1)][int(match.group(2))] = people
    if ignored:
        logger.info("%s: %d file(s) not named camXX_json/camXX.NNNN ignored: %s", kp.source,
                    len(ignored), ", ".join(ignored[:4]) + (" ..." if len(ignored) > 4 else ""))
    frames = sorted(set.intersection(*(set(v) for v in per_camera.values())))
    if not frames:
        raise InputError(f"{kp.source}: no frame has OpenPose files for all of {cameras}")
    return np.array(frames), {c: per_camera[c] for c in cameras}


def image_name(camera: str, frame: int) -> str:
    return f"{camera}/{frame:04d}.jpg"


def triangulate(uv: np.ndarray, weight: np.ndarray, Rt: np.ndarray) -> np.ndarray:
    """Weighted DLT of undistorted observations.

    uv (F, V, P, 2) normalised image coordinates (NaN = missing), weight (F, V, P) scores,
    Rt (V, 3, 4) world-to-camera -> X (F, P, 3), NaN where fewer than two views see the point.
    """
    ok = np.isfinite(uv).all(axis=-1) & (weight > 0)
    w = np.where(ok, weight, 0.0)[..., None]
    u = np.nan_to_num(uv)
    rows_u = w * (u[..., 0:1] * Rt[None, :, None, 2] - Rt[None, :, None, 0])  # (F, V, P, 4)
    rows_v = w * (u[..., 1:2] * Rt[None, :, None, 2] - Rt[None, :, None, 1])
    A = np.concatenate([rows_u, rows_v], axis=1).transpose(0, 2, 1, 3)  # (F, P, 2V, 4)
    h = np.linalg.svd(A)[2][..., -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):  # rows of unseen points are all zero
        X = h[..., :3] / h[..., 3:4]
    X[ok.sum(axis=1) < 2] = np.nan
    return X


def pinhole_errors(X: np.ndarray, uv: np.ndarray, K: np.ndarray, Rt: np.ndarray) -> np.ndarray:
    """Pixel distances in the ideal pinhole of each view: X (F, P, 3), uv (F, V, P, 2) observed
    normalised coordinates, K (V, 3, 3), Rt (V, 3, 4) -> (F, V, P), NaN where unobserved."""
    cam = np.einsum("vij,fpj->fvpi", Rt[:, :, :3], X) + Rt[None, :, None, :, 3]
    proj = cam[..., :2] / cam[..., 2:3]
    f = np.stack([K[:, 0, 0], K[:, 1, 1]], axis=1)[None, :, None, :]
    return np.linalg.norm((proj - uv) * f, axis=-1)


def run(data: Path, out: Path, *, step: int = 4, min_score: float = 0.3,
        overrides: list[str] | None = None, overwrite: bool = False, plots: bool = True) -> dict:
    """The whole pipeline; returns the comparison table (also saved to ``out/comparison.json``)."""
    data, out = Path(data), Path(out)
    calib = data / "calibration" / "Calib.qca.txt"
    out = check_output(out, protected=[data], overwrite=overwrite)
    options = load_options(None, overrides)
    tic = time.perf_counter()

    serials = [c.name for c in read_calibration(calib)]
    cameras = [camera_folder(s) for s in serials]
    kp_all = read_keypoints("openpose", data / "pose", layout=LAYOUT)
    frames, dets = detections(kp_all, cameras)
    kept = {c: [int(f) for f in frames if f % step == k % step] for k, c in enumerate(cameras)}
    logger.info("%d synchronised frames; asynchronous subset: every %d-th frame per camera, "
                "%d images", frames.size, step, sum(map(len, kept.values())))

    with atomic_path(out, mark=True) as tmp:
        tmp.mkdir()
        model = import_calibration(
            calib, tmp / "workspace" / "sparse" / "0",
            {s: [image_name(c, f) for f in kept[c]] for s, c in zip(serials, cameras, strict=True)},
        )
        ws = load_workspace(model.parent.parent)
        kp = Keypoints(layout=kp_all.layout, source=kp_all.source, points={
            image_name(c, f): dets[c][f] for c in cameras for f in kept[c]
        })
        capture = build_capture(ws, kp, min_score=min_score, person="largest").capture
        result = dloe_sfm.reconstruct(capture, options)
        seconds_dloe = result.seconds
        logger.info("DLOE: %s, %.1f s", result.message, seconds_dloe)
        report = export_outputs(tmp / "dloe", capture, result, workspace=ws, layout=kp.layout,
                                plots=plots, report={
                                    "inputs": {"data": str(data.resolve()), "step": step,
                                               "min_score": min_score},
                                    "parameters": options.to_dict()})
        table = compare(ws, capture, result, cameras, frames, dets, kept, min_score, tmp)
        table["timing"] = timing(capture, result, report["sync"], step)
        table["acceptance"] = acceptance(table)
        table["seconds"] = {"dloe_solve": seconds_dloe, "pipeline": time.perf_counter() - tic}
        with open(tmp / "comparison.json", "w") as f:
            json.dump(table, f, indent=2)
    print_table(table)
    logger.info("outputs in %s: workspace/ (COLMAP model), dloe/ (reconstruction), "
                "sync_triangulation.npz, comparison.json", out)
    return table


def compare(ws: Workspace, capture: dloe_sfm.Capture, result: dloe_sfm.Result,
            cameras: list[str], frames: np.ndarray, dets: dict[str, dict[int, np.ndarray]],
            kept: dict[str, list[int]], min_score: float, folder: Path) -> dict:
    """Synchronised DLT of every frame vs. DLOE on the asynchronous images; returns the table
    and writes ``folder/sync_triangulation.npz``."""
    some_image = {c: image_name(c, kept[c][0]) for c in cameras}  # one pose per camera
    K = np.stack([ws.pinhole(some_image[c]) for c in cameras])
    Rt = np.stack([np.concatenate([ws.rotation(some_image[c]),
                                   -ws.rotation(some_image[c]) @ ws.centre(some_image[c])[:, None]],
                                  axis=1) for c in cameras])
    num_points = capture.num_points
    uv = np.full((frames.size, len(cameras), num_points, 2), np.nan)
    score = np.zeros((frames.size, len(cameras), num_points))
    for v, c in enumerate(cameras):
        for t, f in enumerate(frames):
            people = dets[c][int(f)]
            pts = select_person(people, "largest", min_score) if len(people) else None
            if pts is None:
                continue
            s = np.nan_to_num(pts[:, 2])
            good = (s > 0) & (s >= min_score)
            pixels = np.where(good[:, None], pts[:, :2] + 0.5, np.nan)  # OpenPose -> COLMAP
            uv[t, v] = ws.normalised(some_image[c], pixels)
            score[t, v] = np.where(np.isfinite(uv[t, v]).all(axis=1), np.clip(s, 0, 1), 0.0)
    X_sync = triangulate(uv, score, Rt)
    sync_err = pinhole_errors(X_sync, uv, K, Rt)

    # leave-one-camera-out: triangulate without view v, reproject into v (held-out error)
    loo_err = np.full_like(sync_err, np.nan)
    for v in range(len(cameras)):
        others = [o for o in range(len(cameras)) if o != v]
        X_loo = triangulate(uv[:, others], score[:, others], Rt[others])
        loo_err[:, v] = pinhole_errors(X_loo, uv[:, [v]], K[[v]], Rt[[v]])[:, 0]

    # DLOE: error in its own (asynchronous) views, and in the other cameras at the same frame
    frame_row = {int(f): t for t, f in enumerate(frames)}
    view = {c: v for v, c in enumerate(cameras)}
    dloe_own = reprojection_errors(capture, result.X)
    dloe_held = np.full((capture.num_images, len(cameras) - 1, num_points), np.nan)
    sync_same = np.full((capture.num_images, num_points), np.nan)
    distance = np.full((capture.num_images, num_points), np.nan)
    for i, name in enumerate(capture.image_names):
        c, f = name.split("/")[0], int(Path(name).stem)
        t, v = frame_row[f], view[c]
        others = [o for o in range(len(cameras)) if o != v]
        dloe_held[i] = pinhole_errors(result.X[i][None], uv[[t]][:, others], K[others],
                                      Rt[others])[0]
        sync_same[i] = np.where(capture.visible[i], sync_err[t, v], np.nan)
        distance[i] = np.linalg.norm(result.X[i] - X_sync[t], axis=1)

    save_npz(folder / "sync_triangulation.npz", X=X_sync, frames=frames,
             cameras=np.array(cameras), reprojection_error=sync_err)
    return {
        "units": "pixels of the undistorted (ideal pinhole) images; distance in millimetres",
        "dloe_async": {
            "images": capture.num_images,
            "reprojection_error_px": error_stats(dloe_own),
            "held_out_views_error_px": error_stats(dloe_held),
        },
        "sync_triangulation": {
            "images": int(frames.size * len(cameras)),
            "reprojection_error_px": error_stats(sync_err),
            "same_observations_as_dloe_px": error_stats(sync_same),
            "held_out_views_error_px (leave one camera out)": error_stats(loo_err),
        },
        "dloe_vs_sync_distance_mm": error_stats(distance * 1000.0),
    }


def timing(capture: dloe_sfm.Capture, result: dloe_sfm.Result, sync: dict, step: int) -> dict:
    """DLOE's timing against the truth: the true time of image ``camXX/NNNN.jpg`` is frame NNNN.

    The estimated times are the exports' (``mocap_export.image_times``, in frames of the
    reference stream as its images are numbered: 60 Hz frames here). A stream's offset error is
    the median over its images of (estimated - true time) minus the reference stream's; the
    RMS time error is taken after removing the mean of (estimated - true time). ``sync``:
    ``report.json``'s entry, whose first event's clocks (offset at the stream's first image,
    rate) are given for comparison.
    """
    timeline = image_times(solved_capture(capture, result), result)
    names = capture.image_names
    truth = np.array([int(Path(name).stem) for name in names], dtype=np.float64)
    camera = np.array([name.split("/")[0] for name in names])
    stream_ids = capture.stream_ids
    error = timeline.time - truth
    clocks = sync["events"][0]
    reference = clocks["reference_stream"]
    first = {int(s): truth[stream_ids == s][0] - capture.frame[stream_ids == s][0]
             for s in np.unique(stream_ids)}  # true time of each stream's frame 0
    ref_error = float(np.median(error[stream_ids == reference]))
    streams = {}
    for s in np.unique(stream_ids):
        mine = stream_ids == s
        offset = float(np.median(error[mine])) - ref_error
        true_offset = float(first[int(s)] - first[reference])
        clock = clocks["streams"].get(str(s))
        streams[str(camera[mine][0])] = {
            "images": int(mine.sum()),
            "true_offset_frames": true_offset,
            "offset_error_frames": offset,
            "offset_error_stream_frames": offset / step,
            "offset_error_ms": 1000.0 * offset / FPS,
            "clock_offset_error_frames": None if clock is None else
            clock["offset_frames"] - true_offset,
            "clock_rate": None if clock is None else clock["rate"],
        }
    return {
        "units": f"frames at {FPS:g} Hz (the image frame numbers), unless named otherwise; "
                 f"a stream frame is {step} of them",
        "events": len(sync["events"]),
        "time_base": clocks["base"],
        "kendall_tau": kendall_tau(result.order, truth),
        "reference_camera": str(camera[stream_ids == reference][0]),
        "time_error_rms_frames": float(np.sqrt(np.mean((error - error.mean()) ** 2))),
        "streams": streams,
    }


def acceptance(table: dict) -> dict:
    """Issue 14's three acceptance items (offsets: within a fraction of the stream's own frame
    period), each with its measured value and whether it holds."""
    tau = table["timing"]["kendall_tau"]
    offset = max(abs(s["offset_error_stream_frames"])
                 for s in table["timing"]["streams"].values())
    held = table["dloe_async"]["held_out_views_error_px"]["median"]
    return {
        f"kendall |tau| >= {ACCEPT_TAU}": {"value": tau, "pass": tau >= ACCEPT_TAU},
        f"max |stream offset error| <= {ACCEPT_OFFSET_STREAM_FRAMES} stream frame": {
            "value": offset, "pass": offset <= ACCEPT_OFFSET_STREAM_FRAMES},
        f"held-out median <= {ACCEPT_HELD_OUT_MEDIAN_PX:g} px": {
            "value": held, "pass": held is not None and held <= ACCEPT_HELD_OUT_MEDIAN_PX},
    }


def print_table(table: dict) -> None:
    def cell(stats: dict) -> str:
        return "n/a" if stats["mean"] is None else f"{stats['mean']:8.2f} {stats['median']:8.2f}"

    dloe, sync = table["dloe_async"], table["sync_triangulation"]
    rows = [
        ("DLOE, asynchronous", dloe["images"], cell(dloe["reprojection_error_px"]),
         cell(dloe["held_out_views_error_px"])),
        ("sync. DLT, all cameras", sync["images"], cell(sync["reprojection_error_px"]),
         cell(sync["held_out_views_error_px (leave one camera out)"])),
        ("sync. DLT, DLOE's observations", dloe["images"],
         cell(sync["same_observations_as_dloe_px"]), ""),
    ]
    print(f"{'method':32s} {'images':>6s}  {'used views: mean / median px':>28s}  "
          f"{'held-out views: mean / median px':>32s}")
    for name, n, used, held in rows:
        print(f"{name:32s} {n:6d}  {used:>28s}  {held:>32s}")
    d = table["dloe_vs_sync_distance_mm"]
    print(f"DLOE vs. synchronised triangulation, 3D distance: mean {d['mean']:.1f} mm, "
          f"median {d['median']:.1f} mm over {d['count']} joints")
    sync = table["timing"]
    print(f"timing vs. the true frames: Kendall |tau| {sync['kendall_tau']:.4f}, RMS time error "
          f"{sync['time_error_rms_frames']:.3f} frames (base: {sync['time_base']}, reference "
          f"{sync['reference_camera']})")
    print(f"{'stream':8s} {'true offset':>11s}  {'offset error: frames':>20s} "
          f"{'stream frames':>13s} {'ms':>7s}  {'clock: offset error':>19s} {'rate':>6s}")
    for c, s in sync["streams"].items():
        clock = ("" if s["clock_rate"] is None else
                 f"{s['clock_offset_error_frames']:19.3f} {s['clock_rate']:6.3f}")
        print(f"{c:8s} {s['true_offset_frames']:11.0f}  {s['offset_error_frames']:20.3f} "
              f"{s['offset_error_stream_frames']:13.3f} {s['offset_error_ms']:7.2f}  {clock}")
    for item, check in table["acceptance"].items():
        value = "n/a" if check["value"] is None else f"{check['value']:.4g}"
        print(f"{'PASS' if check['pass'] else 'FAIL'}  {item}: {value}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="pose2sim_single_trial folder")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--step", type=int, default=4,
                        help="each camera keeps every STEP-th frame, offset by its index")
    parser.add_argument("--min-score", type=float, default=0.3, help="OpenPose score threshold")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="override one solver option (repeatable)")
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--no-plots", dest="plots", action="store_false")
    args = parser.parse_args(argv)
    try:
        run(args.data, args.out, step=args.step, min_score=args.min_score,
            overrides=args.overrides, overwrite=args.overwrite, plots=args.plots)
    except InputError as e:
        parser.exit(2, f"{parser.prog}: error: {e}\n")
    return 0


if __name__ == "__main__":
    from dloe_sfm.cli import setup_logging

    setup_logging()
    sys.exit(main())
