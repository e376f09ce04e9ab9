"""The simulator: mixed frame rates, random start times and the detector error model."""

import argparse

import numpy as np
import pytest
from scipy import stats

from dloe_sfm.core.capture import project
from dloe_sfm.errors import InputError
from dloe_sfm.stages import simulate as simulate_stage
from dloe_sfm.synth import SimulationSettings, load_mocap, ring_cameras, simulate
from dloe_sfm.synth.detector import DetectorModel
from dloe_sfm.synth.mocap import _interpolate, _ring_radius, _window
from dloe_sfm.synth.scenarios import add_false_detections, limit_presence, simulate_people

RATES = (24.0, 25.0, 29.97, 30.0)


@pytest.fixture(scope="module")
def jumping(assets_dir):
    return load_mocap(assets_dir / "mocap" / "jumping_1.npz")


@pytest.mark.parametrize("random_offsets", [False, True])
def test_mixed_rates_sample_every_stream_at_its_own_rate(jumping, random_offsets):
    s = SimulationSettings(rates=RATES, random_offsets=random_offsets, duration=2.0, start=0.5,
                           seed=4)
    capture, truth = simulate(jumping, s)
    pos = _window(jumping, s)
    span = (pos.shape[0] - 1) / jumping.fps  # seconds of motion
    first = round(s.start * jumping.fps) / jumping.fps
    starts = []
    for k, rate in enumerate(RATES):
        mine = capture.stream == k
        t = truth.t[mine] - first
        starts.append(t[0])
        assert np.array_equal(capture.frame[mine], np.arange(mine.sum()))
        np.testing.assert_allclose(np.diff(t), 1 / rate, rtol=1e-9)
        assert 0 <= t[0] < 1 / rate and t[-1] <= span + 1e-9 < t[-1] + 1 / rate
        if not random_offsets:
            assert t[0] == pytest.approx(k / (rate * len(RATES)))
    if random_offsets:
        assert not np.allclose(starts, [k / (r * 4) for k, r in enumerate(RATES)])
    # the truth is the motion interpolated at the true instants
    frames = truth.t * jumping.fps - round(s.start * jumping.fps)
    np.testing.assert_allclose(truth.X, _interpolate(pos, frames), atol=1e-12)


def test_default_settings_are_the_staggered_common_rate(jumping):
    """Default settings: 4 x 30 Hz, starts k/4 of a period apart, then Gaussian noise drawn
    first from the seed's generator (the construction every earlier result was made with)."""
    s = SimulationSettings(duration=1.0, noise=1.5, seed=7)
    capture, truth = simulate(jumping, s)
    pos = _window(jumping, s)
    period, span = jumping.fps / 30.0, pos.shape[0] - 1
    times = [k * period / 4 + period * np.arange(int(span / period) + 1) for k in range(4)]
    times = [t[t <= span] for t in times]
    t = np.concatenate(times)
    stream = np.repeat(np.arange(4), [v.size for v in times])
    assert np.array_equal(capture.stream, stream)
    assert np.array_equal(truth.t, t / jumping.fps)
    centre = pos.reshape(-1, 3).mean(axis=0)
    K, R, C = ring_cameras(centre, radius=_ring_radius(s, pos.reshape(-1, 3), centre))
    X = _interpolate(pos, t)
    x_clean = project(X, K[stream], R[stream], C[stream])
    noise = 1.5 * np.random.default_rng(7).standard_normal(x_clean.shape)
    assert np.array_equal(capture.x, x_clean + noise)
    assert capture.confidence is None and truth.swaps is None and truth.outliers is None


def test_detector_model_reproduces_the_fitted_statistics(jumping):
    model = DetectorModel.load("openpose")
    real = model.figures["relative_error"]
    errors, scores, missing = [], [], []
    for seed in range(3):
        s = SimulationSettings(detector="openpose", rates=RATES, random_offsets=True, seed=seed,
                               duration=2.0)
        capture, truth = simulate(jumping, s)
        x_clean = truth.x_clean
        height = x_clean[..., 1].max(axis=1) - x_clean[..., 1].min(axis=1)
        error = np.linalg.norm(capture.x - x_clean, axis=-1) / height[:, None]
        seen = np.isfinite(error)
        assert np.all((capture.confidence[seen] > 0) & (capture.confidence[seen] <= 1))
        assert np.all(capture.confidence[~seen] == 0)
        assert truth.swaps.shape == (capture.num_images, len(capture.symmetric_pairs))
        assert truth.outliers[seen].any()
        errors.append(error[seen])
        scores.append(capture.confidence[seen])
        missing.append(~seen)
    error, score, missing = (np.concatenate([v.ravel() for v in a])
                             for a in (errors, scores, missing))
    assert error.size > 3000
    for name, q in (("median", 0.5), ("p90", 0.9), ("p99", 0.99)):
        assert np.quantile(error, q) == pytest.approx(real[name], rel=0.3), name
    assert missing.mean() == pytest.approx(model.miss_rate, abs=0.01)
    rho = stats.spearmanr(score, error).statistic
    assert np.sign(rho) == np.sign(model.figures["spearman_confidence_error"]) and abs(rho) > 0.1


