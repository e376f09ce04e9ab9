"""Real input as it comes (issue 39): a calibration and keypoint files without any image file
(Pose2Sim, anipose), keypoint files where the detector found nobody, empty image files."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scenes import body_at, error_line, look_at, openpose_file, run_cli, write_openpose
from scipy.stats import kendalltau

from dloe_sfm import colmap
from dloe_sfm.viz import readable_images

CAMERAS = 3
FRAMES = 45  # camera k films the frames f with f % 3 == k: 15 each, no two at one instant
SIZE = (1280, 720)
DIST = [-0.1, 0.02, 1e-3, -5e-4]


def rig() -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, K, world-to-camera R | t) of 3 calibrated cameras around the walking figure."""
    K = np.array([[1000.0, 0, 640], [0, 1000.0, 360], [0, 0, 1]])
    cams = []
    for k in range(CAMERAS):
        angle = 2 * np.pi * k / CAMERAS + 0.3
        centre = np.array([3.5 * np.cos(angle), 3.5 * np.sin(angle), 1.2])
        R = look_at(centre, np.array([0.0, 0.0, -0.45]))
        cams.append((f"cam_0{k + 1}", K, np.hstack([R, -R @ centre[:, None]])))
    return cams


def write_anipose(path: Path) -> None:
    """aniposelib's calibration.toml (``CameraGroup.dump``) of ``rig()``."""
    def row(a) -> str:
        return "[" + ", ".join(repr(float(v)) for v in np.ravel(a)) + "]"

    text = ""
    for i, (name, K, Rt) in enumerate(rig()):
        rvec = cv2.Rodrigues(Rt[:, :3])[0]
        text += (f'[cam_{i}]\nname = "{name}"\nsize = [{SIZE[0]}, {SIZE[1]}]\n'
                 f"matrix = [{', '.join(row(r) for r in K)}]\ndistortions = {row(DIST)}\n"
                 f"rotation = {row(rvec)}\ntranslation = {row(Rt[:, 3])}\n\n")
    path.write_text(text)


@pytest.fixture(scope="module")
def pose2sim_trial(tmp_path_factory) -> tuple[Path, Path, list[str]]:
    """A Pose2Sim-like trial without video frames: ``calibration.toml`` and OpenPose files
    ``pose/camXX_json/camXX.NNNN.json`` of an asynchronous rig (COCO_18 stick figure), in two
    of its frames the detector found nobody (no person; a person with every joint 0, 0, 0) and
    a stray empty file as Pose2Sim leaves them. Returns the calibration, the pose folder and
    the keys of the files without a detection."""
    root = tmp_path_factory.mktemp("pose2sim")
    write_anipose(root / "calibration.toml")
    for k, (_, K, Rt) in enumerate(rig()):
        rvec = cv2.Rodrigues(Rt[:, :3])[0]
        for f in range(k, FRAMES, CAMERAS):
            uv = cv2.projectPoints(body_at(f / (FRAMES - 1)), rvec, Rt[:, 3], K,
                                   np.array(DIST))[0].reshape(-1, 2)
            assert ((uv > 0) & (uv < SIZE)).all()
            openpose_file(root / "pose" / f"cam0{k + 1}_json" / f"cam0{k + 1}.{f:04d}.json",
                          np.hstack([uv, np.ones((len(uv), 1))])[None])
    nobody = ["cam02_json/cam02.0022", "cam03_json/cam03.0038"]
    openpose_file(root / "pose" / f"{nobody[0]}.json", np.zeros((0, 18, 3)))
    openpose_file(root / "pose" / f"{nobody[1]}.json", np.zeros((1, 18, 3)))
    openpose_file(root / "pose" / "cam03_json" / "del_000000_0.json", np.zeros((0, 18, 3)))
    return root / "calibration.toml", root / "pose", [*nobody, "cam03_json/del_000000_0"]


def warnings(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if " WARNING] " in line]


