"""COLMAP workspaces: finding models, rays / projection conventions, writing models, and the
round trip image points -> keypoint file -> Capture -> triangulation on real distorted cameras."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from dloe_sfm import colmap
from dloe_sfm.errors import InputError
from dloe_sfm.keypoints import read_keypoints
from dloe_sfm.observations import build_capture


@pytest.fixture(scope="session")
def synthetic(tmp_path_factory) -> Path:
    """A seeded workspace: 3 video cameras x 4 frames, SIMPLE_RADIAL, 50 static points."""
    return colmap.synthetic_workspace(tmp_path_factory.mktemp("synthetic") / "ws")


@pytest.fixture(scope="session")
def ws(synthetic) -> colmap.Workspace:
    return colmap.load_workspace(synthetic)


def model_files(synthetic: Path) -> list[Path]:
    return sorted((synthetic / "sparse" / "0").iterdir())


def copy_model(synthetic: Path, dest: Path) -> None:
    dest.mkdir(parents=True, exist_ok=True)
    for f in model_files(synthetic):
        shutil.copy(f, dest / f.name)


def triangulate(C: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Least-squares intersection of rays: C (N, 3), rays (N, P, 3) unit, NaN = unused
    -> (P, 3)."""
    ok = np.isfinite(rays).all(axis=2)
    d = np.where(ok[..., None], rays, 0.0)
    M = ok[..., None, None] * np.eye(3) - np.einsum("npi,npj->npij", d, d)
    A = M.sum(axis=0)
    b = np.einsum("npij,nj->npi", M, C).sum(axis=0)
    return np.linalg.solve(A, b[..., None])[..., 0]


@pytest.mark.parametrize("layout", ["root", "sparse/0", "sparse", "dense/0/sparse"])
def test_finds_each_layout(synthetic, ws, tmp_path, layout) -> None:
    root = tmp_path / "ws"
    model_dir = root if layout == "root" else root / layout
    copy_model(synthetic, model_dir)
    found = colmap.load_workspace(root)
    assert found.model_dir == model_dir
    assert found.image_names == ws.image_names
    np.testing.assert_array_equal(found.static_xyz, ws.static_xyz)


def test_picks_the_numbered_model_with_most_images(synthetic, ws, tmp_path) -> None:
    root = tmp_path / "ws"
    colmap.synthetic_workspace(tmp_path / "small", num_cameras=2, num_frames=2)
    copy_model(tmp_path / "small", root / "sparse" / "0")
    copy_model(synthetic, root / "sparse" / "1")
    found = colmap.load_workspace(root)
    assert found.model_dir == root / "sparse" / "1"
    assert len(found.image_names) == 12


def test_text_model_and_write_round_trip(tmp_path) -> None:
    rng = np.random.default_rng(1)
    cameras = [
        colmap.CameraSpec(model="OPENCV", width=640, height=480,
                          params=np.array([500.0, 510.0, 320.5, 240.5, -0.1, 0.02, 1e-3, -2e-3])),
        colmap.CameraSpec(model="SIMPLE_PINHOLE", width=800, height=600,
                          params=np.array([700.0, 400.0, 300.0])),
    ]
    poses = []
    for _ in range(3):
        q, _r = np.linalg.qr(rng.normal(size=(3, 3)))
        poses.append((q * np.sign(np.linalg.det(q)), rng.normal(size=3)))
    images = [colmap.ImageSpec(name=f"cam{k % 2}/img{k}.jpg", camera=k % 2, R=R, C=C)
              for k, (R, C) in enumerate(poses)]
    colmap.write_model(tmp_path / "ws" / "sparse", cameras, images, text=True)
    assert (tmp_path / "ws" / "sparse" / "images.txt").is_file()
    ws = colmap.load_workspace(tmp_path / "ws")
    assert ws.image_names == ["cam0/img0.jpg", "cam0/img2.jpg", "cam1/img1.jpg"]
    assert ws.static_xyz.shape == (0, 3)
    for k, (R, C) in enumerate(poses):
        name = images[k].name
        np.testing.assert_allclose(ws.rotation(name), R, atol=1e-12)
        np.testing.assert_allclose(ws.centre(name), C, atol=1e-12)
        assert ws.camera_id(name) == k % 2 + 1
    np.testing.assert_allclose(ws.pinhole("cam0/img0.jpg"),
                               [[500, 0, 320.5], [0, 510, 240.5], [0, 0, 1]])
    with pytest.raises(InputError, match="not empty"):
        colmap.write_model(tmp_path / "ws" / "sparse", cameras, images)
    with pytest.raises(InputError, match="camera 0: model OPENCV needs params"):
        colmap.write_model(tmp_path / "bad", [colmap.CameraSpec(
            model="OPENCV", width=10, height=10, params=np.ones(3))], [])


