"""``noise_px = auto``: the detection noise estimated from the hard-ray solution's residuals."""

import numpy as np
import pytest

from dloe_sfm.core.noise import FIT_RATIO, estimate_noise_px
from dloe_sfm.core.options import AUTO, Options
from dloe_sfm.core.robust import predicted, residuals_px
from dloe_sfm.core.solver import reconstruct
from dloe_sfm.errors import InputError
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
    assert Options().clocks_on  # asked before the estimate: the hard-ray start
    with pytest.raises(InputError, match="auto or a finite number >= 0"):
        Options(noise_px="loud")


def test_shared_residuals_are_noise_and_uneven_ones_are_not(rng):
    sigma = 3.0
    radius = np.hypot(*rng.normal(size=(2, 400, 20)))
    assert estimate_noise_px(FIT_RATIO * sigma * radius) == pytest.approx(sigma, rel=0.05)
    speed = np.linspace(0.2, 3.0, 20)  # slow joints predicted exactly, fast ones not
    assert estimate_noise_px(radius * speed) == 0.0
    few = np.full((400, 20), np.nan)
    few[:, :3] = radius[:, :3]
    assert estimate_noise_px(few) == 0.0  # too few points to tell


@pytest.mark.parametrize("noise", [1.0, 5.0])
def test_the_estimate_recovers_the_simulated_noise(assets_dir, noise):
    estimate = estimate_noise_px(hard_residuals(walking(assets_dir, noise)))
    assert abs(estimate - noise) <= 0.25 * noise, estimate


def test_auto_on_noisy_detections_solves_with_the_estimate(assets_dir):
    r = reconstruct(walking(assets_dir, 2.0), Options(robust_loss="none"))
    assert abs(r.noise_px - 2.0) <= 0.5, r.noise_px
    assert r.clock is None  # stream clocks auto: off with noisy rays


@pytest.mark.slow
def test_auto_on_exact_detections_is_the_hard_ray_solve(assets_dir):
    cap = walking(assets_dir)
    auto = reconstruct(cap)
    told = reconstruct(cap, Options(noise_px=0.0))
    assert auto.noise_px == 0.0 and auto.clock is not None
    np.testing.assert_array_equal(auto.X, told.X)
