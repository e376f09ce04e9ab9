"""Calibration import: Qualisys (checked by triangulating real detections) and anipose TOML."""

from __future__ import annotations

from itertools import combinations
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dloe_sfm import colmap
from dloe_sfm.calibration import import_calibration, read_calibration, read_qualisys
from dloe_sfm.errors import InputError
from dloe_sfm.keypoints import read_keypoints
from dloe_sfm.observations import select_person

FRAMES = 100


def pose2sim(shared_dir: Path) -> Path:
    return shared_dir / "data" / "pose2sim_single_trial"


def test_qualisys_cameras(shared_dir) -> None:
    cams = read_qualisys(pose2sim(shared_dir) / "calibration" / "Calib.qca.txt")
    assert [c.name for c in cams] == ["cam_01", "cam_02", "cam_03", "cam_04"]
    for c in cams:
        assert (c.width, c.height) == (1088, 1920)
        assert 1600 < c.K[0, 0] < 1750 and abs(c.K[0, 0] - c.K[1, 1]) < 1
        assert abs(c.K[0, 2] - 544) < 40 and abs(c.K[1, 2] - 960) < 40
        np.testing.assert_allclose(c.R @ c.R.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(c.R) > 0
        # cameras about 2 m up look down-ish towards the capture volume near the origin
        assert 1.5 < c.centre[2] < 2.5
        assert (c.R @ (np.zeros(3) - c.centre))[2] > 0
    gaps = [np.linalg.norm(a.centre - b.centre) for a, b in combinations(cams, 2)]
    assert min(gaps) > 2.0 and max(gaps) < 8.0


@pytest.fixture(scope="module")
def rig(shared_dir, tmp_path_factory) -> colmap.Workspace:
    names = {f"cam_0{c}": [f"cam0{c}/cam0{c}.{k:04d}.png" for k in range(FRAMES)]
             for c in range(1, 5)}
    root = tmp_path_factory.mktemp("pose2sim") / "ws"
    model = import_calibration(pose2sim(shared_dir) / "calibration" / "Calib.qca.txt",
                               root / "sparse" / "0", names)
    assert model == root / "sparse" / "0"
    return colmap.load_workspace(root)


def test_qualisys_import_triangulates_the_detections(shared_dir, rig) -> None:
    """DLT per joint and synchronous frame over the 4 undistorted views; the reprojection
    medians are ~13 px with the right conversion (and hundreds with a wrong one)."""
    ws = rig
    kp = read_keypoints("openpose", pose2sim(shared_dir) / "pose", workspace=ws, layout="BODY_25B")
    extra = set(kp.points) - set(ws.image_names)  # the data set's empty del_00000k_0.json
    assert len(kp.points) == 4 * FRAMES + 4 and all(kp.points[k].size == 0 for k in extra)
    cams = [f"cam0{c}" for c in range(1, 5)]
    assert {ws.reconstruction.cameras[ws.camera_id(f"{c}/{c}.0000.png")].model_name
            for c in cams} == {"OPENCV"}
    errors: dict[str, list[float]] = {c: [] for c in cams}
    for k in range(FRAMES):
        views = []
        for c in cams:
            name = f"{c}/{c}.{k:04d}.png"
            people = kp.points[name]
            pts = select_person(people, "largest", 0.0) if len(people) else None
            if pts is not None:
                R, C = ws.rotation(name), ws.centre(name)
                views.append((c, name, pts, ws.normalised(name, pts[:, :2] + 0.5),
                              np.hstack([R, -R @ C[:, None]])))
        for j in range(kp.num_points):
            used = [v for v in views if v[2][j, 2] > 0 and np.isfinite(v[3][j]).all()]
            if len(used) < 2:
                continue
            A = np.concatenate([[uv[j, 0] * P[2] - P[0], uv[j, 1] * P[2] - P[1]]
                                for _, _, _, uv, P in used])
            X = np.linalg.svd(A)[2][-1]
            X = X[:3] / X[3]
            for c, name, pts, _, _ in used:
                errors[c].append(np.linalg.norm(ws.project(name, X[None])[0] - pts[j, :2] - 0.5))
    medians = {c: float(np.median(e)) for c, e in errors.items()}
    assert all(len(e) > 2000 for e in errors.values())
    assert np.median(np.concatenate(list(errors.values()))) < 20, medians
    assert max(medians.values()) < 25 and max(medians, key=medians.get) == "cam03", medians


def opencv_project(X: np.ndarray, K: np.ndarray, dist: np.ndarray, R: np.ndarray,
                   t: np.ndarray) -> np.ndarray:
    """OpenCV's pinhole + k1 k2 p1 p2 k3 projection (pixel centres at integers): X (P, 3) ->
    (P, 2)."""
    k1, k2, p1, p2, k3 = dist
    cam = X @ R.T + t
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]])


