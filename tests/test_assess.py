"""Per-image status and reconstructability (core.assess): a corrupted image is flagged and left out
of the exports, a clean capture flags nothing, near-parallel rays determine a depth worse."""

from __future__ import annotations

import csv
from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp
from scenes import toy_capture

from dloe_sfm import reconstruct
from dloe_sfm.core.assess import (
    BLOCK,
    assess,
    depth_variances,
    gap_ratio,
    inverse_diagonals,
    neighbour_deviation,
)
from dloe_sfm.core.clocks import time_chain
from dloe_sfm.core.options import Options, RobustLoss
from dloe_sfm.core.steps import smoothness_matrix
from dloe_sfm.io import CHECK_KEYS, load_result, save_result
from dloe_sfm.synth.mocap import SimulationSettings, load_mocap, simulate


@pytest.fixture(scope="module")
def walking(assets_dir):
    seq = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    return simulate(seq, SimulationSettings(duration=1.0)).capture.validate()


def test_clean_capture_flags_nothing(walking):
    r = reconstruct(walking)
    assert (r.image_status == "ok").all(), r.status_reason[r.image_status != "ok"]
    assert r.supported.all()
    assert r.depth_sd.shape == walking.x.shape[:2] and np.isfinite(r.depth_sd).all()


def test_corrupted_image_flagged_and_left_out_of_exports(walking, tmp_path):
    from dloe_sfm.export import write_outputs

    bad = 20
    C = walking.C.copy()
    C[bad] += [0.6, 0.0, 0.3]  # the camera pose of one image 0.67 m off
    cap = replace(walking, C=C)
    r = reconstruct(cap, Options(robust_loss=RobustLoss.NONE))
    flagged = np.flatnonzero(r.image_status == "inconsistent")
    assert bad in flagged and flagged.size <= 4, r.status_reason[flagged]
    assert not r.supported[bad].any()
    report = write_outputs(tmp_path, cap, r)
    name = str(cap.image_names[bad])
    assert report["image_checks"][name]["status"] == "inconsistent"
    assert name in report["image_status"]["flagged"]
    with np.load(tmp_path / "trajectories.npz") as npz:
        assert np.isnan(npz["X"][bad]).all()
        assert (npz["image_status"][bad] == "inconsistent")
    ok = np.flatnonzero(r.image_status == "ok")[0]
    assert np.isfinite(np.load(tmp_path / "trajectories.npz")["X"][ok]).all()
    assert len(list((tmp_path / "frames").glob("*.ply"))) == cap.num_images - flagged.size
    with open(tmp_path / "trajectories_wide.csv") as f:
        rows = {row["image"]: row for row in csv.DictReader(f)}
    coords = [k for k in rows[name] if k[-2:] in ("_x", "_y", "_z")]
    assert all(rows[name][k] == "" for k in coords)
    assert all(rows[str(cap.image_names[ok])][k] != "" for k in coords)


def test_near_parallel_rays_determine_depth_worse():
    # four images at one instant (W: every other image), point 0 seen by two images whose rays
    # are 1 degree apart, point 1 by two images whose rays are 90 degrees apart
    n = 4
    W = sp.csr_matrix((np.ones((n, n)) - np.eye(n)) / (n - 1))
    Q = smoothness_matrix(W, np.ones(n), 1e-5)
    rays = np.full((n, 2, 3), np.nan)
    a = np.deg2rad(1.0)
    rays[0, 0], rays[1, 0] = [0, 0, 1], [np.sin(a), 0, np.cos(a)]
    rays[0, 1], rays[1, 1] = [0, 0, 1], [1, 0, 0]
    observed = np.isfinite(rays).all(axis=2)
    var = depth_variances(Q, rays, observed)
    assert var[0, 0] > 100 * var[0, 1] and var[1, 0] > 100 * var[1, 1]
    assert np.isfinite(var).all()


def test_checks_round_trip_through_the_result_file(tmp_path):
    capture, result, _ = toy_capture()
    checked = assess(capture, result, lambda1=1e-5)
    loaded = load_result(save_result(tmp_path / "result.npz", checked))
    for key in CHECK_KEYS:
        assert np.array_equal(getattr(loaded, key), getattr(checked, key), equal_nan=key not in
                              ("image_status", "status_reason", "supported")), key
    assert loaded.supported.dtype == bool


