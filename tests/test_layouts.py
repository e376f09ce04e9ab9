"""Keypoint layouts (HALPE_26, COCO-WholeBody body and feet, MediaPipe 33 and the older ones)
checked against their public definitions, their reading by count and by name, and
``--aruco-dict``."""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from dloe_sfm import cli, colmap
from dloe_sfm.errors import InputError
from dloe_sfm.keypoints import LAYOUTS, load_layout, read_keypoints
from dloe_sfm.keypoints.base import get_layout, known_layout

# Pose2Sim's skeletons.py: marker name -> id in its HALPE_26 and COCO_133 trees
POSE2SIM_HALPE_26 = {
    "Nose": 0, "LShoulder": 5, "RShoulder": 6, "LElbow": 7, "RElbow": 8, "LWrist": 9,
    "RWrist": 10, "LHip": 11, "RHip": 12, "LKnee": 13, "RKnee": 14, "LAnkle": 15, "RAnkle": 16,
    "Head": 17, "Neck": 18, "Hip": 19, "LBigToe": 20, "RBigToe": 21, "LSmallToe": 22,
    "RSmallToe": 23, "LHeel": 24, "RHeel": 25,
}
POSE2SIM_COCO_133 = {
    "Nose": 0, "LEye": 1, "REye": 2, "LEar": 3, "REar": 4, "LShoulder": 5, "RShoulder": 6,
    "LElbow": 7, "RElbow": 8, "LWrist": 9, "RWrist": 10, "LHip": 11, "RHip": 12, "LKnee": 13,
    "RKnee": 14, "LAnkle": 15, "RAnkle": 16, "LBigToe": 17, "LSmallToe": 18, "LHeel": 19,
    "RBigToe": 20, "RSmallToe": 21, "RHeel": 22,
}
# MMPose's dataset configs (halpe26.py, coco_wholebody.py): keypoint_info names
MMPOSE_COCO_17 = [
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip",
    "left_knee", "right_knee", "left_ankle", "right_ankle",
]
MMPOSE_HALPE_26 = [*MMPOSE_COCO_17, "head", "neck", "hip", "left_big_toe", "right_big_toe",
                   "left_small_toe", "right_small_toe", "left_heel", "right_heel"]
MMPOSE_WHOLEBODY = [
    *MMPOSE_COCO_17, "left_big_toe", "left_small_toe", "left_heel", "right_big_toe",
    "right_small_toe", "right_heel", *(f"face-{i}" for i in range(68)),
    *(f"{side}_hand_{i}" for side in ("left", "right") for i in range(21)),
]


def components(num_points: int, edges) -> list[set[int]]:
    """Connected components of the skeleton graph, sorted by smallest point."""
    parent = list(range(num_points))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for a, b in edges:
        parent[root(a)] = root(b)
    groups: dict[int, set[int]] = {}
    for i in range(num_points):
        groups.setdefault(root(i), set()).add(i)
    return sorted(groups.values(), key=min)


def mirror(name: str) -> str | None:
    """The other side's name of a left or right point (LHip, left_hip, mouth_left), else None."""
    for left, right in (("left_", "right_"), ("right_", "left_")):
        if name.startswith(left):
            return right + name[len(left):]
    for left, right in (("_left", "_right"), ("_right", "_left")):
        if name.endswith(left):
            return name[:-len(left)] + right
    if len(name) > 1 and name[0] in "LR" and name[1].isupper():
        return {"L": "R", "R": "L"}[name[0]] + name[1:]
    return None


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_layout_structure(name) -> None:
    layout = LAYOUTS[name]
    names, p = layout.point_names, layout.num_points
    assert len(set(names)) == p
    assert all(0 <= a < p and 0 <= b < p and a != b for a, b in layout.edges)
    assert len({frozenset(e) for e in layout.edges}) == len(layout.edges)  # no edge twice
    groups = components(p, layout.edges)
    if name == "MEDIAPIPE_33":  # POSE_CONNECTIONS: eyes and ears, the mouth, the body
        assert groups == [set(range(9)), {9, 10}, set(range(11, 33))]
    else:
        assert groups == [set(range(p))]
    # the pairs are exactly each left point with its right namesake
    index = {n: i for i, n in enumerate(names)}
    sided = {i: mirror(n) for i, n in enumerate(names) if mirror(n) is not None}
    assert all(m in index for m in sided.values()), name
    pairs = {frozenset(pair) for pair in layout.symmetric_pairs}
    assert len(pairs) == len(layout.symmetric_pairs)
    assert pairs == {frozenset((i, index[m])) for i, m in sided.items()}
    for a, b in layout.symmetric_pairs:  # left first
        assert names[a].lower().startswith("l") or names[a].endswith("_left"), names[a]
        assert names[b].lower().startswith("r") or names[b].endswith("_right"), names[b]
    # the skeleton is left/right symmetric: the mirror of an edge is an edge
    swap = {i: index[m] for i, m in sided.items()}
    edges = {frozenset(e) for e in layout.edges}
    assert {frozenset(swap.get(i, i) for i in e) for e in edges} == edges