def toml_list(a: np.ndarray) -> str:
    if a.ndim == 1:
        return "[" + ", ".join(repr(float(v)) for v in a) + "]"
    return "[" + ", ".join(toml_list(row) for row in a) + "]"


def test_anipose_toml_round_trip(tmp_path) -> None:
    rng = np.random.default_rng(2)
    cams = []
    text = ""
    for i, (name, k3) in enumerate([("left", 0.0), ("right", 0.01), ("top", -0.02)]):
        K = np.array([[900.0 + 10 * i, 0, 640.2], [0, 905.0, 359.7], [0, 0, 1]])
        dist = np.array([-0.2, 0.05, 1e-3, -5e-4, k3])
        rvec = rng.normal(scale=0.3, size=3)
        t = rng.normal(size=3) + [0, 0, 4]
        cams.append((name, K, dist, Rotation.from_rotvec(rvec).as_matrix(), t))
        text += (f'[cam_{i}]\nname = "{name}"\nsize = [1280, 720]\nmatrix = {toml_list(K)}\n'
                 f"distortions = {toml_list(dist)}\nrotation = {toml_list(rvec)}\n"
                 f"translation = {toml_list(t)}\n\n")
    text += "[metadata]\nadjusted = false\nerror = 0.3\n"
    (tmp_path / "calibration.toml").write_text(text)
    read = read_calibration(tmp_path / "calibration.toml")
    assert [c.name for c in read] == ["left", "right", "top"]
    model = import_calibration(tmp_path / "calibration.toml", tmp_path / "ws" / "sparse")
    ws = colmap.load_workspace(tmp_path / "ws")
    assert ws.image_names == ["left.jpg", "right.jpg", "top.jpg"]
    assert {ws.reconstruction.cameras[ws.camera_id(n)].model_name for n in ws.image_names} == \
        {"OPENCV", "FULL_OPENCV"}
    X = rng.normal(scale=0.5, size=(50, 3))
    for (_, K, dist, R, t), image in zip(cams, ws.image_names, strict=True):
        np.testing.assert_allclose(ws.rotation(image), R, atol=1e-12)
        np.testing.assert_allclose(ws.centre(image), -R.T @ t, atol=1e-12)
        np.testing.assert_allclose(ws.pinhole(image)[:2, 2], K[:2, 2] + 0.5)
        # COLMAP's projection of the imported camera = OpenCV's, shifted by half a pixel
        np.testing.assert_allclose(ws.project(image, X) - 0.5, opencv_project(X, K, dist, R, t),
                                   atol=1e-9)
    with pytest.raises(InputError, match="not empty"):
        import_calibration(tmp_path / "calibration.toml", model)


def test_bad_calibration_files(tmp_path) -> None:
    (tmp_path / "Calib.qca.txt").write_text("<calibration><cameras><camera")
    with pytest.raises(InputError, match=r"Calib\.qca\.txt: malformed XML"):
        read_calibration(tmp_path / "Calib.qca.txt")
    (tmp_path / "calib.toml").write_text('[cam_0]\nname = "a"\nsize = [10, 10]\nmatrix = [1]\n'
                                         "distortions = [0]\nrotation = [0, 0, 0]\n"
                                         "translation = [0, 0, 1]\n")
    with pytest.raises(InputError, match=r"calib\.toml: camera 'a' field 'matrix' has shape"):
        read_calibration(tmp_path / "calib.toml")
    (tmp_path / "broken.toml").write_text("[cam_0\n")
    with pytest.raises(InputError, match=r"broken\.toml: malformed TOML"):
        read_calibration(tmp_path / "broken.toml")
    (tmp_path / "calib.yaml").write_text("")
    with pytest.raises(InputError, match=r"calib\.yaml: unknown calibration format"):
        read_calibration(tmp_path / "calib.yaml")


def test_unknown_camera_in_image_map(shared_dir, tmp_path) -> None:
    with pytest.raises(InputError, match="no camera named 'cam_9' .*cam_01, cam_02"):
        import_calibration(pose2sim(shared_dir) / "calibration" / "Calib.qca.txt",
                           tmp_path / "model", {"cam_9": ["x.png"]})
