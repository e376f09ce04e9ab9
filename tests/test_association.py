"""Several people on the simulator and on the real Pose2Sim trial (issue 39): a person is a
subject only when the data supports one, and a subject never splits another's event."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from dloe_sfm.calibration import import_calibration
from dloe_sfm.colmap import load_workspace
from dloe_sfm.core.capture import Capture, pixel_rays, project
from dloe_sfm.core.decisions import subject_count
from dloe_sfm.core.multitarget import (
    aggregate,
    associate,
    detection_confidence,
    stream_links,
)
from dloe_sfm.core.options import Options
from dloe_sfm.core.pipeline import finish_single, initial_events, solve_single
from dloe_sfm.core.problem import initialise
from dloe_sfm.core.solver import reconstruct
from dloe_sfm.errors import InputError
from dloe_sfm.keypoints import load_layout, read_keypoints
from dloe_sfm.observations import build_capture
from dloe_sfm.synth import SimulationSettings, load_mocap
from dloe_sfm.synth.scenarios import add_false_detections, simulate_people

QUICK = SimulationSettings(duration=1.0, rate=15)


@pytest.fixture(scope="module")
def two_people(assets_dir) -> tuple[Capture, np.ndarray]:
    """walking_1 and jumping_1 2 m apart, 4 streams x 15 images, person k in slot k."""
    seqs = [load_mocap(assets_dir / "mocap" / f"{m}.npz") for m in ("walking_1", "jumping_1")]
    cap, sim = simulate_people(seqs, QUICK, shuffle=False)
    return cap, sim.subjects


def seen_by_two_streams(cap: Capture) -> Capture:
    """The second person detected by streams 0 and 1 only (out of view of 2 and 3)."""
    x = cap.x.copy()
    x[cap.stream_ids >= 2, 1] = np.nan
    return replace(cap, x=x)


def purity(assignment: np.ndarray, truth: np.ndarray) -> float:
    """Share of the assigned detections on their subject's majority person."""
    right = sum(np.bincount(truth[assignment == k]).max() for k in range(assignment.max() + 1))
    return right / (assignment >= 0).sum()


def test_stream_links_follow_each_person(assets_dir) -> None:
    """Detections in a random order per image: the links of consecutive stream images join one
    person's detections, nearly all of them."""
    seqs = [load_mocap(assets_dir / "mocap" / f"{m}.npz") for m in ("walking_1", "jumping_1")]
    cap, sim = simulate_people(seqs, QUICK)
    pairs = stream_links(cap)
    person = sim.subjects.ravel()
    assert (person[pairs[:, 0]] == person[pairs[:, 1]]).all()
    consecutive = cap.num_images - np.unique(cap.stream).size
    assert len(pairs) >= 0.9 * 2 * consecutive


def test_a_person_seen_by_two_of_four_streams_is_no_subject(two_people, log_lines) -> None:
    cap, _ = two_people
    assignment = associate(seen_by_two_streams(cap), Options())
    assert assignment.max() == 0
    assert (assignment[:, 0] == 0).all()  # the person all four streams see
    seen = np.isfinite(seen_by_two_streams(cap).x[:, 1]).any(axis=(1, 2))
    assert (assignment[seen, 1] == -1).all() and seen.sum() == cap.num_images // 2
    assert (f"{seen.sum()} detection(s) support no subject (in {seen.sum()} image(s), seen by 2 "
            "stream(s); a subject needs 8 images and 3 streams): left out") in log_lines
    assert associate(cap, Options()).max() == 1  # seen by all four: a subject


def test_a_subject_seen_by_some_streams_does_not_split_the_event(two_people) -> None:
    """Where streams 2 and 3 never see the second person, the initial shapes fill its points in
    with its mean (``init.fill_missing``); on the real Pose2Sim trial that lay 0.21 m from
    where streams 0 and 1 put it. Compared on those filled-in values, the images of the two
    camera pairs link only among themselves: two events. Each subject's graph over the images
    that see it: one."""
    cap, truth = two_people
    merged = aggregate(seen_by_two_streams(cap), truth)
    assert merged.subjects == 2 and merged.subset(np.arange(5)).subjects == 2
    with pytest.raises(InputError, match="field 'subjects' must divide the 56 points, got 3"):
        replace(merged, subjects=3).validate("merged")
    options = Options()
    X0 = initialise(merged, options)
    X0[cap.stream_ids >= 2, cap.num_points:] += 0.2
    assert np.unique(initial_events(merged, options, X0)).size == 1
    one_shape = replace(merged, subjects=1)  # the columns as one shape
    assert np.unique(initial_events(one_shape, options, X0)).size == 2