def test_new_layouts_match_their_public_definitions() -> None:
    halpe, whole, mp = LAYOUTS["HALPE_26"], LAYOUTS["COCO_WHOLEBODY"], LAYOUTS["MEDIAPIPE_33"]
    assert (halpe.num_points, whole.num_points, mp.num_points) == (26, 23, 33)
    assert {n: halpe.point_names.index(n) for n in POSE2SIM_HALPE_26} == POSE2SIM_HALPE_26
    assert halpe.point_names[1:5] == ["LEye", "REye", "LEar", "REar"]
    assert dict(zip(whole.point_names, range(23), strict=True)) == POSE2SIM_COCO_133
    assert whole.source_points == 133
    assert halpe.point_names[:17] == whole.point_names[:17]
    assert (mp.point_names[0], mp.point_names[9], mp.point_names[11]) == \
        ("nose", "mouth_left", "left_shoulder")
    assert mp.point_names[29:] == ["left_heel", "right_heel", "left_foot_index",
                                   "right_foot_index"]
    # MMPose's skeleton_info links of halpe26 (the 6 foot links and head - neck - hip)
    edges = {frozenset(e) for e in halpe.edges}
    assert len(halpe.edges) == 27
    assert {frozenset(e) for e in [(15, 20), (15, 22), (15, 24), (16, 21), (16, 23), (16, 25),
                                   (17, 18), (18, 19), (11, 19), (12, 19)]} <= edges
    assert len(whole.edges) == 25 and {(15, 17), (15, 18), (15, 19), (16, 20), (16, 21),
                                       (16, 22)} <= set(whole.edges)
    assert len(mp.edges) == 35 and {(3, 7), (6, 8), (9, 10), (27, 31), (28, 32)} <= set(mp.edges)
    # by name: case, '-' / '_', and Pose2Sim's names
    for spec, want in [("halpe-26", halpe), ("COCO-WholeBody", whole), ("coco_133", whole),
                       ("MediaPipe_33", mp), ("BLAZEPOSE", mp)]:
        assert load_layout(spec) is want
    # MMPose's point names map to the layouts (as in a prediction file's meta_info)
    assert known_layout(MMPOSE_HALPE_26) is halpe
    assert known_layout(MMPOSE_WHOLEBODY) is whole and len(MMPOSE_WHOLEBODY) == 133
    assert known_layout(MMPOSE_WHOLEBODY[:23]) is whole
    assert known_layout(MMPOSE_COCO_17) is LAYOUTS["COCO_17"]
    assert known_layout(MMPOSE_WHOLEBODY[:30]) is None
    assert known_layout(MMPOSE_HALPE_26[:25] + ["left_heel"]) is None


def test_layout_size_checks() -> None:
    assert get_layout("COCO_WHOLEBODY", 133, "f") is LAYOUTS["COCO_WHOLEBODY"]
    with pytest.raises(InputError, match=r"^f: layout COCO_WHOLEBODY has 23 \(or 133\) points, "
                                         r"the data 26$"):
        get_layout("coco-wholebody", 26, "f")
    with pytest.raises(InputError, match="^f: layout HALPE_26 has 26 points, the data 133$"):
        get_layout("HALPE_26", 133, "f")


