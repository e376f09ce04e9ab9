"""``noise_px = auto``: the detection noise estimated from the hard-ray solution's residuals."""

import numpy as np
import pytest

from dloe_sfm.core import pipeline
from dloe_sfm.core.decisions import (
    EXACT_PX,
    NOISY_ROUNDS,
    HardRaysSettled,
    soft_rays_on_clocks,
    soft_wins,
)
from dloe_sfm.core.heldout import FOLDS, image_folds, observation_folds
from dloe_sfm.core.noise import FIT_RATIO, estimate_noise_px, residual_floor_px
from dloe_sfm.core.options import AUTO, Options
from dloe_sfm.core.problem import initialise, normalise
from dloe_sfm.core.robust import predicted, residuals_px
from dloe_sfm.core.solver import reconstruct
from dloe_sfm.errors import InputError
from dloe_sfm.evaluate import point_errors
from dloe_sfm.synth import SimulationSettings, load_mocap, simulate


def walking(assets_dir, noise=0.0):
    seq = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    cap, _ = simulate(seq, SimulationSettings(duration=1.5, noise=noise))
    return cap.validate()


def hard_residuals(cap):
    r = reconstruct(cap, Options(noise_px=0.0, robust_loss="none", stream_clocks=False))
    return residuals_px(cap, predicted(r.W, r.X))


def test_auto_is_the_default_and_any_case_of_the_word():
    assert Options().noise_px == AUTO and Options(noise_px="AUTO").noise_px == AUTO
    with pytest.raises(InputError, match="auto or a finite number >= 0"):
        Options(noise_px="loud")


def test_the_level_is_the_median_residual_of_gaussian_noise(rng):
    sigma = 3.0
    radius = np.hypot(*rng.normal(size=(2, 400, 20)))
    assert estimate_noise_px(FIT_RATIO * sigma * radius) == pytest.approx(sigma, rel=0.05)
    assert residual_floor_px(sigma) == pytest.approx(np.median(FIT_RATIO * sigma * radius),
                                                      rel=0.05)
    few = np.full((400, 20), np.nan)
    few[:, :3] = radius[:, :3]
    assert estimate_noise_px(few) == 0.0  # too few points to tell


def test_observation_folds_are_fixed_balanced_and_only_over_observations(rng):
    visible = rng.random((300, 20)) < 0.8
    fold = observation_folds(visible)
    np.testing.assert_array_equal(fold, observation_folds(visible))
    assert (fold[~visible] == -1).all()
    counts = np.bincount(fold[visible], minlength=FOLDS)
    assert counts.size == FOLDS and counts.min() > 0.9 * visible.sum() / FOLDS


def test_image_folds_take_turns_inside_each_stream():
    streams = np.array([0] * 8 + [1] * 2 + [2])
    frames = np.array([7, 0, 1, 2, 3, 4, 5, 6, 0, 1, 0])
    fold = image_folds(streams, frames)
    np.testing.assert_array_equal(fold[:8], [-1, -1, 0, 1, 2, 0, 1, 2])  # ends never held out
    assert (fold[8:] == -1).all()  # too short a stream, a lone photo
    assert (fold[2:8] != np.roll(fold[2:8], 1)).all() and FOLDS == 3


def test_soft_rays_must_predict_clearly_better():
    hard = np.array([4.0, 5.0, 6.0, np.nan])
    assert soft_wins(hard, 0.9 * hard)
    assert not soft_wins(hard, 0.97 * hard)  # within the margin: detections kept exact
    assert not soft_wins(hard, 1.2 * hard)


@pytest.mark.parametrize("noise", [1.0, 5.0])
def test_the_estimate_recovers_the_simulated_noise(assets_dir, noise):
    estimate = estimate_noise_px(hard_residuals(walking(assets_dir, noise)))
    assert abs(estimate - noise) <= 0.25 * noise, estimate


def test_auto_on_noisy_detections_solves_with_the_estimate(assets_dir):
    r = reconstruct(walking(assets_dir, 2.0), Options(robust_loss="none"))
    assert abs(r.noise_px - 2.0) <= 0.5, r.noise_px


@pytest.mark.slow
def test_auto_on_exact_detections_is_the_hard_ray_solve(assets_dir):
    cap = walking(assets_dir)
    auto = reconstruct(cap)
    told = reconstruct(cap, Options(noise_px=0.0))
    assert auto.noise_px == 0.0 and auto.clock is not None
    np.testing.assert_array_equal(auto.X, told.X)


@pytest.mark.slow
def test_detector_errors_are_solved_with_soft_rays_and_beat_hard_ones(assets_dir):
    """Heavy-tailed, per-camera biased detections (the OpenPose model): their residuals differ
    from point to point, yet soft rays predict held-out detections better, and the result is
    closer to the truth than the hard-ray solve, by more than 10 %."""
    seq = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    cap, truth = simulate(seq, SimulationSettings(duration=1.5, detector="openpose"))
    options = Options(robust_loss="none", fix_swaps=False)
    auto = reconstruct(cap, options)
    hard = reconstruct(cap, options.replace(noise_px=0.0))
    assert auto.noise_px > 1.0, auto.noise_px

    def error(X):
        return point_errors(X, truth.X, cap.visible)["error_mm"]

    assert error(auto.X) < 0.9 * error(hard.X), (error(auto.X), error(hard.X))


