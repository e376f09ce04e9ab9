"""Speed work that must not change a result: the X-step's soft-ray systems assembled entry by
entry equal the sparse products they replace bit for bit, so does the sequencing's Theil-Sen
line scipy's, and the runtime suite's stage meter times a solve without touching it."""

import numpy as np
import scipy.sparse as sp
from scipy.stats import theilslopes

from dloe_sfm.benchmark.jobs import StageMeter
from dloe_sfm.benchmark.suites import STAGES
from dloe_sfm.core import alternation, pipeline
from dloe_sfm.core.options import Options
from dloe_sfm.core.sequencing import theil_sen
from dloe_sfm.core.solver import reconstruct
from dloe_sfm.core.xstep import _soft_system
from dloe_sfm.synth import SimulationSettings, load_mocap, simulate


def _sparse_products(Q, r, C, wgt, reg):
    """The soft-ray system as the X-step built it from sparse sums and products."""
    P_perp = np.eye(3)[None] - r[:, :, None] * r[:, None, :]
    ray_term = sp.block_diag(list(wgt[:, None, None] * P_perp), format="csr")
    H = sp.csc_matrix(sp.kron(Q, sp.identity(3), format="csr") + ray_term)
    H = sp.csc_matrix(H + reg * sp.identity(H.shape[0], format="csc"))
    return H, ray_term @ C.ravel()


def test_soft_system_is_bit_identical(rng) -> None:
    n = 40
    A = sp.random(n, n, density=0.15, format="csr", random_state=rng)
    Q = sp.csr_matrix(A @ A.T + sp.diags(rng.random(n)))
    Q.data[::7] = 0.0  # a few exact zeros, as cancellation can leave
    Q = sp.csr_matrix(Q + sp.csr_matrix((n, n)))
    r = rng.normal(size=(n, 3))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    r[::5] = 0.0  # unobserved: NaN rays become zeros
    r[3, 1] = 0.0
    C = rng.normal(size=(n, 3))
    wgt = 1e4 * rng.random(n)
    wgt[::5] = 0.0
    for reg in (1e-12, 0.0):
        H, rhs = _soft_system(Q, r, C, wgt, reg)
        H_ref, rhs_ref = _sparse_products(Q, r, C, wgt, reg)
        H.sum_duplicates()
        H_ref.sum_duplicates()
        assert np.array_equal(H.indptr, H_ref.indptr)
        assert np.array_equal(H.indices, H_ref.indices)
        assert np.array_equal(H.data, H_ref.data)
        assert np.array_equal(rhs, rhs_ref)
        assert np.array_equal(np.signbit(rhs), np.signbit(rhs_ref))


def test_theil_sen_line_is_scipys(rng) -> None:
    """The line of every stream pair's frame mapping, on as few points as a short stream has
    and as many as the sequencing takes, with ties in the slopes and the values."""
    for size in (2, 3, 8, 57, 256):
        for _ in range(20):
            x = np.sort(rng.choice(4 * size, size, replace=False)).astype(float)
            y = 1.7 * x + 4.0 * rng.standard_t(2, size)
            y[rng.random(size) < 0.2] = np.round(y[0])
            slope, intercept, *_ = theilslopes(y, x)
            assert theil_sen(x, y) == (slope, intercept)


def test_stage_meter_times_every_stage_and_changes_nothing(assets_dir) -> None:
    walk = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    capture, _ = simulate(walk, SimulationSettings(duration=0.6, rate=10, noise=1.0))
    options = Options(max_iterations=8, soft_iterations=4)
    plain = reconstruct(capture, options)
    originals = (pipeline.solve_events, pipeline.clocks_and_offsets, alternation.sequence)
    with StageMeter() as meter:
        metered = reconstruct(capture, options)
    assert (pipeline.solve_events, pipeline.clocks_and_offsets, alternation.sequence) == originals
    assert np.array_equal(metered.X, plain.X)
    assert np.array_equal(metered.order, plain.order)
    assert tuple(meter.seconds) == STAGES
    assert all(v >= 0 for v in meter.seconds.values())
    assert meter.seconds["alternation"] > 0 and meter.seconds["sequencing"] > 0
    # the assessment follows the solve (outside Result.seconds); nothing is exported here
    assert meter.seconds["assess"] > 0 and meter.seconds["export"] == 0
    solve = sum(v for k, v in meter.seconds.items() if k not in ("assess", "export"))
    assert solve <= metered.seconds + 0.05
