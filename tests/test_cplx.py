"""dtoc.util.cplx: the formulations on compiled-in CUDA kernels equal torch's functions (values and gradients),
checked on the CPU by asking for them; the default on the CPU is torch's own function, bit for bit."""

import torch

from dtoc.util import cplx


def _grads(fn, *xs):
    xs = [x.clone().requires_grad_(True) for x in xs]
    y = fn(*xs)
    w = torch.linspace(0.3, 1.7, y.numel(), dtype=torch.float64).reshape(y.shape)
    loss = (y.real * w).sum() + ((y.imag * w.flip(-1)).sum() if y.is_complex() else 0.0)
    return y.detach(), torch.autograd.grad(loss, xs)


def test_cexp_cis_cneg_match_torch():
    g = torch.Generator().manual_seed(3)
    re = torch.randn(7, 5, generator=g, dtype=torch.float64) * 3
    im = torch.randn(7, 5, generator=g, dtype=torch.float64) * 40
    ref, gref = _grads(lambda a, b: torch.exp(torch.complex(a, b)), re, im)
    new, gnew = _grads(lambda a, b: cplx.cexp(a, b, compiled_only=True), re, im)
    assert torch.allclose(new, ref, rtol=1e-14, atol=0)
    for a, b in zip(gnew, gref):
        assert torch.allclose(a, b, rtol=1e-13, atol=1e-300)
    z = torch.complex(re, im)
    ref, gref = _grads(torch.exp, z)
    new, gnew = _grads(lambda a: cplx.cexp_of(a, compiled_only=True), z)
    assert torch.allclose(new, ref, rtol=1e-14, atol=0) and torch.allclose(gnew[0], gref[0], rtol=1e-13, atol=0)
    ref, gref = _grads(lambda b: torch.polar(torch.ones_like(b), b), im)
    new, gnew = _grads(lambda b: cplx.cis(b, compiled_only=True), im)
    assert torch.allclose(new, ref, rtol=1e-14, atol=1e-16) and torch.allclose(gnew[0], gref[0], rtol=1e-13, atol=1e-15)
    z = torch.complex(re, im)
    ref, gref = _grads(lambda a: -a, z)
    new, gnew = _grads(lambda a: cplx.cneg(a, compiled_only=True), z)
    assert torch.equal(new, ref) and torch.equal(gnew[0], gref[0])


def test_cabs_matches_torch_including_zero():
    z = torch.complex(torch.tensor([0.0, 3.0, -1e-3, 2.5]), torch.tensor([0.0, -4.0, 2e-3, 0.0])).to(torch.complex128)
    ref, gref = _grads(torch.abs, z)
    new, gnew = _grads(lambda a: cplx.cabs(a, compiled_only=True), z)
    assert torch.allclose(new, ref, rtol=1e-15, atol=0)
    assert torch.allclose(gnew[0], gref[0], rtol=1e-14, atol=0)  # the derivative at 0 is 0 (as torch's sgn)
    assert cplx.cabs(z.conj(), compiled_only=True)[1] == 5.0  # a conjugate view is resolved first


def test_cpu_default_is_torch_bit_for_bit():
    g = torch.Generator().manual_seed(5)
    re, im = torch.randn(64, generator=g, dtype=torch.float64), torch.randn(64, generator=g, dtype=torch.float64) * 9
    assert torch.equal(cplx.cexp(re, im), torch.exp(torch.complex(re, im)))
    assert torch.equal(cplx.cis(im), torch.polar(torch.ones_like(im), im))
    z = torch.complex(re, im)
    assert torch.equal(cplx.cabs(z), z.abs()) and torch.equal(cplx.cneg(z), -z)
    assert torch.equal(cplx.cexp_of(z), torch.exp(z))


