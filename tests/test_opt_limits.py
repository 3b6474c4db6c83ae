"""Hard limits of dtoc.optimize.limits: feasibility by construction, projection quality, errors."""

import numpy as np
import pytest
import torch

from dtoc.errors import LimitError
from dtoc.optimize.limits import EdgeProjector, Limits, edges_to_played, limit_violations, waveform_extremes
from dtoc.seq.ir import edges_to_fine

RASTER = 10e-6


def _random_problem(seed=0, n=400):
    rng = np.random.default_rng(seed)
    base = np.zeros((3, n + 1))
    # a fixed trapezoid on x at the start (within limits: 20 mT/m, 1 mT/m per raster = 100 T/m/s)
    base[0, :21] = np.minimum(np.arange(21), 20) * 1.0
    free = np.ones((3, n + 1), bool)
    free[:, :21] = False
    free[:, -1] = False  # waveform must end at 0
    y = rng.normal(0, 40, size=(3, n + 1))
    return base, free, y


def test_projection_meets_limits_exactly_and_keeps_fixed():
    base, free, y = _random_problem()
    lim = Limits(25.0, 150.0)
    P = EdgeProjector(base, free, RASTER, lim)
    x = P.project(y)
    assert np.array_equal(x[~free], base[~free])
    assert np.abs(x).max() <= lim.gmax_eff_mT_per_m + 1e-12
    assert np.abs(np.diff(x, axis=1)).max() <= lim.step_max_mT_per_m(RASTER) + 1e-12
    fine = edges_to_played(x, edges_to_fine(base), P.fine_free_mask())
    assert limit_violations(fine, RASTER / 2, lim) == []
    ex = waveform_extremes(fine, RASTER / 2)
    assert max(ex["smax_T_per_m_per_s"]) <= 150.0 * (1 - 0.01) + 1e-6


def test_projection_is_identity_on_feasible_and_near_euclidean():
    base, free, _ = _random_problem(1)
    lim = Limits(25.0, 150.0)
    P = EdgeProjector(base, free, RASTER, lim)
    rng = np.random.default_rng(3)
    z = P.project(rng.normal(0, 5, size=base.shape))  # a feasible point
    assert np.allclose(P.project(z), z, atol=1e-12)
    # small perturbation of a strictly interior feasible point: projection returns it (up to tiny)
    y = z + np.where(free, 0.001, 0.0)
    x = P.project(y, n_iter=200)
    # Euclidean-projection optimality: for any feasible w, <y - x, w - x> <= ~0
    for s in range(5):
        w = P.project(np.random.default_rng(10 + s).normal(0, 10, size=base.shape))
        assert np.sum((y - x) * (w - x)) <= 1e-3 * np.linalg.norm(y - x) * np.linalg.norm(w - x) + 1e-9


def test_projection_of_amplitude_violation_is_clipping():
    base = np.zeros((3, 11))
    free = np.ones_like(base, bool)
    lim = Limits(10.0, 1e6, amp_margin=0.0, slew_margin=0.0)
    P = EdgeProjector(base, free, RASTER, lim)
    y = np.linspace(-20, 20, 11)[None].repeat(3, 0)
    assert np.allclose(P.project(y), np.clip(y, -10, 10))


def test_slew_projection_pair_is_symmetric():
    base = np.zeros((3, 2))
    free = np.ones_like(base, bool)
    lim = Limits(100.0, 100.0, amp_margin=0.0, slew_margin=0.0)  # 1 mT/m per raster
    P = EdgeProjector(base, free, RASTER, lim)
    x = P.project(np.array([[0.0, 3.0]] * 3))
    assert np.allclose(x, [[1.0, 2.0]] * 3, atol=1e-9)


def test_torch_in_torch_out():
    base, free, y = _random_problem(2)
    P = EdgeProjector(base, free, RASTER, Limits(25.0, 150.0))
    xt = P.project(torch.tensor(y, dtype=torch.float32))
    assert isinstance(xt, torch.Tensor) and xt.dtype == torch.float32
    assert np.allclose(xt.numpy(), P.project(y), atol=1e-4)


def test_fixed_sample_beyond_gmax_raises():
    base, free, _ = _random_problem()
    with pytest.raises(LimitError, match="beyond gmax"):
        EdgeProjector(base, free, RASTER, Limits(15.0, 150.0))


def test_fixed_segment_beyond_slew_raises():
    base, free, _ = _random_problem()
    with pytest.raises(LimitError, match="smax"):
        EdgeProjector(base, free, RASTER, Limits(25.0, 50.0))


def test_unreachable_between_fixed_samples_raises():
    # +10 then -10 mT/m fixed, 2 rasters apart: needs 10 mT/m per raster = 1000 T/m/s
    base = np.zeros((3, 5))
    base[0, 0], base[0, 4] = 10.0, -10.0
    free = np.ones_like(base, bool)
    free[:, 0] = free[:, 4] = False
    with pytest.raises(LimitError, match="no waveform"):
        EdgeProjector(base, free, RASTER, Limits(20.0, 400.0))
    EdgeProjector(base, free, RASTER, Limits(20.0, 600.0))  # 5 mT/m per raster: reachable


def test_bad_limits_raise():
    with pytest.raises(LimitError):
        Limits(0.0, 100.0)
    with pytest.raises(LimitError):
        Limits(10.0, float("nan"))


def test_gmax_below_readout_amplitude_is_impossible():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from opt_synth import gre_ir

    from dtoc.optimize.limits import check_area_reachable

    ir = gre_ir(8, reps=2)  # readout 7.34 mT/m (one dk per 0.1 ms dwell at FOV 32 mm)
    check_area_reachable(ir, Limits(7.5, 500.0))
    with pytest.raises(LimitError, match="7.34"):
        check_area_reachable(ir, Limits(7.0, 500.0))


@pytest.mark.parametrize("n", [0, 1, 2, 4095, 4096, 4097, 8193, 20_000])
def test_waveform_extremes_by_pieces_are_the_whole_arrays(monkeypatch, n):
    """A long waveform's peak amplitude and slew are read in pieces overlapping by one sample (no whole-length
    temporaries): the same maxima as the whole arrays', a step across a piece border included."""
    import dtoc.optimize.limits as lim

    rng = np.random.default_rng(n)
    g = rng.normal(size=(3, n)) * 10
    if n > 4097:
        g[1, 4096] = 90.0  # the largest value and (with its neighbours) the largest steps, at a piece border
    dt = RASTER / 2
    amp = np.abs(g).max(axis=-1) if n else np.zeros(3)
    slew = np.abs(np.diff(g, axis=-1)).max(axis=-1) / dt * 1e-3 if n > 1 else np.zeros(3)
    monkeypatch.setattr(lim, "EXTREMES_CHUNK", 4096)
    ex = waveform_extremes(g, dt)
    assert ex["gmax_mT_per_m"] == amp.tolist() and ex["smax_T_per_m_per_s"] == slew.tolist()