def test_a_subject_of_one_stream_links_no_images(two_people) -> None:
    """A subject one stream sees (a stray cluster kept where it was its image's only detection)
    has no graph of its own; the other subject's links the images."""
    cap, truth = two_people
    x = cap.x.copy()
    x[np.flatnonzero(cap.stream_ids == 0)[2:], 1] = np.nan
    x[cap.stream_ids > 0, 1] = np.nan
    merged = aggregate(replace(cap, x=x), truth)
    options = Options()
    assert np.unique(initial_events(merged, options, initialise(merged, options))).size == 1


def test_one_image_with_an_extra_detection_adds_no_subject(two_people) -> None:
    """One image's first person split into two partial skeletons (a third detection) is not a
    third person: the count is the most detections 8 images hold, and the extra partial
    skeleton is left out."""
    cap, truth = two_people
    n, _, p = cap.x.shape[:3]
    x = np.concatenate([cap.x, np.full((n, 1, p, 2), np.nan)], axis=1)
    half = np.arange(p) < p // 2
    x[5, 2, half], x[5, 0, half] = x[5, 0, half], np.nan
    split = replace(cap, x=x, confidence=None)
    assert subject_count(np.nonzero(np.isfinite(x).all(axis=3).any(axis=2))[0]) == 2
    assignment = associate(split, Options())
    assert assignment.max() == 1
    assert purity(assignment[:, :2], truth) == 1.0
    assert (assignment[5] >= 0).sum() == 2


def test_one_person_with_a_few_double_detections_keeps_one_per_image(two_people) -> None:
    """Fewer than 8 images with a second detection: one subject, and each of those images
    keeps its fuller detection."""
    cap, _ = two_people
    x = cap.x.copy()
    few = np.arange(5)
    x[np.setdiff1d(np.arange(cap.num_images), few), 1] = np.nan
    x[few, 1, 10:] = np.nan
    assignment = associate(replace(cap, x=x, confidence=None), Options())
    assert (assignment[:, 0] == 0).all() and (assignment[:, 1] == -1).all()


def test_detection_confidence_tells_the_right_subject_from_a_wrong_one(assets_dir) -> None:
    """On a solve of the two people (detections shuffled per image): near 1 on the subject whose
    graph prediction a detection fits, 0 when an image's two detections are exchanged."""
    seqs = [load_mocap(assets_dir / "mocap" / f"{m}.npz") for m in ("walking_1", "jumping_1")]
    cap, sim = simulate_people(seqs, QUICK)
    result = reconstruct(cap)
    sure = detection_confidence(cap, result.assignment, result)
    assert purity(result.assignment, sim.subjects) == 1.0
    assert np.median(sure) > 0.95 and (sure > 0.5).all()
    wrong = result.assignment.copy()
    wrong[3] = wrong[3, ::-1]
    assert (detection_confidence(cap, wrong, result)[3] == 0.0).all()


@pytest.mark.parametrize("detector", [None, "openpose"])
def test_false_detections_that_follow_no_motion_make_no_subject(assets_dir, detector) -> None:
    """Two people, exact or under the detector model, and a third detection in 30 % of the
    images, another image's detection moved 50-200 px (``add_false_detections``): enough images
    for a third subject, which the association makes. Held out, its detections are predicted
    hundreds of pixels off (``heldout.held_out_subjects``), the people's within a few: it is
    dropped (``unfit_subjects``), they are left out, and the two people keep every image."""
    seqs = [load_mocap(assets_dir / "mocap" / f"{m}.npz") for m in ("walking_1", "jumping_1")]
    cap, sim = simulate_people(seqs, replace(QUICK, detector=detector), shuffle=False)
    cap, gt = add_false_detections(cap, sim, 0.3, seed=4)
    options = Options(stream_clocks="off")
    assert associate(cap, options).max() == 2
    result = reconstruct(cap, options)
    false = (gt.subjects == -1) & cap.visible.any(axis=2)
    assert result.assignment.max() == 1 and (result.assignment[false] == -1).all()
    assert purity(result.assignment[:, :2], sim.subjects) == 1.0
    assert (result.assignment[:, :2] >= 0).all()


