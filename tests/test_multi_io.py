"""Several people per image: ``build_capture(person=...)``, export and plots of subjects."""

from __future__ import annotations

import argparse
import csv
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import scipy.sparse as sp
from scenes import body_at, openpose_file, toy_capture

import dloe_sfm.stages.reconstruct as stage
from dloe_sfm import Capture, InputError, Result, colmap
from dloe_sfm.columns import frame_file_stem
from dloe_sfm.core.capture import project
from dloe_sfm.export import export_outputs
from dloe_sfm.keypoints import LAYOUTS, Layout, read_keypoints
from dloe_sfm.observations import build_capture, observed_layout

NUM_CAMERAS, NUM_FRAMES = 4, 10  # 40 images
LAYOUT = LAYOUTS["COCO_18"]
SECOND = np.array([-0.3, 0.3, 0.0])  # the second person walks beside the first


@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> colmap.Workspace:
    """4 cameras x 10 frames, with (blank) image files so overlays are drawn."""
    root = colmap.synthetic_workspace(tmp_path_factory.mktemp("multi") / "ws",
                                      num_cameras=NUM_CAMERAS, num_frames=NUM_FRAMES)
    ws = colmap.load_workspace(root)
    (root / "images").mkdir()
    for name in ws.image_names:
        w, h = ws.image_size(name)
        cv2.imwrite(str(root / "images" / name), np.full((h, w, 3), 200, np.uint8))
    return colmap.load_workspace(root)


def bodies(ws: colmap.Workspace) -> dict[str, np.ndarray]:
    """(2, 18, 3) true joints of the two people in every image (image k at time k / 39)."""
    n = len(ws.image_names)
    return {name: np.stack([body_at(k / (n - 1)), body_at(k / (n - 1)) + SECOND])
            for k, name in enumerate(ws.image_names)}


def write_people(folder: Path, ws: colmap.Workspace, counts: dict[str, int]) -> Path:
    """OpenPose files with the first ``counts[name]`` of the two people of ``bodies``, in a
    shuffled order; returns ``folder``."""
    rng = np.random.default_rng(1)
    for name, X in bodies(ws).items():
        people = []
        for person in X[:counts[name]]:
            uv = ws.project(name, person) - 0.5
            w, h = ws.image_size(name)
            assert np.isfinite(uv).all() and (uv > 0).all() and (uv < [w, h]).all(), name
            people.append(np.column_stack([uv, np.ones(len(uv))]))
        people = [people[k] for k in rng.permutation(len(people))]
        openpose_file(folder / f"{Path(name).stem}_keypoints.json",
                      np.array(people).reshape(-1, LAYOUT.num_points, 3))
    return folder


def pinhole(capture: Capture, i: int, X: np.ndarray) -> np.ndarray:
    return project(X[None], capture.K[i:i + 1], capture.R[i:i + 1], capture.C[i:i + 1])[0]


def test_all_keeps_every_usable_detection(ws, tmp_path) -> None:
    counts = {name: 2 - (k % 5 == 0) for k, name in enumerate(ws.image_names)}
    folder = write_people(tmp_path / "openpose", ws, counts)
    # a fragment (4 of 18 joints: under a quarter) beside the two people of the last image
    last = ws.image_names[-1]
    fragment = np.full((18, 3), np.nan)
    fragment[:4] = (500.0, 400.0, 1.0)
    with open(folder / f"{Path(last).stem}_keypoints.json") as f:
        people = [np.array(p["pose_keypoints_2d"]).reshape(18, 3) for p in json.load(f)["people"]]
    openpose_file(folder / f"{Path(last).stem}_keypoints.json", np.stack([*people, fragment]))
    kp = read_keypoints("openpose", folder, workspace=ws)
    capture = build_capture(ws, kp, person="all").capture
    assert capture.x.shape == (40, 2, 18, 2) and capture.num_people == 2
    assert capture.confidence.shape == (40, 2, 18)
    np.testing.assert_array_equal(capture.symmetric_pairs, LAYOUT.symmetric_pairs)
    truth = bodies(ws)
    for i, name in enumerate(capture.image_names):
        want = [pinhole(capture, i, X) for X in truth[name][:counts[name]]]
        got = [x for x in capture.x[i] if np.isfinite(x).all()]
        assert len(got) == counts[name], name
        # detections in no particular order: match each to its nearest true person
        for x in got:
            assert min(np.abs(x - w).max() for w in want) < 1e-6, name
        empty = ~np.isfinite(capture.x[i]).all(axis=(1, 2))
        np.testing.assert_array_equal(capture.confidence[i][empty], 0.0)
    capture.validate()


