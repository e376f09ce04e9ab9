"""Workspace outputs (docs/interfaces.md, "Reconstruct outputs") from a hand-built capture and
result."""

from __future__ import annotations

import csv
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scenes import TOY_LAYOUT, F, P, toy_capture

from dloe_sfm import Capture, InputError, Result
from dloe_sfm import export as export_module
from dloe_sfm.columns import frame_file_stem
from dloe_sfm.core.bias import without_offsets
from dloe_sfm.export import export_outputs, reprojection_errors
from dloe_sfm.io import load_result, save_result
from dloe_sfm.viz import plot_stream_offsets


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Capture, Result]:
    capture, result, X = toy_capture()
    out = tmp_path_factory.mktemp("export") / "out"
    static_rgb = np.array([[255, 0, 0], [0, 128, 255], [10, 20, 30]], dtype=np.uint8)
    export_outputs(out, capture, result, static_xyz=X[0, :3], static_rgb=static_rgb,
                   layout=TOY_LAYOUT,
                   report={"inputs": {"workspace": "synthetic"}, "parameters": {"lambda1": 1e-5}},
                   plots=False)
    return out, capture, result


def test_frame_names_carry_rank_and_a_unique_stem() -> None:
    assert frame_file_stem(3, "cam01/0012.jpg", 10) == "00003_cam01_0012"
    assert frame_file_stem(7, "a b(1).png", 100_001) == "000007_a_b_1"


def test_frames_read_back_in_open3d(exported) -> None:
    out, capture, result = exported
    files = sorted((out / "frames").glob("*.ply"))
    assert len(files) == capture.num_images
    for i, name in enumerate(capture.image_names):
        path = out / "frames" / f"{frame_file_stem(int(result.rank[i]), name, len(files))}.ply"
        cloud = o3d.t.io.read_point_cloud(str(path))
        np.testing.assert_array_equal(cloud.point.point_id.numpy().ravel(), np.arange(P))
        np.testing.assert_allclose(cloud.point.positions.numpy(), result.X[i], atol=1e-6, rtol=0)
        np.testing.assert_array_equal(cloud.point.observed.numpy().ravel(), capture.visible[i])
        assert (cloud.point.event.numpy() == result.events[i]).all()
        np.testing.assert_allclose(cloud.point.confidence.numpy().ravel(), capture.confidence[i],
                                   atol=1e-6)
    first = Path(capture.image_names[result.order[0]])
    assert files[0].name == f"00000_{first.parent.name}_{first.stem}.ply"


def test_skeleton_and_static_clouds(exported) -> None:
    out, capture, result = exported
    skeletons = sorted((out / "skeleton").glob("*.ply"))
    assert len(skeletons) == capture.num_images
    lines = o3d.io.read_line_set(str(skeletons[0]))
    np.testing.assert_array_equal(np.asarray(lines.lines), np.array(TOY_LAYOUT.edges))
    np.testing.assert_allclose(np.asarray(lines.points), result.X[result.order[0]], atol=1e-6)
    static = o3d.t.io.read_point_cloud(str(out / "static.ply"))
    np.testing.assert_array_equal(static.point.colors.numpy(), [[255, 0, 0], [0, 128, 255],
                                                                 [10, 20, 30]])


