"""Stream offsets (``core.bias``): a detector's constant offset of each point in each video,
estimated against the points' prediction along the clocks and taken out before they are fitted
again."""

from dataclasses import replace

import numpy as np
import pytest

from dloe_sfm.core.bias import stream_offsets, without_offsets
from dloe_sfm.core.capture import Capture, project
from dloe_sfm.core.decisions import OFFSET_GAIN
from dloe_sfm.core.options import Options
from dloe_sfm.core.solver import reconstruct
from dloe_sfm.synth import SimulationSettings, load_mocap
from dloe_sfm.synth.scenarios import simulate_people


@pytest.fixture(scope="module")
def walking(assets_dir):
    """2 s of walking_1 at 4 x 15 Hz, exact detections: the capture and the true shapes."""
    clip = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    cap, truth = simulate_people([clip], SimulationSettings(duration=2.0, rate=15),
                                 shuffle=False)
    cap = Capture(x=cap.x[:, 0], K=cap.K, R=cap.R, C=cap.C, stream=cap.stream, frame=cap.frame)
    return cap, truth.X[:, 0], truth.t


def offset(cap: Capture, px: float, seed: int = 0) -> np.ndarray:
    """(N, P, 2) a random constant offset per (stream, point), ``px`` per coordinate."""
    rng = np.random.default_rng(seed)
    return rng.normal(0.0, px, (cap.stream.max() + 1, cap.num_points, 2))[cap.stream]


def test_offsets_are_found_up_to_a_shift_of_the_point(walking):
    """Exact predictions: the offsets of every stream come back but for what one 3D shift of
    the point explains (its image motion, left to the point), and they predict the frames
    they were not estimated on to nothing."""
    cap, X, _ = walking
    true = offset(cap, 4.0)
    bad = replace(cap, x=cap.x + true)
    none = np.zeros(cap.x.shape[:2], dtype=bool)
    found, before, after = stream_offsets(bad, X, none)
    assert after < 0.02 * before
    vis = cap.visible
    assert np.corrcoef(found[vis].ravel(), true[vis].ravel())[0, 1] > 0.7
    rest = true - found  # the image motion of one small shift of each point
    for k in range(cap.num_points):
        seen = vis[:, k]
        J = np.stack([project_shifted(cap, X, k, e)[seen] - cap.x[seen, k] for e in np.eye(3)],
                     axis=-1) / 1e-4  # (M, 2, 3) pixels per metre
        left, kept = rest[seen, k], found[seen, k]
        assert np.abs(shift_motion(J, left) - left).max() < 0.2  # what is left is a shift...
        assert np.abs(shift_motion(J, kept)).max() < 0.2  # ...and nothing of the offsets is


def shift_motion(J: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(M, 2) the image motion ``J delta`` of the 3D shift that best explains ``values``."""
    return J @ np.linalg.lstsq(J.reshape(-1, 3), values.ravel(), rcond=None)[0]


def project_shifted(cap: Capture, X: np.ndarray, k: int, e: np.ndarray) -> np.ndarray:
    """(N, 2) point k projected after a 0.1 mm shift along ``e``."""
    return project(X + 1e-4 * e * (np.arange(X.shape[1]) == k)[None, :, None], cap.K, cap.R,
                   cap.C)[:, k]


def test_noise_does_not_pass_for_offsets(walking):
    """Independent detection noise (2 px) and no offset: estimated on every other frame, the
    medians do not predict the frames in between (``decisions.OFFSET_GAIN`` refuses them)."""
    cap, X, _ = walking
    noisy = replace(cap, x=cap.x + np.random.default_rng(2).normal(0.0, 2.0, cap.x.shape))
    _, before, after = stream_offsets(noisy, X, np.zeros(cap.x.shape[:2], dtype=bool))
    assert after > OFFSET_GAIN * before


def test_offsets_are_taken_out_before_the_clocks(walking):
    """Exact detections with a 4 px offset per (stream, point), default options: the offsets
    are found and taken out (``Result.offset_px``, ``solved``), and the clocks come out at
    under 0.6 of the timing error (0.53: 0.73 against 1.37 ms RMS) and the points closer to
    the truth than with the detections as they are (``stream_offsets = false``)."""
    cap, X, t = walking
    true = offset(cap, 4.0)
    bad = replace(cap, x=cap.x + true)

    def scores(r):
        fit = np.polyval(np.polyfit(r.clock, t, 1), r.clock)
        return (float(np.sqrt(np.mean((fit - t) ** 2))),
                float(np.linalg.norm(r.X - X, axis=-1).mean()))

    plain = reconstruct(bad, Options(stream_offsets=False))
    r = reconstruct(bad)
    assert plain.offset_px is None and r.offset_px is not None
    assert np.allclose(r.solved.x[cap.visible], without_offsets(bad, r.offset_px).x[cap.visible])
    (time_plain, error_plain), (time_r, error_r) = scores(plain), scores(r)
    assert time_r < 0.6 * time_plain
    assert error_r < 0.95 * error_plain
