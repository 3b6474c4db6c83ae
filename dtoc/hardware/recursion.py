"""Exact exponential convolution of piecewise-linear (PWL) waveforms, as a vectorised linear scan.

The exponential eddy-current terms of the hardware twin need

    e(t) = integral_{-inf}^{t} g'(s) exp(-(t - s) / tau) ds

for a demanded waveform ``g`` that is piecewise linear between samples ``g[n]`` at ``t_n = n*dt`` and
zero before ``t = 0`` (so a non-zero ``g[0]`` is a jump at ``t = 0``).  Because ``g'`` is constant
(``(g[n+1] - g[n]) / dt``) on every segment, the convolution has the exact per-step update

    e[0]   = g[0]
    e[n+1] = a * e[n] + b * (g[n+1] - g[n]),   a = exp(-dt/tau),  b = (tau/dt) * (1 - a)

(no quadrature error, any tau).  The recursion ``x[n] = a x[n-1] + u[n]`` is evaluated with a
Hillis-Steele prefix scan: ``ceil(log2 T)`` vectorised steps ``x[n] += a^s x[n-s]`` (s = 1, 2, 4, ...),
stopped early once ``a^s`` is below 1e-30 (the remaining terms are below float64 round-off).  Cost is
O(T log T) element operations with no Python loop over samples (a 1 s time constant costs the same as
a 1 ms one), numerically stable (only factors <= 1 are multiplied), differentiable with respect to the
waveform and to ``tau`` by autograd, and device/dtype agnostic.  The scan stops early by the largest decay
rate read on the host: one ``.item()``, free on the CPU, a device synchronisation elsewhere.

Off the CPU (:func:`batched`: the GPU's schedule, as ``PDGConfig(schedule='auto')`` of the simulator) the
same recursion is evaluated as what it is, the linear convolution ``x = u * h`` with ``h[n] = a^n``
(n = 0..T-1), by one zero-padded FFT (:func:`fft_scan`): a constant number of operations whatever T and
the time constants, no host read, O(T log T) work and O(T) memory under autograd (the scan keeps
``log2 T`` intermediate copies).  The two agree to float rounding (FFT error ~ eps log2(T) relative to
the largest response of the channel; tests/test_recursion_fft.py); the CPU keeps the scan, bit for bit.
"""

from __future__ import annotations

import numpy as np
import torch

from dtoc.hardware.convolution import conv_length

_NEGLIGIBLE = 1e-30


def batched(device: torch.device | str) -> bool:
    """Whether the recursion on ``device`` is evaluated by FFT (:func:`fft_scan`) instead of the scan: off
    the CPU (a constant number of kernels and no host read, what a GPU needs; the CPU keeps the scan)."""
    return torch.device(device).type != "cpu"


def fft_scan(u: torch.Tensor, log_a: torch.Tensor) -> torch.Tensor:
    """:func:`linear_scan` as the linear convolution ``x[n] = sum_{m <= n} a^(n-m) u[m]`` by zero-padded FFT.

    ``a^k = exp(k log_a)`` for k = 0..T-1 (underflows to 0 for fast decays, as the scan's early stop); real
    inputs use the real FFT.  A constant number of operations and no host read; differentiable w.r.t. ``u``
    and ``log_a``.  Equal to the scan up to FFT rounding (~ eps log2(nfft) relative to the channel's largest
    value)."""
    T = u.shape[-1]
    if T == 0:
        return u
    nfft = conv_length(T, T)[1]
    rdt = {torch.complex64: torch.float32, torch.complex128: torch.float64}.get(u.dtype, u.dtype)
    k = torch.arange(T, device=u.device, dtype=rdt)
    h = torch.exp(log_a * k)  # (..., T): the impulse response a^k
    if u.is_complex() or h.is_complex():
        return torch.fft.ifft(torch.fft.fft(u, n=nfft) * torch.fft.fft(h, n=nfft))[..., :T]
    return torch.fft.irfft(torch.fft.rfft(u, n=nfft) * torch.fft.rfft(h, n=nfft), n=nfft)[..., :T]


def linear_scan(u: torch.Tensor, log_a: torch.Tensor) -> torch.Tensor:
    """Solve ``x[n] = exp(log_a) * x[n-1] + u[n]`` with ``x[-1] = 0`` along the last axis.

    Args:
        u: (..., T) inputs.
        log_a: per-channel log decay factor (real part <= 0; complex for a damped oscillation),
            broadcastable to ``u[..., :1]``.
    Returns:
        (..., T) states ``x``, differentiable w.r.t. ``u`` and ``log_a``.
    """
    T = u.shape[-1]
    x = u
    s = 1
    max_log_a = float(log_a.detach().real.max()) if log_a.numel() else 0.0
    while s < T:
        if max_log_a * s < -69.0:  # exp(-69) ~ 1e-30: further contributions are below round-off
            break
        a_s = torch.exp(log_a * s)
        x = torch.cat([x[..., :s], x[..., s:] + a_s * x[..., :-s]], dim=-1)
        s *= 2
    return x


def _pole_scan(g: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """The exact PWL update ``r[0] = g[0]``, ``r[n+1] = a r[n] + b (g[n+1] - g[n])`` with ``a = exp(z)``,
    ``b = (a - 1) / z``, ``z = p dt`` (real for an exponential, complex for a damped oscillation); ``g``
    already in the dtype of ``z``."""
    b = torch.expm1(z) / z
    dg = torch.diff(g, dim=-1)
    u = torch.cat([g[..., :1].expand(np.broadcast_shapes(tuple(g[..., :1].shape), tuple(b.shape))), b * dg], dim=-1)
    return fft_scan(u, z) if batched(u.device) else linear_scan(u, z)


def exp_response(g: torch.Tensor, dt_s: float, tau_s: torch.Tensor) -> torch.Tensor:
    """Exact ``e = g' conv H(t) exp(-t/tau)`` of a PWL waveform at its sample times.

    Args:
        g: (..., T) waveform samples at ``t_n = n*dt`` (any unit; zero before t = 0).
        dt_s: sample spacing, s.
        tau_s: time constant(s), s, broadcastable against ``g[..., :1]`` (e.g. shape (K, 1) with
            ``g`` of shape (..., 1, T) for K time constants at once).
    Returns:
        (..., T) ``e`` in the unit of ``g`` (broadcast shape of ``g`` and ``tau``).
    """
    tau = tau_s.to(dtype=g.dtype, device=g.device)
    return _pole_scan(g, -dt_s / tau)  # b = (tau/dt)(1 - a), accurate for small dt/tau via expm1


def pole_response(g: torch.Tensor, dt_s: float, pole_per_s: torch.Tensor) -> torch.Tensor:
    """Exact ``r = g' conv H(t) exp(p t)`` of a PWL waveform for a complex pole ``p`` (Re p < 0).

    The same update as :func:`exp_response` with ``-1/tau`` replaced by ``p``; a damped oscillation
    ``exp(-sigma t) (cos + i sin)(omega_d t)`` for ``p = -sigma + i omega_d``.

    Args:
        g: (..., T) real waveform samples at ``t_n = n*dt``.
        pole_per_s: complex pole(s), 1/s, broadcastable against ``g[..., :1]``.
    Returns:
        (..., T) complex ``r`` in the unit of ``g``.
    """
    cdt = torch.complex128 if g.dtype == torch.float64 else torch.complex64
    return _pole_scan(g.to(cdt), pole_per_s.to(dtype=cdt, device=g.device) * dt_s)
