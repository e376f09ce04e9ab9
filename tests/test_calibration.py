"""Calibration import: Qualisys (also checked by triangulating real detections), anipose and
Pose2Sim TOML, OpenCV YAML / XML and EasyMocap, each projecting like its source."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dloe_sfm import cli, colmap
from dloe_sfm.calibration import (
    images_per_camera,
    import_calibration,
    read_calibration,
    read_qualisys,
)
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


@dataclass
class Cam:
    """A synthetic camera in OpenCV's conventions: world-to-camera ``rvec`` (Rodrigues), ``t``,
    pixel (0, 0) = centre of the top-left pixel."""

    name: str
    K: np.ndarray
    dist: np.ndarray
    rvec: np.ndarray
    t: np.ndarray
    size: tuple[int, int] = (1280, 720)
    fisheye: bool = False

    @property
    def R(self) -> np.ndarray:
        return cv2.Rodrigues(self.rvec)[0]

    def project(self, X: np.ndarray) -> np.ndarray:
        """OpenCV's own projection (``cv2.projectPoints``, ``cv2.fisheye.projectPoints``)."""
        if self.fisheye:
            uv, _ = cv2.fisheye.projectPoints(X[:, None], self.rvec, self.t, self.K, self.dist)
        else:
            uv, _ = cv2.projectPoints(X, self.rvec, self.t, self.K, self.dist)
        return uv.reshape(-1, 2)


def make_cameras(rng: np.random.Generator, names: list[str], dists: list[list[float]],
        fisheye: tuple[bool, ...] = (False, False, False)) -> list[Cam]:
    """Cameras about 4 m from the origin looking at it, rolled at random."""
    cams = []
    for i, (name, dist, fish) in enumerate(zip(names, dists, fisheye, strict=True)):
        azimuth = 2 * np.pi * i / len(names) + rng.uniform(-0.3, 0.3)
        centre = np.array([4 * np.cos(azimuth), 4 * np.sin(azimuth), rng.uniform(0.5, 2.0)])
        z = -centre / np.linalg.norm(centre)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        R = Rotation.from_rotvec([0, 0, rng.uniform(-0.2, 0.2)]).as_matrix() @ np.stack(
            [x, np.cross(z, x), z])
        K = np.array([[rng.uniform(800, 1200), 0, rng.uniform(600, 680)],
                      [0, rng.uniform(800, 1200), rng.uniform(330, 390)], [0, 0, 1]])
        cams.append(Cam(name=name, K=K, dist=np.array(dist, dtype=np.float64),
                        rvec=cv2.Rodrigues(R)[0].ravel(), t=-R @ centre, fisheye=fish))
    return cams


def points(rng: np.random.Generator) -> np.ndarray:
    """(60, 3) points around the origin, well inside every camera's view."""
    return rng.normal(scale=0.6, size=(60, 3))


def assert_same_projections(ws: colmap.Workspace, cams: list[Cam], images: list[str],
                            X: np.ndarray) -> None:
    """COLMAP's projection through the imported model = the source's own, once COLMAP's
    half-pixel offset (pixel centre (0.5, 0.5) vs OpenCV's (0, 0)) is taken off."""
    for cam, image in zip(cams, images, strict=True):
        np.testing.assert_allclose(ws.project(image, X) - 0.5, cam.project(X), rtol=0,
                                   atol=1e-6, err_msg=cam.name)
        np.testing.assert_allclose(ws.rotation(image), cam.R, atol=1e-12)
        assert ws.image_size(image) == cam.size


def camera_models(ws: colmap.Workspace) -> list[str]:
    return [ws.reconstruction.cameras[ws.camera_id(n)].model_name for n in ws.image_names]


PINHOLE_DISTS = [[-0.2, 0.05, 1e-3, -5e-4], [-0.1, 0.02, -2e-3, 1e-3, 0.01],
                 [0.15, -0.3, 5e-4, 2e-3, 0.05, 0.01, -0.02, 0.03]]
FISHEYE_DIST = [0.05, -0.01, 0.003, -0.001]


def toml_list(a: np.ndarray) -> str:
    a = np.asarray(a)
    if a.ndim == 1:
        return "[" + ", ".join(repr(float(v)) for v in a) + "]"
    return "[" + ", ".join(toml_list(row) for row in a) + "]"


def attrs(**values: float) -> str:
    return " ".join(f'{key}="{float(v)!r}"' for key, v in values.items())


