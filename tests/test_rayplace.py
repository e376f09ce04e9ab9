"""Lone photos placed on the time line by their own rays (``core.rayplace``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dloe_sfm import reconstruct
from dloe_sfm.core.options import Options
from dloe_sfm.core.rayplace import place_by_rays
from dloe_sfm.core.sequencing import kendall_tau, order_from_embedding
from dloe_sfm.evaluate import evaluate, oracle_reconstruct
from dloe_sfm.export import export_outputs
from dloe_sfm.io import load_result, save_result
from dloe_sfm.synth import SimulationSettings, load_mocap, simulate


def unit_rays(X: np.ndarray, C: np.ndarray) -> np.ndarray:
    V = X - C[:, None, :]
    return V / np.linalg.norm(V, axis=2, keepdims=True)


def shuffled_places(t: np.ndarray, spread: float, rng: np.random.Generator) -> np.ndarray:
    """An embedding of the images: their time ranks, each moved by about ``spread`` places."""
    rank = np.argsort(np.argsort(t)).astype(np.float64)
    return rank + rng.normal(0.0, spread, t.size)


def test_lone_photos_are_put_where_their_rays_meet_the_curve(assets_dir):
    """300 lone photos of a walk under the detector model, with shapes 30 mm off (the noise of
    a solve) in an order whose every image is about 8 places off: placed by their own
    detections on the curve of those shapes, the order is the time order to |tau| >= 0.98,
    where the shapes' order was 0.95, and no image fits another time as well."""
    seq = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    cap, truth = simulate(seq, SimulationSettings(num_streams=0, lone_photos=300, seed=0,
                                                  detector="openpose", duration=3.0))
    rng = np.random.default_rng(0)
    X = truth.X + rng.normal(0.0, 0.03 / np.sqrt(3), truth.X.shape)
    f = shuffled_places(truth.t, 8.0, rng)
    before = kendall_tau(order_from_embedding(f), truth.t)
    placed, ambiguous = place_by_rays(X, cap.rays(), cap.C, cap.visible, f,
                                      np.ones(cap.num_images, dtype=bool))
    assert before < 0.96
    assert kendall_tau(order_from_embedding(placed), truth.t) >= 0.98
    assert not ambiguous.any()
    np.testing.assert_array_equal(np.sort(placed), np.sort(f))


def test_a_pose_seen_again_is_flagged_and_left_in_place():
    """Points that go out and come back along the same path: a photo of the way out fits the
    way back as well. Such photos are flagged and keep their places; photos of a motion that
    never comes back are all placed, none flagged; images that are not lone photos stay."""
    rng = np.random.default_rng(1)
    n, p = 200, 12
    t = np.sort(rng.uniform(0.0, 1.0, n))
    base = rng.normal(0.0, 0.3, (p, 3))
    C = rng.normal(0.0, 1.0, (n, 3))
    C = 4.0 * C / np.linalg.norm(C, axis=1, keepdims=True)
    visible = np.ones((n, p), dtype=bool)
    f = shuffled_places(t, 3.0, rng)
    lone = np.ones(n, dtype=bool)

    def shapes(position):
        return base[None] + position[:, None, None] * np.array([1.0, 0.5, 0.0])

    straight = shapes(t)
    placed, ambiguous = place_by_rays(straight, unit_rays(straight, C), C, visible, f, lone)
    assert not ambiguous.any()
    assert kendall_tau(order_from_embedding(placed), t) >= 0.995

    there_and_back = shapes(1.0 - np.abs(2.0 * t - 1.0))
    placed, ambiguous = place_by_rays(there_and_back, unit_rays(there_and_back, C), C, visible,
                                      f, lone)
    away_from_turn = np.abs(t - 0.5) > 0.1
    assert ambiguous[away_from_turn].mean() > 0.9
    rank, placed_rank = np.argsort(np.argsort(f)), np.argsort(np.argsort(placed))
    held = ambiguous | ~lone
    np.testing.assert_array_equal(np.argsort(rank[held]), np.argsort(placed_rank[held]))

    some = rng.uniform(size=n) < 0.5
    placed, ambiguous = place_by_rays(straight, unit_rays(straight, C), C, visible, f, some)
    assert not ambiguous[~some].any()
    stay = np.flatnonzero(~some)
    np.testing.assert_array_equal(np.argsort(f[stay]), np.argsort(placed[stay]))


