"""Keypoint adapters (round trips, ArUco detection, bad input) and ``build_capture``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from scenes import openpose_file

from dloe_sfm import colmap
from dloe_sfm.errors import InputError
from dloe_sfm.keypoints import FORMATS, LAYOUTS, load_layout, match_names, read_keypoints
from dloe_sfm.keypoints.detect import KINDS, looks_like
from dloe_sfm.observations import assign_streams, build_capture

P = 25


@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> colmap.Workspace:
    """3 video cameras x 4 frames (``cameraNNNNNN_frameNNNNNN.png``, 1024 x 768)."""
    return colmap.load_workspace(colmap.synthetic_workspace(tmp_path_factory.mktemp("kp") / "ws"))


def random_people(rng: np.random.Generator, m: int, p: int = P) -> np.ndarray:
    """(m, p, 3): person k spans ~(k + 1) x 100 px; about a fifth of the joints missing."""
    pts = np.empty((m, p, 3))
    for k in range(m):
        pts[k, :, :2] = rng.uniform(100, 100 + 100 * (k + 1), size=(p, 2))
        pts[k, :, 2] = rng.uniform(0.1, 1.0, size=p)
    missing = rng.random((m, p)) < 0.2
    pts[missing] = (np.nan, np.nan, 0.0)
    return pts


@pytest.fixture(scope="module")
def truth(ws) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    return {name: random_people(rng, 1 + i % 3) for i, name in enumerate(ws.image_names)}


def assert_same(points: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> None:
    assert sorted(points) == sorted(truth)
    for name, want in truth.items():
        np.testing.assert_allclose(points[name], want, rtol=0, atol=1e-9, err_msg=name)


def test_openpose_round_trip(ws, truth, tmp_path) -> None:
    for name, people in truth.items():
        openpose_file(tmp_path / f"{Path(name).stem}_keypoints.json", people)
    kp = read_keypoints("openpose", tmp_path, workspace=ws)
    assert kp.layout.name == "BODY_25"
    assert_same(kp.points, truth)
    kp = read_keypoints("OpenPose", tmp_path, workspace=ws, layout="body_25b")
    assert kp.layout.point_names[17:19] == ["UpperNeck", "HeadTop"]


def test_pose2sim_folders_match_by_stem(tmp_path) -> None:
    rng = np.random.default_rng(0)
    for cam in (1, 2):
        for k in range(3):
            openpose_file(tmp_path / f"cam{cam:02d}_json" / f"cam{cam:02d}.{k:04d}.json",
                          random_people(rng, 1, 18))
    (tmp_path / "cam02_json" / "cam02.0005.json").write_text('{"people": []}')
    kp = read_keypoints("openpose", tmp_path)
    assert kp.layout.name == "COCO_18"
    assert kp.points["cam02_json/cam02.0005"].shape == (0, 18, 3)
    names = [f"cam{c:02d}/cam{c:02d}.{k:04d}.png" for c in (1, 2) for k in range(6)]
    mapping = match_names(list(kp.points), names, tmp_path)
    assert mapping["cam01_json/cam01.0002"] == "cam01/cam01.0002.png"
    assert mapping["cam02_json/cam02.0005"] == "cam02/cam02.0005.png"


def test_reading_openpose_does_not_load_pycolmap(tmp_path) -> None:
    """The keypoint adapters run without pycolmap: only the workspace side needs it."""
    rng = np.random.default_rng(0)
    for k in range(2):
        openpose_file(tmp_path / f"frame{k}_keypoints.json", random_people(rng, 1))
    code = (
        "import sys, dloe_sfm.keypoints\n"
        f"kp = dloe_sfm.keypoints.read_keypoints('openpose', {str(tmp_path)!r})\n"
        "assert len(kp.points) == 2, sorted(kp.points)\n"
        "assert 'pycolmap' not in sys.modules, 'reading OpenPose files imported pycolmap'\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr


def test_match_names_rules() -> None:
    names = ["cam01/0012.jpg", "video/000007.png", "a/x.1.jpg", "b/x.1.jpg", "IMG_3.JPG"]
    mapping = match_names(["cam01/0012", "video/7", "IMG_3", "zzz"], names, "src")
    assert mapping == {"cam01/0012": "cam01/0012.jpg", "video/7": "video/000007.png",
                       "IMG_3": "IMG_3.JPG", "zzz": "zzz"}
    assert match_names(["cam01/0012.jpg"], names, "src") == {"cam01/0012.jpg": "cam01/0012.jpg"}
    # a file stem several images share matches none of them (build_capture reports the key)
    assert match_names(["x.1", "c/x.1"], names, "src") == {"x.1": "x.1", "c/x.1": "c/x.1"}
    with pytest.raises(InputError, match="src: keypoints 'a/x.1' match several images"):
        match_names(["a/x.1"], [*names, "a/x.1.png"], "src")
    with pytest.raises(InputError, match="both match image 'cam01/0012.jpg'"):
        match_names(["cam01/0012", "cam01/0012.jpg"], names, "src")


def test_layouts_are_connected_skeletons() -> None:
    for name in ("BODY_25", "BODY_25B", "COCO_18", "COCO_17"):  # all: test_layouts.py
        layout = LAYOUTS[name]
        p = layout.num_points
        reached, frontier = {0}, [0]
        while frontier:
            a = frontier.pop()
            for e in layout.edges:
                if a in e and (b := e[1 - e.index(a)]) not in reached:
                    reached.add(b)
                    frontier.append(b)
        assert reached == set(range(p)), name
        for a, b in layout.symmetric_pairs:
            left, right = layout.point_names[a], layout.point_names[b]
            assert left.lower().startswith("l") and right.lower().startswith("r"), (left, right)
            assert left.removeprefix("left_")[1 if left[0] == "L" else 0:] == \
                right.removeprefix("right_")[1 if right[0] == "R" else 0:]
    assert len(LAYOUTS["BODY_25"].symmetric_pairs) == 11
    assert len(LAYOUTS["COCO_17"].symmetric_pairs) == 8


def test_coco_round_trip(ws, truth, tmp_path) -> None:
    names = LAYOUTS["COCO_17"].point_names
    images, annotations, want = [], [], {}
    for i, (name, people) in enumerate(truth.items()):
        images.append({"id": 100 + i, "file_name": name, "width": 1024, "height": 768})
        sub = people[:, :17].copy()
        flags = np.where(np.isnan(sub[..., 0]), 0, 2)
        for k, person in enumerate(sub):
            values = np.column_stack([np.nan_to_num(person[:, :2]), flags[k]]).ravel()
            annotations.append({"id": len(annotations), "image_id": 100 + i, "category_id": 1,
                                "keypoints": values.tolist(), "num_keypoints": int(flags[k].sum())})
        sub[..., 2] = np.where(flags > 0, 1.0, 0.0)
        want[name] = sub
    images.append({"id": 999, "file_name": "unannotated.jpg"})
    want["unannotated.jpg"] = np.zeros((0, 17, 3))
    skeleton = [[a + 1, b + 1] for a, b in LAYOUTS["COCO_17"].edges]
    data = {"images": images, "annotations": annotations,
            "categories": [{"id": 1, "name": "person", "keypoints": names, "skeleton": skeleton}]}
    (tmp_path / "kp.json").write_text(json.dumps(data))
    kp = read_keypoints("coco", tmp_path / "kp.json")
    assert kp.layout is LAYOUTS["COCO_17"]
    assert_same(kp.points, want)


def test_mmpose_round_trip(ws, truth, tmp_path) -> None:
    meta = {"dataset_name": "mine", "keypoint_id2name": {str(i): f"j{i}" for i in range(P)},
            "skeleton_links": [[i, i + 1] for i in range(P - 1)], "flip_pairs": [[0, 1]]}
    for i, (name, people) in enumerate(truth.items()):
        instances = [{"keypoints": np.nan_to_num(p[:, :2]).tolist(),
                      "keypoint_scores": p[:, 2].tolist(), "bbox": [[0, 0, 1, 1]],
                      "bbox_score": 0.9} for p in people]
        data = {"meta_info": meta, "instance_info": instances} if i % 2 else instances
        (tmp_path / f"{Path(name).stem}.json").write_text(json.dumps(data))
    kp = read_keypoints("mmpose", tmp_path, workspace=ws)
    assert kp.layout.name == "mine" and kp.layout.point_names[3] == "j3"
    assert kp.layout.symmetric_pairs == [(0, 1)]
    assert_same(kp.points, truth)


def test_mmpose_video_frames(tmp_path) -> None:
    rng = np.random.default_rng(5)
    frames = [random_people(rng, 1, 17) for _ in range(3)]
    data = [{"frame_id": k, "instances": [{"keypoints": np.nan_to_num(f[0, :, :2]).tolist(),
                                           "keypoint_scores": f[0, :, 2].tolist()}]}
            for k, f in enumerate(frames)]
    (tmp_path / "walk.json").write_text(json.dumps(data))
    kp = read_keypoints("mmpose", tmp_path / "walk.json", frame_offset=1)
    assert sorted(kp.points) == ["walk/1", "walk/2", "walk/3"]
    np.testing.assert_allclose(kp.points["walk/3"], frames[2])
    names = [f"walk/{k:06d}.jpg" for k in range(1, 4)]
    assert match_names(list(kp.points), names, "x")["walk/1"] == "walk/000001.jpg"


def test_csv_round_trip(ws, truth, tmp_path) -> None:
    lines = ["person,image,point_id,x,y,score"]
    for name, people in truth.items():
        for m, person in enumerate(people):
            for j, (x, y, s) in enumerate(person):
                if s > 0:
                    lines.append(f"{m},{name},{j},{float(x)!r},{float(y)!r},{float(s)!r}")
    (tmp_path / "kp.csv").write_text("\n".join(lines) + "\n\n")
    kp = read_keypoints("csv", tmp_path / "kp.csv", workspace=ws, layout="BODY_25")
    assert kp.layout is LAYOUTS["BODY_25"]
    assert_same(kp.points, truth)


def marker_corners(H: np.ndarray, size: int) -> np.ndarray:
    """(4, 2) outer corners of a size x size marker image mapped by H (pixel centres at
    integers, so the image's outer edge is at -0.5 and size - 0.5)."""
    c = np.array([[-0.5, -0.5], [size - 0.5, -0.5], [size - 0.5, size - 0.5], [-0.5, size - 0.5]])
    h = np.c_[c, np.ones(4)] @ H.T
    return h[:, :2] / h[:, 2:]


def test_aruco_detects_rendered_markers(tmp_path) -> None:
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    size = 120
    want = {}
    for k, (marker_id, angle, tilt) in enumerate([(3, 0.0, 0.0), (7, 25.0, 4e-4),
                                                   (0, -40.0, -3e-4)]):
        canvas = np.full((480, 640), 255, np.uint8)
        marker = cv2.aruco.generateImageMarker(dictionary, marker_id, size)
        a = np.deg2rad(angle)
        H = np.array([[np.cos(a), -np.sin(a), 200.0 + 40 * k],
                      [np.sin(a), np.cos(a), 150.0],
                      [tilt, -tilt, 1.0]])
        warped = cv2.warpPerspective(marker, H, (640, 480), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=255)
        mask = cv2.warpPerspective(np.ones_like(marker), H, (640, 480), flags=cv2.INTER_NEAREST)
        canvas[mask > 0] = warped[mask > 0]
        name = f"view{k}.png"
        cv2.imwrite(str(tmp_path / name), canvas)
        want[name] = (marker_id, marker_corners(H, size))
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((100, 100), 255, np.uint8))
    kp = read_keypoints("aruco", tmp_path, num_markers=10)
    assert kp.num_points == 40 and kp.layout.edges[:2] == [(0, 1), (1, 2)]
    for name, (marker_id, corners) in want.items():
        pts = kp.points[name][0]
        got = pts[4 * marker_id:4 * marker_id + 4, :2]
        assert np.abs(got - corners).max() < 0.5, (name, got - corners)
        assert np.isfinite(pts[:, 0]).sum() == 4  # nothing else detected
    assert np.isnan(kp.points["blank.png"]).all() or not kp.points["blank.png"][..., 2].any()
    assert read_keypoints("aruco", tmp_path).num_points == 4 * 8  # largest id seen + 1
    with pytest.raises(InputError, match="unknown ArUco dictionary 'DICT_9X9'"):
        read_keypoints("aruco", tmp_path, dictionary="DICT_9X9")


