"""The hand-written adjoint of the line-aware readout products (:class:`dtoc.sim.pdg_signal._LineProducts`): its
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


def _inputs(n_ro, n_pe, sizes, W, mrs, dtype=torch.complex128, seed=0):
    """Random batches [(b0, b1, F)] (F (n_ro, b S, n_pe), b = sizes[i] windows each), H (n_ro, n_pe, M R),
    X = exp(-i theta) (nW, W, n_ro), dlp (nW, W, R) and the real drift variable u (nW, W, S) of dq = u (real
    values, as in the simulator: powers of times, Chebyshev polynomials of a real moment)."""
    M, R, S_ = mrs
    g = torch.Generator().manual_seed(seed)
    rdt = torch.float64 if dtype == torch.complex128 else torch.float32

    def c(*shape):
        return torch.complex(torch.randn(*shape, generator=g, dtype=rdt), torch.randn(*shape, generator=g, dtype=rdt))

    nW = sum(sizes)
    edges = [0, *torch.cumsum(torch.tensor(sizes), 0).tolist()]
    batches = [(b0, b1, c(n_ro, (b1 - b0) * S_, n_pe)) for b0, b1 in zip(edges[:-1], edges[1:])]
    H = c(n_ro, n_pe, M * R)
    theta = torch.randn(nW, W, n_ro, generator=g, dtype=rdt)
    X = torch.complex(torch.cos(theta), -torch.sin(theta))
    dlp = torch.randn(nW, W, R, generator=g, dtype=rdt).to(dtype)
    u = torch.randn(nW, W, S_, generator=g, dtype=rdt)
    return batches, H, X, dlp, u


def _plain(H, X, dq, dlp, batches, mrs):
    """The products as the simulator wrote them before the custom node, left to torch's autograd."""
    return torch.cat([S._line_batch_products(F, H, X[b0:b1], dlp[b0:b1], dq[b0:b1], mrs)[0] for b0, b1, F in batches])


@pytest.mark.parametrize("needs", ["HXq", "H", "X", "q", "Xq"])
def test_line_products_gradcheck(needs):
    """torch.autograd.gradcheck (finite differences, complex inputs H and X in both real directions) of the
    custom node over two batches of windows, for every subset of differentiable inputs (the adjoint computes
    only the gradients asked for)."""
    mrs = (2, 3, 2)
    batches, H, X, dlp, u = _inputs(3, 4, (2, 1), 5, mrs)
    H.requires_grad_("H" in needs)
    X.requires_grad_("X" in needs)
    u.requires_grad_("q" in needs)

    def fn(H, X, u):
        return S._LineProducts.apply(H, X, u.to(H.dtype), dlp, batches, mrs)

    assert torch.autograd.gradcheck(fn, (H, X, u), eps=1e-6, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("dtype", [torch.complex128, torch.complex64])
def test_line_products_equal_autograd_of_the_products(dtype):
    """Forward bit for bit the plain products (what the simulator computed before the custom node); the
    gradients of a non-trivial real loss those of torch's autograd through the same products on the same
    tensors (three batches): 1e-12 relative in float64, 1e-5 in float32 (different summation orders only)."""
    mrs = (3, 4, 5)
    batches, H, X, dlp, u = _inputs(16, 12, (3, 2, 3), 10, mrs, dtype=dtype, seed=1)
    w = torch.randn(8, 10, 3, dtype=dtype, generator=torch.Generator().manual_seed(2))
    res = {}
    for kind in ("plain", "custom"):
        h, x, q = (t.detach().clone().requires_grad_(True) for t in (H, X, u))
        if kind == "plain":
            out = _plain(h, x, q.to(dtype), dlp, batches, mrs)
        else:
            out = S._line_products(h, x, q.to(dtype), dlp, iter(batches), mrs)
            assert out.grad_fn is not None and "_LineProducts" in type(out.grad_fn).__name__
        loss = (out * w).real.sum() + (out.abs() ** 2).sum()
        loss.backward()
        res[kind] = (out.detach(), h.grad, x.grad, q.grad)
    assert torch.equal(res["plain"][0], res["custom"][0])
    tol = 1e-12 if dtype == torch.complex128 else 1e-5
    for name, a, b in zip(("H", "X", "dq"), res["plain"][1:], res["custom"][1:]):
        scale = float(a.abs().max())
        assert scale > 0, name
        assert float((a - b).abs().max()) <= tol * scale, name


def test_line_products_without_grad_are_the_plain_forward():
    """Under no_grad (or with no differentiable input) the products run plain, without the custom node."""
    mrs = (1, 2, 3)
    batches, H, X, dlp, u = _inputs(5, 6, (2, 2), 4, mrs)
    out = S._line_products(H, X, u.to(H.dtype), dlp, iter(batches), mrs)
    assert out.grad_fn is None
    assert torch.equal(out, _plain(H, X, u.to(H.dtype), dlp, batches, mrs))


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
    seen = []
    orig = S._line_products

    def spy(H, X, dq, dlp, batches, mrs):
        nb = []

        def counted():
            for b in batches:
                nb.append(b[:2])
                yield b

        out = orig(H, X, dq, dlp, counted(), mrs)
        seen.append((H.requires_grad, X.requires_grad, dq.requires_grad, type(out.grad_fn).__name__, len(nb)))
        return out

    monkeypatch.setattr(S, "_line_products", spy)
    res = {}
    for kind in ("custom", "plain"):
        if kind == "plain":
            monkeypatch.setattr(S, "_line_products", _plain)
        G = G0.clone().requires_grad_(True)
        s = simulate(ir, ph, graph=graph, grad_mT_per_m=G, config=cfg, dtype=torch.float64)
        (s.real**2 + s.imag**2).sum().backward()
        res[kind] = (s.detach(), G.grad)
    # the custom node ran once, over 8 batches, with all three inputs differentiable
    assert len(seen) == 1 and seen[0][:3] == (True, True, True) and "_LineProducts" in seen[0][3]
    assert seen[0][4] == 8
    assert torch.equal(res["custom"][0], res["plain"][0])
    g_ref, g_new = res["plain"][1], res["custom"][1]
    scale = float(g_ref.abs().max())
    assert scale > 0
    assert float((g_new - g_ref).abs().max()) <= 1e-12 * scale
