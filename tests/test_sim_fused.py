"""The fused propagation (dtoc/sim/pdg_fused.py) against the per-interval one (dtoc/sim/pdg_evolve.py):
the same recursion, so the same amplitudes up to rounding."""

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from test_sim_physics import rich_phantom, small_gre  # noqa: E402

from dtoc.sim.pdg import PDGConfig
from dtoc.sim.pdg_main import main_loop, prepare


def test_final_state_of_a_dummy_train_equals_the_streaming_path():
    """The dummy train's final amplitudes (the GPU default; the CPU streams) equal the per-interval path to
    1e-12 of their maximum in float64, with diffusion, B0 and T2' in the phantom."""
    ir = small_gre(n_rep=6)
    ph = rich_phantom()
    out = []
    for fused in (True, False):
        with torch.no_grad():
            p = prepare(ir, ph, None, PDGConfig(), None, None, None, torch.float64, "cpu", final_z=True)
            _, A, K = main_loop(p, False, True, fused=fused)
        out.append((A.numpy(), K.numpy()))
    (A1, K1), (A0, K0) = out
    assert A1.shape == A0.shape and np.abs(A0).max() > 0
    assert np.abs(A1 - A0).max() < 1e-12 * np.abs(A0).max()
    assert np.array_equal(K1, K0)


def test_signal_and_gradient_equal_the_per_interval_propagation():
    """Signal (1e-12) and gradient w.r.t. the gradient waveform (1e-10, through the diffusion b-values)
    of the fused and the per-interval propagation, float64."""
    ir = small_gre(n_rep=6)
    ph = rich_phantom()
    res = []
    for fused in (True, False):
        g = torch.as_tensor(ir.grad_mT_per_m).clone().requires_grad_(True)
        p = prepare(ir, ph, None, PDGConfig(), g, None, None, torch.float64, "cpu")
        pieces, _, _ = main_loop(p, True, False, fused=fused)
        s = torch.cat([x for _, x in sorted(pieces, key=lambda t: t[0])], 1)
        (s.real**2 + s.imag**2).sum().backward()
        res.append((s.detach().numpy(), g.grad.numpy()))
    (s1, g1), (s0, g0) = res
    assert np.abs(g0).max() > 0
    assert np.abs(s1 - s0).max() < 1e-12 * np.abs(s0).max()
    assert np.abs(g1 - g0).max() < 1e-10 * np.abs(g0).max()


def test_batched_bucket_products_equal_the_per_block_products():
    """The 'batched' schedule (the GPU's: fused propagation, padded blocks, one batched product per bucket),
    selected on the CPU, equals the CPU's 'per_interval' schedule (block-by-block products): signal 1e-12,
    gradient 1e-10 (float64; B0, T2' and Taylor orders of the in-window diffusion present)."""
    from dtoc.sim.pdg import simulate

    ir = small_gre(n_rep=6)
    ph = rich_phantom()
    ph.d_m2_per_s = ph.d_m2_per_s * 100.0
    res = []
    for cfg in (PDGConfig(schedule="batched"), PDGConfig()):
        g = torch.as_tensor(ir.grad_mT_per_m).clone().requires_grad_(True)
        s = simulate(ir, ph, g, config=cfg)
        (s.real**2 + s.imag**2).sum().backward()
        res.append((s.detach().numpy(), g.grad.numpy()))
    (s1, g1), (s0, g0) = res
    assert np.abs(g0).max() > 0
    assert np.abs(s1 - s0).max() < 1e-12 * np.abs(s0).max()
    assert np.abs(g1 - g0).max() < 1e-10 * np.abs(g0).max()