@pytest.mark.parametrize("kwargs, flag", [
    ({"rates": (24.0, 25.0)}, "--rates"),
    ({"rates": (24.0, 0.0, 30.0, 30.0)}, "--rates"),
    ({"rates": (24.0, float("nan"), 30.0, 30.0)}, "--rates"),
    ({"random_offsets": 1}, "--random-offsets"),
    ({"detector": "alphapose"}, "--detector"),
    ({"detector": "openpose", "noise": 2.0}, "--detector"),
])
def test_invalid_settings_name_the_flag(kwargs, flag):
    with pytest.raises(InputError) as e:
        SimulationSettings(**kwargs)
    message = str(e.value)
    assert message.startswith(flag + " ") and "\n" not in message


def test_cli_flags(jumping, assets_dir, tmp_path):
    parser = argparse.ArgumentParser()
    simulate_stage.configure_parser(parser)
    out = tmp_path / "capture.npz"
    args = parser.parse_args([str(assets_dir / "mocap" / "jumping_1.npz"), "--out", str(out),
                              "--rates", "24", "25", "29.97", "30", "--random-offsets",
                              "--detector", "openpose", "--duration", "1"])
    assert simulate_stage.run(args) == 0
    with np.load(out) as saved:
        assert {"swap_true", "outlier_true", "confidence"} <= set(saved.files)


def test_people_shuffle_keeps_scores_and_truth_with_their_detections(jumping, assets_dir):
    """With the detector model the confidence and the true outliers / swaps follow the
    shuffled detection slots (the render before the shuffle is the same either way)."""
    walking = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    s = SimulationSettings(detector="openpose", duration=0.5, seed=3)
    (cap, truth), (ref, ref_truth) = (
        simulate_people([jumping, walking], s, shuffle=shuffle) for shuffle in (True, False)
    )
    slots = truth.subjects
    assert (slots != ref_truth.subjects).any()
    rows = np.arange(cap.num_images)[:, None]
    np.testing.assert_array_equal(cap.x, ref.x[rows, slots])
    np.testing.assert_array_equal(cap.confidence, ref.confidence[rows, slots])
    for name in ("x_clean", "outliers", "swaps"):
        np.testing.assert_array_equal(getattr(truth, name), getattr(ref_truth, name)[rows, slots])


@pytest.mark.filterwarnings("ignore:Mean of empty slice", "ignore:Degrees of freedom",
                            "ignore:All-NaN slice")
def test_a_late_person_and_false_detections_keep_their_truth(jumping, assets_dir):
    """``limit_presence`` removes a person's detections outside its interval (truth -1 there);
    ``add_false_detections`` adds a slot holding, in about the asked share of images, another
    image's detection moved 50-200 px, with truth -1 and no clean projection."""
    walking = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    cap, truth = simulate_people([jumping, walking], SimulationSettings(duration=1.0, seed=2))
    late, late_truth = limit_presence(cap, truth, 1, 0.3, 0.7)
    inside = (truth.t >= 0.3) & (truth.t <= 0.7)
    assert 0 < inside.sum() < cap.num_images
    assert ((late_truth.subjects == 1).any(axis=1) == inside).all()
    assert (late.visible.any(axis=2) == (late_truth.subjects >= 0)).all()
    more, more_truth = add_false_detections(late, late_truth, 0.25, seed=1)
    n = cap.num_images
    assert more.x.shape[1] == 3 and more_truth.subjects.shape == (n, 3)
    false = np.flatnonzero(more.visible[:, 2].any(axis=1))
    assert 0.1 * n < false.size < 0.4 * n and (more_truth.subjects[:, 2] == -1).all()
    assert np.isnan(more_truth.x_clean[:, 2]).all()
    np.testing.assert_array_equal(more.x[:, :2], late.x)
    for i in false:  # a real detection of another image (another instant), moved as a whole
        d = late.x - more.x[i, 2]
        spread = np.nanmax(np.nanstd(d, axis=2), axis=-1)
        src = np.unravel_index(np.nanargmin(spread), spread.shape)
        assert spread[src] < 1e-9 and src[0] != i
        assert 50 <= np.linalg.norm(np.nanmean(d[src], axis=0)) <= 200


