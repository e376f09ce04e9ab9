"""TRC / C3D / wide-CSV exports (issue 16): read back against the formats, not the writer."""

from __future__ import annotations

import csv
import json
from dataclasses import replace
from pathlib import Path

import ezc3d
import numpy as np
import pytest
import scipy.sparse as sp
from scenes import TOY_LAYOUT, toy_capture, write_openpose

import dloe_sfm.stages.reconstruct as stage
from dloe_sfm import Capture, InputError, Result, cli, colmap
from dloe_sfm.export import export_outputs, write_outputs
from dloe_sfm.keypoints import Layout
from dloe_sfm.keypoints.base import LAYOUTS
from dloe_sfm.mocap_export import (
    image_times,
    resample_uniform,
    whole_factor,
    write_c3d,
    write_trc,
)

NAMES = ["head", "hip", "foot"]
VELOCITY = np.array([[0.3, -0.2, 0.1], [0.0, 0.5, 0.0], [-0.4, 0.0, 0.25]])  # mm per unit
START = np.array([[10.0, 20.0, 1500.0], [0.0, 5.0, 1000.0], [-50.0, 8.0, 40.0]])


def linear(t: np.ndarray) -> np.ndarray:
    """(T, 3, 3) points moving in straight lines: exact under linear interpolation."""
    return START[None] + np.asarray(t, dtype=np.float64)[:, None, None] * VELOCITY[None]


def read_trc(path: Path) -> dict:
    """A TRC reader from the format's description (OpenSim / Pose2Sim): five header lines, a
    blank line, then ``Frame#  Time  X1 Y1 Z1 ...`` rows, tab-separated, empty = missing."""
    lines = Path(path).read_text().split("\n")
    first = lines[0].split("\t")
    assert first[:3] == ["PathFileType", "4", "(X/Y/Z)"] and first[3] == Path(path).name
    keys, values = lines[1].split("\t"), lines[2].split("\t")
    assert keys == ["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units",
                    "OrigDataRate", "OrigDataStartFrame", "OrigNumFrames"]
    header = dict(zip(keys, values, strict=True))
    num = int(header["NumMarkers"])
    labels = lines[3].split("\t")
    assert labels[:2] == ["Frame#", "Time"] and len(labels) == 2 + 3 * num
    names = labels[2::3]
    assert all(labels[3 + 3 * k: 5 + 3 * k] == ["", ""] for k in range(num))  # two tabs each
    axes = lines[4].split("\t")
    assert axes == ["", ""] + [f"{a}{k}" for k in range(1, num + 1) for a in "XYZ"]
    assert lines[5] == "" and lines[-1] == ""
    rows = [line.split("\t") for line in lines[6:-1]]
    assert all(len(row) == 2 + 3 * num for row in rows)
    frame = np.array([int(row[0]) for row in rows])
    time = np.array([float(row[1]) for row in rows])
    xyz = np.array([[float(v) if v else np.nan for v in row[2:]] for row in rows])
    return {"header": header, "names": names, "frame": frame, "time": time,
            "xyz": xyz.reshape(len(rows), num, 3)}


def read_c3d(path: Path) -> dict:
    c3d = ezc3d.c3d(str(path))
    params = c3d["parameters"]
    return {"names": list(params["POINT"]["LABELS"]["value"]),
            "rate": float(params["POINT"]["RATE"]["value"][0]),
            "units": params["POINT"]["UNITS"]["value"][0],
            "start": float(params["DLOE_SFM"]["START_TIME"]["value"][0]),
            "unit": params["DLOE_SFM"]["TIME_UNIT"]["value"][0],
            "xyz": np.transpose(c3d["data"]["points"][:3], (2, 1, 0))}


def check_trc_and_c3d(trc_path: Path, c3d_path: Path, names: list[str]) -> dict:
    """The TRC header agrees with its data and the C3D with the TRC; returns the TRC."""
    trc = read_trc(trc_path)
    header = trc["header"]
    count, rate = int(header["NumFrames"]), float(header["DataRate"])
    assert header["Units"] == "mm" and trc["names"] == names
    assert float(header["CameraRate"]) == float(header["OrigDataRate"]) == rate
    assert int(header["NumMarkers"]) == len(names) and int(header["OrigNumFrames"]) == count
    np.testing.assert_array_equal(trc["frame"], np.arange(1, count + 1))
    np.testing.assert_allclose(trc["time"], trc["time"][0] + np.arange(count) / rate,
                               rtol=0, atol=1e-9)  # uniform DataRate
    c3d = read_c3d(c3d_path)
    assert c3d["names"] == names and c3d["units"] == "mm" and c3d["rate"] == pytest.approx(rate)
    assert c3d["start"] == pytest.approx(trc["time"][0]) and c3d["xyz"].shape == trc["xyz"].shape
    # ezc3d reads the points written invalid (residual -1) as NaN
    np.testing.assert_array_equal(np.isnan(c3d["xyz"]), np.isnan(trc["xyz"]))
    np.testing.assert_allclose(c3d["xyz"], trc["xyz"], rtol=1e-6, atol=1e-4)  # float32
    return trc


