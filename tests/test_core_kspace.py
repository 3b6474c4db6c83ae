"""The IR's exact piecewise-linear integration and k-space conventions."""

import numpy as np
import pytest
import torch

from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
from dtoc.seq.ir import ADCEvent, RFEvent, SequenceIR, edges_to_fine
from dtoc.seq.kspace import kspace_at, pwl_cumulative, pwl_integral_at


def _dense_integral(g, dt, t, oversample=2000):
    """Reference: integrate the linearly interpolated waveform on a very fine grid."""
    tt = np.linspace(0, t, int(oversample * max(t / dt, 1)) + 1)
    gg = np.interp(tt, np.arange(len(g)) * dt, g)
    return np.trapezoid(gg, tt)


def test_pwl_integral_matches_dense_reference():
    rng = np.random.default_rng(1)
    g = rng.normal(size=41)
    dt = 5e-6
    t = np.array([0.0, 3.3e-6, 5e-6, 17.2e-6, 99.99e-6, 200e-6])
    got = pwl_integral_at(g, dt, t).numpy()
    ref = np.array([_dense_integral(g, dt, ti) for ti in t])
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-12)


def test_trapezoid_area_exact_on_fine_grid():
    # 100 us ramp, 200 us flat, 100 us ramp at 10 mT/m on a 10 us raster: area 3e-3 mT/m*s... exactly.
    raster = 10e-6
    edges = np.concatenate([np.linspace(0, 10, 11), np.full(19, 10.0), np.linspace(10, 0, 11)])
    fine = edges_to_fine(edges)
    area = pwl_cumulative(fine, raster / 2)[-1].item()
    assert area == pytest.approx(10.0 * (200e-6 + 100e-6), rel=1e-12)


def test_kspace_resets_at_excitation_and_negates_at_refocusing():
    raster = 10e-6
    n = 100  # 1 ms
    g = np.zeros((3, 2 * n + 1))
    g[0, :] = 1.0  # constant 1 mT/m on x
    dt = raster / 2
    t = np.array([0.2e-3, 0.5e-3, 0.8e-3])
    k = kspace_at(g, dt, t, [0.1e-3, 0.4e-3, 0.6e-3], ["excitation", "excitation", "refocusing"]).numpy()
    # after 2nd excitation at 0.4 ms: 0.1 ms of gradient at 0.5 ms; refocused at 0.6 ms: -(0.2 ms) + 0.2 ms = 0 at 0.8 ms
    np.testing.assert_allclose(k[0], GAMMA_RAD_PER_S_PER_MT * np.array([0.1e-3, 0.1e-3, 0.0]), atol=1e-9)
    assert np.all(k[1:] == 0)


def test_kspace_is_differentiable():
    g = torch.zeros(3, 21, dtype=torch.float64, requires_grad=True)
    k = kspace_at(g, 5e-6, [60e-6])
    k[0, 0].backward()
    # d k / d g_m = gamma * trapezoid weights up to t = 60 us (12 fine steps)
    w = g.grad[0].numpy() / GAMMA_RAD_PER_S_PER_MT
    assert w.sum() == pytest.approx(60e-6, rel=1e-12)
    assert w[0] == pytest.approx(2.5e-6) and w[12] == pytest.approx(2.5e-6) and abs(w[13]) < 1e-20


def test_ir_nominal_kspace_and_shapes():
    raster = 10e-6
    edges = np.zeros((3, 101))
    edges[0, 10:90] = 5.0
    ir = SequenceIR(
        raster_s=raster,
        grad_mT_per_m=edges_to_fine(edges),
        block_edges_s=np.array([0.0, 1e-3]),
        rf=[RFEvent(0, 0.0, 0.0, 0.0, np.pi / 2, 0.0, 0.0, "excitation")],
        adc=[ADCEvent(0, 0.2e-3, 4, 10e-6)],
        fov_m=(0.25, 0.25, 0.005),
    )
    assert ir.n_fine == 201 and ir.duration_s == pytest.approx(1e-3)
    np.testing.assert_allclose(ir.adc_times_s, 0.2e-3 + (np.arange(4) + 0.5) * 10e-6)
    k = ir.nominal_kspace_rad_per_m()
    assert k.shape == (3, 4)
    # gradient on from 0.1 ms (edge 10) with a vertical step: PWL from edge 9 (0) to edge 10 (5) ramps over one raster
    t = ir.adc_times_s
    expected = GAMMA_RAD_PER_S_PER_MT * 5.0 * (t - 0.1e-3 + 0.5 * raster)
    np.testing.assert_allclose(k[0], expected, rtol=1e-12)
    assert ir.dk_rad_per_m[0] == pytest.approx(2 * np.pi / 0.25)
    with pytest.raises(ValueError):
        SequenceIR(raster_s=raster, grad_mT_per_m=np.zeros((3, 10)), block_edges_s=np.array([0, 1]))
