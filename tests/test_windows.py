"""Overlapping time windows solved apart and stitched (dloe_sfm.core.windows)."""

import logging
import os

import numpy as np
import pytest

from dloe_sfm.core import parallel
from dloe_sfm.core.options import Options
from dloe_sfm.core.parallel import MIN_PARALLEL_SLOTS, kept_workers, map_in_processes, worker_count
from dloe_sfm.core.sequencing import kendall_tau
from dloe_sfm.core.solver import reconstruct
from dloe_sfm.core.windows import plan_windows
from dloe_sfm.errors import InputError
from dloe_sfm.synth import SimulationSettings, load_mocap, simulate


def test_plan_windows_cover_and_overlap(rng):
    times = rng.permutation(1000).astype(float)
    windows, home = plan_windows(times, 300, 30)
    assert all(w.size == 300 for w in windows)
    rank = np.argsort(np.argsort(times))
    spans = [(rank[w].min(), rank[w].max()) for w in windows]
    assert all(hi - lo == 299 for lo, hi in spans)  # runs of consecutive times
    starts = np.diff([lo for lo, _ in spans])
    assert (starts[:-1] == 270).all() and 0 < starts[-1] <= 270  # the last ends at the last image
    assert spans[0][0] == 0 and spans[-1][1] == 999
    for i in range(1000):  # every image from a window that holds it, away from its ends
        w = windows[home[i]]
        assert i in w
        lo, hi = spans[home[i]]
        assert min(rank[i] - lo, hi - rank[i]) >= min(14, rank[i], 999 - rank[i])
    assert plan_windows(times, 1000, 0)[0][0].size == 1000  # one window: the whole capture
    with pytest.raises(InputError, match="overlap"):
        plan_windows(times, 300, 300)


@pytest.mark.slow
def test_windowed_solve_matches_the_single_solve(assets_dir):
    cap, truth = simulate(load_mocap(assets_dir / "mocap" / "basketball_signal_1.npz"),
                          SimulationSettings(duration=2.5, seed=0, num_streams=4, rate=30.0,
                                             noise=1.0))
    single = reconstruct(cap, Options(window_images=0))
    windowed = reconstruct(cap, Options(window_images=120, workers=1))
    err = [1000 * np.linalg.norm(r.X - truth.X, axis=2).mean() for r in (single, windowed)]
    assert err[1] <= 1.1 * err[0] + 0.05, err
    assert kendall_tau(windowed.order, truth.t) >= 0.99  # single: 0.9998
    assert windowed.W.shape == (cap.num_images,) * 2
    assert np.allclose(np.asarray(windowed.W.sum(axis=1)).ravel(), 1.0)
    assert windowed.image_status is not None and (windowed.image_status == "ok").mean() > 0.95
    # the windows in two worker processes: the same numbers
    parallel = reconstruct(cap, Options(window_images=120, workers=2))
    np.testing.assert_array_equal(parallel.X, windowed.X)
    np.testing.assert_array_equal(parallel.order, windowed.order)


def test_workers_by_default_from_enough_work(monkeypatch):
    """``workers = auto``: one process per core and task from ``MIN_PARALLEL_SLOTS`` (image,
    point) slots; below, or with one task, the calling process; a number is taken as given."""
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    assert worker_count("auto", 3, MIN_PARALLEL_SLOTS) == 2
    assert worker_count("auto", 3, MIN_PARALLEL_SLOTS - 1) == 1
    assert worker_count("auto", 1, 10 * MIN_PARALLEL_SLOTS) == 1
    assert worker_count(4, 3, 1) == 3
    # Shelf's four people: 278 images of 100 points, solved in two workers; one person's not
    assert worker_count("auto", 2, 278 * 100) == 2 and worker_count("auto", 2, 278 * 25) == 1


def _pid(_: int) -> int:
    """The worker's process id, logged."""
    logging.getLogger("dloe_sfm").info("task in a worker")
    return os.getpid()


def test_kept_workers_serve_every_parallel_step_and_end_after(log_lines):
    """Inside ``kept_workers`` the processes ``map_in_processes`` starts serve its next calls
    and end on leaving; outside, each call starts its own; with one worker, the tasks run
    here. What a task logs is logged here."""
    with kept_workers():
        first = list(map_in_processes(_pid, range(4), 2))
        again = list(map_in_processes(_pid, range(4), 2))
        pools = list(parallel._kept.values())
    assert set(again) <= set(first) and len(set(first)) <= 2 and os.getpid() not in first
    assert parallel._kept is None and all(p._shutdown_thread for p in pools)
    assert log_lines == ["task in a worker"] * 8
    assert not set(map_in_processes(_pid, range(2), 2)) & set(first)
    assert set(map_in_processes(_pid, range(2), 1)) == {os.getpid()}  # one: here


def test_windows_need_videos(assets_dir):
    cap, _ = simulate(load_mocap(assets_dir / "mocap" / "walking_1.npz"),
                      SimulationSettings(duration=1.0, num_streams=8, rate=15))
    lone = type(cap)(x=cap.x, K=cap.K, R=cap.R, C=cap.C, stream=np.full(cap.num_images, -1))
    with pytest.raises(InputError, match="two or more video streams"):
        reconstruct(lone, Options(window_images=50))