def test_calibration_and_keypoints_without_images(pose2sim_trial, tmp_path, capsys) -> None:
    """import-calibration --keypoints gives the frame list; reconstruct reads the same files,
    leaves out those without a detection, and skips the overlays with one warning given before
    the solve; every other output is written."""
    calib, pose, nobody = pose2sim_trial
    model = tmp_path / "ws" / "sparse" / "0"
    code, err = run_cli("import-calibration", calib, "--format", "anipose", "--keypoints", pose,
                        "--out", model, capsys=capsys)
    assert code == 0, err
    ws = colmap.load_workspace(tmp_path / "ws")
    assert ws.image_dir is None and len(ws.image_names) == FRAMES + 1  # and the stray file
    cameras = {folder: {ws.camera_id(n) for n in ws.image_names if n.startswith(folder)}
               for folder in ("cam01_json/", "cam02_json/", "cam03_json/")}
    assert all(len(ids) == 1 for ids in cameras.values())  # a folder is its camera's
    assert len(set.union(*cameras.values())) == CAMERAS
    assert {f"{k}.jpg" for k in nobody} <= set(ws.image_names)

    out = tmp_path / "out"
    code, err = run_cli("reconstruct", tmp_path / "ws", "--keypoints", pose, "--format",
                        "openpose", "--out", out, capsys=capsys)
    assert code == 0, err
    lines = err.splitlines()
    warned = warnings(err)
    assert len(warned) == 2, warned
    detections, images = warned
    assert "3 image(s) without a usable detection" in detections
    assert all(f"'{k}.jpg'" in detections for k in nobody)
    assert "sparse/0: no image folder for 43 of 43 image(s)" in images
    solve_log = next(i for i, line in enumerate(lines) if "DLOE: " in line)
    assert lines.index(images) < solve_log  # checked before the solve
    report = json.loads((out / "report.json").read_text())
    assert sorted(report["inputs"]["skipped_images"]) == sorted(f"{k}.jpg" for k in nobody)
    assert report["images"] == FRAMES - 2 and report["subjects"] == 1 and report["events"] == 1
    assert (out / "plots" / "sequence.png").is_file()
    assert (out / "plots" / "animation.gif").is_file() and not (out / "plots" / "overlays").exists()
    with np.load(out / "trajectories.npz") as data:
        names, X = [str(n) for n in data["image_names"]], data["X"]
    frames = np.array([int(re.search(r"\.(\d+)\.jpg$", n).group(1)) for n in names])
    X_true = np.stack([body_at(f / (FRAMES - 1)) for f in frames])
    assert np.median(np.linalg.norm(X - X_true, axis=2)) < 0.01  # model units: metres
    ranks = {line.split(",")[1]: int(line.split(",")[0])
             for line in (out / "sequence.csv").read_text().splitlines()[1:]}
    assert abs(kendalltau([ranks[n] for n in names], frames).statistic) > 0.99


def test_import_calibration_keypoints_errors(pose2sim_trial, tmp_path, capsys) -> None:
    calib, pose, _ = pose2sim_trial
    (tmp_path / "images").mkdir()
    for args, message in [
        (["--keypoints", pose, "--images-dir", tmp_path / "images"],
         "from the image folder"),
        (["--keypoints", tmp_path / "nowhere"], "nowhere: no such keypoint file or folder"),
        (["--keypoints", calib.parent / "pose" / "cam01_json" / "cam01.0000.json",
          "--keypoint-format", "coco"], "cam01.0000.json"),
    ]:
        code, err = run_cli("import-calibration", calib, "--format", "anipose", "--out",
                            tmp_path / "model", *args, capsys=capsys)
        assert code == 2 and message in error_line(err), err
        assert not (tmp_path / "model").exists()