def test_bad_workspaces(tmp_path) -> None:
    with pytest.raises(InputError, match="nope: no such workspace"):
        colmap.load_workspace(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="empty: no COLMAP model"):
        colmap.load_workspace(tmp_path / "empty")
    colmap.write_model(tmp_path / "unposed" / "sparse" / "0", [colmap.CameraSpec(
        model="SIMPLE_PINHOLE", width=10, height=10, params=np.array([10.0, 5, 5]))], [])
    with pytest.raises(InputError, match=r"unposed/sparse/0: the COLMAP model has no registered"):
        colmap.load_workspace(tmp_path / "unposed")
    bad = tmp_path / "corrupt" / "sparse" / "0"
    bad.mkdir(parents=True)
    for name in colmap.MODEL_FILES:
        (bad / f"{name}.bin").write_bytes(b"\x07")
    with pytest.raises(InputError, match="corrupt/sparse/0: cannot read"):
        colmap.load_workspace(tmp_path / "corrupt")


def test_unregistered_images_are_listed(synthetic, tmp_path) -> None:
    root = tmp_path / "ws"
    copy_model(synthetic, root / "sparse" / "0")
    images = root / "images"
    images.mkdir()
    ws0 = colmap.load_workspace(root)
    for name in [*ws0.image_names, "extra/late_arrival.JPG"]:
        (images / name).parent.mkdir(parents=True, exist_ok=True)
        (images / name).write_bytes(b"")
    (images / "notes.txt").write_text("not an image")
    ws = colmap.load_workspace(root)
    assert ws.image_dir == images
    assert ws.unregistered == ["extra/late_arrival.JPG"]
    assert ws.image_names == ws0.image_names


def test_rays_pass_through_projected_points(ws) -> None:
    X = ws.static_xyz
    for name in ws.image_names:
        x = ws.project(name, X)
        seen = np.isfinite(x).all(axis=1)
        assert seen.sum() > 10
        rays = ws.rays(name, x[seen])
        d = X[seen] - ws.centre(name)
        # distance of each point from its ray, relative to its depth
        off = np.linalg.norm(np.cross(d, rays), axis=1) / np.linalg.norm(d, axis=1)
        assert off.max() < 1e-6
        assert (np.einsum("ij,ij->i", d, rays) > 0).all()  # in front, not behind


def test_project_matches_pinhole_without_distortion(tmp_path) -> None:
    path = colmap.synthetic_workspace(tmp_path / "ws", camera_model="PINHOLE", num_cameras=2,
                                      num_frames=1)
    ws = colmap.load_workspace(path)
    for name in ws.image_names:
        K, R, C = ws.pinhole(name), ws.rotation(name), ws.centre(name)
        h = (ws.static_xyz - C) @ R.T @ K.T
        x = ws.project(name, ws.static_xyz)
        front = h[:, 2] > 0
        np.testing.assert_allclose(x[front], h[front, :2] / h[front, 2:], rtol=1e-10)
        assert np.isnan(x[~front]).all()


def test_non_invertible_pixels_are_missing(ws, tmp_path) -> None:
    name = ws.image_names[0]
    # k > 0: every pixel has an undistorted preimage, even far outside the image
    uv = ws.normalised(name, np.array([[512.0, 384.0], [1e5, 384.0], [np.nan, 3.0]]))
    np.testing.assert_allclose(uv[0], 0.0, atol=1e-12)  # the principal point
    r = uv[1, 0]
    np.testing.assert_allclose(r * (1 + 0.05 * r**2), (1e5 - 512) / 1280, rtol=1e-9)
    assert np.isnan(uv[2]).all()
    # k < 0 (barrel): radii beyond the fold at r = 1 / sqrt(3 |k|) have no preimage
    path = colmap.synthetic_workspace(tmp_path / "barrel", num_cameras=2, num_frames=1,
                                      camera_params=[1280.0, 512.0, 384.0, -0.2])
    barrel = colmap.load_workspace(path)
    fold = 1 / np.sqrt(0.6) * (1 - 0.2 / 0.6) * 1280  # largest distorted radius, pixels
    uv = barrel.normalised(barrel.image_names[0], np.array([[512.0 + 0.9 * fold, 384.0],
                                                             [512.0 + 1.1 * fold, 384.0]]))
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1]).all()
    # this fisheye folds near x = 1140: COLMAP's iterative inverse returns a finite but wrong
    # point beyond it, which the projection check rejects
    path = colmap.synthetic_workspace(tmp_path / "fisheye", num_cameras=2, num_frames=1,
                                      camera_model="OPENCV_FISHEYE",
                                      camera_params=[600, 600, 512, 384, 0.1, -0.2, 0.05, 0.01])
    fisheye = colmap.load_workspace(path)
    name = fisheye.image_names[0]
    pixels = np.array([[1000.0, 384.0], [1500.0, 384.0], [3000.0, 384.0]])
    uv = fisheye.normalised(name, pixels)
    assert np.isfinite(uv[:2]).all() and np.isnan(uv[2]).all()
    cam = np.c_[uv[:2], np.ones(2)] @ fisheye.rotation(name) + fisheye.centre(name)
    np.testing.assert_allclose(fisheye.project(name, cam), pixels[:2], atol=1e-6)


