"""Smoke tests of the pipelines: on the real data in ``../shared/data`` (skipped without it) and on
the bundled mocap clips."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import numpy as np
import open3d as o3d
import pytest
from scenes import body_at

from dloe_sfm import colmap, synth

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"


def load_pipeline(name: str) -> ModuleType:
    return synth.load_pipeline(PIPELINES, name)


@pytest.mark.slow
@pytest.mark.shared
def test_lab_rig(shared_dir, tmp_path) -> None:
    lab_rig = load_pipeline("lab_rig")
    out = tmp_path / "lab_rig"
    table = lab_rig.run(shared_dir / "data" / "pose2sim_single_trial", out, plots=False)
    assert json.loads((out / "comparison.json").read_text()) == table
    sync = table["sync_triangulation"]
    # a correct calibration import gives ~13 px medians on these detections
    assert 8 < sync["reprojection_error_px"]["median"] < 18
    dloe = table["dloe_async"]
    assert dloe["images"] == 100
    # default options: soft rays at the estimated noise along the stream clocks (13.65 px
    # held out, 11.6 mm from the synchronised triangulation; hard rays: 21.0 px, 42.7 mm)
    report = json.loads((out / "dloe" / "report.json").read_text())
    assert 5 < report["solver"]["noise_px"] < 15
    held_dloe = dloe["held_out_views_error_px"]["median"]
    held_sync = sync["held_out_views_error_px (leave one camera out)"]["median"]
    assert held_dloe < min(15.0, held_sync)
    assert table["dloe_vs_sync_distance_mm"]["median"] < 20
    # timing against the true frames: |tau| 0.9899, offset errors up to 0.19 stream frame
    # (cam03), RMS time error 0.96 frames
    timing = table["timing"]
    assert timing["kendall_tau"] >= 0.985
    assert np.isfinite(timing["time_error_rms_frames"]) and timing["time_error_rms_frames"] < 1.5
    assert set(timing["streams"]) == {"cam01", "cam02", "cam03", "cam04"}
    assert timing["streams"][timing["reference_camera"]]["offset_error_frames"] == 0
    for stream in timing["streams"].values():
        assert np.isfinite([stream["offset_error_frames"], stream["offset_error_stream_frames"],
                            stream["offset_error_ms"], stream["clock_offset_error_frames"],
                            stream["clock_rate"]]).all()
        assert abs(stream["offset_error_stream_frames"]) < 0.3
    assert len(table["acceptance"]) == 3
    assert len(list((out / "dloe" / "frames").glob("*.ply"))) == 100
    assert (out / "workspace" / "sparse" / "0" / "images.bin").is_file()


@pytest.mark.shared
@pytest.mark.slow
def test_crowd_photos(shared_dir, tmp_path) -> None:
    """SfM of the 10 Sacre-Coeur photos, keypoints of a moving figure projected with the
    reference model, then the reconstruct stage with overlays on the real images."""
    crowd = load_pipeline("crowd_photos")
    data = shared_dir / "data" / "sacre_coeur"
    reference = colmap.load_workspace(data)
    centre = np.median(reference.static_xyz, axis=0)
    size = np.linalg.norm(np.ptp(np.percentile(reference.static_xyz, [10, 90], axis=0), axis=0))
    keypoints = tmp_path / "keypoints"
    keypoints.mkdir()
    for k, name in enumerate(reference.image_names):
        X = body_at(k / 9) * 0.1 * size + centre
        uv = reference.project(name, X) - 0.5
        values = np.concatenate([uv, np.ones((len(uv), 1))], axis=1).ravel().tolist()
        (keypoints / f"{Path(name).stem}_keypoints.json").write_text(
            json.dumps({"people": [{"pose_keypoints_2d": values}]}))
    out = crowd.run(data / "images", keypoints, "openpose", tmp_path / "crowd")
    report = json.loads((out / "report.json").read_text())
    assert report["images"] == 10 and report["layout"] == "COCO_18"
    assert len(list((out / "plots" / "overlays").glob("*.png"))) == 4
    assert (tmp_path / "crowd" / "workspace" / "images").resolve() == (data / "images").resolve()


@pytest.mark.slow
def test_multi_person(assets_dir, tmp_path) -> None:
    """Two people (shuffled OpenPose detections) and left/right swaps through the COLMAP stage:
    1.5 s of the bundled clips at 15 Hz (90 images); tolerances about 2 x the measured values
    (walking_1 2.4 mm, jumping_1 0.30 mm, 91 % of the swaps fixed, none wrongly)."""
    multi = load_pipeline("multi_person")
    out = tmp_path / "multi"
    doc = multi.main(out, data=assets_dir / "mocap", cases=("people", "swaps"), duration=1.5,
                     rate=15.0)
    assert json.loads((out / "results.json").read_text())["cases"] == doc["cases"]
    people, swaps = doc["cases"]
    assert people["subjects_found"] == 2 and people["associated"] >= 0.98
    errors = {p["motion"]: p["error_mm"] for p in people["people"]}
    assert errors["walking_1"] < 5.0 and errors["jumping_1"] < 0.6
    frames = sorted((out / "people" / "reconstruction" / "frames").glob("*.ply"))
    assert len(frames) == people["images"] == 90
    cloud = o3d.t.io.read_point_cloud(str(frames[0]))
    np.testing.assert_array_equal(cloud.point["subject_id"].numpy().ravel(), np.repeat([0, 1], 28))
    assert swaps["found"] >= 0.8 and swaps["false_swaps"] <= 2


def shelf_frame(people: list[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Joint candidates and part affinities of one frame as the Shelf detection files hold them:
    the people's joints pooled per joint type, in a shuffled order, affinity 0.9 between two
    candidates of one person, 0.1 across people."""
    rng = np.random.default_rng(0)
    shelf = load_pipeline("shelf")
    owner, candidates = [], []
    for j in range(shelf.JOINTS):
        found = [(k, p[j]) for k, p in enumerate(people) if p[j, 2] > 0]
        order = rng.permutation(len(found))
        owner.append(np.array([found[i][0] for i in order], dtype=int))
        candidates.append(np.array([found[i][1] for i in order]).reshape(-1, 3))
    affinities = [np.where(owner[a][:, None] == owner[b][None, :], 0.9, 0.1)
                  for a, b in shelf.PAFS]
    return candidates, affinities


def test_shelf_parsing_groups_each_person() -> None:
    """The port of OpenPose's greedy parsing gives back each person whole from pooled
    candidates (the parts of one person that the limbs' order builds apart are merged); a
    fragment of fewer than 5 joints is dropped."""
    shelf = load_pipeline("shelf")
    rng = np.random.default_rng(1)
    people = [np.column_stack([rng.uniform(0, 1000, (25, 2)), rng.uniform(0.3, 1, 25)])
              for _ in range(3)]
    people[1][[15, 16, 17, 18, 19, 20, 21, 22, 23, 24], 2] = 0  # no face nor feet
    fragment = np.zeros((25, 3))
    fragment[[4, 3], :] = [[5, 5, 0.8], [6, 6, 0.8]]  # a lone forearm
    candidates, affinities = shelf_frame([*people, fragment])
    parsed = shelf.parse_people(candidates, affinities)
    assert len(parsed) == 3
    key = sorted(range(3), key=lambda k: people[k][1, 0])
    for got, want in zip(sorted(parsed, key=lambda p: p[1, 0]), (people[k] for k in key),
                         strict=True):
        np.testing.assert_array_equal(got, np.where(want[:, 2:] > 0, want, 0.0))
