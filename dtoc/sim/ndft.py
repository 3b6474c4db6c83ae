"""Non-Cartesian image reconstruction on the nominal trajectory: a non-uniform DFT (adjoint) with density
compensation, for 2D sequences without a Cartesian grid (radial, UTE, spiral with a known FOV).

``I(r_p) = sum_j w_j s_j exp(+i k_j . r_p)`` over the kept ADC samples j, pixels r_p of an (N, N) grid with the
sequence's FOV centred as :mod:`dtoc.sim.recon` centres its images; ``w`` are Pipe-Menon density weights
(``w <- w / |E E^H w|``, 12 iterations, computed once per sequence and sample mask).  Exact (no gridding
kernel) and differentiable in the signal; cost N_adc x N^2 per image, which for the 2D sizes dtoc optimizes
(10^3-10^4 samples, 32^2-96^2 pixels) is a single matrix product; above :data:`EXACT_MAX_ENTRIES` the same
operator is computed by a gridding NUFFT (:mod:`dtoc.sim.nufft`).  Both the ideal and the realized image use
the same operator, so the NRMSE compares like with like.
"""

from __future__ import annotations

import numpy as np
import torch

#: largest kept samples x pixels of the exact (dense matrix, 16 bytes an entry) operator; larger images are
#: computed by :mod:`dtoc.sim.nufft` (the same operator by a gridding NUFFT, to 1e-10)
EXACT_MAX_ENTRIES = 2e7
_CACHE: dict = {}
_NOMINAL: dict = {}  # id(ir) -> (ir, k_xy, k_key): the trajectory once per sequence, not once per image


def _nominal_xy(ir) -> tuple[np.ndarray, bytes]:
    """(2, N) nominal in-plane k of ``ir`` and its bytes (the operator cache key), computed once per IR (the
    entry holds the IR, so its id cannot be reused while cached)."""
    hit = _NOMINAL.get(id(ir))
    if hit is not None and hit[0] is ir:
        return hit[1], hit[2]
    k_xy = np.ascontiguousarray(ir.nominal_kspace_rad_per_m()[:2])
    if len(_NOMINAL) > 8:
        _NOMINAL.clear()
    _NOMINAL[id(ir)] = (ir, k_xy, k_xy.tobytes())
    return k_xy, _NOMINAL[id(ir)][2]


def _operator(
    k_xy: np.ndarray, k_key: bytes, shape: tuple[int, int], fov_xy: tuple[float, float], keep: np.ndarray, dtype, device
):
    key = (k_key, shape, fov_xy, keep.tobytes(), dtype, str(device))
    if key in _CACHE:
        return _CACHE[key]
    ny, nx = shape
    x = (np.arange(nx) - nx // 2) * fov_xy[0] / nx
    y = (np.arange(ny) - ny // 2) * fov_xy[1] / ny
    X, Y = np.meshgrid(x, y)  # (ny, nx)
    r = np.stack([X.ravel(), Y.ravel()])  # (2, P)
    kk = k_xy[:, keep]
    E = np.exp(-1j * (kk.T @ r))  # (N, P): forward model s_j = sum_p m_p exp(-i k_j r_p)
    w = np.ones(kk.shape[1])
    for _ in range(12):
        d = np.abs(E @ (E.conj().T @ w))
        w = w / np.maximum(d, 1e-30)
    w = w / w.sum() * kk.shape[1] / (nx * ny)
    cdt = torch.complex128 if dtype == torch.float64 else torch.complex64
    EH = torch.as_tensor(E.conj().T * w[None, :], dtype=cdt, device=device)  # (P, N) weighted adjoint
    if len(_CACHE) > 8:
        _CACHE.clear()
    _CACHE[key] = EH
    return EH


def ndft_image(signal, ir, keep_mask=None) -> torch.Tensor:
    """(..., ny, nx) complex image from (..., N_adc) samples on the nominal in-plane (x, y) trajectory (the coil
    combination is :func:`dtoc.sim.recon.reconstruct`'s)."""
    s = torch.as_tensor(signal)
    geo = ir.geometry
    ny, nx = geo.image_shape
    k_xy, k_key = _nominal_xy(ir)
    n = k_xy.shape[1]
    keep = np.ones(n, dtype=bool) if keep_mask is None else np.asarray(torch.as_tensor(keep_mask).cpu(), dtype=bool)
    real = torch.float64 if s.dtype in (torch.complex128, torch.float64) else torch.float32
    cplx = torch.complex128 if real == torch.float64 else torch.complex64
    sk = s[..., torch.as_tensor(np.flatnonzero(keep), device=s.device)].to(cplx)
    if int(keep.sum()) * ny * nx > EXACT_MAX_ENTRIES:  # the same operator by a gridding NUFFT (dtoc.sim.nufft)
        from dtoc.sim import nufft

        return nufft.nufft_image(sk, nufft.plan(k_xy, k_key, (ny, nx), geo.fov_xy_m, keep, real))
    EH = _operator(k_xy, k_key, (ny, nx), geo.fov_xy_m, keep, real, s.device)
    return (sk @ EH.T).reshape(*s.shape[:-1], ny, nx)
