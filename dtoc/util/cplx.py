"""Elementwise functions on the CUDA kernels torch ships compiled.

On CUDA, torch builds some elementwise kernels at their first use in a process with NVRTC (its
"jiterator"): among those dtoc uses, the complex exponential, ``abs`` and negation, ``sgn`` (the backward
of a complex ``abs`` and of ``polar``) and ``sinc`` (every dtype).  On a machine without torch's kernel cache
each costs 0.2-1 s in the first optimize of a process (docs/benchmarks.md, "CPU and CUDA side by side").  These
functions form the same values from kernels that are compiled in (real ``exp``, ``cos``, ``sin``,
``vector_norm`` and complex construction), forward and backward.  On any other device they are the torch
functions themselves, so CPU results are bit for bit what they were.

``sinc`` stays torch's: ``sin(pi x) / (pi x)`` written out differentiates as ``cos/px - sin/px^2``, which cancels
to garbage of order 1 where ``x`` is a rounding residue (1e-17) instead of 0; that version's gradient failed
tests/test_sim_cuda.py on an H200 (2026-11-27) and was taken out.  A replacement needs a series near 0.
"""

from __future__ import annotations

import torch


def _compiled_only(t: torch.Tensor, compiled_only: bool | None) -> bool:
    """Whether to take the formulation on compiled-in kernels: given, or where ``t`` lives on CUDA."""
    return t.device.type == "cuda" if compiled_only is None else compiled_only


def cexp(re: torch.Tensor, im: torch.Tensor, compiled_only: bool | None = None) -> torch.Tensor:
    """exp(re + i im), complex of the real tensors' dtype (broadcast), differentiable in both.
    ``compiled_only``: None, by the device (module doc); True / False to choose (tests)."""
    if not _compiled_only(re, compiled_only):
        return torch.exp(torch.complex(re, im))
    mag = torch.exp(re)
    return torch.complex(mag * torch.cos(im), mag * torch.sin(im))


def cis(phase: torch.Tensor, compiled_only: bool | None = None) -> torch.Tensor:
    """exp(i phase) (complex, differentiable; cos + i sin, no exponential of a zero real part)."""
    if not _compiled_only(phase, compiled_only):
        return torch.polar(torch.ones_like(phase), phase)
    return torch.complex(torch.cos(phase), torch.sin(phase))


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