def test_cuda_formulations_match_the_cpu():  # the default on CUDA: the compiled-in formulation
    import pytest

    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    g = torch.Generator().manual_seed(7)
    re, im = torch.randn(256, generator=g, dtype=torch.float64), torch.randn(256, generator=g, dtype=torch.float64) * 30
    dev = torch.device("cuda")
    assert torch.allclose(cplx.cexp(re.to(dev), im.to(dev)).cpu(), torch.exp(torch.complex(re, im)), rtol=1e-13, atol=0)
    z = torch.complex(re, im)
    assert torch.allclose(cplx.cabs(z.to(dev)).cpu(), z.abs(), rtol=1e-14, atol=0)


def _signal_and_gradient(compiled_only, monkeypatch, calibrate: bool):
    import numpy as np
    from test_sim_physics import rich_phantom, small_gre

    from dtoc.sim.pdg import PDGConfig, build_graph, simulate

    monkeypatch.setattr(cplx, "COMPILED_ONLY", compiled_only)
    ir = small_gre(n_rep=4)
    ph = rich_phantom()
    ph.coil_sens = np.stack([np.ones((4, 4)), np.exp(1j * np.arange(16).reshape(4, 4) / 3.0)])
    cfg = PDGConfig(calibrate_emission=calibrate)
    g = torch.as_tensor(ir.grad_mT_per_m, dtype=torch.float64).clone().requires_grad_(True)
    s = simulate(ir, ph, g, graph=build_graph(ir, cfg, ph), config=cfg, dtype=torch.float64)
    (s.real**2 + s.imag**2).sum().backward()
    return s.detach().numpy(), g.grad.numpy()


def _epi_signal_and_gradient(compiled_only, monkeypatch, method: str):
    from pathlib import Path

    from dtoc.seq.load import load_sequence
    from dtoc.sim.pdg import PDGConfig, build_graph, simulate
    from dtoc.sim.phantom import brain_phantom

    monkeypatch.setattr(cplx, "COMPILED_ONLY", compiled_only)
    ir = load_sequence(Path(__file__).resolve().parents[1] / "sequences" / "epi_esp081.seq")
    ph = brain_phantom(32, fov_m=ir.fov_m[:2], b0=True)
    cfg = PDGConfig(signal_method=method)
    g = torch.as_tensor(ir.grad_mT_per_m).clone()
    g[1] += 0.004  # the phase moment drifts along each readout line (the line-aware series)
    g.requires_grad_(True)
    s = simulate(ir, ph, graph=build_graph(ir, cfg, ph), grad_mT_per_m=g, config=cfg, dtype=torch.float64)
    (s.real**2 + s.imag**2).sum().backward()
    return s.detach().numpy(), g.grad.numpy()


def test_the_cuda_formulations_give_the_epi_signal_and_gradient(monkeypatch):
    """The same check on the 64x64 EPI with B0: the line-aware readout signal ('separable', exp(-tc lam) advanced
    window by window) and the per-state one ('gemm')."""
    import numpy as np

    for method in ("separable", "gemm"):
        s0, g0 = _epi_signal_and_gradient(False, monkeypatch, method)
        s1, g1 = _epi_signal_and_gradient(True, monkeypatch, method)
        assert np.abs(s1 - s0).max() <= 1e-9 * np.abs(s0).max()
        assert np.abs(g1 - g0).max() <= 1e-9 * np.abs(g0).max()


def test_the_cuda_formulations_give_the_simulators_signal_and_gradient(monkeypatch):
    """tests/test_sim_cuda.py's check (1e-9 of the largest value) of the CUDA formulations, run on the CPU: the
    difference that test sees comes from the formulations, so a wrong one fails here without a GPU (the sinc
    without its series near 0 did: its gradient was 3.4e-3 off)."""
    import numpy as np

    for calibrate in (False, True):
        s0, g0 = _signal_and_gradient(False, monkeypatch, calibrate)
        s1, g1 = _signal_and_gradient(True, monkeypatch, calibrate)
        assert np.abs(s1 - s0).max() <= 1e-9 * np.abs(s0).max()
        assert np.abs(g1 - g0).max() <= 1e-9 * np.abs(g0).max()
