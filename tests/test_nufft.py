"""The gridding NUFFT image (dtoc.sim.nufft) against the exact non-uniform DFT (dtoc.sim.ndft): same operator,
same density weights, same gradient."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dtoc.sim import ndft, nufft

pytestmark = pytest.mark.skipif(not nufft.available(), reason="finufft not installed")


def _spiral(m: int, kmax: float, turns: float = 8.0, shots: int = 3) -> np.ndarray:
    t = np.linspace(0, 1, m // shots)
    k = [kmax * t * np.exp(1j * (2 * np.pi * turns * np.sqrt(t) + 2 * np.pi * s / shots)) for s in range(shots)]
    k = np.concatenate(k)
    return np.stack([k.real, k.imag])


@pytest.mark.parametrize("real", [torch.float64, torch.float32])
def test_nufft_equals_exact_ndft_and_its_gradient(real):
    ny, nx, fov = 24, 28, (0.24, 0.22)
    kmax = np.pi * min(nx / fov[0], ny / fov[1])  # the grid covers the trajectory
    k = _spiral(3000, kmax)
    keep = np.ones(k.shape[1], dtype=bool)
    keep[::7] = False
    rng = np.random.default_rng(0)
    cd = torch.complex128 if real == torch.float64 else torch.complex64
    s = torch.as_tensor(rng.standard_normal((2, k.shape[1])) + 1j * rng.standard_normal((2, k.shape[1])), dtype=cd)
    EH = ndft._operator(k, k.tobytes(), (ny, nx), fov, keep, real, "cpu")  # (P, M) exact, with its own weights
    p = nufft.plan(k, k.tobytes(), (ny, nx), fov, keep, real)
    sk = s[:, torch.as_tensor(np.flatnonzero(keep))].clone().requires_grad_(True)
    sk2 = sk.detach().clone().requires_grad_(True)
    img_exact = (sk @ EH.T).reshape(2, ny, nx)
    img = nufft.nufft_image(sk2, p)
    tol = 1e-8 if real == torch.float64 else 2e-5
    scale = float(img_exact.detach().abs().max())
    assert scale > 0.1
    np.testing.assert_allclose(img.detach().numpy(), img_exact.detach().numpy(), rtol=0, atol=tol * scale)
    # the weights themselves (Pipe-Menon by NUFFTs vs by the dense matrix)
    W = np.abs(EH.numpy()).max(axis=0)  # |E^H W| entries are w_j (|exp| = 1)
    np.testing.assert_allclose(p.w, W, rtol=tol * 10)
    target = torch.as_tensor(rng.standard_normal((2, ny, nx)), dtype=real)
    for im in (img_exact, img):
        ((im.abs() - target) ** 2).sum().backward()
    gs = float(sk.grad.abs().max())
    np.testing.assert_allclose(sk2.grad.numpy(), sk.grad.numpy(), rtol=0, atol=tol * 10 * gs)


def test_large_trajectory_image_goes_through_the_nufft(monkeypatch):
    """ndft_image switches to the NUFFT above EXACT_MAX_ENTRIES and gives the exact image."""
    from types import SimpleNamespace

    ny = nx = 20
    fov = (0.2, 0.2)
    k = _spiral(1500, np.pi * nx / fov[0])
    ir = SimpleNamespace(
        geometry=SimpleNamespace(image_shape=(ny, nx), fov_xy_m=fov),
        nominal_kspace_rad_per_m=lambda: np.vstack([k, 0 * k[:1]]),
    )
    s = torch.as_tensor(np.random.default_rng(1).standard_normal(k.shape[1]) + 0j)
    exact = ndft.ndft_image(s, ir)
    calls = []
    monkeypatch.setattr(ndft, "EXACT_MAX_ENTRIES", 1e3)
    orig = nufft.nufft_image
    monkeypatch.setattr(nufft, "nufft_image", lambda *a: calls.append(1) or orig(*a))
    approx = ndft.ndft_image(s, ir)
    assert calls  # the gridded path ran
    np.testing.assert_allclose(approx.numpy(), exact.numpy(), rtol=0, atol=1e-8 * float(exact.abs().max()))
