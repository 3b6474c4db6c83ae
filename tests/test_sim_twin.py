"""dtoc.sim.twin (the one forward model), dtoc.sim.imager and dtoc.seq.geometry."""

from pathlib import Path

import numpy as np
import pytest
import torch

from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
from dtoc.errors import InputError
from dtoc.hardware.model import HardwareModel, build_effect
from dtoc.seq.geometry import encoding_geometry
from dtoc.seq.load import load_sequence
from dtoc.sim.comparison import compare_ideal_realized
from dtoc.sim.imager import Imager
from dtoc.sim.pdg import simulate, steady_state_mz
from dtoc.sim.phantom import phantom_for
from dtoc.sim.twin import HardwareChain, Realization, Twin

SEQ = Path(__file__).resolve().parents[1] / "sequences"


@pytest.fixture(scope="module")
def epi():
    return load_sequence(SEQ / "epi_small.yaml")


def test_ideal_twin_plays_the_demanded_waveform(epi):
    r = Twin(epi, None).forward()
    assert isinstance(r, Realization)
    assert r.realized_grad_mT_per_m is r.demanded_grad_mT_per_m  # ideal: G is g itself
    assert r.b0_uT is None
    np.testing.assert_array_equal(r.kspace_rad_per_m.numpy(), epi.nominal_kspace_rad_per_m())
    assert r.moments_rad_per_m is None  # a single-shot EPI has one RF pulse


def test_a_readout_delay_shifts_k_by_gamma_g_tau(epi):
    """A pure delay tau of the readout axis: during the flat top of a readout line (gradient g), the
    realized k lags the nominal by gamma * g * tau exactly (the PWL waveform is shifted, not filtered)."""
    tau = 3e-6
    model = HardwareModel([build_effect("delay", {"seconds": tau}, axis="x")]).frozen()
    assert isinstance(model, HardwareChain)
    tw = Twin(epi, model)
    r = tw.forward()
    G, b0 = model(torch.as_tensor(epi.grad_mT_per_m)[None], epi.dt_fine_s)
    torch.testing.assert_close(r.realized_grad_mT_per_m, G[0], rtol=0, atol=0)
    torch.testing.assert_close(r.b0_uT, b0[0], rtol=0, atol=0)
    # middle sample of the middle line: the readout gradient is flat around it
    a = epi.adc[len(epi.adc) // 2]
    i0 = sum(e.num_samples for e in epi.adc[: len(epi.adc) // 2]) + a.num_samples // 2
    g_ro = float(np.interp(epi.adc_times_s[i0], epi.t_fine_s, epi.grad_mT_per_m[0]))
    assert abs(g_ro) > 1.0
    dk = float(r.kspace_rad_per_m[0, i0]) - float(epi.nominal_kspace_rad_per_m()[0, i0])
    assert dk == pytest.approx(-GAMMA_RAD_PER_S_PER_MT * g_ro * tau, rel=1e-9)
    assert float(r.kspace_rad_per_m[1, i0]) == pytest.approx(float(epi.nominal_kspace_rad_per_m()[1, i0]), abs=1e-9)


def test_forward_is_differentiable_in_the_demanded_waveform(epi):
    g = torch.as_tensor(epi.grad_mT_per_m).clone().requires_grad_(True)
    r = Twin(epi, HardwareModel([build_effect("gain", {"factor": 0.97}, axis="x")]).frozen()).forward(g)
    r.kspace_rad_per_m[0].sum().backward()
    assert g.grad is not None and float(g.grad[0].abs().sum()) > 0 and float(g.grad[1].abs().sum()) == 0


def test_simulate_with_dummies_is_the_manual_pipeline():
    """compare_ideal_realized = steady state (steady_state_mz's own defaults) + PDG + iFFT, bit for bit."""
    ir = load_sequence(SEQ / "gre_small.yaml")
    ph = phantom_for(ir, "brain")
    model = HardwareModel([build_effect("delay", {"seconds": 4e-6}, axis="x")]).frozen()
    res = compare_ideal_realized(ir, ph, model, n_dummies=5)
    mz0 = steady_state_mz(ir, ph, 5)
    G, b0 = model(torch.as_tensor(ir.grad_mT_per_m)[None], ir.dt_fine_s)
    im = Imager(ir, [ph], mz0=[mz0])
    img = im.image(simulate(ir, ph, G[0], b0[0], graph=im.graph, initial_mz=mz0)).abs()
    np.testing.assert_array_equal(res.realized_image, img.numpy())
    np.testing.assert_array_equal(res.ideal_image, im.targets[0].abs().numpy())
    assert res.metrics["nrmse"] > 1e-4  # a 4 us delay is visible (6e-4)


def test_geometry_orients_the_matrix_by_the_readout_axis():
    g = encoding_geometry((0.3, 0.2, 0.005), (96, 64), readout_axis=1)
    assert (g.readout_axis, g.phase_axis) == (1, 0)
    assert g.matrix_xy == (64, 96) and g.image_shape == (96, 64)
    assert g.voxel_m == pytest.approx((0.3 / 64, 0.2 / 96, None))
    assert g.dk_rad_per_m[:2] == pytest.approx((2 * np.pi / 0.3, 2 * np.pi / 0.2))
    assert g.phase_image_dim == -1 and g.in_plane
    assert encoding_geometry(None, (64, 64)) is None and encoding_geometry((0.2, 0.2, 0), (64,)) is None
    with pytest.raises(InputError):
        encoding_geometry((0.2, 0.2, 0.0), (64, 64), readout_axis=0, phase_axis=0)


def test_sequence_geometry_and_phantom_grid(epi):
    geo = epi.geometry
    assert geo.matrix_xy == (16, 16) and geo.fov_xy_m == pytest.approx((0.25, 0.25))
    ph = phantom_for(epi, "brain-noscalp")
    assert ph.shape == geo.image_shape and tuple(ph.fov_m) == pytest.approx(geo.fov_xy_m)
    assert phantom_for(epi, "brain", size=8).shape == (8, 8)