def test_qualisys_round_trip(tmp_path, rng) -> None:
    """A .qca.txt written from known cameras, checked against Pose2Sim's reading of the format
    (``calibration.read_qca`` / ``calib_qca_fun``): f, c = value / 64 - fov_video offset,
    position in mm, rotation r11..r33 column-wise, then world-to-camera and a half turn about
    x. Qualisys' radialDistortion3 is k3 (Pose2Sim drops it)."""
    cams = make_cameras(rng, ["cam_01", "cam_02", "cam_03"],
               [[-0.05, 0.14, 6e-4, 7e-4, 0.0], [-0.04, 0.1, 1e-3, 3e-4, 0.0],
                [-0.05, 0.12, -5e-4, 2e-4, 0.02]])
    flip = np.diag([1.0, -1.0, -1.0])
    xml = "<calibration><cameras>\n"
    expected = []
    for cam, (left, top) in zip(cams, [(0, 0), (16, 8), (32, 0)], strict=True):
        r = flip @ cam.R  # the transform's rows r11 r12 r13 / r21 ... as QTM prints them
        position = -cam.R.T @ cam.t * 1000
        k1, k2, p1, p2, k3 = cam.dist
        right, bottom = left + cam.size[0] - 1, top + cam.size[1] - 1
        transform = attrs(**{f"r{a + 1}{b + 1}": r[a, b] for a in range(3) for b in range(3)},
                          x=position[0], y=position[1], z=position[2])
        intrinsic = attrs(
            focalLengthU=cam.K[0, 0] * 64, focalLengthV=cam.K[1, 1] * 64,
            centerPointU=(cam.K[0, 2] + left) * 64, centerPointV=(cam.K[1, 2] + top) * 64,
            radialDistortion1=k1, radialDistortion2=k2, radialDistortion3=k3,
            tangentalDistortion1=p1, tangentalDistortion2=p2)
        xml += (f'<camera active="1" serial="{cam.name}" viewrotation="0">'
                f'<fov_video left="{left}" top="{top}" right="{right}" bottom="{bottom}"/>'
                f"<transform {transform}/><intrinsic {intrinsic}/></camera>\n")
        # Pose2Sim's steps, from the attributes as written
        Rq = r.reshape(3, 3).T  # "by-column to by-line"
        R_cam, t_cam = Rq.T, -Rq.T @ (position / 1000)  # world_to_camera_persp
        R_cam, t_cam = flip @ R_cam, flip @ t_cam  # rotate_cam(ang_x=pi)
        expected.append(Cam(name=cam.name, K=cam.K, dist=cam.dist,
                            rvec=cv2.Rodrigues(R_cam)[0].ravel(), t=t_cam, size=cam.size))
    (tmp_path / "Calib.qca.txt").write_text(xml + "</cameras></calibration>\n")
    import_calibration(tmp_path / "Calib.qca.txt", tmp_path / "model", fmt="qualisys")
    ws = colmap.load_workspace(tmp_path / "model")
    assert ws.image_names == ["cam_01.jpg", "cam_02.jpg", "cam_03.jpg"]
    assert camera_models(ws) == ["OPENCV", "OPENCV", "FULL_OPENCV"]
    assert_same_projections(ws, expected, ws.image_names, points(rng))
    for cam, image in zip(cams, ws.image_names, strict=True):
        np.testing.assert_allclose(ws.centre(image), -cam.R.T @ cam.t, atol=1e-9)


def test_anipose_toml_round_trip(tmp_path, rng) -> None:
    """aniposelib's ``CameraGroup.dump`` layout: ``cam_<i>`` tables, Rodrigues rotation, a
    fisheye camera (``FisheyeCamera``: k1..k4, ``fisheye = true``) beside pinhole ones."""
    cams = make_cameras(rng, ["left", "right", "top"],
                        [PINHOLE_DISTS[0], PINHOLE_DISTS[1], FISHEYE_DIST],
                        fisheye=(False, False, True))
    text = ""
    for i, cam in enumerate(cams):
        text += (f'[cam_{i}]\nname = "{cam.name}"\nsize = [{cam.size[0]}, {cam.size[1]}]\n'
                 f"matrix = {toml_list(cam.K)}\ndistortions = {toml_list(cam.dist)}\n"
                 f"rotation = {toml_list(cam.rvec)}\ntranslation = {toml_list(cam.t)}\n"
                 + ("fisheye = true\n" if cam.fisheye else "") + "\n")
    text += "[metadata]\nadjusted = false\nerror = 0.3\n"
    (tmp_path / "calibration.toml").write_text(text)
    assert [c.name for c in read_calibration(tmp_path / "calibration.toml")] == \
        ["left", "right", "top"]
    model = import_calibration(tmp_path / "calibration.toml", tmp_path / "ws" / "sparse",
                               fmt="anipose")
    ws = colmap.load_workspace(tmp_path / "ws")
    assert ws.image_names == ["left.jpg", "right.jpg", "top.jpg"]
    assert camera_models(ws) == ["OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE"]
    np.testing.assert_allclose(ws.pinhole("left.jpg")[:2, 2], cams[0].K[:2, 2] + 0.5)
    assert_same_projections(ws, cams, ws.image_names, points(rng))
    with pytest.raises(InputError, match="not empty"):
        import_calibration(tmp_path / "calibration.toml", model)


