"""The bundled crowd workspace (assets/crowd): lone photos and short bursts of handheld cameras
all around the scene, read through real pycolmap and dloe_sfm, and ``dloe-sfm demo --crowd``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from dloe_sfm import cli
from dloe_sfm.colmap import find_model, load_workspace, run_sfm
from dloe_sfm.errors import InputError
from dloe_sfm.evaluate import evaluate_output
from dloe_sfm.keypoints import read_keypoints
from dloe_sfm.observations import build_capture
from dloe_sfm.stages.demo import CROWD
from dloe_sfm.synth import load_pipeline

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"


@pytest.fixture(scope="module")
def crowd(assets_dir: Path) -> Path:
    path = assets_dir / "crowd"
    if not (path / "sparse" / "0").is_dir():
        pytest.fail(f"{path} is missing; see its README (pipelines/make_demo_assets, --crowd)")
    return path


@pytest.fixture(scope="module")
def crowd_pipeline():
    """``pipelines/crowd_workspaces/pipeline.py`` as a module."""
    return load_pipeline(PIPELINES, "crowd_workspaces")


@pytest.fixture(scope="module")
def truth(crowd: Path) -> dict[str, np.ndarray]:
    with np.load(crowd / "ground_truth.npz") as data:
        return {k: data[k] for k in data.files}


def test_the_package_ships_the_crowd_workspace(crowd):
    assert CROWD.resolve() == crowd.resolve()


def test_lone_photos_and_bursts_from_all_around(crowd, truth):
    """Real pycolmap reads the model: every image registered near its true pose, one COLMAP
    camera with its own true intrinsics per handheld camera, cameras all around the room."""
    model = pycolmap.Reconstruction(crowd / "sparse" / "0")
    images = {model.image(i).name: model.image(i) for i in model.reg_image_ids()}
    names = [str(n) for n in truth["image_names"]]
    folder = crowd / "images"
    on_disk = sorted(str(p.relative_to(folder)) for p in folder.rglob("*.jpg"))
    assert sorted(images) == on_disk == names
    streams, counts = np.unique(truth["stream"], return_counts=True)
    assert 20 <= streams.size <= 40 and counts.max() <= 5
    assert (counts == 1).sum() >= 5 and (counts > 1).sum() >= 3
    assert model.num_cameras() == streams.size
    focal = {}
    for s in streams:
        sel = np.flatnonzero(truth["stream"] == s)
        (camera_id,) = {images[names[i]].camera_id for i in sel}
        assert np.allclose(model.camera(camera_id).params, truth["camera_params"][sel[0]])
        focal[s] = truth["camera_params"][sel[0], 0]
        if sel.size > 1:  # a burst: its own rate in 1-3 Hz, every image its own pose
            rate = truth["frame_rate"][sel[0]]
            assert 1 <= rate <= 3 and np.allclose(np.diff(truth["t_true"][sel]), 1 / rate)
            assert np.linalg.norm(np.diff(truth["C_true"][sel], axis=0), axis=1).min() > 1e-3
        else:
            assert np.isnan(truth["frame_rate"][sel[0]])
    assert max(focal.values()) / min(focal.values()) > 1.2
    centres = np.stack([images[n].projection_center() for n in names])
    assert np.linalg.norm(centres - truth["C_true"], axis=1).max() < 0.05  # metres
    rotations = np.stack([images[n].cam_from_world().rotation.matrix() for n in names])
    cos = (np.einsum("nij,nij->n", rotations, truth["R_true"]) - 1) / 2
    assert np.rad2deg(np.arccos(np.clip(cos, -1, 1))).max() < 0.5
    azimuth = np.sort(np.arctan2(truth["C_true"][:, 1], truth["C_true"][:, 0]))
    assert np.diff(np.r_[azimuth, azimuth[0] + 2 * np.pi]).max() < np.deg2rad(60)
    assert np.ptp(np.hypot(*truth["C_true"][:, :2].T)) > 1.0  # metres: near and far
    assert model.compute_mean_reprojection_error() < 1.0


def test_dloe_sfm_reads_lone_photos_and_streams(crowd, truth):
    ws = load_workspace(crowd)
    kp = read_keypoints("csv", crowd / "keypoints.csv", workspace=ws)
    capture = build_capture(ws, kp).capture
    row = {str(n): i for i, n in enumerate(truth["image_names"])}
    stream = truth["stream"][[row[str(n)] for n in capture.image_names]]
    _, counts = np.unique(truth["stream"], return_counts=True)
    lone = np.isin(stream, np.flatnonzero(counts == 1))
    assert (capture.stream[lone] == -1).all()
    assert (capture.stream[~lone] >= 0).all()
    assert np.unique(capture.stream[~lone]).size == (counts > 1).sum()


def test_sfm_holds_each_cameras_own_intrinsics(crowd, truth, tmp_path):
    """``run_sfm`` with intrinsics per image name: a COLMAP camera per folder holding its own."""
    names = [str(n) for n in truth["image_names"]]
    folders = ["cam2", "cam3", "cam4"]  # bursts of 3 and 4, a lone photo; 15-20 degrees apart
    images = tmp_path / "images"
    for folder in folders:
        shutil.copytree(crowd / "images" / folder, images / folder)
    params = {n: truth["camera_params"][i] for i, n in enumerate(names)
              if n.split("/")[0] in folders}
    sfm = run_sfm(images, tmp_path / "sfm", camera_params=params, num_threads=2, seed=0)
    model = pycolmap.Reconstruction(find_model(sfm))
    assert model.num_cameras() == len(folders)
    for image_id in model.reg_image_ids():
        image = model.image(image_id)
        assert np.allclose(model.camera(image.camera_id).params, params[image.name])
    mixed = dict(params, **{"cam3/001.jpg": params["cam2/000.jpg"]})
    with pytest.raises(InputError, match="shares camera"):
        run_sfm(images, tmp_path / "mixed", camera_params=mixed, num_threads=2)


def test_demo_crowd_runs_and_scores(tmp_path, capsys, truth, crowd_pipeline):
    """``dloe-sfm demo --crowd``: every image reconstructed and ordered (|tau| >= 0.99: the
    bursts' few frames sequenced by the shapes and placed by their rays; the bursts' clocks
    fitted to the rays lose the held-out check here and would order them at 0.97-0.99,
    docs/method.md, "Clocks of bursts"); the 3D error is measured, not bounded here
    (issue 38 asks 1.3 x the oracle + 2 mm, not reached yet): assets/crowd/README.md. Every
    burst's offset has an uncertainty (one of two frames had 0) that covers its error."""
    out = tmp_path / "demo_crowd"
    assert cli.main(["demo", "--crowd", "--out", str(out), "--no-plots"]) == 0
    printed = capsys.readouterr().out
    lone = int((np.unique(truth["stream"], return_counts=True)[1] == 1).sum())
    assert f"{lone} lone photos" in printed and "|Kendall tau|" in printed
    for name in ("trajectories.npz", "sequence.csv", "report.json"):
        assert (out / name).is_file()
    json.loads((out / "report.json").read_text())
    s = evaluate_output(out, CROWD / "ground_truth.npz")
    assert s["images"] == truth["image_names"].size  # every image reconstructed
    assert {"error_mm", "error_aligned_mm", "kendall_tau", "sync_rms_ms"} <= s.keys()
    assert np.isfinite([s["error_mm"], s["kendall_tau"], s["sync_rms_ms"]]).all()
    assert s["kendall_tau"] >= 0.99
    errors = crowd_pipeline.offset_errors(CROWD, out)
    bursts = int((np.unique(truth["stream"], return_counts=True)[1] > 1).sum())
    assert len(errors) == bursts - 1 and (errors[:, 2] > 0).all()  # all but the reference
    assert (np.abs(errors[:, 1]) <= 2 * errors[:, 2]).all(), errors


