"""The simulator on CUDA equals the CPU run (signal and gradient); skipped where no CUDA device exists.

Everything in dtoc runs and is tested on CPU; this file is the check of the ``device`` argument for
machines with a GPU (float64: rounding only, 1e-9 of the maximum; float32: 1e-4).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_sim_physics import rich_phantom, small_gre

from dtoc.sim.pdg import PDGConfig, build_graph, simulate

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 1e-4)])
@pytest.mark.parametrize("calibrate", [False, True])
def test_cuda_equals_cpu(dtype, tol, calibrate):
    ir = small_gre(n_rep=4)
    ph = rich_phantom()
    ph.coil_sens = np.stack([np.ones((4, 4)), np.exp(1j * np.arange(16).reshape(4, 4) / 3.0)])
    cfg = PDGConfig(calibrate_emission=calibrate)
    graph = build_graph(ir, cfg, ph)
    out = {}
    for dev in ("cpu", "cuda"):
        g = torch.as_tensor(ir.grad_mT_per_m, dtype=dtype, device=dev).clone().requires_grad_(True)
        s = simulate(ir, ph, g, graph=graph, config=cfg, dtype=dtype, device=dev)
        assert s.device.type == dev
        (s.real**2 + s.imag**2).sum().backward()
        out[dev] = (s.detach().cpu().numpy(), g.grad.cpu().numpy())
    (s0, g0), (s1, g1) = out["cpu"], out["cuda"]
    assert np.abs(s1 - s0).max() <= tol * np.abs(s0).max()
    assert np.abs(g1 - g0).max() <= tol * np.abs(g0).max()