def test_a_robust_round_resumed_from_another_association_fits_its_own(assets_dir) -> None:
    """The association's later rounds under detector noise (``finish_single``'s ``resumed``):
    the solve of an association with 3 images' people exchanged weights the robust round of
    the right one, which re-solves it about as well as a solve of its own; with no round to
    run, the capture is solved on its own."""
    seqs = [load_mocap(assets_dir / "mocap" / f"{m}.npz") for m in ("walking_1", "jumping_1")]
    options = Options(stream_clocks="off", robust_iterations=1)
    cap, sim = simulate_people(seqs, replace(QUICK, detector="openpose"), shuffle=False)
    wrong = sim.subjects.copy()
    wrong[[10, 30, 50]] = wrong[[10, 30, 50], ::-1]
    merged = aggregate(cap, sim.subjects)

    def error_mm(X: np.ndarray) -> float:
        return float(np.linalg.norm(X - sim.X.reshape(X.shape), axis=-1).mean() * 1000)

    start = solve_single(aggregate(cap, wrong), options)
    one_event = np.zeros(cap.num_images, dtype=np.int64)
    resumed = finish_single(merged, options, start, one_event, resumed=True)
    own = solve_single(merged, options)
    assert error_mm(start.X) > 3 * error_mm(own.X)
    assert error_mm(resumed.X) <= 1.2 * error_mm(own.X)
    assert resumed.nit > start.nit  # its sweeps count the start's
    # no round to resume (none asked): the capture is solved on its own, not left at the start
    unrounded = finish_single(merged, options.replace(robust_iterations=0), start, one_event,
                              resumed=True)
    assert error_mm(unrounded.X) <= 1.2 * error_mm(own.X)


@pytest.mark.shared
def test_pose2sim_trial_made_asynchronous_is_one_subject_and_one_event(shared_dir,
                                                                         tmp_path) -> None:
    """The real trial, every 4th frame per camera (camera k from frame k - 1), calibration +
    keypoints only: OpenPose's still second person, in every image of cameras 1 and 2 and none
    of 3 and 4, is left out; the main person is one subject in one event."""
    trial = shared_dir / "data" / "pose2sim_single_trial"
    for k in range(1, 5):
        folder = tmp_path / "pose" / f"cam0{k}_json"
        folder.mkdir(parents=True)
        for f in range(k - 1, 100, 4):
            name = f"cam0{k}.{f:04d}.json"
            (folder / name).write_bytes((trial / "pose" / f"cam0{k}_json" / name).read_bytes())
    import_calibration(trial / "calibration" / "Calib.qca.txt", tmp_path / "ws" / "sparse" / "0",
                       fmt="qualisys", keypoints=tmp_path / "pose")
    ws = load_workspace(tmp_path / "ws")
    kp = read_keypoints("openpose", tmp_path / "pose", workspace=ws,
                        layout=load_layout("BODY_25B"))
    cap = build_capture(ws, kp).capture
    options = Options()
    assignment = associate(cap, options)
    assert assignment.max() == 0 and (assignment[:, 0] == 0).all()
    assert (assignment[:, 1] == -1).all() and np.isfinite(cap.x[:, 1]).any(axis=(1, 2)).sum() == 50
    # why: triangulated from cameras 1 and 2 it stands outside the views of cameras 3 and 4
    rays = pixel_rays(cap.x[:, 1], cap.K, cap.R)
    seen = np.isfinite(rays).all(axis=2)
    joints = []
    for j in np.flatnonzero(seen.sum(axis=0) >= 2):
        r = rays[seen[:, j], j]
        Q = np.eye(3) - r[:, :, None] * r[:, None, :]
        joints.append(np.linalg.solve(Q.sum(axis=0), np.einsum("nij,nj->i", Q, cap.C[seen[:, j]])))
    where = np.median(joints, axis=0)
    for stream in range(4):
        i = np.flatnonzero(cap.stream_ids == stream)[0]
        u = project(where[None, None], cap.K[i:i + 1], cap.R[i:i + 1], cap.C[i:i + 1])[0, 0]
        inside = 0 <= u[0] <= 1088 and 0 <= u[1] <= 1920
        assert inside == (stream < 2), (stream, u)
    merged = aggregate(cap, assignment)
    assert np.unique(initial_events(merged, options, initialise(merged, options))).size == 1
    # were the still person a subject, it would not split the main person's event
    both = aggregate(cap, np.where(np.isfinite(cap.x).all(axis=3).any(axis=2), [0, 1], -1))
    X0 = initialise(both, options)
    assert np.unique(initial_events(both, options, X0)).size == 1
    one_shape = replace(both, subjects=1)  # compared on filled-in points
    assert np.unique(initial_events(one_shape, options, X0)).size == 2