def test_synthetic_workspace_is_deterministic(synthetic, ws, tmp_path) -> None:
    again = colmap.load_workspace(colmap.synthetic_workspace(tmp_path / "again"))
    np.testing.assert_array_equal(again.static_xyz, ws.static_xyz)
    for name in ws.image_names:
        np.testing.assert_array_equal(again.centre(name), ws.centre(name))
    with pytest.raises(InputError, match="already there"):
        colmap.synthetic_workspace(synthetic)


def test_rig_frames_mark_synchronous_images(tmp_path) -> None:
    path = colmap.synthetic_workspace(tmp_path / "rig", num_cameras=1, cameras_per_rig=2,
                                      num_frames=3)
    ws = colmap.load_workspace(path)
    names = ws.image_names
    rows = ["image,point_id,x,y"]
    for name in names:
        for j, (u, v) in enumerate(ws.project(name, ws.static_xyz[:5]) - 0.5):
            if np.isfinite(u):
                rows.append(f"{name},{j},{u},{v}")
    (tmp_path / "kp.csv").write_text("\n".join(rows))
    capture = build_capture(ws, read_keypoints("csv", tmp_path / "kp.csv", workspace=ws)).capture
    frame_ids = capture.image_ids["colmap_frame_id"]
    assert {ws.rig_id(n) for n in names} == {1}
    # camera 1 and camera 2 images of frame k share a COLMAP frame, streams follow cameras
    np.testing.assert_array_equal(capture.stream, [0, 0, 0, 1, 1, 1])
    np.testing.assert_array_equal(capture.frame, [0, 1, 2, 0, 1, 2])
    np.testing.assert_array_equal(frame_ids[:3], frame_ids[3:])
    assert np.unique(frame_ids).size == 3


def test_sacre_coeur_round_trip(shared_dir, tmp_path) -> None:
    """Real distorted cameras: project known points, write them as (0, 0)-convention CSV
    keypoints, build the capture, triangulate the static scene back."""
    ws = colmap.load_workspace(shared_dir / "data" / "sacre_coeur")
    assert len(ws.image_names) == 10 and ws.image_dir is not None
    assert {ws.reconstruction.cameras[ws.camera_id(n)].model_name
            for n in ws.image_names} == {"SIMPLE_RADIAL"}
    X = ws.static_xyz[::50]
    rows = ["image,point_id,x,y,score"]
    pixels = {}
    for name in ws.image_names:
        x = ws.project(name, X)
        w, h = ws.image_size(name)
        inside = np.isfinite(x).all(axis=1) & (x > 0).all(axis=1) & (x < [w, h]).all(axis=1)
        pixels[name] = np.where(inside[:, None], x, np.nan)
        for j in np.flatnonzero(inside):
            u, v = x[j] - 0.5  # COLMAP (0.5, 0.5) -> keypoint (0, 0) convention
            rows.append(f"{name},{j},{float(u)!r},{float(v)!r},0.9")
    (tmp_path / "kp.csv").write_text("\n".join(rows) + "\n")
    kp = read_keypoints("csv", tmp_path / "kp.csv", workspace=ws, num_points=len(X))
    capture = build_capture(ws, kp).capture
    assert list(capture.image_names) == ws.image_names
    assert (capture.stream == -1).all()  # one photo per camera: lone photos
    rays = capture.rays()
    for i, name in enumerate(ws.image_names):
        np.testing.assert_allclose(rays[i], ws.rays(name, pixels[name]), atol=1e-12)
        np.testing.assert_array_equal(capture.K[i], ws.pinhole(name))
    np.testing.assert_allclose(capture.confidence[capture.visible], 0.9)
    seen = capture.visible.sum(axis=0)
    assert (seen >= 2).all()
    Xhat = triangulate(capture.C, rays)
    err = np.linalg.norm(Xhat - X, axis=1) / np.linalg.norm(X - capture.C.mean(axis=0), axis=1)
    assert err.max() < 1e-6