@pytest.mark.parametrize("noise", [0.0, 2.0])
def test_the_hard_phase_settles_only_on_a_prediction_that_stopped_improving(assets_dir, noise):
    """``decisions.HardRaysSettled``: a prediction that no longer improves ends the hard-ray
    phase under noise, never for exact detections (their residual is below ``EXACT_PX``), and
    never while it still improves."""
    cap = walking(assets_dir, noise=noise)
    options = Options(noise_px=0.0, robust_loss="none", stream_clocks=False)
    r = reconstruct(cap, options)
    norm = normalise(cap, options, r.X)
    X = norm.to_normal(r.X)
    level = float(np.nanmedian(residuals_px(cap, predicted(r.W, r.X))))
    assert (level > EXACT_PX) == (noise > 0), level
    settled = HardRaysSettled(cap, options, norm)
    assert settled(r.W, 1.2 * X) is None and settled(r.W, 1.1 * X) is None
    assert settled(r.W, X) is None  # still improving
    assert settled(r.W, X) is None  # 20 sweeps ago it was worse
    why = settled(r.W, X)
    assert (why is not None) == (noise > 0), why
    assert settled.reason == why


def test_under_detector_noise_the_hard_phase_stops_early_at_no_cost(assets_dir, monkeypatch):
    """100 lone photos under the OpenPose model's detections: the hard-ray phase stops once its
    prediction settles, far within its budget (run in full it fits W to the noise for about
    200 sweeps), and the solve is at least as accurate as with every hard sweep run."""
    seq = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    cap, truth = simulate(seq, SimulationSettings(duration=1.5, num_streams=0, lone_photos=100,
                                                  detector="openpose"))
    options = Options(robust_loss="none", fix_swaps=False, stream_clocks=False)
    X_world = initialise(cap, options)

    def error(r):
        return point_errors(r.X, truth.X, cap.visible)["error_mm"]

    stopped = pipeline.solve_event(cap, options, X_world)
    monkeypatch.setattr(HardRaysSettled, "__call__", lambda self, W, X: None)
    every = pipeline.solve_event(cap, options, X_world)
    assert stopped.noise_px > 1.0 and every.noise_px > 1.0
    assert stopped.nit <= every.nit - 100, (stopped.nit, every.nit)
    assert error(stopped) <= 1.02 * error(every), (error(stopped), error(every))


def test_exact_detections_the_hard_phase_stopped_for_resume_it_to_its_end(assets_dir,
                                                                          monkeypatch):
    """Exact detections at 7.5 Hz with frames dropped: the graph's interpolation leaves
    residuals above ``EXACT_PX``, so the hard-ray phase stops for the soft rays; the held-out
    check keeps hard rays, and their phase is resumed to its end: the same points as a hard
    phase never stopped. The progress never steps back (the soft sweeps thrown away count)."""
    seq = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    cap, _ = simulate(seq, SimulationSettings(rate=7.5, drop=0.3, missing=0.3))
    options = Options(robust_loss="none", stream_clocks=False)
    X_world = initialise(cap, options)
    reasons = []
    call = HardRaysSettled.__call__

    def noted(self, W, X):
        reasons.append(call(self, W, X))
        return reasons[-1]

    monkeypatch.setattr(HardRaysSettled, "__call__", noted)
    calls = []
    resumed = pipeline.solve_event(cap, options, X_world,
                                   progress=lambda done, total, _: calls.append((done, total)))
    assert any(reasons) and resumed.noise_px == 0.0
    done = [d for d, _ in calls]
    assert done == sorted(done) and done[-1] == calls[-1][1] > resumed.nit
    monkeypatch.setattr(HardRaysSettled, "__call__", lambda self, W, X: None)
    never = pipeline.solve_event(cap, options, X_world)
    assert resumed.nit == never.nit
    np.testing.assert_allclose(resumed.X, never.X, atol=1e-6)


@pytest.mark.parametrize("noise", [0.0, 3.0])
def test_soft_rays_along_the_clocks_only_for_noisy_detections(assets_dir, noise):
    """``decisions.soft_rays_on_clocks`` along the true clocks of a hard-ray solve: 3 px detections
    get soft rays at the level the graph's fit leaves (held-out images predicted better); exact
    ones stay exact (the level their fit leaves is below ``decisions.CHAIN_MIN_PX``)."""
    seq = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    cap, truth = simulate(seq, SimulationSettings(duration=1.5, noise=noise))
    options = Options(noise_px=0.0, stream_clocks="off", robust_loss="none")
    r = reconstruct(cap, options)
    level, _ = soft_rays_on_clocks(cap, options, r.X, r.D, r.W, truth.t)
    assert abs(level - noise) <= 0.25 * noise, level


@pytest.mark.slow
def test_robust_rounds_under_detector_noise_solve_once_more(assets_dir, monkeypatch):
    """The OpenPose model's detections: every solve finds their noise, and the robust rounds
    re-solve ``NOISY_ROUNDS`` times (each round's scale, from a fit without the last round's
    rejects, would reject more), not up to ``robust_iterations``; the result is still closer to
    the truth than the plain solve."""
    seq = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    cap, truth = simulate(seq, SimulationSettings(duration=1.5, detector="openpose"))
    plain = reconstruct(cap, Options(robust_loss="none", fix_swaps=False))
    solves = []
    solve_events = pipeline.solve_events
    monkeypatch.setattr(pipeline, "solve_events",
                        lambda *args: solves.append(1) or solve_events(*args))
    result = reconstruct(cap)
    assert result.noise_px > 1.0 and len(solves) == 1 + NOISY_ROUNDS
    assert result.outliers.size > 0

    def error(X):
        return point_errors(X, truth.X, cap.visible)["error_mm"]

    assert error(result.X) < error(plain.X), (error(result.X), error(plain.X))