def test_a_walker_turned_back_crosses_the_other(assets_dir):
    """``simulate_people``'s ``turns``: a person's motion turned about the vertical through its
    centre, rigidly (every bone length kept); a walk turned by pi comes back the other way, so
    two walkers 0.6 m apart pass each other, their centres within 0.7 m mid-way."""
    walking = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    settings = SimulationSettings(duration=3.0)
    _, straight = simulate_people([walking, walking], settings, spacing=0.6, shuffle=False)
    _, crossed = simulate_people([walking, walking], settings, spacing=0.6, shuffle=False,
                                 turns=(0.0, np.pi))
    np.testing.assert_allclose(crossed.X[:, 0], straight.X[:, 0])
    bones = [np.linalg.norm(t.X[:, 1, 1:] - t.X[:, 1, t.parents[1:]], axis=-1)
             for t in (straight, crossed)]
    np.testing.assert_allclose(bones[1], bones[0], atol=1e-12)
    centres = crossed.X.mean(axis=2)  # (N, 2, 3)
    along = np.diff(centres[[0, -1]], axis=0)[0, :, 2]  # each walker's way along z
    assert along[0] > 2.0 and along[1] < -2.0
    gap = np.linalg.norm(centres[:, 0] - centres[:, 1], axis=-1)
    assert gap.min() < 0.7 and gap.max() > 2.5
    with pytest.raises(InputError, match="turns"):
        simulate_people([walking, walking], settings, turns=(0.0,))


def test_cli_refuses_swaps_with_the_detector(assets_dir, tmp_path):
    with pytest.raises(InputError, match="--detector"):
        simulate_stage.main(assets_dir / "mocap" / "jumping_1.npz", tmp_path / "c.npz",
                            SimulationSettings(detector="openpose"), swaps=0.1)
    assert not (tmp_path / "c.npz").exists()


def test_lone_photos_and_bursts_come_from_handheld_cameras_all_around(jumping):
    """The crowd mode: lone photos (stream -1, no frame rate) and bursts of 2-5 frames at one
    period in 0.1-1 s, each from its own camera around the motion, every point in front of it
    and the person mostly in the picture; the ring's streams are drawn as without them."""
    s = SimulationSettings(num_streams=2, lone_photos=40, bursts=6, duration=2.0, seed=3)
    capture, truth = simulate(jumping, s)
    lone = capture.stream == -1
    assert lone.sum() == 40 and np.isnan(capture.fps[lone]).all()
    ring = np.isin(capture.stream, [0, 1])
    assert np.isfinite(capture.fps[ring]).all()
    plain, plain_truth = simulate(jumping, SimulationSettings(num_streams=2, duration=2.0, seed=3))
    np.testing.assert_array_equal(truth.t[ring], plain_truth.t)
    for b in range(2, 8):
        mine = capture.stream == b
        assert 2 <= mine.sum() <= 5 and np.isnan(capture.fps[mine]).all()
        gaps = np.diff(truth.t[mine][np.argsort(capture.frame[mine])])
        np.testing.assert_allclose(gaps, gaps[0], rtol=1e-9)
        assert 0.1 - 1e-9 <= gaps[0] <= 1.0 + 1e-9
    hand = ~ring
    centres = {tuple(c) for c in capture.C[hand].round(9)}
    assert len(centres) == 40 + 6  # one camera per photo and per burst
    assert len({float(k) for k in capture.K[lone, 0, 0]}) == 40
    depth = np.einsum("nk,npk->np", capture.R[:, 2], truth.X - capture.C[:, None, :])
    assert (depth > 0).all()
    inside = ((capture.x >= 0) & (capture.x <= s.image_size)).all(axis=2)
    assert inside[hand].mean() > 0.95
    yaw = np.arctan2(capture.C[lone, 0], capture.C[lone, 2])
    assert np.ptp(np.unwrap(np.sort(yaw))) > np.pi  # all around, not on one side