# --- bad input -------------------------------------------------------------------------------

def test_malformed_json_names_the_file(tmp_path) -> None:
    (tmp_path / "frame_keypoints.json").write_text('{"people": [')
    for fmt in ("openpose", "mmpose", "coco"):
        with pytest.raises(InputError, match=r"frame_keypoints\.json: malformed JSON at line 1"):
            read_keypoints(fmt, tmp_path / "frame_keypoints.json")


def test_nan_coordinates_are_rejected(tmp_path) -> None:
    values = [1.0, 2.0, 0.5] * 24 + [float("nan"), 3.0, 0.9]
    (tmp_path / "a_keypoints.json").write_text(json.dumps({"people": [
        {"pose_keypoints_2d": values}]}))
    with pytest.raises(InputError, match=r"a_keypoints\.json person 0: .*NaN or infinite"):
        read_keypoints("openpose", tmp_path)
    (tmp_path / "kp.csv").write_text("image,point_id,x,y\na.jpg,0,1,2\na.jpg,1,inf,2\n")
    with pytest.raises(InputError, match=r"kp\.csv:3: column 'x' is NaN or infinite"):
        read_keypoints("csv", tmp_path / "kp.csv")


@pytest.mark.parametrize(("text", "message"), [
    ("image,point_id,x\n", r"kp\.csv:1: header lacks column\(s\) y"),
    ("image,point_id,x,y\na.jpg,0,1,2\na.jpg,1,2\n", r"kp\.csv:3: 3 fields, the header has 4"),
    ("image,point_id,x,y\na.jpg,0,1,2\n\na.jpg,one,1,2\n", r"kp\.csv:4: column 'point_id'"),
    ("image,point_id,x,y\na.jpg,-1,1,2\n", r"kp\.csv:2: point_id -1 out of range"),
    ("image,point_id,x,y\na.jpg,25,1,2\n", r"kp\.csv:2: point_id 25 out of range 0\.\.24"),
    ("image,point_id,x,y\na.jpg,2,1,2\na.jpg,2,1,2\n", r"kp\.csv:3: point 2 .* given twice"),
    ("image,point_id,x,y\n", r"kp\.csv: no keypoint rows"),
])
def test_bad_csv_lines(tmp_path, text, message) -> None:
    (tmp_path / "kp.csv").write_text(text)
    with pytest.raises(InputError, match=message):
        read_keypoints("csv", tmp_path / "kp.csv", layout="BODY_25")