def test_linear_motion_at_irregular_times_is_exact_on_the_grid(tmp_path) -> None:
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0.0, 10.0, 40))
    t[[0, -1]] = 0.0, 10.0
    grid, Y = resample_uniform(t, linear(t), np.ones((t.size, 3), bool), rate=4.0)
    np.testing.assert_allclose(grid, np.arange(41) / 4.0, rtol=0, atol=1e-12)
    write_trc(tmp_path / "m.trc", grid, Y, NAMES, 4.0)
    write_c3d(tmp_path / "m.c3d", grid, Y, NAMES, 4.0, unit="frame", note="test")
    trc = check_trc_and_c3d(tmp_path / "m.trc", tmp_path / "m.c3d", NAMES)
    assert float(trc["header"]["DataRate"]) == 4.0 and len(trc["time"]) == 41
    np.testing.assert_allclose(trc["xyz"], linear(trc["time"]), rtol=0, atol=1e-6)


def test_gaps_are_left_empty_and_segments_never_bridged() -> None:
    t = np.array([0.0, 1.0, 2.0, 5.0, 6.0, 8.0, 9.0])
    segments = np.array([0, 0, 0, 0, 0, 1, 1])
    valid = np.ones((t.size, 3), bool)
    valid[1, 1] = False  # point 1 unobserved at t = 1: its 0..2 gap is 2 > 1.5
    X = linear(t)
    X[4, 2] = np.nan  # point 2 not finite at t = 6: its last sample is t = 5
    grid, Y = resample_uniform(t, X, valid, rate=2.0, segments=segments, max_gap=1.5)
    np.testing.assert_allclose(grid, np.arange(19) / 2.0)
    filled = np.isfinite(Y[..., 0])
    inside = (grid <= 2.0) | ((grid >= 5.0) & (grid <= 6.0)) | (grid >= 8.0)
    np.testing.assert_array_equal(filled[:, 0], inside)  # 2..5 (gap 3) and 6..8 (events)
    np.testing.assert_array_equal(filled[:, 1], inside & ~((grid > 0) & (grid < 2)))
    np.testing.assert_array_equal(filled[:, 2], inside & (grid != 5.5) & (grid != 6.0))
    np.testing.assert_allclose(Y[filled], linear(grid)[filled], rtol=0, atol=1e-9)
    # a per-segment gap: segment 1 allows nothing longer than 0.5, its 8..9 gap goes empty
    _, Y2 = resample_uniform(t, X, valid, rate=2.0, segments=segments, max_gap=[1.5, 0.5])
    np.testing.assert_array_equal(np.isfinite(Y2[:, 0, 0]), inside & ~(grid > 8.0) | (grid == 9))


def test_duplicate_sample_times_are_averaged() -> None:
    t = np.array([0.0, 1.0, 1.0, 2.0])
    X = linear(t)
    X[1] += 1.0
    X[2] -= 1.0
    _, Y = resample_uniform(t, X, np.ones((4, 3), bool), rate=1.0)
    np.testing.assert_allclose(Y, linear([0.0, 1.0, 2.0]), rtol=0, atol=1e-12)