def openpose_folder(folder: Path, people_per_file: list[np.ndarray]) -> None:
    folder.mkdir(parents=True)
    for k, people in enumerate(people_per_file):
        (folder / f"cam01.{k:04d}_keypoints.json").write_text(json.dumps({"people": [
            {"pose_keypoints_2d": p.ravel().tolist()} for p in people]}))


def people(rng: np.random.Generator, m: int, p: int) -> np.ndarray:
    """(m, p, 3) pixel positions and scores in (0.1, 1)."""
    return np.concatenate([rng.uniform(0, 1000, (m, p, 2)), rng.uniform(0.1, 1, (m, p, 1))], -1)


class Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@pytest.fixture
def dloe_logs():
    """Messages of the ``dloe_sfm`` logger, at INFO (whether or not it propagates)."""
    logger, handler = logging.getLogger("dloe_sfm"), Records()
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    yield handler.messages
    logger.removeHandler(handler)
    logger.setLevel(level)


@pytest.mark.parametrize("count, name", [(26, "HALPE_26"), (33, "MEDIAPIPE_33"),
                                         (25, "BODY_25"), (18, "COCO_18")])
def test_openpose_layout_by_count(tmp_path, count, name) -> None:
    rng = np.random.default_rng(count)
    files = [people(rng, 2, count), people(rng, 1, count)]
    openpose_folder(tmp_path / "op", files)
    kp = read_keypoints("openpose", tmp_path / "op")
    assert kp.layout is LAYOUTS[name]
    np.testing.assert_allclose(kp.points["cam01.0001"], files[1])


# six real OpenPose BODY_25B files of the Pose2Sim trial (tests/data/README.md)
BODY_25B_FILES = Path(__file__).parent / "data" / "pose2sim_body_25b"


def as_body_25(people_25b: np.ndarray) -> np.ndarray:
    """(M, 25, 3) BODY_25B detections in BODY_25's order, its Neck and MidHip the midpoints of
    the shoulders and hips (as OpenPose trains them), missing (0, 0, 0) where one is."""
    names_b = LAYOUTS["BODY_25B"].point_names
    out = np.zeros_like(people_25b)
    for k, name in enumerate(LAYOUTS["BODY_25"].point_names):
        pair = {"Neck": ("LShoulder", "RShoulder"), "MidHip": ("LHip", "RHip")}.get(name)
        out[:, k] = (people_25b[:, names_b.index(name)] if pair is None else
                     people_25b[:, [names_b.index(n) for n in pair]].mean(axis=1))
    return np.nan_to_num(out, nan=0.0)


def test_body_25b_is_told_from_body_25_by_the_data(tmp_path, dloe_logs) -> None:
    kp = read_keypoints("openpose", BODY_25B_FILES)
    assert kp.layout is LAYOUTS["BODY_25B"]
    assert [m for m in dloe_logs if "read as BODY_25B, not BODY_25, from the data" in m
            and "--layout NAME" in m], dloe_logs
    openpose_folder(tmp_path / "b25", [as_body_25(p) for p in kp.points.values()])
    dloe_logs.clear()
    assert read_keypoints("openpose", tmp_path / "b25").layout is LAYOUTS["BODY_25"]
    assert [m for m in dloe_logs if "read as BODY_25, not BODY_25B, from the data" in m]
    dloe_logs.clear()  # a layout given is taken as it is, nothing guessed
    assert read_keypoints("openpose", BODY_25B_FILES, layout="body_25").layout.name == "BODY_25"
    assert not [m for m in dloe_logs if "joints per detection" in m], dloe_logs
    # random points are neither: BODY_25, OpenPose's default, with a warning saying how to choose
    openpose_folder(tmp_path / "random", [people(np.random.default_rng(k), 2, 25)
                                          for k in range(4)])
    assert read_keypoints("openpose", tmp_path / "random").layout is LAYOUTS["BODY_25"]
    assert [m for m in dloe_logs if "BODY_25 or BODY_25B (Pose2Sim's default): the data does "
            "not tell" in m and "--layout BODY_25B" in m], dloe_logs


