"""The hand-written adjoint of the line-aware readout products (:class:`dtoc.sim.pdg_signal._LineBatch`): its
forward is the plain torch products bit for bit, its gradients are torch autograd's of those products (finite
differences by ``gradcheck``; autograd of the same products on the same tensors, 1e-12 relative in float64), and
one whole ``simulate`` backward of an EPI through it equals the one through the plain products."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import dtoc.sim.pdg_signal as S
from dtoc.seq.load import load_sequence
from dtoc.sim.pdg import PDGConfig, build_graph, simulate
from dtoc.sim.phantom import brain_phantom

REPO = Path(__file__).resolve().parents[1]


def _inputs(n_ro, n_pe, b, W, mrs, dtype=torch.complex128, seed=0):
    """Random F (n_ro, b S, n_pe), H (n_ro, n_pe, M R), X = exp(-i theta) (b, W, n_ro), dlp (b, W, R) and the
    real drift variable u (b, W, S) of dq = u (real values, as in the simulator: powers of times, Chebyshev
    polynomials of a real moment)."""
    M, R, S_ = mrs
    g = torch.Generator().manual_seed(seed)
    rdt = torch.float64 if dtype == torch.complex128 else torch.float32

    def c(*shape):
        return torch.complex(torch.randn(*shape, generator=g, dtype=rdt), torch.randn(*shape, generator=g, dtype=rdt))

    F = c(n_ro, b * S_, n_pe)
    H = c(n_ro, n_pe, M * R)
    theta = torch.randn(b, W, n_ro, generator=g, dtype=rdt)
    X = torch.complex(torch.cos(theta), -torch.sin(theta))
    dlp = torch.randn(b, W, R, generator=g, dtype=rdt).to(dtype)
    u = torch.randn(b, W, S_, generator=g, dtype=rdt)
    return F, H, X, dlp, u


@pytest.mark.parametrize("needs", ["HXq", "H", "X", "q", "Xq"])
def test_line_batch_gradcheck(needs):
    """torch.autograd.gradcheck (finite differences, complex inputs H and X in both real directions) of the
    custom node for every subset of differentiable inputs (the adjoint skips the gradients not asked for)."""
    mrs = (2, 3, 2)
    F, H, X, dlp, u = _inputs(3, 4, 2, 5, mrs)
    H.requires_grad_("H" in needs)
    X.requires_grad_("X" in needs)
    u.requires_grad_("q" in needs)

    def fn(H, X, u):
        return S._LineBatch.apply(F, H, X, dlp, u.to(F.dtype), mrs)

    assert torch.autograd.gradcheck(fn, (H, X, u), eps=1e-6, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("dtype", [torch.complex128, torch.complex64])
def test_line_batch_equals_autograd_of_the_products(dtype):
    """Forward bit for bit the plain products (what the simulator computed before the custom node); the
    gradients of a non-trivial real loss those of torch's autograd through the same products on the same
    tensors: 1e-12 relative in float64, 1e-5 in float32 (different summation orders only)."""
    mrs = (3, 4, 5)
    F, H, X, dlp, u = _inputs(16, 12, 3, 10, mrs, dtype=dtype, seed=1)
    w = torch.randn(3, 10, 3, dtype=dtype, generator=torch.Generator().manual_seed(2))
    res = {}
    for kind in ("plain", "custom"):
        h, x, q = (t.detach().clone().requires_grad_(True) for t in (H, X, u))
        if kind == "plain":
            out = S._line_batch_products(F, h, x, dlp, q.to(dtype), mrs)[0]
        else:
            out = S._line_batch(F, h, x, dlp, q.to(dtype), mrs)
            assert out.grad_fn is not None and "_LineBatch" in type(out.grad_fn).__name__
        loss = (out * w).real.sum() + (out.abs() ** 2).sum()
        loss.backward()
        res[kind] = (out.detach(), h.grad, x.grad, q.grad)
    assert torch.equal(res["plain"][0], res["custom"][0])
    tol = 1e-12 if dtype == torch.complex128 else 1e-5
    for name, a, b in zip(("H", "X", "dq"), res["plain"][1:], res["custom"][1:]):
        scale = float(a.abs().max())
        assert scale > 0, name
        assert float((a - b).abs().max()) <= tol * scale, name


def test_line_batch_without_grad_is_the_plain_forward():
    """Under no_grad (or with no differentiable input) the products run plain, without the custom node."""
    mrs = (1, 2, 3)
    F, H, X, dlp, u = _inputs(5, 6, 2, 4, mrs)
    out = S._line_batch(F, H, X, dlp, u.to(F.dtype), mrs)
    assert out.grad_fn is None
    assert torch.equal(out, S._line_batch_products(F, H, X, dlp, u.to(F.dtype), mrs)[0])


@pytest.fixture(scope="module")
def epi():
    ir = load_sequence(REPO / "sequences" / "epi_esp081.seq")
    ph = brain_phantom(32, fov_m=ir.fov_m[:2], b0=True)
    return ir, ph


def test_simulate_backward_equals_plain_autograd(epi, monkeypatch):
    """One whole ``simulate`` of the 64x64 EPI (32x32 phantom with B0, float64, the phase moment drifting along
    every line: a 7-term drift series), line-aware signal in 8 batches of windows (small ``chunk_elems``):
    signal bit for bit and the gradient w.r.t. the whole (3, 2N+1) waveform within 1e-12 (relative to its
    largest entry) of the same simulate with the batch products left to torch's autograd."""
    ir, ph = epi
    cfg = PDGConfig(signal_method="separable", chunk_elems=7 * 32 * 32 * 8)
    graph = build_graph(ir, cfg, ph)
    G0 = torch.as_tensor(ir.grad_mT_per_m).clone()
    G0[1] += 0.004  # 4 uT/m on the phase axis: the phase moment drifts along each readout line
    batches = []
    orig = S._line_batch

    def spy(F, H, X, dlp, dq, mrs):
        out = orig(F, H, X, dlp, dq, mrs)
        batches.append((H.requires_grad, X.requires_grad, dq.requires_grad, type(out.grad_fn).__name__))
        return out

    monkeypatch.setattr(S, "_line_batch", spy)
    res = {}
    for kind in ("custom", "plain"):
        if kind == "plain":
            monkeypatch.setattr(
                S, "_line_batch", lambda F, H, X, dlp, dq, mrs: S._line_batch_products(F, H, X, dlp, dq, mrs)[0]
            )
        G = G0.clone().requires_grad_(True)
        s = simulate(ir, ph, graph=graph, grad_mT_per_m=G, config=cfg, dtype=torch.float64)
        (s.real**2 + s.imag**2).sum().backward()
        res[kind] = (s.detach(), G.grad)
    # the custom node ran for every batch, with all three inputs differentiable
    assert len(batches) == 8
    assert all(b[:3] == (True, True, True) and "_LineBatch" in b[3] for b in batches)
    assert torch.equal(res["custom"][0], res["plain"][0])
    g_ref, g_new = res["plain"][1], res["custom"][1]
    scale = float(g_ref.abs().max())
    assert scale > 0
    assert float((g_new - g_ref).abs().max()) <= 1e-12 * scale