def clocked_capture(clock: bool) -> tuple[Capture, Result]:
    """Two streams of 6 frames, stream 1 a third of a frame behind, an estimated order that
    interleaves them; with ``clock`` the result holds the fitted clock (a stream-1 rate 2 %
    off), else its embedding is the clock scaled by 0.1 (the affine embedding)."""
    stream = np.array([0, 1] * 6)
    frame = np.repeat(np.arange(6), 2)
    true_time = frame + stream / 3.0
    ticks = np.where(stream == 1, 1.02 * frame + 1 / 3.0, frame)
    n = stream.size
    capture = Capture(x=np.zeros((n, 3, 2)), K=np.tile(np.eye(3), (n, 1, 1)),
                      R=np.tile(np.eye(3), (n, 1, 1)), C=np.zeros((n, 3)), stream=stream,
                      frame=frame)
    chain = sp.identity(n, format="csr")
    result = Result(X=linear(true_time) / 1000.0, order=np.argsort(true_time), A=chain, W=chain,
                    D=np.ones(n), events=np.zeros(n, dtype=np.int64),
                    embedding=(5.0 + 0.1 * ticks) if not clock else np.arange(n) * 7.0,
                    cost_history=np.zeros(1), change_history=np.zeros(1), nit=1, success=True,
                    message="", seconds=0.0, clock=(3.0 + 2.0 * ticks) if clock else None)
    return capture, result


@pytest.mark.parametrize("clock", [True, False])
def test_image_times_follow_the_clock_or_the_affine_embedding(clock) -> None:
    capture, result = clocked_capture(clock)
    timeline = image_times(capture, result)
    stream, frame = capture.stream, capture.frame
    expected = np.where(stream == 1, 1.02 * frame + 1 / 3.0, frame)
    np.testing.assert_allclose(timeline.time, expected, rtol=0, atol=1e-9)
    (event,) = timeline.events
    assert event["base"] == ("clock" if clock else "affine embedding")
    assert event["reference_stream"] == 0 and timeline.unit == "frame"
    assert timeline.rate == 1.0  # stream 1 is 2 % slower: the reference's rate is the fastest
    assert event["max_gap"] == pytest.approx(1.5 * 1.02)


def test_streams_keeping_every_4th_frame_interpolate_across_their_own_step() -> None:
    """Cameras that keep every 4th frame of their video sample a point every 4 frame periods:
    the gap a point is interpolated across is 1.5 of those (the asynchronous Pose2Sim trial's
    TRC had 29 % empty rows with 1.5 frame periods)."""
    capture, result = clocked_capture(True)
    stepped = replace(capture, frame=4 * capture.frame)
    (event,) = image_times(stepped, result).events
    assert event["max_gap"] == pytest.approx(1.5 * 4 * 1.02)


def test_rank_times_between_reference_frames_and_events_not_bridged() -> None:
    capture, result = clocked_capture(False)
    result.embedding = np.sqrt(np.arange(12.0))[np.argsort(result.order)]  # not affine
    result.events = (capture.frame >= 3).astype(np.int64)  # the video stopped between 2 and 3
    capture.frame = np.where(capture.frame >= 3, capture.frame + 10, capture.frame)
    timeline = image_times(capture, result)
    first, second = timeline.events
    assert first["base"] == second["base"] == "rank"
    assert second["offset_known"] and not first["offset_known"]
    # reference (stream 0) images at their frames, stream 1 halfway to the next by rank
    np.testing.assert_allclose(timeline.time[capture.stream == 0], [0, 1, 2, 13, 14, 15])
    np.testing.assert_allclose(timeline.time[capture.stream == 1],
                               [0.5, 1.5, 2.5, 13.5, 14.5, 15.5])
    # different reference streams: the later event is placed 2 frames after the first
    capture.stream = np.where(capture.frame >= 13, capture.stream + 2, capture.stream)
    second = image_times(capture, result).events[1]
    assert not second["offset_known"] and second["start"] == pytest.approx(2.5 + 2.0)


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Capture, Result]:
    capture, result, _ = toy_capture()
    out = tmp_path_factory.mktemp("mocap") / "out"
    export_outputs(out, capture, result, layout=TOY_LAYOUT, plots=False)
    return out, capture, result