def test_a_layout_by_joint_count_is_logged_with_the_others_of_that_count(tmp_path, dloe_logs
                                                                         ) -> None:
    rng = np.random.default_rng(0)
    for count, said in ((18, "read as COCO_18 (other known layouts of 18 joints: none;"),
                        (17, "no layout taken: points p0, p1, ... (known layouts of 17 joints: "
                             "COCO_17; --layout NAME|FILE.json to choose)")):
        openpose_folder(tmp_path / str(count), [people(rng, 1, count)])
        read_keypoints("openpose", tmp_path / str(count))
        assert [m for m in dloe_logs if said in m], dloe_logs


def test_wholebody_133_points_keep_body_and_feet(tmp_path, dloe_logs) -> None:
    rng = np.random.default_rng(1)
    files = [people(rng, 2, 133), people(rng, 3, 133)]
    openpose_folder(tmp_path / "op", files)
    kp = read_keypoints("openpose", tmp_path / "op")
    assert kp.layout is LAYOUTS["COCO_WHOLEBODY"] and kp.num_points == 23
    for k, want in enumerate(files):
        got = kp.points[f"cam01.{k:04d}"]
        assert got.shape == (len(want), 23, 3)
        np.testing.assert_array_equal(got, want[:, :23])
    said = [m for m in dloe_logs if "face and hands dropped" in m]
    assert len(said) == 1 and "first 23 of 133 points" in said[0], said
    # a 23-point file is read as it is, nothing said
    dloe_logs.clear()
    openpose_folder(tmp_path / "op23", [people(rng, 1, 23)])
    kp = read_keypoints("openpose", tmp_path / "op23", layout="COCO-WholeBody")
    assert kp.points["cam01.0000"].shape == (1, 23, 3)
    assert not [m for m in dloe_logs if "dropped" in m]


def test_wholebody_in_mmpose_coco_and_csv(tmp_path) -> None:
    rng = np.random.default_rng(2)
    person = people(rng, 1, 133)[0]
    meta = {"dataset_name": "coco_wholebody",
            "keypoint_id2name": {str(i): n for i, n in enumerate(MMPOSE_WHOLEBODY)}}
    instance = {"keypoints": person[:, :2].tolist(), "keypoint_scores": person[:, 2].tolist()}
    (tmp_path / "img0.json").write_text(json.dumps({"meta_info": meta,
                                                    "instance_info": [instance]}))
    kp = read_keypoints("mmpose", tmp_path / "img0.json")
    assert kp.layout is LAYOUTS["COCO_WHOLEBODY"]
    np.testing.assert_allclose(kp.points["img0"][0], person[:23])
    # MMPose halpe26 names -> HALPE_26
    meta = {"dataset_name": "halpe26",
            "keypoint_id2name": {str(i): n for i, n in enumerate(MMPOSE_HALPE_26)}}
    instance = {"keypoints": person[:26, :2].tolist()}
    (tmp_path / "img1.json").write_text(json.dumps({"meta_info": meta,
                                                    "instance_info": [instance]}))
    assert read_keypoints("mmpose", tmp_path / "img1.json").layout is LAYOUTS["HALPE_26"]
    # a COCO category naming the 133 points
    coco = {"images": [{"id": 1, "file_name": "a.jpg"}],
            "annotations": [{"image_id": 1, "category_id": 1,
                             "keypoints": np.c_[person[:, :2], np.full(133, 2)].ravel().tolist()}],
            "categories": [{"id": 1, "name": "person", "keypoints": MMPOSE_WHOLEBODY}]}
    (tmp_path / "coco.json").write_text(json.dumps(coco))
    kp = read_keypoints("coco", tmp_path / "coco.json")
    assert kp.layout is LAYOUTS["COCO_WHOLEBODY"]
    np.testing.assert_allclose(kp.points["a.jpg"][0, :, :2], person[:23, :2])
    # CSV with point ids of all 133 points, or only of the first 23
    rows = ["image,point_id,x,y"] + [f"a.jpg,{j},{x!r},{y!r}" for j, (x, y, _) in
                                     enumerate(person.tolist())]
    (tmp_path / "all.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "body.csv").write_text("\n".join(rows[:24]) + "\n")
    for file in ("all.csv", "body.csv"):
        kp = read_keypoints("csv", tmp_path / file, layout="COCO_WHOLEBODY")
        assert kp.points["a.jpg"].shape == (1, 23, 3), file
        np.testing.assert_allclose(kp.points["a.jpg"][0, :, :2], person[:23, :2])
    with pytest.raises(InputError, match="point_id 133 out of range 0..132"):
        (tmp_path / "bad.csv").write_text("image,point_id,x,y\na.jpg,133,1,2\n")
        read_keypoints("csv", tmp_path / "bad.csv", layout="COCO_WHOLEBODY")


def marker_image(path: Path, dictionary: int, marker_id: int) -> None:
    marker = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(dictionary),
                                           marker_id, 140)
    canvas = np.full((400, 500), 255, np.uint8)
    canvas[100:240, 150:290] = marker
    cv2.imwrite(str(path), canvas)