@pytest.mark.slow
def test_crowd_workspaces_pipeline_scores_against_the_oracle(crowd, truth, tmp_path,
                                                             crowd_pipeline):
    """``pipelines/crowd_workspaces`` on the bundled workspace: the references on the same SfM
    cameras and the five acceptance lines are there (measured figures: assets/crowd/README.md)."""
    pipeline = crowd_pipeline
    s = pipeline.score_workspace(crowd, tmp_path / "dloe")
    counts = np.unique(truth["stream"], return_counts=True)[1]
    assert (s["lone_photos"], s["bursts"]) == ((counts == 1).sum(), (counts > 1).sum())
    assert s["images"] == truth["image_names"].size and s["images_without_points"] == 0
    assert np.isfinite([s["oracle_mm"], s["pseudo_triangulation_mm"], s["sync_periods"]]).all()
    assert 0 < s["oracle_mm"] < s["pseudo_triangulation_mm"]
    assert set(s["acceptance"]) == {"mean_vs_oracle", "worst_image", "tau", "sync", "seconds"}
    assert s["offsets"] == (counts > 1).sum() - 1 and 0 <= s["offsets_within_2sd"] <= 1
    assert len(pipeline.table([dict(s, seed=0)]).splitlines()) == 3  # head, the row, the key