def test_export_files_agree_with_the_trajectories(exported) -> None:
    out, capture, result = exported
    trc = check_trc_and_c3d(out / "trajectories.trc", out / "trajectories.c3d",
                            TOY_LAYOUT.point_names)
    with open(out / "sequence.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    order = result.order
    assert [r["image"] for r in rows] == capture.image_names[order].tolist()
    time = np.array([float(r["time"]) for r in rows])
    assert (np.diff(time) > 0).all()
    # at an image's own instant, every observed point is that image's X in mm
    for i, t in zip(order, time, strict=True):
        at = np.flatnonzero(np.isclose(trc["time"], t, rtol=0, atol=1e-9))
        if at.size:
            seen = capture.visible[i]
            np.testing.assert_allclose(trc["xyz"][at[0], seen], result.X[i, seen] * 1000.0,
                                       rtol=0, atol=1e-6)
    # the toy's point 2 is unobserved in image 4: the TRC leaves that instant empty there
    (at,) = np.flatnonzero(np.isclose(trc["time"], time[result.rank[4]]))
    assert np.isnan(trc["xyz"][at, 2]).all() and np.isfinite(trc["xyz"][at, [0, 1, 3]]).all()
    report = json.loads((out / "report.json").read_text())["mocap_export"]
    assert report["units"] == "mm" and report["samples"] == len(trc["time"])
    assert [e["event"] for e in report["events"]] == [1, 0]  # estimated order: reversed


def test_wide_csv_round_trip(exported) -> None:
    out, capture, result = exported
    with open(out / "trajectories_wide.csv", newline="") as f:
        reader = csv.reader(f)
        header = next(reader)
        rows = list(reader)
    assert header == ["rank", "image", "event", "stream", "frame", "time",
                      *(f"{n}_{a}" for n in TOY_LAYOUT.point_names for a in "xyz")]
    order = result.order
    assert [int(r[0]) for r in rows] == list(range(len(order)))
    assert [r[1] for r in rows] == capture.image_names[order].tolist()
    np.testing.assert_array_equal([int(r[2]) for r in rows], result.events[order])
    np.testing.assert_array_equal([int(r[3]) for r in rows], capture.stream[order])
    np.testing.assert_array_equal([int(r[4]) for r in rows], capture.frame[order])
    X = np.array([[float(v) for v in r[6:]] for r in rows]).reshape(result.X.shape)
    np.testing.assert_array_equal(X, result.X[order])
    with open(out / "sequence.csv", newline="") as f:
        times = [r["time"] for r in csv.DictReader(f)]
    assert [r[5] for r in rows] == times


def test_several_subjects_are_prefixed(tmp_path) -> None:
    capture, result, _ = toy_capture()
    result.subject_id = np.array([0, 0, 0, 1, 1])
    result.point_id = np.array([0, 1, 2, 0, 1])
    export_outputs(tmp_path / "out", capture, result, layout=Layout("three", ["a", "b", "c"]),
                   plots=False)
    names = ["s0_a", "s0_b", "s0_c", "s1_a", "s1_b"]
    check_trc_and_c3d(tmp_path / "out" / "trajectories.trc",
                      tmp_path / "out" / "trajectories.c3d", names)


def test_export_rate_is_checked_and_used(tmp_path) -> None:
    capture, result, _ = toy_capture()
    for k, bad in enumerate((0.0, np.nan, 1e9)):  # 1e9: a grid of 1.8e10 samples
        (tmp_path / str(k)).mkdir()
        with pytest.raises(InputError, match="--export-rate"):
            write_outputs(tmp_path / str(k), capture, result, layout=TOY_LAYOUT, export_rate=bad)
    for bad in ("-1", "0", "nan", "fast"):
        with pytest.raises(SystemExit) as exit_info:
            cli.main(["reconstruct", str(tmp_path), "--format", "csv", "--out",
                      str(tmp_path / "o"), "--export-rate", bad])
        assert exit_info.value.code == 2
    (tmp_path / "ok").mkdir()
    report = write_outputs(tmp_path / "ok", capture, result, layout=TOY_LAYOUT, export_rate=2.5)
    trc = read_trc(tmp_path / "ok" / "trajectories.trc")
    assert float(trc["header"]["DataRate"]) == report["mocap_export"]["rate"] == 2.5


def test_known_frame_rates_put_the_exports_in_seconds_and_hz(tmp_path) -> None:
    """With the reference stream's 60 fps known, the TRC / C3D / wide CSV are those in frames
    with time over 60 and the rate times 60 (Hz); with its rate unknown they stay in frames."""
    capture, result, _ = toy_capture()
    result = replace(result, order=np.arange(capture.num_images))  # stream 0 the reference
    reports, trcs = {}, {}
    for name, fps in (("frames", None), ("seconds", 60.0), ("unknown", {1: 60.0, 2: 60.0})):
        reports[name] = export_outputs(tmp_path / name, capture, result, layout=TOY_LAYOUT,
                                       plots=False, fps=fps)["mocap_export"]
        trcs[name] = check_trc_and_c3d(tmp_path / name / "trajectories.trc",
                                       tmp_path / name / "trajectories.c3d",
                                       TOY_LAYOUT.point_names)
    assert all(e["reference_stream"] == 0 for e in reports["seconds"]["events"])
    frames, seconds = trcs["frames"], trcs["seconds"]
    assert float(seconds["header"]["DataRate"]) == 60.0 * float(frames["header"]["DataRate"])
    assert float(seconds["header"]["DataRate"]) == reports["seconds"]["rate"] == 60.0
    np.testing.assert_allclose(seconds["time"], frames["time"] / 60.0, rtol=1e-12)
    np.testing.assert_array_equal(seconds["xyz"], frames["xyz"])
    assert read_c3d(tmp_path / "seconds" / "trajectories.c3d")["unit"] == "s"
    assert reports["seconds"]["time_unit"] == "s" and reports["seconds"]["fps"] == 60.0
    with open(tmp_path / "seconds" / "trajectories_wide.csv", newline="") as f:
        wide = [float(r["time"]) for r in csv.DictReader(f)]
    with open(tmp_path / "seconds" / "sequence.csv", newline="") as f:
        assert wide == [float(r["time"]) for r in csv.DictReader(f)]  # seconds in both
    assert trcs["unknown"]["header"] == frames["header"]
    assert reports["unknown"]["time_unit"] == "frame" and reports["unknown"]["fps"] is None


def test_frame_numbers_in_steps_warn_what_fps_means(tmp_path, log_lines) -> None:
    """Frames named at a video's rate with every 4th kept: --fps counts the numbers, and the
    warning says what to give if the rate was meant as the images'."""
    capture, result, _ = toy_capture()
    result = replace(result, order=np.arange(capture.num_images))
    export_outputs(tmp_path / "one", capture, result, layout=TOY_LAYOUT, plots=False, fps=60.0)
    assert not [line for line in log_lines if "step by" in line]
    stepped = replace(capture, frame=4 * capture.frame)
    report = export_outputs(tmp_path / "four", stepped, result, layout=TOY_LAYOUT,
                            plots=False, fps=60.0)
    assert [line for line in log_lines if line.startswith(
        "stream(s) 0, 1, 2: the frame numbers in the image names step by 4, so at 60 fps (the "
        "rate of those numbers, --fps) the images are 15 per second; if 60 fps is the images' "
        "own rate, the numbers run at 240: give --fps 240")], log_lines
    assert report["mocap_export"]["fps"] == 60.0  # times still count the numbers at 60
    stepped = replace(capture, frame=np.where(capture.stream == 1, 4, 1) * capture.frame)
    export_outputs(tmp_path / "one_stream", stepped, result, layout=TOY_LAYOUT, plots=False,
                   fps={0: 60.0, 1: 15.0, 2: 60.0})
    assert any(line.startswith("stream(s) 1: the frame numbers in the image names step by 4")
               and line.endswith("give --fps 1=60") for line in log_lines), log_lines


def test_a_clock_a_whole_factor_off_its_rate_names_the_fps_it_implies() -> None:
    clock = {"implied_fps": 59.2, "fps": 15.0}
    assert whole_factor(clock, 2).endswith("(about 4), as when its frame numbers count frames "
                                           "at another rate than the images': --fps 2=60 if "
                                           "they count frames at that rate")
    assert "(about 1/4)" in whole_factor({"implied_fps": 15.1, "fps": 60.0}, 0)
    assert whole_factor({"implied_fps": 29.0, "fps": 25.0}, 0) == ""  # a rate off, no factor
    assert whole_factor({"implied_fps": 37.5, "fps": 15.0}, 0) == ""  # 2.5: no whole factor


def test_reconstruct_output_folder_has_the_exports(tmp_path, monkeypatch) -> None:
    """The stage end to end (2 cameras x 4 frames, a few iterations)."""
    monkeypatch.setattr("test_reconstruct_stage.NUM_CAMERAS", 2)
    monkeypatch.setattr("test_reconstruct_stage.NUM_FRAMES", 4)
    workspace = colmap.synthetic_workspace(tmp_path / "ws", num_cameras=2, num_frames=4,
                                           num_points3D=20)
    write_openpose(tmp_path / "openpose", colmap.load_workspace(workspace))
    out = stage.main(workspace, tmp_path / "openpose", "openpose", tmp_path / "out", plots=False,
                     overrides=["max_iterations=5", "robust_iterations=0"], export_rate=2.0)
    trc = check_trc_and_c3d(out / "trajectories.trc", out / "trajectories.c3d",
                            LAYOUTS["COCO_18"].point_names)
    assert float(trc["header"]["DataRate"]) == 2.0
    assert (out / "trajectories_wide.csv").stat().st_size > 0
