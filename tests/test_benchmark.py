"""Smoke tests of ``dloe-sfm benchmark`` on tiny grids of the shared mocap data."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dloe_sfm import benchmark
from dloe_sfm.benchmark.jobs import run_jobs
from dloe_sfm.core.parallel import map_in_processes


@pytest.mark.slow
@pytest.mark.shared
def test_noise_quick(shared_dir, tmp_path) -> None:
    out = tmp_path / "noise"
    doc = benchmark.main("noise", out=out, data=shared_dir / "data" / "mocap", quick=True,
                         motions=["walking_1"], duration=0.4)
    assert (out / "noise.png").stat().st_size > 1000
    assert (out / "table.md").read_text().startswith("| method \\ 2D noise sigma (px) | 0 | 3 |")
    saved = json.loads((out / "results.json").read_text())
    assert saved["suite"] == "noise" and saved["values"] == [0.0, 3.0]
    assert {"platform", "cpu_count", "cpu_model", "numpy", "scipy", "git_commit"} <= set(
        saved["machine"])
    assert len(saved["runs"]) == 2 * len(benchmark.METHODS)
    assert not any("failed" in r for r in saved["runs"])
    summary = doc["summary"]
    assert set(summary) == set(benchmark.METHODS)
    for setting in ("0", "3"):
        assert summary["DLOE oracle"][setting]["mean"] < \
            summary["pseudo-triangulation"][setting]["mean"]


@pytest.mark.shared
@pytest.mark.slow
def test_runtime_quick(shared_dir, tmp_path) -> None:
    out = tmp_path / "runtime"
    doc = benchmark.main("runtime", out=out, data=shared_dir / "data" / "mocap", quick=True,
                         sizes=[40, 80], streams=4)
    runs = sorted(doc["runs"], key=lambda r: r["num_images"])
    assert doc["num_streams"] == 4
    assert all(r["stage_seconds"]["export"] > 0 and r["stage_seconds"]["assess"] > 0
               for r in runs)
    assert [r["target"] for r in runs] == [40, 80]
    assert all(abs(r["num_images"] - r["target"]) <= 4 for r in runs)  # clip length rounding
    assert all(r["peak_rss_mb"] >= r["rss_before_mb"] > 0 for r in runs)
    assert np.isfinite(doc["summary"]["fits"]["seconds"]["exponent"])
    assert "Fitted growth exponents" in (out / "table.md").read_text()
    assert (out / "runtime.png").is_file()


def test_runtime_clip_too_short(tmp_path) -> None:
    # the bundled basketball_signal_1 clip is 3.5 s: 10^5 images at 8 streams of 30 Hz need 417 s
    with pytest.raises(benchmark.InputError,
                       match=r"need 416\.7 s .* \(--streams 955 or more, or a higher --rate\)"):
        benchmark.main("runtime", out=tmp_path, sizes=[100000])


def test_streams_suite_sizes(tmp_path) -> None:
    # issue 38's many-camera sizes; the bundled 3.5 s clip holds only the --quick ones
    assert benchmark.STREAMS_SIZES[0] == ((11_000, 16, 30.0), (10_000, 64, 6.5))
    with pytest.raises(benchmark.InputError,
                       match=r"10000 images need 24\.0 s at 64 streams of 6\.5 Hz \(--data"):
        benchmark.main("streams", out=tmp_path)


def test_unknown_suite(tmp_path) -> None:
    with pytest.raises(benchmark.InputError, match="unknown suite"):
        benchmark.main("speed", out=tmp_path)


def test_fit_exponent() -> None:
    n = np.array([100.0, 200.0, 400.0, 800.0])
    slope, _ = benchmark.fit_exponent(n, 3e-4 * n ** 1.5)
    assert slope == pytest.approx(1.5)


def test_lone_suite_quick(tmp_path) -> None:
    """The lone-photo runtime grid: every photo its own camera; the clean photos solved to well
    under a millimetre (0.22 mm measured), the detector-model row labelled as such and left out
    of the growth fit."""
    doc = benchmark.main("lone", out=tmp_path, quick=True)
    clean, detected = sorted(doc["runs"], key=lambda r: r["detector"] is not None)
    assert clean["detector"] is None and detected["detector"] == "openpose"
    assert clean["num_images"] == clean["num_streams"] == 60
    assert clean["error_mm"] < 0.5 < detected["error_mm"]
    assert doc["summary"]["fits"] == {}  # one clean size: nothing to fit
    assert "| 60 (openpose detector) | 60 |" in (tmp_path / "table.md").read_text()


def _spawning_job(spec: dict) -> list[int]:
    """A job whose own work runs in worker processes, as a solve's events do from 1000 images."""
    return [sum(map_in_processes(abs, spec["values"], 2))]


def test_fresh_jobs_may_start_processes() -> None:
    """A runtime job's process may start workers of its own (the 4 000-photo solve of the lone
    suite did, and a pool's daemon process may not)."""
    assert run_jobs(_spawning_job, [{"values": [-1, -2]}, {"values": [3]}], 1, "t",
                    fresh=True) == [3, 3]
