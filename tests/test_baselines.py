"""The baselines on synthetic captures whose answer is known exactly."""

from __future__ import annotations

import numpy as np
import pytest

from dloe_sfm.baselines import (
    dct_basis,
    high_pass_filter,
    pseudo_triangulation,
    sedl,
    select_num_bases,
    trajectory_basis,
    triangulate_instants,
)
from dloe_sfm.core.capture import Capture, project
from dloe_sfm.synth import ring_cameras

CENTRE = np.array([0.0, 1.0, 0.0])


def interleaved_capture(X: np.ndarray, times: np.ndarray, num_streams: int = 4) -> Capture:
    """Noise-free capture of X (N, P, 3) at times (N,): image n seen by camera n mod num_streams."""
    n = X.shape[0]
    K, R, C = ring_cameras(CENTRE, num=num_streams)
    stream = np.arange(n) % num_streams
    return Capture(x=project(X, K[stream], R[stream], C[stream]), K=K[stream], R=R[stream],
                   C=C[stream], stream=stream, frame=np.arange(n) // num_streams)


def relative_error(X: np.ndarray, X_true: np.ndarray) -> float:
    return float(np.abs(X - X_true).max() / np.abs(X_true - CENTRE).max())


def test_trajectory_basis_exact_in_its_basis(rng) -> None:
    times = np.linspace(0.0, 2.0, 80)
    beta = 0.3 * rng.standard_normal((5, 6, 3))  # (P, K = 6, 3)
    X = CENTRE + np.einsum("nk,pkc->npc", dct_basis(times, 6), beta)
    cap = interleaved_capture(X, times)
    k, scores = select_num_bases(cap, times, max_bases=15)
    assert k == 6
    assert scores[4] > 1e3 * scores[5]
    assert relative_error(trajectory_basis(cap, times, max_bases=15), X) < 1e-6


def test_high_pass_exact_on_constant_velocity_and_static(rng) -> None:
    times = np.linspace(0.0, 1.0, 60)
    start = CENTRE + 0.3 * rng.standard_normal((4, 3))
    velocity = 0.5 * rng.standard_normal((4, 3))
    moving = start[None] + times[:, None, None] * velocity[None]
    cap = interleaved_capture(moving, times)
    cap.x[7, 1] = np.nan  # an unobserved point is interpolated exactly too
    assert relative_error(high_pass_filter(cap, times, degrees=(2,)), moving) < 1e-6
    # the first-difference filter penalises velocity: it cannot reproduce this motion
    assert relative_error(high_pass_filter(cap, times, degrees=(1,)), moving) > 1e-3
    static = np.broadcast_to(start, moving.shape).copy()
    X_static = high_pass_filter(interleaved_capture(static, times), times)
    assert relative_error(X_static, static) < 1e-6


def test_triangulate_instants_exact_on_concurrent_views(rng) -> None:
    instants = np.repeat(np.arange(10), 4)  # 4 cameras at each of 10 instants
    X = CENTRE + 0.4 * rng.standard_normal((10, 6, 3))
    cap = interleaved_capture(X[instants], instants.astype(float))
    cap.x[0, 2] = np.nan
    X_hat = triangulate_instants(cap, instants)
    assert relative_error(X_hat, X[instants]) < 1e-9
    # a point seen once at an instant is undetermined
    one = cap.subset(np.array([0, 1, 4, 5]))
    one.x[1, 3] = np.nan
    assert np.isnan(triangulate_instants(one, np.array([0, 0, 1, 1]))[:2, 3]).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_sedl_beats_pseudo_triangulation(seed) -> None:
    rng = np.random.default_rng(seed)
    times = np.sort(rng.uniform(0.0, 2.0, 120))
    phase = rng.uniform(0, 2 * np.pi, (8, 3))
    amp = rng.uniform(0.1, 0.4, (8, 3))
    X = CENTRE + amp * np.sin(2.0 * times[:, None, None] + phase)
    cap = interleaved_capture(X, times)
    err_init = np.linalg.norm(pseudo_triangulation(cap) - X, axis=2).mean()
    err_sedl = np.linalg.norm(sedl(cap) - X, axis=2).mean()
    assert err_sedl < 0.7 * err_init
