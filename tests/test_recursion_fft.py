"""The eddy-current recursion by FFT (the GPU's schedule, dtoc/hardware/recursion.py ``fft_scan``) against
the scan the CPU keeps: the same exact PWL exponential convolution up to FFT rounding, its gradients, and no
host read at a constant number of operations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from dtoc.hardware import recursion as R

DT = 5e-6


def _trapezoids(T: int, axes: int = 3, seed: int = 0) -> np.ndarray:
    """(axes, T) train of trapezoids (ramps of 40 samples), random heights up to 40 mT/m; a jump at t = 0."""
    rng = np.random.default_rng(seed)
    g = np.zeros((axes, T))
    for a in range(axes):
        for s in range(0, T - 500, 1600):
            h = rng.uniform(-40, 40)
            g[a, s : s + 40] = np.linspace(0, h, 40)
            g[a, s + 40 : s + 400] = h
            g[a, s + 400 : s + 440] = np.linspace(h, 0, 40)
        g[a, 0] = rng.uniform(-5, 5)
    return g


@pytest.fixture
def fft(monkeypatch):
    def use(on: bool):
        monkeypatch.setattr(R, "batched", lambda device: on)

    return use


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest error per channel relative to the channel's largest value."""
    return float(((a - b).abs().amax(-1) / b.abs().amax(-1)).max())


def test_fft_exp_response_and_gradients_equal_the_scan(fft):
    """exp_response with tau from 20 us (a^T underflows) to 1 s (no early stop), float64: value to 1e-13 of
    each channel's maximum, gradients w.r.t. the waveform and tau to 1e-11."""
    g0 = torch.as_tensor(_trapezoids(60_000))[None, :, None, :]
    tau0 = torch.tensor([[20e-6], [1e-3], [0.1], [1.0]], dtype=torch.float64)
    w = torch.randn((1, 3, 4, 60_000), dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    out = {}
    for on in (False, True):
        fft(on)
        g, tau = g0.clone().requires_grad_(True), tau0.clone().requires_grad_(True)
        e = R.exp_response(g, DT, tau)
        (e * w).sum().backward()
        out[on] = (e.detach(), g.grad, tau.grad)
    (e0, gg0, gt0), (e1, gg1, gt1) = out[False], out[True]
    assert e0.abs().amax() > 1.0 and torch.all(gt0.abs() > 0)
    assert _rel(e1, e0) < 1e-13
    assert float((gg1 - gg0).abs().max() / gg0.abs().max()) < 1e-11
    assert float(((gt1 - gt0).abs() / gt0.abs()).max()) < 1e-11


def test_fft_pole_response_equals_the_scan(fft):
    """A damped 1.3 kHz coil resonance (complex pole), complex128: value to 1e-13, gradient w.r.t. the pole to 1e-10."""
    g = torch.as_tensor(_trapezoids(30_000, axes=2, seed=3))
    out = {}
    for on in (False, True):
        fft(on)
        p = torch.tensor([complex(-800.0, 2 * np.pi * 1300.0)], dtype=torch.complex128, requires_grad=True)
        r = R.pole_response(g, DT, p)
        (r.real.sum() + 0.3 * r.imag.sum()).backward()
        out[on] = (r.detach(), p.grad)
    (r0, p0), (r1, p1) = out[False], out[True]
    assert _rel(r1, r0) < 1e-13
    assert abs(complex(p1 - p0)) < 1e-10 * abs(complex(p0))


def test_fft_recursion_reads_nothing_on_the_host_and_its_count_does_not_grow(fft):
    """The FFT path dispatches the same number of operations at 4x the samples and no
    ``aten::_local_scalar_dense`` (a device synchronisation on a GPU); the scan reads its decay rate once."""

    class Count(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.n, self.reads = 0, 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.n += 1
            self.reads += str(func).startswith(("aten._local_scalar_dense", "aten.item"))
            return func(*args, **(kwargs or {}))

    tau = torch.tensor([[1e-3], [0.1]], dtype=torch.float64)
    counts = {}
    for on in (True, False):
        fft(on)
        for T in (4_000, 16_000):
            g = torch.as_tensor(_trapezoids(T))[None, :, None, :]
            with Count() as c:
                R.exp_response(g, DT, tau)
            counts[on, T] = (c.n, c.reads)
    assert counts[True, 4_000] == counts[True, 16_000] and counts[True, 4_000][1] == 0, counts
    assert counts[False, 16_000][0] > counts[False, 4_000][0] and counts[False, 4_000][1] == 1, counts