def one_of_each_format(folder: Path) -> dict[str, Path]:
    """A small input of every keypoint format (two of OpenPose's and of MMPose's), by path ->
    the format it is."""
    rng = np.random.default_rng(1)
    person = random_people(rng, 1, 17)[0]
    xy, scores = np.nan_to_num(person[:, :2]).tolist(), person[:, 2].tolist()
    openpose_file(folder / "op" / "f0_keypoints.json", person[None])
    for cam in (1, 2):
        (folder / "p2s" / f"cam{cam:02d}_json").mkdir(parents=True)
        (folder / "p2s" / f"cam{cam:02d}_json" / "cam.0000.json").write_text('{"people": []}')
    openpose_file(folder / "p2s" / "cam02_json" / "cam.0001.json", person[None])
    (folder / "coco.json").write_text(json.dumps({
        "images": [{"id": 1, "file_name": "a.jpg"}],
        "annotations": [{"image_id": 1, "keypoints": np.c_[xy, scores].ravel().tolist()}],
        "categories": [{"id": 1, "keypoints": LAYOUTS["COCO_17"].point_names}]}))
    (folder / "mm").mkdir()
    (folder / "mm" / "a.json").write_text(json.dumps([{"keypoints": xy,
                                                         "keypoint_scores": scores}]))
    (folder / "mm_video.json").write_text(json.dumps([{"frame_id": 0, "instances": [
        {"keypoints": xy, "keypoint_scores": scores}]}]))
    (folder / "kp.csv").write_text("image,point_id,x,y\na.jpg,0,1,2\n")
    (folder / "images").mkdir()
    marker = cv2.aruco.generateImageMarker(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), 3, 60)
    cv2.imwrite(str(folder / "images" / "a.png"), np.pad(marker, 20, constant_values=255))
    return {folder / "op": "openpose", folder / "p2s": "openpose", folder / "coco.json": "coco",
            folder / "mm": "mmpose", folder / "mm_video.json": "mmpose",
            folder / "kp.csv": "csv", folder / "images": "aruco"}