def test_a_point_nobody_shows_is_left_out(ws, tmp_path) -> None:
    folder = write_people(tmp_path / "openpose", ws, dict.fromkeys(ws.image_names, 2))
    kp = read_keypoints("openpose", folder, workspace=ws)
    full = build_capture(ws, kp, person="all").capture
    for people in kp.points.values():
        people[:, 16] = (np.nan, np.nan, 0.0)
    capture, _, unobserved = build_capture(ws, kp, person="all")
    assert unobserved == [16]
    kept = [j for j in range(kp.num_points) if j != 16]
    # the same detections, less REar (their slot order may differ: it is by detection size)
    for got, want in zip(capture.x, full.x[:, :, kept], strict=True):
        rows = [sorted(map(tuple, np.nan_to_num(a, nan=-1).reshape(len(a), -1)))
                for a in (got, want)]
        assert rows[0] == rows[1]
    layout = observed_layout(kp.layout, unobserved)
    assert layout.point_names == [kp.layout.point_names[j] for j in kept]
    assert "REar" not in layout.point_names
    # edges and left/right pairs renumbered: the same named pairs, minus those of REar
    named = {tuple(sorted((kp.layout.point_names[a], kp.layout.point_names[b])))
             for a, b in kp.layout.edges if 16 not in (a, b)}
    assert {tuple(sorted((layout.point_names[a], layout.point_names[b])))
            for a, b in layout.edges} == named
    np.testing.assert_array_equal(capture.symmetric_pairs, np.asarray(layout.symmetric_pairs))
    assert ("LEar", "REar") not in [(layout.point_names[a], layout.point_names[b])
                                    for a, b in layout.symmetric_pairs]
    for people in kp.points.values():
        people[:] = (np.nan, np.nan, 0.0)
    with pytest.raises(InputError, match="no usable observation|no point observed"):
        build_capture(ws, kp, person="all")


@pytest.mark.parametrize(("second", "mode"), [
    (0, "largest"),  # one person everywhere
    (36, "all"),  # two people in most images
    (4, "all"),  # 10 % of the images: the threshold
    (3, "largest"),
    (1, "largest"),  # a stray second detection in 1 of 40 images
])
def test_auto_follows_everyone_when_people_recur(ws, tmp_path, second, mode) -> None:
    counts = {name: 1 + (k < second) for k, name in enumerate(ws.image_names)}
    kp = read_keypoints("openpose", write_people(tmp_path / "op", ws, counts), workspace=ws)
    capture = build_capture(ws, kp).capture
    chosen = build_capture(ws, kp, person=mode).capture
    np.testing.assert_array_equal(capture.x, chosen.x)
    assert capture.x.ndim == (4 if mode == "all" else 3)


def test_cli_person_values() -> None:
    parser = argparse.ArgumentParser()
    stage.configure_parser(parser)
    base = ["ws", "--format", "openpose", "--out", "o"]
    assert parser.parse_args(base).person == "auto"
    for value, want in (("largest", "largest"), ("all", "all"), ("auto", "auto"), ("2", 2)):
        assert parser.parse_args([*base, "--person", value]).person == want
    for bad in ("-1", "tallest"):
        with pytest.raises(SystemExit):
            parser.parse_args([*base, "--person", bad])


# --- export of a several-subject result ---------------------------------------------------------

TOY = Layout("toy", ["head", "lhand", "rhand", "lfoot", "rfoot"],
             [(0, 1), (0, 2), (0, 3), (0, 4)], [(1, 2), (3, 4)])
P = TOY.num_points


