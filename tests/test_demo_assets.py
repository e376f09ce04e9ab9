"""The bundled demo workspace (assets/demo) is consistent with its ground truth."""

import csv
from pathlib import Path

import numpy as np
import pycolmap
import pytest


@pytest.fixture(scope="module")
def demo(assets_dir: Path) -> Path:
    path = assets_dir / "demo"
    if not (path / "sparse" / "0").is_dir():
        pytest.fail(f"{path} is missing; run pipelines/make_demo_assets/pipeline.py")
    return path


@pytest.fixture(scope="module")
def model(demo: Path) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(demo / "sparse" / "0")


@pytest.fixture(scope="module")
def truth(demo: Path) -> dict[str, np.ndarray]:
    with np.load(demo / "ground_truth.npz") as data:
        return {k: data[k] for k in data.files}


def test_every_image_registered_with_its_true_pose(demo, model, truth):
    on_disk = sorted(str(p.relative_to(demo / "images")) for p in (demo / "images").rglob("*.jpg"))
    images = {model.image(i).name: model.image(i) for i in model.reg_image_ids()}
    assert sorted(images) == on_disk == list(truth["image_names"])
    assert model.num_cameras() == np.unique(truth["stream"]).size
    centres = np.stack([images[n].projection_center() for n in truth["image_names"]])
    assert np.linalg.norm(centres - truth["C_true"], axis=1).max() < 0.05  # metres, ring of 3.6 m
    rotations = np.stack([images[n].cam_from_world().rotation.matrix()
                          for n in truth["image_names"]])
    cos = (np.einsum("nij,nij->n", rotations, truth["R_true"]) - 1) / 2
    assert np.rad2deg(np.arccos(np.clip(cos, -1, 1))).max() < 0.5
    assert model.compute_mean_reprojection_error() < 1.0


def test_keypoints_match_projected_truth(demo, model, truth):
    images = {model.image(i).name: model.image(i) for i in model.reg_image_ids()}
    row = {str(n): i for i, n in enumerate(truth["image_names"])}
    errors = []
    with open(demo / "keypoints.csv", newline="") as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames == ["image", "point_id", "x", "y", "score"]
        for r in reader:
            n, p = row[r["image"]], int(r["point_id"])
            score = float(r["score"])
            assert 0 <= score <= 1
            # CSV pixels put (0, 0) at the centre of the top-left pixel; COLMAP puts it at 0.5.
            projected = images[r["image"]].project_point(truth["X_true"][n, p]) - 0.5
            errors.append(np.hypot(*(projected - (float(r["x"]), float(r["y"])))))
    visible = truth["visible_fraction"] > 0
    assert len(errors) >= 0.95 * visible.sum()
    assert np.median(errors) < 1.5
    # Every marker is seen by at least two cameras in most images' time steps.
    per_stream = [visible[truth["stream"] == s].mean(axis=0) for s in np.unique(truth["stream"])]
    assert ((np.array(per_stream) > 0.5).sum(axis=0) >= 2).all()


def test_assets_are_small(assets_dir):
    """A few MB in all: the demo, field and crowd workspaces, the clips, the Pose2Sim trial's
    keypoint files and the README's figures."""
    size = sum(f.stat().st_size for f in assets_dir.rglob("*") if f.is_file())
    assert size < 8e6