def test_a_file_of_another_format_names_the_format_it_looks_like(tmp_path) -> None:
    inputs = one_of_each_format(tmp_path)
    for path, fmt in inputs.items():
        assert looks_like(path) == fmt, path
        read_keypoints(fmt, path)
        for other in set(FORMATS) - {fmt}:
            with pytest.raises(InputError) as e:
                read_keypoints(other, path)
            assert str(e.value) == (f"{path}: looks like {KINDS[fmt]}, not {other} keypoints: "
                                    f"use --format {fmt}"), (path, other)
    (tmp_path / "notes.txt").write_text("a,b\n")
    assert looks_like(tmp_path / "notes.txt") is None
    with pytest.raises(InputError, match=r"notes\.txt: malformed JSON at line 1"):
        read_keypoints("openpose", tmp_path / "notes.txt")


def test_unknown_format_option_and_path(tmp_path) -> None:
    with pytest.raises(InputError, match="unknown keypoint format 'dlc'.*openpose, coco"):
        read_keypoints("dlc", tmp_path)
    with pytest.raises(InputError, match="format 'csv' has no option colour"):
        read_keypoints("csv", tmp_path, colour="red")
    with pytest.raises(InputError, match="missing.csv: no such keypoint file"):
        read_keypoints("csv", tmp_path / "missing.csv")
    assert set(FORMATS) == {"openpose", "coco", "mmpose", "csv", "aruco"}