def test_pose2sim_toml_round_trip(tmp_path, rng) -> None:
    """Text exactly as Pose2Sim's ``calibration.toml_write`` prints it: float sizes, 4
    distortions, ``fisheye = false``, a ``[metadata]`` table."""
    cams = make_cameras(rng, ["cam_01", "cam_02", "cam_03"], [PINHOLE_DISTS[0]] * 3)
    text = ""
    for c in cams:
        K, D, R, T = c.K, c.dist, c.rvec, c.t
        text += (f"[{c.name}]\nname = \"{c.name}\"\n"
                 f"size = [ {float(c.size[0])}, {float(c.size[1])}]\n"
                 f"matrix = [ [ {K[0, 0]}, 0.0, {K[0, 2]}], [ 0.0, {K[1, 1]}, {K[1, 2]}], "
                 "[ 0.0, 0.0, 1.0]]\n"
                 f"distortions = [ {D[0]}, {D[1]}, {D[2]}, {D[3]}]\n"
                 f"rotation = [ {R[0]}, {R[1]}, {R[2]}]\n"
                 f"translation = [ {T[0]}, {T[1]}, {T[2]}]\nfisheye = false\n\n")
    text += "[metadata]\nadjusted = false\nerror = 0.0\n"
    (tmp_path / "Calib_scene.toml").write_text(text)
    import_calibration(tmp_path / "Calib_scene.toml", tmp_path / "model", fmt="pose2sim")
    ws = colmap.load_workspace(tmp_path / "model")
    assert camera_models(ws) == ["OPENCV"] * 3
    assert_same_projections(ws, cams, ws.image_names, points(rng))


def write_storage(path: Path, **nodes) -> None:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in nodes.items():
        storage.write(key, value)
    storage.release()


def write_easymocap(folder: Path, cams: list[Cam], *, sizes: bool = True) -> None:
    """EasyMocap's ``write_intri`` / ``write_extri`` nodes: ``names``; ``K_``, ``dist_`` (1, 5)
    [, ``H_``, ``W_``]; ``R_`` (Rodrigues (3, 1)), ``Rot_``, ``T_`` (3, 1)."""
    folder.mkdir(parents=True, exist_ok=True)
    intri, extri = {"names": [c.name for c in cams]}, {"names": [c.name for c in cams]}
    for c in cams:
        intri[f"K_{c.name}"] = c.K
        intri[f"dist_{c.name}"] = np.pad(c.dist, (0, 5 - c.dist.size))[None]
        if sizes:
            intri[f"H_{c.name}"], intri[f"W_{c.name}"] = c.size[1], c.size[0]
        extri[f"R_{c.name}"] = c.rvec[:, None]
        extri[f"Rot_{c.name}"] = c.R
        extri[f"T_{c.name}"] = c.t[:, None]
    write_storage(folder / "intri.yml", **intri)
    write_storage(folder / "extri.yml", **extri)


def test_easymocap_round_trip(tmp_path, rng) -> None:
    cams = make_cameras(rng, ["01", "02", "03"],
                        [PINHOLE_DISTS[0], PINHOLE_DISTS[1], [0.1, 0.0, 0, 0]])
    write_easymocap(tmp_path / "calib", cams)
    X = points(rng)
    # the folder, or the intrinsics file with its extri.yml found beside it
    for i, calib in enumerate([tmp_path / "calib", tmp_path / "calib" / "intri.yml"]):
        import_calibration(calib, tmp_path / f"model{i}", fmt="opencv")
        ws = colmap.load_workspace(tmp_path / f"model{i}")
        assert ws.image_names == ["01.jpg", "02.jpg", "03.jpg"]
        assert camera_models(ws) == ["OPENCV", "FULL_OPENCV", "OPENCV"]
        assert_same_projections(ws, cams, ws.image_names, X)


