"""Kernel resampling and zero-padded FFT convolution for GIRF-type (LTI) effects.

A GIRF kernel ``h[l]`` (per-sample response, dimensionless or uT per mT/m) lives on its own grid
``t_l = t0 + l * dt_h``: ``h[l]`` is the response at ``t_l`` to a unit-area impulse, integrated over one
sample, i.e. the continuous impulse response is ``h_c(t_l) ~ h[l] / dt_h`` and ``sum(h)`` is the DC gain.

Resampling onto a waveform grid ``dt`` (:func:`resample_kernel`): the kernel is interpreted as a
band-limited signal, cut off at ``f_c = min(1/(2 dt_h), 1/(2 dt))`` (the GIRF is unknown above its own
Nyquist frequency and is taken as zero there; when going to a coarser grid the cut-off is the anti-alias
filter), reconstructed with a Kaiser-windowed sinc (16 zero crossings each side, beta 8) and sampled at
``t0_new + n*dt`` with ``t0_new`` a multiple of ``dt``; ``h_new[n] = dt * h_c(t0_new + n dt)``.  Each input
tap's weights are normalised to sum to one, so the DC gain (``sum(h)``) is preserved exactly.  When
``dt == dt_h`` and ``t0`` is a multiple of ``dt``, the kernel is used as is (exact).  The map is linear
in ``h`` (a fixed sparse gather), so it is differentiable with respect to the kernel.

Convolution (:func:`fft_convolve`): ``G[o, n] = sum_i sum_j h[o, i, j] g[i, n - j - s]`` with
``s = t0_new / dt`` (integer), by zero-padded real FFTs (no circular wrap): the waveform is zero outside
its samples.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

HALF_WIDTH_ZEROS = 16
KAISER_BETA = 8.0


def _same(a: float, b: float, rel: float = 1e-9) -> bool:
    return abs(a - b) <= rel * max(abs(a), abs(b))


@lru_cache(maxsize=64)
def _resample_plan(L: int, dt_h: float, t0_h: float, dt: float):
    """Gather indices (L2, K), weights (L2, K) and integer start shift for resampling."""
    fc = min(0.5 / dt_h, 0.5 / dt)
    w_t = HALF_WIDTH_ZEROS / (2.0 * fc)  # window half-width, s
    t_last = t0_h + (L - 1) * dt_h
    s0 = math.floor((t0_h - w_t) / dt + 1e-9)
    s1 = math.ceil((t_last + w_t) / dt - 1e-9)
    t_new = (s0 + np.arange(s1 - s0 + 1)) * dt  # (L2,)
    K = int(math.ceil(2 * w_t / dt_h)) + 2
    l_lo = np.ceil((t_new - w_t - t0_h) / dt_h - 1e-9).astype(np.int64)
    idx = l_lo[:, None] + np.arange(K)[None, :]  # (L2, K)
    valid = (idx >= 0) & (idx < L)
    x = t_new[:, None] - (t0_h + idx * dt_h)  # s
    inside = np.abs(x) < w_t
    win = np.zeros_like(x)
    arg = 1.0 - (x[inside] / w_t) ** 2
    win[inside] = np.i0(KAISER_BETA * np.sqrt(np.clip(arg, 0.0, None))) / np.i0(KAISER_BETA)
    wts = dt * 2.0 * fc * np.sinc(2.0 * fc * x) * win
    wts[~(valid & inside)] = 0.0
    idx = np.clip(idx, 0, L - 1)
    col = np.zeros(L)
    np.add.at(col, idx.ravel(), wts.ravel())
    col[col == 0] = 1.0
    wts = wts / col[idx]
    return idx, wts, int(s0)


def resample_kernel(h: torch.Tensor, dt_h_s: float, t0_h_s: float, dt_s: float) -> tuple[torch.Tensor, int]:
    """Resample per-sample kernel taps onto the grid ``dt_s``.

    Args:
        h: (..., L) taps at ``t0_h_s + l*dt_h_s``.
        dt_h_s: kernel sample spacing, s.
        t0_h_s: time of tap 0 relative to the impulse, s.
        dt_s: target spacing, s.
    Returns:
        ``(h_new (..., L2), shift)``: taps at ``(shift + n) * dt_s``, differentiable w.r.t. ``h``.
    """
    L = h.shape[-1]
    if _same(dt_h_s, dt_s):
        s = t0_h_s / dt_s
        if abs(s - round(s)) < 1e-6:
            return h, int(round(s))
    idx, wts, s0 = _resample_plan(L, float(dt_h_s), float(t0_h_s), float(dt_s))
    idx_t = torch.as_tensor(idx, device=h.device)
    w_t = torch.as_tensor(wts, dtype=h.dtype, device=h.device)
    return (h[..., idx_t] * w_t).sum(-1), s0


def _shift_slice(c: torch.Tensor, start: int, T: int) -> torch.Tensor:
    """``out[..., n] = c[..., n + start]`` for n in [0, T), zero where out of range."""
    N = c.shape[-1]
    front = max(0, -start)
    back = max(0, start + T - N)
    if front or back:
        c = torch.nn.functional.pad(c, (front, back))
    s = start + front
    return c[..., s : s + T]


#: waveforms longer than this are convolved by overlap-add in blocks of OLA_BLOCK samples (memory and time
#: linear in the length: a 5-minute sequence at 5 us is 6e7 samples); shorter ones by one FFT
OLA_MIN = 1 << 21
OLA_BLOCK = 1 << 18


def _pow2(n: int) -> int:
    return 1 << max(1, (n - 1).bit_length())  # power of two: torch's FFTs are slowest on 5-smooth sizes


def conv_length(T: int, L: int) -> tuple[int, int]:
    """(full linear-convolution length N = T + L - 1, FFT length: >= N, or >= OLA_BLOCK + L - 1 for
    overlap-add of a long waveform)."""
    N = T + L - 1
    if T > OLA_MIN and L - 1 <= OLA_BLOCK:
        return N, _pow2(OLA_BLOCK + L - 1)
    return N, _pow2(N)


def kernel_spectrum(h: torch.Tensor, T: int) -> torch.Tensor:
    """rfft of kernel taps (O, I, L) zero-padded for waveforms of length T (reusable across calls)."""
    _, nfft = conv_length(T, h.shape[-1])
    return torch.fft.rfft(h, n=nfft)


def fft_convolve(g: torch.Tensor, h: torch.Tensor, shift: int, spectrum: torch.Tensor | None = None) -> torch.Tensor:
    """Multi-input multi-output linear convolution by zero-padded FFT.

    Args:
        g: (..., I, T) input waveforms on the grid dt (zero outside).
        h: (O, I, L) taps on the same grid, tap j at time ``(shift + j) * dt``.
        shift: integer start of the kernel in samples (negative for centred kernels).
        spectrum: optional precomputed :func:`kernel_spectrum` of ``h`` for this T.
    Returns:
        (..., O, T) with ``out[o, n] = sum_i sum_j h[o, i, j] g[i, n - j - shift]``.
    """
    T = g.shape[-1]
    L = h.shape[-1]
    N, nfft = conv_length(T, L)
    Hf = torch.fft.rfft(h.to(g.dtype), n=nfft) if spectrum is None else spectrum
    if nfft < N:  # overlap-add: blocks of OLA_BLOCK samples, each tail (L - 1 <= OLA_BLOCK) added to the next
        pieces, tail = [], None
        for s in range(0, T, OLA_BLOCK):
            seg = g[..., s : s + OLA_BLOCK]
            n = seg.shape[-1]
            y = torch.fft.irfft((torch.fft.rfft(seg, n=nfft).unsqueeze(-3) * Hf).sum(-2), n=nfft)[..., : n + L - 1]
            if tail is not None:
                y = y + torch.nn.functional.pad(tail, (0, y.shape[-1] - tail.shape[-1]))
            pieces.append(y[..., :n])
            tail = y[..., n:]
        c = torch.cat(pieces + [tail], dim=-1)[..., :N]
        return _shift_slice(c, -shift, T)
    Gf = torch.fft.rfft(g, n=nfft)
    Cf = (Gf.unsqueeze(-3) * Hf).sum(-2)  # (..., O, F); elementwise (an einsum here becomes F tiny matmuls)
    c = torch.fft.irfft(Cf, n=nfft)[..., :N]
    return _shift_slice(c, -shift, T)