def test_keypoints_for_images_not_in_the_model(ws, tmp_path) -> None:
    lines = ["image,point_id,x,y"] + [f"holiday_{k}.jpg,0,1,2" for k in range(7)]
    lines += [f"{ws.image_names[0]},0,1,2"]
    (tmp_path / "kp.csv").write_text("\n".join(lines))
    kp = read_keypoints("csv", tmp_path / "kp.csv", workspace=ws)
    with pytest.raises(InputError, match=r"kp\.csv: keypoints for 7 image\(s\) not in the COLMAP "
                       r"model .*'holiday_0\.jpg', .*'holiday_4\.jpg' and 2 more$"):
        build_capture(ws, kp)


# --- build_capture ---------------------------------------------------------------------------

def projected_csv(ws: colmap.Workspace, path: Path, X: np.ndarray, names: list[str],
                  extra: str = "") -> Path:
    """A CSV of the (0, 0)-convention projections of X (P, 3) into ``names``; point j of image
    i scores 0.5 + 0.1 ((i + j) mod 5)."""
    lines = ["image,point_id,x,y,score,person"]
    for i, name in enumerate(names):
        for j, (u, v) in enumerate(ws.project(name, X) - 0.5):
            lines.append(f"{name},{j},{float(u)!r},{float(v)!r},{0.5 + 0.1 * ((i + j) % 5)},0")
    path.write_text("\n".join(lines) + "\n" + extra)
    return path


