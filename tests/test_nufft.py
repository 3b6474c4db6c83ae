"""The gridding NUFFT image (dtoc.sim.nufft) against the exact non-uniform DFT (dtoc.sim.ndft): same operator,
same density weights, same gradient."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dtoc.sim import ndft, nufft


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


def _ramp_lines(n_lines: int, n_s: int, dk_y: float, kx_max: float, ro: int = 0) -> tuple[np.ndarray, list[int]]:
    """EPI-like lines, alternating direction, samples dense on the ramps (sin-spaced) along axis ``ro``."""
    u = np.sin(np.linspace(-np.pi / 2, np.pi / 2, n_s))  # non-uniform, monotonic
    k = np.zeros((3, n_lines * n_s))
    for i in range(n_lines):
        sl = slice(i * n_s, (i + 1) * n_s)
        k[ro, sl] = kx_max * (u if i % 2 == 0 else -u)
        k[1 - ro, sl] = (i - n_lines // 2) * dk_y
    return k, [n_s] * n_lines


@pytest.mark.parametrize("ro", [0, 1])
def test_line_cartesian_reads_ramp_sampled_readouts(ro):
    from dtoc.seq.geometry import line_cartesian, radial_like_step

    k, sizes = _ramp_lines(24, 30, 2 * np.pi / 0.2, 2 * np.pi / 0.25 * 15)
    if ro:
        k = k[[1, 0, 2]]
    got = line_cartesian(k, sizes)
    assert got is not None
    a, b, s_ro, s_pe, n_ro, n_pe = got
    assert (a, b) == (ro, 1 - ro)
    assert s_pe == pytest.approx(2 * np.pi / 0.2, rel=1e-9)
    assert s_ro == pytest.approx(2 * (2 * np.pi / 0.25 * 15) / 29, rel=1e-9)  # span / (samples - 1)
    assert (n_ro, n_pe) == (30, 24)
    assert radial_like_step(k, sizes) is None  # not a constant step: the radial rule does not apply
    spiral = np.vstack([_spiral(900, 300.0), np.zeros((1, 900))])
    assert line_cartesian(spiral, [300, 300, 300]) is None
    k[1 - ro, 5] += 1.0  # the phase coordinate moves inside a readout: not line-Cartesian
    assert line_cartesian(k, sizes) is None


def test_radial_flat_top_step_with_ramp_sampling():
    from dtoc.seq.geometry import radial_like_step

    r = np.concatenate([[0.0], np.cumsum(np.linspace(0.2, 2.0, 10)), 11 + np.arange(1, 21) * 2.0])  # ramp, then 2
    ang = np.linspace(0, np.pi, 8, endpoint=False)
    k = np.concatenate([np.stack([r * np.cos(t), r * np.sin(t), 0 * r]) for t in ang], axis=1)
    sizes = [r.size] * ang.size
    assert radial_like_step(k, sizes) is None
    assert radial_like_step(k, sizes, constant=False) == pytest.approx(2.0, rel=1e-9)