def two_subjects() -> tuple[Capture, Result]:
    """The toy capture's helix walker and a second one 0.8 to the side: the (N, 2, 5, 2) input
    (detections swapped in odd images) and a result with subject-major columns, an outlier and
    a fixed swap."""
    one, single, X = toy_capture()
    n = one.num_images
    X2 = np.concatenate([X, X + [0.8, 0.0, 0.0]], axis=1)  # (N, 10, 3)
    x2 = project(X2, one.K, one.R, one.C)
    x2[4, 2] = np.nan
    x2[7, 5:] = np.nan  # subject 1 unseen in image 7
    confidence = np.where(np.isfinite(x2).all(axis=2), 0.9, 0.0)
    solved = Capture(x=x2, K=one.K, R=one.R, C=one.C, stream=one.stream, frame=one.frame,
                     confidence=confidence, image_names=one.image_names,
                     symmetric_pairs=TOY.symmetric_pairs)
    x4 = x2.reshape(n, 2, P, 2).copy()
    x4[1::2] = x4[1::2, ::-1]
    capture = Capture(x=x4, K=one.K, R=one.R, C=one.C, stream=one.stream, frame=one.frame,
                      confidence=confidence.reshape(n, 2, P), image_names=one.image_names,
                      symmetric_pairs=TOY.symmetric_pairs)
    assignment = np.tile([0, 1], (n, 1))
    assignment[1::2] = [1, 0]
    assignment[7] = [-1, 0]  # odd image: subject 1, unseen, was in slot 0
    result = Result(
        X=X2 + 1e-3 * np.random.default_rng(1).normal(size=X2.shape), order=single.order,
        A=single.A, W=single.W, D=single.D, events=single.events, embedding=single.embedding,
        cost_history=single.cost_history, change_history=single.change_history, nit=2,
        success=True, message="converged", seconds=0.5,
        subject_id=np.repeat([0, 1], P), point_id=np.tile(np.arange(P), 2),
        assignment=assignment, outliers=np.array([[3, 8]]), outlier_residual_px=np.array([42.5]),
        swaps=np.array([[5, 6, 7]]), solved=solved,
    )
    return capture, result


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Capture, Result]:
    capture, result = two_subjects()
    out = tmp_path_factory.mktemp("export") / "out"
    export_outputs(out, capture, result, layout=TOY, plots=False)
    return out, capture, result


def test_frames_carry_subject_and_point_ids(exported) -> None:
    out, capture, result = exported
    for i, name in enumerate(capture.image_names):
        stem = frame_file_stem(int(result.rank[i]), name, capture.num_images)
        cloud = o3d.t.io.read_point_cloud(str(out / "frames" / f"{stem}.ply"))
        np.testing.assert_array_equal(cloud.point.subject_id.numpy().ravel(), result.subject_id)
        np.testing.assert_array_equal(cloud.point.point_id.numpy().ravel(), result.point_id)
        np.testing.assert_allclose(cloud.point.positions.numpy(), result.X[i], atol=1e-6)
        np.testing.assert_array_equal(cloud.point.observed.numpy().ravel(),
                                      result.solved.visible[i])
        lines = o3d.io.read_line_set(str(out / "skeleton" / f"{stem}.ply"))
        np.testing.assert_array_equal(np.asarray(lines.lines),
                                      np.concatenate([TOY.edges, np.add(TOY.edges, P)]))