@pytest.fixture(scope="module")
def placeholders(tmp_path_factory) -> tuple[Path, Path, list[str]]:
    """A COLMAP workspace whose image files are empty placeholders and its OpenPose files, two
    of them without a detection (no person; every joint 0, 0, 0)."""
    root = tmp_path_factory.mktemp("placeholders")
    workspace = colmap.synthetic_workspace(root / "ws", num_cameras=4, num_frames=12)
    ws = colmap.load_workspace(workspace)
    write_openpose(root / "openpose", ws)
    nobody = [ws.image_names[5], ws.image_names[30]]
    openpose_file(root / "openpose" / f"{Path(nobody[0]).stem}_keypoints.json",
                  np.zeros((0, 18, 3)))
    openpose_file(root / "openpose" / f"{Path(nobody[1]).stem}_keypoints.json",
                  np.zeros((1, 18, 3)))
    for name in ws.image_names:
        (workspace / "images" / name).parent.mkdir(parents=True, exist_ok=True)
        (workspace / "images" / name).touch()
    return workspace, root / "openpose", nobody


def test_empty_detections_and_empty_image_files(placeholders, tmp_path, capsys) -> None:
    workspace, keypoints, nobody = placeholders
    out = tmp_path / "out"
    code, err = run_cli("reconstruct", workspace, "--keypoints", keypoints, "--format",
                        "openpose", "--out", out, capsys=capsys)
    assert code == 0, err
    warned = warnings(err)
    assert len(warned) == 2, warned
    assert "2 image(s) without a usable detection" in warned[0]
    assert f"'{nobody[0]}', '{nobody[1]}'" in warned[0]
    assert "images: no readable image file for 46 of 46 image(s)" in warned[1]
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"]["skipped_images"] == nobody and report["images"] == 46
    assert (out / "plots" / "trajectories.png").is_file()
    assert not (out / "plots" / "overlays").exists()


def test_overlays_only_on_readable_images(placeholders, tmp_path, log_lines) -> None:
    workspace, _, _ = placeholders
    images = tmp_path / "images"
    shutil.copytree(workspace / "images", images)
    ws = colmap.load_workspace(workspace, image_dir=images)
    log_lines.clear()
    real, empty, missing = ws.image_names[:3]
    cv2.imwrite(str(images / real), np.full((48, 64, 3), 200, np.uint8))
    (images / missing).unlink()
    assert readable_images(ws, [real, empty, missing]) == [real]
    assert len(log_lines) == 1 and "no readable image file for 2 of 3" in log_lines[0]
    assert f"'{empty}', '{missing}'" in log_lines[0]
    log_lines.clear()
    assert readable_images(ws, [real]) == [real] and log_lines == []


@pytest.mark.shared
def test_import_calibration_from_pose2sim_keypoint_folders(shared_dir, tmp_path, capsys) -> None:
    """The real trial: one image per OpenPose file, each in its folder's camera."""
    trial = shared_dir / "data" / "pose2sim_single_trial"
    code, err = run_cli("import-calibration", trial / "calibration" / "Calib.qca.txt",
                        "--format", "qualisys", "--keypoints", trial / "pose", "--out",
                        tmp_path / "ws" / "sparse" / "0", capsys=capsys)
    assert code == 0, err
    ws = colmap.load_workspace(tmp_path / "ws")
    # 100 frames per camera, and the empty del_00000k_0.json Pose2Sim left in cam03 and cam04
    assert len(ws.image_names) == 404 and "cam04_json/del_000001_0.jpg" in ws.image_names
    cameras: dict[str, set[int]] = {}
    for name in ws.image_names:
        cameras.setdefault(name.split("/")[0], set()).add(ws.camera_id(name))
    assert sorted(cameras) == [f"cam0{k}_json" for k in range(1, 5)]
    assert all(len(ids) == 1 for ids in cameras.values())
    assert len(set.union(*cameras.values())) == 4
    assert ws.image_size("cam03_json/cam03.0042.jpg") == (1088, 1920)