def test_trajectories_npz_and_csv(exported) -> None:
    out, capture, result = exported
    with np.load(out / "trajectories.npz") as data:
        np.testing.assert_array_equal(data["X"], result.X)
        np.testing.assert_array_equal(data["order"], result.order)
        np.testing.assert_array_equal(data["image_names"], capture.image_names)
        np.testing.assert_array_equal(data["events"], result.events)
    with open(out / "trajectories.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["rank", "image", "point_id", "x", "y", "z", "observed", "subject_id"]
    assert {row["subject_id"] for row in rows} == {"0"}
    assert len(rows) == capture.num_images * P
    index = {name: i for i, name in enumerate(capture.image_names)}
    for row in rows:
        i, j = index[row["image"]], int(row["point_id"])
        assert int(row["rank"]) == result.rank[i]
        xyz = [float(row[k]) for k in "xyz"]
        np.testing.assert_allclose(xyz, result.X[i, j], rtol=0, atol=1e-12)
        assert int(row["observed"]) == int(capture.visible[i, j])
    with open(out / "sequence.csv", newline="") as f:
        seq = list(csv.DictReader(f))
    assert [r["image"] for r in seq] == capture.image_names[result.order].tolist()
    assert [int(r["rank"]) for r in seq] == list(range(capture.num_images))
    assert [int(r["stream"]) for r in seq] == capture.stream[result.order].tolist()
    assert [int(r["frame"]) for r in seq] == capture.frame[result.order].tolist()
    assert [int(r["event"]) for r in seq] == result.events[result.order].tolist()


def test_report_fields_and_errors(exported) -> None:
    out, capture, result = exported
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"] == {"workspace": "synthetic"}
    assert report["parameters"] == {"lambda1": 1e-5}
    assert report["solver"]["iterations"] == 2 and report["solver"]["cost_history"] == [2.0, 1.0]
    assert report["events"] == 2
    assert [e["num_images"] for e in report["event_summaries"]] == [12, 6]
    errors = reprojection_errors(capture, result.X)
    stats = report["reprojection_error_px"]
    assert stats["all"]["count"] == int(capture.visible.sum()) == capture.num_images * P - 1
    assert stats["all"]["mean"] == pytest.approx(np.nanmean(errors))
    name = str(capture.image_names[4])
    assert stats["per_image"][name]["count"] == P - 1
    assert stats["per_image"][name]["max"] == pytest.approx(np.nanmax(errors[4]))
    assert [p["name"] for p in stats["per_point"]] == TOY_LAYOUT.point_names
    assert stats["per_point"][2]["count"] == capture.num_images - 1


def test_reprojection_error_is_in_pixels() -> None:
    capture, _, X = toy_capture()
    exact = reprojection_errors(capture, X)
    assert np.nanmax(exact) < 1e-9
    assert np.isnan(exact[4, 2]) and np.isfinite(exact).sum() == capture.visible.sum()
    moved = X.copy()
    depth = (capture.R[0] @ (X[0, 0] - capture.C[0]))[2]
    moved[0, 0] += 0.01 * capture.R[0][0]  # 1 cm along the camera's x axis
    assert reprojection_errors(capture, moved)[0, 0] == pytest.approx(F * 0.01 / depth, rel=1e-9)


def test_existing_out_dir_is_refused_unless_overwrite(tmp_path) -> None:
    capture, result, _ = toy_capture()
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("user data")
    for overwrite in (False, True):  # never replaced: another path is asked for
        with pytest.raises(InputError, match="not written by dloe-sfm .*choose another output"):
            export_outputs(out, capture, result, overwrite=overwrite)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    (out / "keep.txt").unlink()
    export_outputs(out, capture, result, overwrite=True, plots=False)  # an empty folder
    (out / "stale.txt").write_text("an earlier export")
    export_outputs(out, capture, result, overwrite=True, plots=False)  # ours (.dloe_sfm marker)
    assert not (out / "stale.txt").exists() and (out / "report.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_failure_leaves_nothing_behind(tmp_path, monkeypatch) -> None:
    capture, result, _ = toy_capture()
    calls = []
    real = export_module.write_point_cloud

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 5:
            raise OSError("disk full")
        return real(*args, **kwargs)

    monkeypatch.setattr(export_module, "write_point_cloud", failing)
    with pytest.raises(InputError, match=r"out: cannot write it \(disk full\)"):
        export_outputs(tmp_path / "out", capture, result)
    assert list(tmp_path.iterdir()) == []


def test_mismatched_result_is_refused(tmp_path) -> None:
    capture, result, _ = toy_capture()
    result.order = result.order[:-1]
    with pytest.raises(InputError, match="order"):
        export_outputs(tmp_path / "out", capture, result)
    assert list(tmp_path.iterdir()) == []


def test_stream_offsets_in_the_report_and_the_result_file(tmp_path) -> None:
    """A result whose observations had each stream's offsets taken out (``offset_px``,
    ``solved``): report.json lists them by stream and point name, the exported errors are
    against the observations without them, and a result file keeps them for a later export."""
    capture, result, X = toy_capture()
    shift = np.zeros((capture.stream.max() + 1, P, 2))
    shift[1, 0], shift[2, 3] = [3.0, -1.0], [0.0, 2.5]
    offsets = shift[capture.stream]
    detected = Capture(x=capture.x + offsets, K=capture.K, R=capture.R, C=capture.C,
                       stream=capture.stream, frame=capture.frame,
                       confidence=capture.confidence, image_names=capture.image_names)
    exact = replace(result, X=X, offset_px=offsets, solved=without_offsets(detected, offsets))
    report = export_outputs(tmp_path / "out", detected, exact, layout=TOY_LAYOUT, plots=False)
    listed = {(o["stream"], o["point"]): o["offset_px"]
              for o in report["stream_offsets"]["offsets"]}
    assert listed == {(1, TOY_LAYOUT.point_names[0]): [3.0, -1.0],
                      (2, TOY_LAYOUT.point_names[3]): [0.0, 2.5]}
    assert report["reprojection_error_px"]["all"]["max"] < 1e-6
    loaded = load_result(save_result(tmp_path / "result.npz", replace(exact, solved=None)))
    assert np.array_equal(loaded.offset_px, offsets)
    again = export_outputs(tmp_path / "again", detected, loaded, layout=TOY_LAYOUT, plots=False)
    assert again["reprojection_error_px"]["all"]["max"] < 1e-6
    plain = export_outputs(tmp_path / "plain", detected, replace(exact, offset_px=None,
                                                                 solved=None), plots=False)
    assert plain["stream_offsets"]["count"] == 0
    assert plain["reprojection_error_px"]["all"]["max"] == pytest.approx(np.sqrt(10.0))
    png = plot_stream_offsets(exact, exact.solved, tmp_path / "offsets.png",
                              TOY_LAYOUT.point_names)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