def test_trajectories_name_subjects(exported) -> None:
    out, capture, result = exported
    with np.load(out / "trajectories.npz") as data:
        np.testing.assert_array_equal(data["X"], result.X)
        np.testing.assert_array_equal(data["subject_id"], result.subject_id)
        np.testing.assert_array_equal(data["point_id"], result.point_id)
        assert data["point_names"].tolist() == TOY.point_names * 2
        np.testing.assert_array_equal(data["observed"], result.solved.visible)
    with open(out / "trajectories.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == capture.num_images * 2 * P
    index = {name: i for i, name in enumerate(capture.image_names)}
    for row in rows:
        i, s, j = index[row["image"]], int(row["subject_id"]), int(row["point_id"])
        np.testing.assert_allclose([float(row[k]) for k in "xyz"], result.X[i, s * P + j],
                                   rtol=0, atol=1e-12)
        assert int(row["observed"]) == int(result.solved.visible[i, s * P + j])
    assert sum(row["image"] == capture.image_names[7] and row["observed"] == "1"
               for row in rows) == P


def test_report_lists_subjects_outliers_and_swaps(exported) -> None:
    out, capture, result = exported
    report = json.loads((out / "report.json").read_text())
    assert report["subjects"] == 2 and report["points"] == P
    first, second = report["subject_summaries"]
    assert first["num_images_seen"] == second["num_images_seen"] + 1 == capture.num_images
    assert capture.image_names[7] not in second["images_seen"]
    n = capture.num_images
    assert second["observed_fraction"] == pytest.approx((n - 1) / n)
    assert first["reprojection_error_px"]["count"] == capture.num_images * P - 1
    assert report["downweighted"] == {"count": 1, "observations": [
        {"image": str(capture.image_names[3]), "point": "lfoot", "subject_id": 1,
         "residual_px": 42.5}]}
    assert report["swaps_fixed"] == {"count": 1, "swaps": [
        {"image": str(capture.image_names[5]), "points": ["lhand", "rhand"], "subject_id": 1}]}
    assert [(p["subject_id"], p["name"]) for p in report["reprojection_error_px"]["per_point"]] \
        == [(s, name) for s in (0, 1) for name in TOY.point_names]


def test_report_counts_the_detections_left_out(exported, tmp_path, log_lines) -> None:
    out, capture, result = exported
    assert json.loads((out / "report.json").read_text())["detections_left_out"] == {
        "count": 0, "images": []}  # image 7's unassigned slot is empty
    assignment = result.assignment.copy()
    assignment[2, 1] = -1  # a detection no subject took (multitarget.associate: a stray)
    report = export_outputs(tmp_path / "out", capture, replace(result, assignment=assignment),
                            layout=TOY, plots=False)
    assert report["detections_left_out"] == {"count": 1, "images": [capture.image_names[2]]}
    assert any(", 1 detection(s) supporting none left out;" in line for line in log_lines)


def test_several_subjects_need_the_solved_capture(tmp_path) -> None:
    capture, result = two_subjects()
    result.solved = None
    with pytest.raises(InputError, match="result: field 'solved' is missing"):
        export_outputs(tmp_path / "out", capture, result, layout=TOY)
    assert list(tmp_path.iterdir()) == []


def test_stage_exports_people_of_a_workspace(ws, tmp_path) -> None:
    """The stage's export and plots (overlays included) from a 4-D workspace capture."""
    folder = write_people(tmp_path / "openpose", ws, dict.fromkeys(ws.image_names, 2))
    kp = read_keypoints("openpose", folder, workspace=ws)
    capture = build_capture(ws, kp).capture
    n, p = capture.num_images, LAYOUT.num_points
    truth = bodies(ws)
    X = np.stack([truth[name] for name in capture.image_names]).reshape(n, 2 * p, 3)
    slots = np.stack([[np.argmin([np.nanmax(np.abs(d - pinhole(capture, i, person)))
                                  for d in capture.x[i]]) for person in truth[name]]
                      for i, name in enumerate(capture.image_names)])  # (N, 2) slot of subject
    rows = np.arange(n)[:, None]
    solved = Capture(x=capture.x[rows, slots].reshape(n, 2 * p, 2), K=capture.K, R=capture.R,
                     C=capture.C, stream=capture.stream, frame=capture.frame,
                     confidence=capture.confidence[rows, slots].reshape(n, 2 * p),
                     image_names=capture.image_names)
    chain = sp.diags(np.ones(n - 1), 1, shape=(n, n), format="csr")
    result = Result(
        X=X, order=np.arange(n), A=chain + chain.T, W=chain, D=np.ones(n),
        events=np.zeros(n, dtype=np.int64), embedding=np.linspace(0, 1, n),
        cost_history=np.ones(1), change_history=np.ones(1), nit=1, success=True,
        message="converged", seconds=0.1, subject_id=np.repeat([0, 1], p),
        point_id=np.tile(np.arange(p), 2), assignment=np.argsort(slots, axis=1), solved=solved,
    )
    out = tmp_path / "out"
    report = export_outputs(out, capture, result, workspace=ws, layout=kp.layout)
    assert report["reprojection_error_px"]["all"]["max"] < 1e-6
    assert report["subjects"] == 2 and report["downweighted"]["count"] == 0
    for png in ("sequence.png", "affinity.png", "events.png", "trajectories.png"):
        assert (out / "plots" / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(list((out / "plots" / "overlays").glob("*.png"))) == 4
    # detection_subject follows the files' person order, not the capture's (largest first)
    with np.load(out / "trajectories.npz") as data:
        detection_subject = data["detection_subject"]
        confidence = data["detection_confidence"]
    assert confidence.shape == detection_subject.shape
    assert ((confidence >= 0) & (confidence <= 1))[detection_subject >= 0].all()
    assert np.isnan(confidence[detection_subject < 0]).all()
    for i, name in enumerate(capture.image_names):
        with open(folder / f"{Path(name).stem}_keypoints.json") as f:
            people = [np.reshape(q["pose_keypoints_2d"], (p, 3))[:, :2]
                      for q in json.load(f)["people"]]
        want = [np.argmin([np.abs(ws.project(name, person) - 0.5 - q).max()
                           for person in truth[name]]) for q in people]
        np.testing.assert_array_equal(detection_subject[i], want)
    assert (capture.image_ids["detection_index"] != np.arange(2)).any()  # some were reordered