def test_build_capture_streams_people_and_scores(ws, tmp_path) -> None:
    X = ws.static_xyz[:6]
    assert all(np.isfinite(ws.project(n, X)).all() for n in ws.image_names)
    names = [n for n in ws.image_names if not n.startswith("camera000003") or n.endswith("1.png")]
    # a second, smaller "person" in the first image
    small = f"{names[0]},0,1.0,1.0,1.0,1\n{names[0]},1,2.0,2.0,1.0,1\n"
    kp = read_keypoints("csv", projected_csv(ws, tmp_path / "kp.csv", X, names, small),
                        workspace=ws)
    capture = build_capture(ws, kp, person="largest").capture
    assert list(capture.image_names) == names
    np.testing.assert_array_equal(capture.stream, [0] * 4 + [1] * 4 + [-1])
    np.testing.assert_array_equal(capture.frame, [0, 1, 2, 3, 0, 1, 2, 3, 0])
    for i in range(len(names)):
        h = (X - capture.C[i]) @ capture.R[i].T @ capture.K[i].T
        np.testing.assert_allclose(capture.x[i], h[:, :2] / h[:, 2:], atol=1e-8)
    scores = 0.5 + 0.1 * ((np.arange(len(names))[:, None] + np.arange(6)) % 5)
    np.testing.assert_allclose(capture.confidence, scores)
    # min_score drops the low scores; person 1 is the small one
    capture = build_capture(ws, kp, min_score=0.65, person="largest").capture
    np.testing.assert_array_equal(capture.visible, scores >= 0.65)
    np.testing.assert_array_equal(np.isnan(capture.x[..., 0]), scores < 0.65)
    # person 1 is only in the first image (points p2..p5 left out as observed nowhere): one stream
    with pytest.raises(InputError, match=r"the 1 image\(s\) with keypoints form one stream"):
        build_capture(ws, kp, person=1)
    capture = build_capture(ws, kp, person="largest",
                            stream_pattern=r"camera0*(?P<stream>\d+)_frame(?P<frame>\d+)").capture
    np.testing.assert_array_equal(capture.stream, [0] * 4 + [1] * 4 + [-1])
    with pytest.raises(InputError, match="does not match stream pattern"):
        build_capture(ws, kp, stream_pattern=r"cam(?P<stream>\d)_(?P<frame>\d+)")
    with pytest.raises(InputError, match="needs named groups"):
        build_capture(ws, kp, stream_pattern=r"camera(\d+)")
    with pytest.raises(InputError, match="person must be 'largest', 'all', 'auto' or an index"):
        build_capture(ws, kp, person="tallest")


def test_default_frames_keep_the_gaps_of_the_names(ws) -> None:
    """A missing frame number is a gap (a video that stopped), not the next frame."""
    names = [n for n in ws.image_names if not n.endswith("frame000001.png")]
    stream, frame = assign_streams(ws, names, None)
    np.testing.assert_array_equal(stream, np.repeat([0, 1, 2], 3))
    np.testing.assert_array_equal(frame, [0, 2, 3] * 3)


def test_layout_files(tmp_path) -> None:
    path = tmp_path / "mine.json"
    path.write_text(json.dumps({"point_names": ["a", "b", "c"], "edges": [[0, 1], [1, 2]],
                                "symmetric_pairs": [[0, 2]]}))
    layout = load_layout(path)
    assert layout.name == "mine" and layout.edges == [(0, 1), (1, 2)]
    assert layout.symmetric_pairs == [(0, 2)]
    assert load_layout("body-25") is LAYOUTS["BODY_25"] and load_layout(layout) is layout
    path.write_text(json.dumps({"point_names": ["a", "b"], "edges": [[0, 2]]}))
    with pytest.raises(InputError, match=r"mine\.json: 'edges'\[0\] \(0, 2\) out of range 0\.\.1"):
        load_layout(path)
    path.write_text(json.dumps({"names": ["a"]}))
    with pytest.raises(InputError, match="needs a non-empty 'point_names' list"):
        load_layout(path)


def test_one_stream_is_not_enough(ws, tmp_path) -> None:
    names = [n for n in ws.image_names if n.startswith("camera000001")]
    kp = read_keypoints("csv", projected_csv(ws, tmp_path / "kp.csv", ws.static_xyz[:3], names),
                        workspace=ws)
    with pytest.raises(InputError, match=r"kp\.csv: the 4 image\(s\) .* form one stream"):
        build_capture(ws, kp)
