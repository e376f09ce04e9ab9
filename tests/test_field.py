"""The bundled field workspace (assets/field): handheld cameras at their own frame rates, as its
README says, and what ``reconstruct`` with default options reaches on it."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from dloe_sfm.colmap import load_workspace
from dloe_sfm.synth import load_pipeline

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"


@pytest.fixture(scope="module")
def field(assets_dir: Path) -> Path:
    path = assets_dir / "field"
    if not (path / "sparse" / "0").is_dir():
        pytest.fail(f"{path} is missing; see docs/field.md")
    return path


@pytest.fixture(scope="module")
def truth(field: Path) -> dict[str, np.ndarray]:
    with np.load(field / "ground_truth.npz") as data:
        return {k: data[k] for k in data.files}


def field_pipeline() -> ModuleType:
    return load_pipeline(PIPELINES, "field")


def test_cameras_are_handheld_at_their_own_rates(field, truth):
    ws = load_workspace(field)
    names = [str(n) for n in truth["image_names"]]
    assert sorted(ws.image_names) == sorted(names)
    streams = np.unique(truth["stream"])
    assert streams.size >= 4
    rates = np.array([truth["frame_rate"][truth["stream"] == s][0] for s in streams])
    assert ((rates >= 8) & (rates <= 12)).all()
    assert np.diff(np.sort(rates)).min() > 0.05  # every camera its own rate
    for s in streams:
        sel = np.flatnonzero(truth["stream"] == s)
        assert np.allclose(truth["frame_rate"][sel], rates[s])
        assert np.allclose(np.diff(truth["t_true"][sel]), 1 / rates[s])
        # one COLMAP camera (shared intrinsics) per folder, a pose of its own per image
        assert len({ws.camera_id(names[i]) for i in sel}) == 1
        C_true, C_sfm = truth["C_true"][sel], np.stack([ws.centre(names[i]) for i in sel])
        assert np.linalg.norm(np.diff(C_true, axis=0), axis=1).min() > 1e-3  # metres
        assert np.linalg.norm(C_sfm - C_true, axis=1).max() < 0.05
        assert np.linalg.norm(np.diff(truth["R_true"][sel], axis=0), axis=(1, 2)).min() > 1e-4
    assert len({ws.camera_id(n) for n in names}) == streams.size
    starts = np.array([truth["t_true"][truth["stream"] == s].min() for s in streams])
    assert np.unique(np.round(starts, 6)).size == streams.size


@pytest.mark.slow
def test_default_reconstruction_against_the_oracle(field, tmp_path):
    """Default options; measured (docs/field.md): 10.6 mm against an 11.1 mm oracle, tau 1.0,
    sync RMS 0.012 of a frame period, worst image 1.24 x the median, the capture's first frame
    (which its chain row copies from an image 60 ms later) `uncertain`, its points kept: the
    issue's four acceptance lines, nothing dropped."""
    pipeline = field_pipeline()
    out = tmp_path / "dloe"
    pipeline.reconstruct_main(field, field / "keypoints.csv", "csv", out, plots=False)
    s = pipeline.score(field, out)
    assert s["images"] == 26 and s["images_without_points"] == 0
    assert s["kendall_tau"] >= pipeline.MIN_TAU
    assert s["error_mm"] <= pipeline.ORACLE_FACTOR * s["oracle_mm"] + pipeline.ORACLE_SLACK_MM
    assert s["error_aligned_mm"] <= 6.0
    assert s["worst_over_median"] <= pipeline.WORST_OVER_MEDIAN
    assert s["sync_periods"] <= pipeline.MAX_SYNC_PERIODS