def test_a_burst_moves_as_a_whole_its_frames_in_order():
    """Bursts of three frames each, a quarter of the images, every burst put 40 places late
    on the line: in one placement their frames go back to within a place or two of their
    times, in frame order, and the whole order is near the time order again (the curve they
    are placed on is traced by the misplaced bursts too); a burst with a frame that sees
    nothing stays where it was."""
    rng = np.random.default_rng(2)
    n, p = 240, 10
    t = np.sort(rng.uniform(0.0, 1.0, n))
    base = rng.normal(0.0, 0.3, (p, 3))
    X = base[None] + (np.sin(3.0 * t)[:, None, None] * np.array([1.0, 0.4, 0.2])
                      + t[:, None, None] * np.array([0.0, 0.0, 0.8]))
    C = rng.normal(0.0, 1.0, (n, 3))
    C = 4.0 * C / np.linalg.norm(C, axis=1, keepdims=True)
    visible = np.ones((n, p), dtype=bool)
    frames = rng.permutation(n)[:60].reshape(20, 3)
    bursts = [np.sort(b) for b in frames]  # frame order = time order (t is sorted)
    rank = np.arange(n, dtype=np.float64)
    f = rank.copy()
    for b in bursts:
        f[b] += 40.5
    lone = np.ones(n, dtype=bool)
    lone[frames.ravel()] = False
    placed, _ = place_by_rays(X, unit_rays(X, C), C, visible, f, lone, bursts)
    assert kendall_tau(order_from_embedding(f), t) < 0.95
    assert kendall_tau(order_from_embedding(placed), t) >= 0.98
    rank = np.argsort(np.argsort(placed))
    assert np.abs(rank[frames.ravel()] - frames.ravel()).mean() <= 1.5
    assert all((np.diff(placed[b]) > 0).all() for b in bursts)

    blind = visible.copy()
    blind[bursts[0][1]] = False
    placed, _ = place_by_rays(X, unit_rays(X, C), C, blind, f, lone, bursts)
    fixed, _ = place_by_rays(X, unit_rays(X, C), C, blind, f, lone, bursts[1:])
    np.testing.assert_array_equal(placed, fixed)  # as if it were no burst to move


@pytest.mark.slow
def test_lone_detector_photos_are_ordered_and_within_the_oracle(assets_dir, tmp_path):
    """300 lone photos of a walk under the detector model, default options: one event, the
    order at |tau| >= 0.98 and the points within issue 38's 1.5 x the true-time oracle + 1 mm
    (on the code before the photos were placed by their rays: 83 mm, |tau| 0.94, oracle 54 mm).
    The flags survive the result file and reach report.json."""
    seq = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    cap, truth = simulate(seq, SimulationSettings(num_streams=0, lone_photos=300, seed=0,
                                                  detector="openpose", duration=3.0))
    r = reconstruct(cap, Options())
    assert r.events.max() == 0
    scores = evaluate(cap, truth, r)
    assert scores["kendall_tau"] >= 0.98
    oracle = 1000 * np.linalg.norm(oracle_reconstruct(cap, truth.t) - truth.X, axis=2).mean()
    assert scores["error_mm"] <= 1.5 * oracle + 1.0
    assert r.order_ambiguous is not None and r.order_ambiguous.shape == (cap.num_images,)
    np.testing.assert_array_equal(load_result(save_result(tmp_path / "r.npz", r))
                                  .order_ambiguous, r.order_ambiguous)
    export_outputs(tmp_path / "out", cap, r, plots=False)
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    flagged = [name for name, row in report["image_checks"].items() if row["order_ambiguous"]]
    assert flagged == report["image_status"]["order_ambiguous"]
    assert len(flagged) == int(r.order_ambiguous.sum())