def test_easymocap_sizes_and_names_from_the_images(tmp_path, rng) -> None:
    """No ``H_`` / ``W_``: each camera's size is its first image's; cameras 1, 2, 3 own the
    folders images/01, 02, 03 (leading zeros don't matter)."""
    cams = make_cameras(rng, ["1", "2", "3"], [PINHOLE_DISTS[0]] * 3)
    for c in cams:
        c.size = (64 + 8 * int(c.name), 48)
    write_easymocap(tmp_path / "data", cams, sizes=False)
    images = tmp_path / "data" / "images"
    for c in cams:
        (images / f"0{c.name}").mkdir(parents=True)
        for frame in range(2):
            cv2.imwrite(str(images / f"0{c.name}" / f"{frame:06d}.png"),
                        np.zeros((c.size[1], c.size[0]), np.uint8))
    with pytest.raises(InputError, match="camera '1': image size unknown"):
        import_calibration(tmp_path / "data", tmp_path / "nosize", fmt="opencv")
    assert not (tmp_path / "nosize").exists()
    import_calibration(tmp_path / "data", tmp_path / "data" / "sparse" / "0", fmt="opencv",
                       image_dir=images)
    ws = colmap.load_workspace(tmp_path / "data")
    assert ws.image_names == [f"0{k}/{f:06d}.png" for k in (1, 2, 3) for f in range(2)]
    assert ws.unregistered == []
    assert_same_projections(ws, [c for c in cams for _ in range(2)], ws.image_names, points(rng))


def test_opencv_single_camera_files_round_trip(tmp_path, rng) -> None:
    """One file per camera with the keys of OpenCV's calibration sample (``camera_matrix``,
    ``distortion_coefficients``, ``image_width`` / ``image_height``, ``fisheye_model``) and
    the pose as ``R`` (matrix) + ``T`` or ``rvec`` + ``tvec``; XML and YAML."""
    cams = make_cameras(rng, ["cam_a", "cam_b", "wide"],
                        [PINHOLE_DISTS[2], PINHOLE_DISTS[0], FISHEYE_DIST],
                        fisheye=(False, False, True))
    files = []
    for c, suffix in zip(cams, [".xml", ".yml", ".xml"], strict=True):
        pose = ({"R": c.R, "T": c.t[:, None]} if c.name == "cam_a"
                else {"rvec": c.rvec[:, None], "tvec": c.t[:, None]})
        files.append(tmp_path / f"{c.name}{suffix}")
        write_storage(files[-1], image_width=c.size[0], image_height=c.size[1],
                      fisheye_model=int(c.fisheye), camera_matrix=c.K,
                      distortion_coefficients=c.dist[:, None], **pose)
    assert [c.name for c in read_calibration(files)] == ["cam_a", "cam_b", "wide"]
    import_calibration(files, tmp_path / "model", fmt="opencv")
    ws = colmap.load_workspace(tmp_path / "model")
    assert camera_models(ws) == ["FULL_OPENCV", "OPENCV", "OPENCV_FISHEYE"]
    assert_same_projections(ws, cams, ws.image_names, points(rng))


def test_images_per_camera(tmp_path) -> None:
    for name in ["cam1/0001.jpg", "cam1/0002.jpg", "cam10_img/0001.jpg", "CAM-01_0003.png",
                 "camera/x.jpg", "other.png"]:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).touch()
    assert images_per_camera(tmp_path, ["cam_1", "cam_10", "cam"]) == {
        "cam_1": ["CAM-01_0003.png", "cam1/0001.jpg", "cam1/0002.jpg"],
        "cam_10": ["cam10_img/0001.jpg"], "cam": []}
    with pytest.raises(InputError, match="no image in a folder or file named after a camera"):
        images_per_camera(tmp_path, ["left", "right"])