def random_band(m: int, width: int, rng: np.random.Generator) -> sp.csr_matrix:
    """A random SPD matrix of bandwidth ``width``: ``B B^T`` plus a ridge, B lower-banded."""
    B = sp.diags([rng.uniform(0.5, 2.0, m)] + [rng.standard_normal(m - k)
                                                for k in range(1, width + 1)],
                 list(range(0, -width - 1, -1)), shape=(m, m))
    return sp.csr_matrix(B @ B.T + 1e-3 * sp.identity(m))


def dense_diagonal(H: sp.spmatrix) -> np.ndarray:
    return np.diag(np.linalg.inv(H.toarray()))


def test_inverse_diagonal_is_exact(rng):
    # a random sparse SPD matrix spanning many blocks, in scrambled order
    m = 40 * BLOCK + 57
    A = sp.random(m, m, density=3.0 / m, random_state=1) + sp.diags(np.ones(m - 1), 1)
    H = sp.csr_matrix(A @ A.T + 0.1 * sp.identity(m))
    perm = rng.permutation(m)
    H = H[perm][:, perm]
    assert np.allclose(inverse_diagonals([H])[0], dense_diagonal(H), rtol=1e-10)


@pytest.mark.parametrize("width", [0, 1, 2, BLOCK - 1, BLOCK, BLOCK + 1, 3 * BLOCK])
def test_selected_inversion_matches_the_dense_inverse_on_a_band(width, rng):
    m = 300
    H = random_band(m, width, rng)
    assert np.allclose(inverse_diagonals([H])[0], dense_diagonal(H), rtol=1e-10, atol=0)
    # the same band scrambled: reverse Cuthill-McKee recovers it
    perm = rng.permutation(m)
    scrambled = H[perm][:, perm]
    assert np.allclose(inverse_diagonals([scrambled])[0], dense_diagonal(scrambled), rtol=1e-10,
                       atol=0)


def test_lockstep_matrices_of_any_size_and_width_singular_ones_inf(rng, monkeypatch):
    monkeypatch.setattr("dloe_sfm.core.assess.CHUNK", 500)  # several chunks of blocks
    sizes = [(1, 0), (5, 2), (BLOCK, 1), (97, 3 * BLOCK), (400, 4), (401, BLOCK + 1)]
    matrices = [random_band(m, w, rng) for m, w in sizes]
    matrices.insert(2, sp.csr_matrix(np.ones((4, 4))))  # rank 1
    diags = inverse_diagonals(matrices)
    assert np.isinf(diags[2]).all()
    for H, diag in zip(matrices[:2] + matrices[3:], diags[:2] + diags[3:], strict=True):
        assert np.allclose(diag, dense_diagonal(H), rtol=1e-10, atol=0)


def test_neighbour_deviation_of_some_rows_equals_theirs_among_all(rng):
    # the flagging loop re-predicts only the images that use a newly flagged one
    n = 60
    W = sp.random(n, n, density=0.1, random_state=2, format="csr")
    W.setdiag(0)
    W.eliminate_zeros()
    X = rng.standard_normal((n, 5, 3))
    observed = rng.random((n, 5)) > 0.3
    excluded = rng.random(n) > 0.8
    excluded[W[0].indices] = True  # image 0 has no neighbour left
    rows = np.append(rng.choice(np.arange(1, n), 17, replace=False), 0)
    every = neighbour_deviation(X, W, observed, excluded, np.arange(n))
    assert np.isnan(every).any() and np.isfinite(every).any()
    assert np.array_equal(neighbour_deviation(X, W, observed, excluded, rows), every[rows],
                          equal_nan=True)


def test_an_end_far_from_its_neighbour_in_time_reaches_that_far():
    """The time line's first image, 5 intervals before the next (as a camera that starts alone):
    its chain row copies that neighbour, so its deviation is judged in steps 5 times as long
    (the bundled field workspace's first frame, 60 ms before any other camera's, was flagged
    inconsistent at 3.5 steps with nothing wrong: 13.9 mm against a 10.7 mm median)."""
    t = np.array([0.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0])
    W, _ = time_chain(t[::-1])
    ratio = gap_ratio(t[::-1], W)
    np.testing.assert_allclose(ratio[::-1], [5.0, 5 / 3, 1.0, 1.0, 1.0, 1.0, 1.0])
    assert np.array_equal(gap_ratio(t, sp.csr_matrix((7, 7))), np.ones(7))
