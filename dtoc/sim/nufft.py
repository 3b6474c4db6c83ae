"""The non-Cartesian image of :mod:`dtoc.sim.ndft` by a gridding NUFFT (finufft), for trajectories beyond the exact
non-uniform DFT's size.

Same operator, same weights: ``I(r_p) = sum_j w_j s_j exp(+i k_j . r_p)`` on the (ny, nx) grid that
:mod:`dtoc.sim.ndft` uses (pixel ``m`` at ``(m - n // 2) FOV / n``), with Pipe-Menon density weights
(``w <- w / |E E^H w|``, 12 iterations), here computed by type-1 (adjoint) and type-2 (forward) NUFFTs: with
``x_j = k_j FOV / n`` (rad per pixel) the pixel grid is finufft's centred mode grid.  Error: finufft's
tolerance (1e-10 in float64, 1e-6 in float32) relative to the exact sum; cost ``O(M + N^2 log N)`` per image
instead of ``M N^2``.  Differentiable in the signal: the backward of ``s -> E^H W s`` is ``W E`` (a type-2
NUFFT).  finufft runs on the CPU (GPU tensors are moved there and back) with one thread, so that the same
inputs give the same bits.  Why finufft: docs/benchmarks.md ("Non-Cartesian image operator").
"""

from __future__ import annotations

import numpy as np
import torch

#: requested relative accuracy of the NUFFTs by real precision
EPS = {torch.float64: 1e-10, torch.float32: 1e-6}
_CACHE: dict = {}


class _Plan:
    """Coordinates, density weights and precision of one (trajectory, grid, sample mask)."""

    def __init__(self, k_xy: np.ndarray, shape: tuple[int, int], fov_xy: tuple[float, float], real: torch.dtype):
        ny, nx = shape
        self.shape = shape
        self.np_real = np.float64 if real == torch.float64 else np.float32
        self.np_cplx = np.complex128 if real == torch.float64 else np.complex64
        self.eps = EPS[real]
        self.x = np.ascontiguousarray(k_xy[0] * fov_xy[0] / nx, dtype=self.np_real)
        self.y = np.ascontiguousarray(k_xy[1] * fov_xy[1] / ny, dtype=self.np_real)
        m = self.x.size
        w = np.ones(m, dtype=self.np_real)
        for _ in range(12):
            d = np.abs(self.forward(self.adjoint(w.astype(self.np_cplx))))
            w = (w / np.maximum(d, 1e-30)).astype(self.np_real)
        self.w = (w / w.sum() * m / (nx * ny)).astype(self.np_real)

    def adjoint(self, c: np.ndarray) -> np.ndarray:
        """(..., M) -> (..., ny, nx): ``sum_j c_j exp(+i k_j . r_p)``."""
        import finufft

        ny, nx = self.shape
        c2 = np.ascontiguousarray(c.reshape(-1, c.shape[-1]), dtype=self.np_cplx)
        f = finufft.nufft2d1(self.x, self.y, c2 if c2.shape[0] > 1 else c2[0], (nx, ny), eps=self.eps, isign=1,
                             nthreads=1)  # fmt: skip
        f = f.reshape(-1, nx, ny)
        return np.swapaxes(f, -1, -2).reshape(*c.shape[:-1], ny, nx)

    def forward(self, img: np.ndarray) -> np.ndarray:
        """(..., ny, nx) -> (..., M): ``sum_p m_p exp(-i k_j . r_p)``."""
        import finufft

        ny, nx = self.shape
        f = np.ascontiguousarray(np.swapaxes(img.reshape(-1, ny, nx), -1, -2), dtype=self.np_cplx)
        c = finufft.nufft2d2(self.x, self.y, f if f.shape[0] > 1 else f[0], eps=self.eps, isign=-1, nthreads=1)
        return c.reshape(*img.shape[:-2], self.x.size)


def plan(k_xy: np.ndarray, k_key: bytes, shape, fov_xy, keep: np.ndarray, real: torch.dtype) -> _Plan:
    """The cached :class:`_Plan` of the kept samples."""
    key = (k_key, tuple(shape), tuple(fov_xy), keep.tobytes(), real)
    if key not in _CACHE:
        if len(_CACHE) > 8:
            _CACHE.clear()
        _CACHE[key] = _Plan(np.ascontiguousarray(k_xy[:, keep]), tuple(shape), tuple(fov_xy), real)
    return _CACHE[key]


class _WeightedAdjoint(torch.autograd.Function):
    @staticmethod
    def forward(ctx, s: torch.Tensor, p: _Plan) -> torch.Tensor:
        ctx.p = p
        out = p.adjoint(s.detach().cpu().numpy() * p.w)
        return torch.as_tensor(out, device=s.device)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        p = ctx.p
        gs = p.forward(g.detach().cpu().numpy()) * p.w
        return torch.as_tensor(gs, device=g.device), None


def nufft_image(sk: torch.Tensor, p: _Plan) -> torch.Tensor:
    """(..., ny, nx) image ``E^H W s`` of the kept samples ``sk`` (..., M), differentiable in ``sk``."""
    return _WeightedAdjoint.apply(sk, p)