def test_import_calibration_command(tmp_path, rng, capsys) -> None:
    cams = make_cameras(rng, ["cam_01", "cam_02", "cam_03"], [PINHOLE_DISTS[0]] * 3)
    write_easymocap(tmp_path / "calib", cams)
    out = tmp_path / "ws" / "sparse" / "0"
    args = ["import-calibration", tmp_path / "calib" / "intri.yml",
            tmp_path / "calib" / "extri.yml", "--format", "opencv", "--out", out]
    assert cli.main(list(map(str, args))) == 0  # what the ``dloe-sfm`` script runs
    assert capsys.readouterr().out == f"COLMAP model written to {out}\n"
    ws = colmap.load_workspace(tmp_path / "ws")
    assert ws.image_names == ["cam_01.jpg", "cam_02.jpg", "cam_03.jpg"]
    assert_same_projections(ws, cams, ws.image_names, points(rng))
    # bad input: one line, exit code 2, nothing written
    for argv, message in [
        (args, f"{out}: output folder exists (use --overwrite to replace it)"),
        (["import-calibration", tmp_path / "calib" / "extri.yml", "--format", "pose2sim",
          "--out", tmp_path / "other"], "extri.yml: malformed TOML"),
    ]:
        with pytest.raises(SystemExit) as exit_info:
            cli.main(list(map(str, argv)))
        # the one error line, after the log lines (``[time dloe_sfm LEVEL] ...``)
        err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("[")]
        assert exit_info.value.code == 2 and len(err) == 1 and message in err[0], err
    assert not (tmp_path / "other").exists()


def test_bad_calibration_files(tmp_path) -> None:
    (tmp_path / "Calib.qca.txt").write_text("<calibration><cameras><camera")
    with pytest.raises(InputError, match=r"Calib\.qca\.txt: malformed XML"):
        read_calibration(tmp_path / "Calib.qca.txt")
    (tmp_path / "calib.toml").write_text('[cam_0]\nname = "a"\nsize = [10, 10]\nmatrix = [1]\n'
                                         "distortions = [0]\nrotation = [0, 0, 0]\n"
                                         "translation = [0, 0, 1]\n")
    with pytest.raises(InputError, match=r"calib\.toml: camera 'a' field 'matrix' has shape"):
        read_calibration(tmp_path / "calib.toml")
    (tmp_path / "fish.toml").write_text(
        '[cam_0]\nname = "f"\nsize = [10, 10]\nmatrix = [[5, 0, 5], [0, 5, 5], [0, 0, 1]]\n'
        "distortions = [0.1, 0, 0, 0, 0]\nrotation = [0, 0, 0]\ntranslation = [0, 0, 1]\n"
        "fisheye = true\n")
    with pytest.raises(InputError, match="camera 'f': fisheye needs <= 4 distortions, got 5"):
        import_calibration(tmp_path / "fish.toml", tmp_path / "model", fmt="pose2sim")
    (tmp_path / "broken.toml").write_text("[cam_0\n")
    with pytest.raises(InputError, match=r"broken\.toml: malformed TOML"):
        read_calibration(tmp_path / "broken.toml")
    (tmp_path / "calib.txt").write_text("")
    with pytest.raises(InputError, match=r"calib\.txt: unknown calibration format"):
        read_calibration(tmp_path / "calib.txt")
    (tmp_path / "bad.yml").write_text("%YAML:1.0\na: [1, 2\nb: {\n")
    with pytest.raises(InputError, match=r"bad\.yml: not an OpenCV YAML / XML / JSON file"):
        read_calibration(tmp_path / "bad.yml")
    write_storage(tmp_path / "cam0.yml", camera_matrix=np.eye(3), rvec=np.zeros(3),
                  tvec=np.ones(3))
    with pytest.raises(InputError, match=r"cam0\.yml: camera 'cam0' lacks "
                                         "'distortion_coefficients' / 'dist'"):
        read_calibration(tmp_path / "cam0.yml")
    write_storage(tmp_path / "intri.yml", names=["c"], K_c=np.eye(3), dist_c=np.zeros((1, 5)))
    with pytest.raises(InputError, match=r"intri\.yml: camera 'c' lacks 'R_c' / 'Rot_c'"):
        read_calibration(tmp_path / "intri.yml")
    with pytest.raises(InputError, match="the qualisys format is one file, got 2"):
        read_calibration([tmp_path / "Calib.qca.txt"] * 2, "qualisys")


def test_unknown_camera_in_image_map(shared_dir, tmp_path) -> None:
    with pytest.raises(InputError, match="no camera named 'cam_9' .*cam_01, cam_02"):
        import_calibration(pose2sim(shared_dir) / "calibration" / "Calib.qca.txt",
                           tmp_path / "model", {"cam_9": ["x.png"]})
