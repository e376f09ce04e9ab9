"""The ``reconstruct`` stage end to end: COLMAP model + OpenPose files -> section-4 outputs."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scenes import COCO_LAYOUT, NUM_CAMERAS, NUM_FRAMES, image_time, write_openpose

import dloe_sfm
import dloe_sfm.stages.reconstruct as stage
from dloe_sfm import cli, colmap
from dloe_sfm.core.solver import reconstruct as solver
from dloe_sfm.errors import InputError


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[Path, Path, dict[str, np.ndarray]]:
    root = tmp_path_factory.mktemp("stage")
    workspace = colmap.synthetic_workspace(root / "ws", num_cameras=NUM_CAMERAS,
                                           num_frames=NUM_FRAMES, num_points3D=60)
    ws = colmap.load_workspace(workspace)
    assert len(ws.image_names) == NUM_CAMERAS * NUM_FRAMES
    truth = write_openpose(root / "openpose", ws)
    return workspace, root / "openpose", truth


@pytest.fixture(scope="module")
def reconstructed(scene, tmp_path_factory) -> Path:
    workspace, keypoints, _ = scene
    out = tmp_path_factory.mktemp("out") / "recon"
    assert stage.main(workspace, keypoints, "openpose", out) == out
    return out


def model_snapshot(workspace: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((workspace / "sparse" / "0").iterdir())}


def test_points_match_the_truth(scene, reconstructed) -> None:
    _, _, truth = scene
    with np.load(reconstructed / "trajectories.npz") as data:
        X, names = data["X"], data["image_names"]
    X_true = np.stack([truth[str(n)] for n in names])
    scene_size = np.linalg.norm(np.ptp(X_true.reshape(-1, 3), axis=0))
    error = np.linalg.norm(X - X_true, axis=2) / scene_size
    # the first and last instants can only be extrapolated (DLOE's rows are convex
    # combinations): they are held to a looser bound than the interior
    by_time = error[np.argsort([image_time(str(n)) for n in names])]
    assert by_time[1:-1].mean() < 1e-2
    assert np.median(error) < 5e-3
    assert by_time[[0, -1]].mean(axis=1).max() < 0.2


def test_evaluate_scores_an_output_folder(scene, reconstructed, tmp_path, capsys) -> None:
    from dloe_sfm.evaluate import evaluate_output

    _, _, truth = scene
    names = sorted(truth)
    X_true = np.stack([truth[n] for n in names])
    t_true = np.array([image_time(n) for n in names])
    np.savez(tmp_path / "truth.npz", image_names=names, X_true=X_true, t_true=t_true)
    scores = evaluate_output(reconstructed, tmp_path / "truth.npz")
    with np.load(reconstructed / "trajectories.npz") as data:
        X = data["X"]
        row = {n: i for i, n in enumerate(names)}
        expected = np.linalg.norm(X - X_true[[row[str(n)] for n in data["image_names"]]], axis=2)
    assert scores["images"] == len(names)
    assert scores["error_mm"] == pytest.approx(1000 * expected.mean(), rel=1e-9)
    # already in the truth's frame: the alignment (least squares, not least mean) barely moves it
    assert scores["alignment_scale"] == pytest.approx(1, abs=1e-2)
    assert scores["error_aligned_mm"] < 2 * scores["error_mm"] and scores["kendall_tau"] > 0.99
    assert 0 <= scores["sync_rms_ms"] < 1000 * 0.25 / len(names)  # a quarter of an image slot
    assert scores["order_ambiguous"] == 0 and "kendall_tau_unambiguous" not in scores
    # two images' true times swapped, the first and the last: flagged order-ambiguous in the
    # report, they are left out of the order and the sync scored without them
    flagged = tmp_path / "flagged"
    flagged.mkdir()
    for name in ("trajectories.npz", "sequence.csv", "report.json"):
        shutil.copy(reconstructed / name, flagged / name)
    first, last = int(np.argmin(t_true)), int(np.argmax(t_true))
    swapped = t_true.copy()
    swapped[[first, last]] = t_true[[last, first]]
    np.savez(tmp_path / "swapped.npz", image_names=names, X_true=X_true, t_true=swapped)
    report = json.loads((flagged / "report.json").read_text())
    report["image_status"]["order_ambiguous"] = [names[first], names[last]]
    (flagged / "report.json").write_text(json.dumps(report))
    both = evaluate_output(flagged, tmp_path / "swapped.npz")
    assert both["order_ambiguous"] == 2
    assert both["kendall_tau"] < 0.95 and both["sync_rms_ms"] > 1000 * 0.25 / len(names)
    assert both["kendall_tau_unambiguous"] > 0.99
    assert 0 <= both["sync_rms_unambiguous_ms"] < 1000 * 0.25 / len(names)
    (flagged / "report.json").write_text("{")
    with pytest.raises(InputError, match="report.json: cannot read the flagged images"):
        evaluate_output(flagged, tmp_path / "swapped.npz")
    # the same truth in another frame and scale: the aligned error scales with it, no more
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    np.savez(tmp_path / "moved.npz", image_names=names, X_true=2 * X_true @ R.T + [1, 2, 3],
             t_true=t_true)
    moved = evaluate_output(reconstructed, tmp_path / "moved.npz")
    assert moved["error_aligned_mm"] == pytest.approx(2 * scores["error_aligned_mm"], rel=1e-6)
    assert moved["alignment_scale"] == pytest.approx(2 * scores["alignment_scale"], rel=1e-6)
    assert moved["error_mm"] > 100 * scores["error_mm"]
    # through the command line; a folder that is not an output: one line, exit 2
    assert cli.main(["evaluate", str(reconstructed), str(tmp_path / "truth.npz")]) == 0
    assert "error_aligned_mm" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["evaluate", str(tmp_path), str(tmp_path / "truth.npz")])
    assert exit_info.value.code == 2
    assert "not a reconstruct output folder" in one_error_line(capsys.readouterr().err)


def test_a_point_no_image_observes_is_left_out_and_reported(scene, reconstructed,
                                                              tmp_path) -> None:
    workspace, keypoints, _ = scene
    folder = tmp_path / "openpose"
    folder.mkdir()
    for file in keypoints.iterdir():  # the nose (point 0) never detected
        data = json.loads(file.read_text())
        data["people"][0]["pose_keypoints_2d"][:3] = [0.0, 0.0, 0.0]
        (folder / file.name).write_text(json.dumps(data))
    out = stage.main(workspace, folder, "openpose", tmp_path / "out", plots=False)
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"]["unobserved_points"] == [COCO_LAYOUT.point_names[0]]
    with np.load(out / "trajectories.npz") as got, \
            np.load(reconstructed / "trajectories.npz") as full:
        assert list(got["point_names"]) == COCO_LAYOUT.point_names[1:]
        assert got["X"].shape == (full["X"].shape[0], len(COCO_LAYOUT.point_names) - 1, 3)
        # the other points as without the change, to the solver's accuracy
        assert np.abs(got["X"] - full["X"][:, 1:]).max() < 0.05


def test_outputs_are_complete(scene, reconstructed) -> None:
    _, _, truth = scene
    frames = sorted((reconstructed / "frames").glob("*.ply"))
    assert len(frames) == len(truth)
    cloud = o3d.t.io.read_point_cloud(str(frames[0]))
    np.testing.assert_array_equal(cloud.point.point_id.numpy().ravel(), np.arange(18))
    assert len(list((reconstructed / "skeleton").glob("*.ply"))) == len(truth)
    static = o3d.t.io.read_point_cloud(str(reconstructed / "static.ply"))
    assert static.point.positions.shape[0] == 60
    report = json.loads((reconstructed / "report.json").read_text())
    assert report["inputs"]["format"] == "openpose" and report["layout"] == "COCO_18"
    assert report["images"] == 60 and report["points"] == 18
    assert report["reprojection_error_px"]["all"]["median"] < 1.0
    for png in ("sequence.png", "affinity.png", "events.png", "trajectories.png"):
        assert (reconstructed / "plots" / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_matches_python_and_leaves_the_model_alone(scene, reconstructed, tmp_path) -> None:
    workspace, keypoints, _ = scene
    before = model_snapshot(workspace)
    out = tmp_path / "cli"
    layout = tmp_path / "coco.json"  # COCO_18 under another name: a custom layout file
    layout.write_text(json.dumps({"name": "mine", "point_names": COCO_LAYOUT.point_names,
                                  "edges": COCO_LAYOUT.edges,
                                  "symmetric_pairs": COCO_LAYOUT.symmetric_pairs}))
    proc = subprocess.run(
        [sys.executable, "-m", "dloe_sfm", "reconstruct", str(workspace), "--keypoints",
         str(keypoints), "--format", "openpose", "--out", str(out), "--no-plots",
         "--layout", str(layout)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert not (out / "plots").exists()
    assert json.loads((out / "report.json").read_text())["layout"] == "mine"
    with np.load(out / "trajectories.npz") as a, np.load(reconstructed / "trajectories.npz") as b:
        np.testing.assert_allclose(a["X"], b["X"], atol=1e-9)
    assert model_snapshot(workspace) == before


def run_cli(args: list[str], capsys) -> tuple[int, str]:
    """Exit code and the error message of ``dloe-sfm reconstruct ARGS`` (exactly one line)."""
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["reconstruct", *map(str, args)])
    return exit_info.value.code, one_error_line(capsys.readouterr().err)


def one_error_line(stderr: str) -> str:
    """The ``dloe-sfm: error: ...`` line of stderr (logs and progress bars aside); exactly one."""
    lines = [line for line in re.split(r"[\r\n]", stderr) if ": error: " in line]
    assert len(lines) == 1, stderr
    return lines[0]


def test_missing_workspace(scene, tmp_path, capsys) -> None:
    _, keypoints, _ = scene
    code, err = run_cli([tmp_path / "nope", "--keypoints", keypoints, "--format", "openpose",
                         "--out", tmp_path / "out"], capsys)
    assert code == 2 and "nope" in err
    assert not (tmp_path / "out").exists()


def test_empty_workspace(scene, tmp_path, capsys) -> None:
    _, keypoints, _ = scene
    (tmp_path / "empty").mkdir()
    code, err = run_cli([tmp_path / "empty", "--keypoints", keypoints, "--format", "openpose",
                         "--out", tmp_path / "out"], capsys)
    assert code == 2 and "no COLMAP model" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"]


def test_keypoints_of_unknown_images(scene, tmp_path, capsys) -> None:
    workspace, _, _ = scene
    folder = tmp_path / "other"
    folder.mkdir()
    person = {"people": [{"pose_keypoints_2d": [100.0, 100.0, 1.0] * 18}]}
    for k in range(3):
        (folder / f"holiday_{k:03d}_keypoints.json").write_text(json.dumps(person))
    code, err = run_cli([workspace, "--keypoints", folder, "--format", "openpose",
                         "--out", tmp_path / "out"], capsys)
    assert code == 2 and "holiday_000" in err
    assert not (tmp_path / "out").exists()


def test_existing_out_dir_is_refused_by_the_cli(scene, tmp_path) -> None:
    workspace, keypoints, _ = scene
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    proc = subprocess.run(
        [sys.executable, "-m", "dloe_sfm.stages.reconstruct", str(workspace), "--keypoints",
         str(keypoints), "--format", "openpose", "--out", str(out)],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    assert one_error_line(proc.stderr).endswith(
        "never replaced; choose another output path"), proc.stderr
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_stage_module_leaves_the_solver_function() -> None:
    """The stage module (imported above) does not shadow the package's ``reconstruct``."""
    assert stage.__name__ == "dloe_sfm.stages.reconstruct"
    assert callable(dloe_sfm.reconstruct) and dloe_sfm.reconstruct is solver
