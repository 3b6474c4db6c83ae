"""Elementwise functions on the CUDA kernels torch ships compiled.

On CUDA, torch builds some elementwise kernels at their first use in a process with NVRTC (its
"jiterator"): among those dtoc uses, the complex exponential, ``abs`` and negation, ``sgn`` (the backward
of a complex ``abs`` and of ``polar``) and ``sinc`` (every dtype).  On a machine without torch's kernel cache
each costs 0.2-1 s in the first optimize of a process (docs/benchmarks.md, "CPU and CUDA side by side").  These
functions form the same values from kernels that are compiled in (real ``exp``, ``cos``, ``sin``,
``vector_norm`` and complex construction), forward and backward.  On any other device they are the torch
functions themselves, so CPU results are bit for bit what they were.

``sinc`` near 0 is its Taylor series: the quotient ``sin(pi x) / (pi x)`` differentiates as ``cos/px - sin/px^2``,
which cancels to garbage of order 1 where ``x`` is a rounding residue (1e-17) instead of 0; a version without the
series failed tests/test_sim_cuda.py on an H200 (2026-11-27).  tests/test_cplx.py runs the simulator's signal and
gradient with these formulations on the CPU against torch's functions, at that test's tolerance.
"""

from __future__ import annotations

import math

import torch

#: None: the formulations on compiled-in kernels on CUDA only; True / False: everywhere / nowhere (tests run the
#: CUDA formulation on the CPU with it)
COMPILED_ONLY: bool | None = None


def _compiled_only(t: torch.Tensor, compiled_only: bool | None) -> bool:
    """Whether to take the formulation on compiled-in kernels: given, else :data:`COMPILED_ONLY`, else where ``t``
    lives on CUDA."""
    if compiled_only is None:
        compiled_only = COMPILED_ONLY
    return t.device.type == "cuda" if compiled_only is None else compiled_only


def cexp(re: torch.Tensor, im: torch.Tensor, compiled_only: bool | None = None) -> torch.Tensor:
    """exp(re + i im), complex of the real tensors' dtype (broadcast), differentiable in both.
    ``compiled_only``: None, by the device (module doc); True / False to choose (tests)."""
    if not _compiled_only(re, compiled_only):
        return torch.exp(torch.complex(re, im))
    mag = torch.exp(re)
    return torch.complex(mag * torch.cos(im), mag * torch.sin(im))


def cexp_of(z: torch.Tensor, compiled_only: bool | None = None) -> torch.Tensor:
    """exp(z) of a complex tensor (differentiable)."""
    if not _compiled_only(z, compiled_only):
        return torch.exp(z)
    return cexp(z.real, z.imag, compiled_only=True)


def cis(phase: torch.Tensor, compiled_only: bool | None = None) -> torch.Tensor:
    """exp(i phase) (complex, differentiable; cos + i sin, no exponential of a zero real part)."""
    if not _compiled_only(phase, compiled_only):
        return torch.polar(torch.ones_like(phase), phase)
    return torch.complex(torch.cos(phase), torch.sin(phase))


#: below this |pi x| the sinc is its Taylor series to x^8 (truncation < 3e-18 relative; above it the quotient's
#: derivative loses at most ~1e-12 relative to cancellation)
SINC_SERIES_BELOW = 0.1


def sinc(x: torch.Tensor, compiled_only: bool | None = None) -> torch.Tensor:
    """The normalised sinc, sin(pi x) / (pi x), 1 at 0 (real x; differentiable).  Near 0 its Taylor series: the
    quotient's derivative, cos/px - sin/px^2, cancels to garbage of order 1 where x is a rounding residue (1e-17)."""
    if not _compiled_only(x, compiled_only):
        return torch.sinc(x)
    px = math.pi * x
    small = px.abs() < SINC_SERIES_BELOW
    safe = torch.where(small, torch.ones_like(px), px)
    p2 = torch.where(small, px, torch.zeros_like(px)) ** 2
    series = 1.0 - p2 / 6.0 * (1.0 - p2 / 20.0 * (1.0 - p2 / 42.0 * (1.0 - p2 / 72.0)))
    return torch.where(small, series, torch.sin(safe) / safe)


def cabs(z: torch.Tensor, compiled_only: bool | None = None) -> torch.Tensor:
    """|z| of a complex or real tensor (differentiable; the derivative at 0 is 0, as torch's)."""
    if not _compiled_only(z, compiled_only) or not z.is_complex():
        return z.abs()
    return torch.linalg.vector_norm(torch.view_as_real(z.resolve_conj()), dim=-1)


def cneg(z: torch.Tensor, compiled_only: bool | None = None) -> torch.Tensor:
    """-z of a complex tensor (differentiable)."""
    if not _compiled_only(z, compiled_only) or not z.is_complex():
        return -z
    return torch.complex(-z.real, -z.imag)