def test_aruco_dictionary_option(tmp_path) -> None:
    marker_image(tmp_path / "view.png", cv2.aruco.DICT_5X5_100, 42)
    for name in ("DICT_5X5_100", "dict_5x5_100", "5X5_100"):
        kp = read_keypoints("aruco", tmp_path, dictionary=name)
        assert kp.layout.name == "aruco_DICT_5X5_100" and kp.num_points == 4 * 43
        corners = kp.points["view.png"][0, 4 * 42:4 * 43, :2]
        want = [[149.5, 99.5], [289.5, 99.5], [289.5, 239.5], [149.5, 239.5]]
        np.testing.assert_allclose(corners, want, atol=0.5)
        assert np.isfinite(kp.points["view.png"][0, :, 0]).sum() == 4
    with pytest.raises(InputError, match="no DICT_4X4_50 marker found in 1 image"):
        read_keypoints("aruco", tmp_path)


@pytest.fixture(scope="module")
def blank_workspace(tmp_path_factory) -> Path:
    """A synthetic COLMAP workspace whose images are blank (no marker of any dictionary)."""
    root = colmap.synthetic_workspace(tmp_path_factory.mktemp("lay") / "ws", num_frames=2)
    (root / "images").mkdir()
    for name in colmap.load_workspace(root).image_names:
        cv2.imwrite(str(root / "images" / name), np.full((96, 128), 255, np.uint8))
    return root


def reconstruct_error(capsys, *args) -> tuple[int, str]:
    """Exit code and the one error line (the last of stderr) of ``dloe-sfm reconstruct ARGS``,
    run in this process."""
    try:
        code = cli.main(["reconstruct", *map(str, args)])
    except SystemExit as e:
        code = e.code
    lines = [line for line in re.split(r"[\r\n]", capsys.readouterr().err) if line.strip()]
    errors = [i for i, line in enumerate(lines) if ": error: " in line]
    assert errors == [len(lines) - 1], lines
    return code, lines[-1]


def test_aruco_dict_on_the_command_line(blank_workspace, tmp_path, capsys) -> None:
    out = tmp_path / "out"
    code, line = reconstruct_error(capsys, blank_workspace, "--format", "aruco", "--out", out,
                                   "--aruco-dict", "dict_5x5_100")
    assert code == 2 and "no DICT_5X5_100 marker found in 6 image(s)" in line, line
    code, line = reconstruct_error(capsys, blank_workspace, "--format", "aruco", "--out", out)
    assert code == 2 and "no DICT_4X4_50 marker found" in line, line
    code, line = reconstruct_error(capsys, blank_workspace, "--format", "aruco", "--out", out,
                                   "--aruco-dict", "DICT_9X9_7")
    assert code == 2 and "unknown ArUco dictionary 'DICT_9X9_7' (known: " in line, line
    assert "DICT_5X5_100" in line and "DICT_APRILTAG_36H11" in line
    code, line = reconstruct_error(capsys, blank_workspace, "--format", "csv", "--out", out,
                                   "--keypoints", tmp_path, "--aruco-dict", "DICT_5X5_100")
    assert code == 2 and "--aruco-dict is only for --format aruco, not 'csv'" in line, line
    assert not out.exists()
