"""The PDG amplitude propagation as a fixed, small number of tensor operations per RF interval.

Same recursion as :mod:`dtoc.sim.pdg_evolve` (read its docstring first), rewritten so that everything
that does not depend on the previous interval's amplitudes is computed for ALL intervals at once, and
each interval is three operations (gather, multiply, scatter-add) on one preallocated buffer:

* The amplitudes of interval n are a *mirrored* block of 2 (S_n + 1) rows ``[A_n; 1; conj(A_n); 1]``;
  the constant rows carry the T1 recovery of the equilibrium state (scaled by the interval's ``rec_n``,
  it enters through the equilibrium state's RF edges, as in :func:`dtoc.sim.pdg_evolve._rf`).
* ``F_n = [fac_n; rec_n]`` (relaxation x diffusion factors of all intervals, and the recovery) is one
  (sum of rows, U) real tensor computed with a handful of operations (the only place where the gradient
  waveform enters, through the diffusion b-integrals).
* An RF edge p -> c with coefficient c_e is ``x_c += c_e F_p x_p`` (plain) or ``x_c += c_e F_p conj(x_p)``
  (conjugating).  With the conjugates stored beside the amplitudes, a conjugating edge reads the mirror
  row ``conj(x_p)`` and every edge has a mirror ``conj(x_c) += conj(c_e) F_p (conj(x_p) | x_p)`` that keeps
  the mirror half the conjugate of the first: the step is complex-LINEAR in the mirrored block,
  ``B_{n+1} += scatter(child, w * B_n[parent])`` with the weights ``w = coef x F`` of all edges of all
  steps computed at once before the loop.  Twice the edges of a plain split, three dispatched operations
  per step.  The products are the same up to rounding (``c (F x)`` there, ``(c F) x`` here): equal to the
  per-interval path to the tolerances of tests/test_sim_fused.py.
* The emitting rows of every interval are gathered from the buffer at the end (one gather).

The backward is the adjoint of that complex-linear recursion (torch's convention grad = dL/dRe + i dL/dIm:
for y = w x, grad_x = conj(w) grad_y):  ``L_n += scatter(parent, conj(w) L_{n+1}[child])``, three
operations per step; then for all edges at once (in chunks of at most a buffer's rows)
``dL/dF_p = sum_e Re(L_{n+1}[child_e] conj(c_e) conj(B_n[parent_e]))`` (the mirror edges count as uses of F).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dtoc.sim.pdg_rows import CONJ


@dataclass
class FusedPlan:
    """Index arrays of the buffer propagation (graph only; cached per graph and device).

    Attributes:
        sizes: (NI,) rows m_n = S_n + 1 of each interval's block ``[A_n; 1]``.
        offs: (NI + 1,) block offsets in the row space of the scales F (one block of m_n rows per interval).
        frow: (sum of rows,) long tensor: row of ``[fac of all states; rec of all intervals]`` that
            scales each row of F.
        offs2: (NI + 1,) block offsets in the mirrored buffer (2 m_n rows per interval: ``[A_n; 1; conj(A_n); 1]``).
        one_rows2: long tensor: the constant rows of every mirrored block.
        parent2, child2: per step n (0..NI-2) long tensors: source row in mirrored block n, target row in
            mirrored block n + 1, of the step's main edges followed by their mirrors.
        n_edges2: per step, its number of mirrored edges; step_edges2: their cumulative sum (NI entries).
        crow2: (E2,) row of ``[CT; conj(CT)]`` of every mirrored edge (pulse * 6 + kind, + 6 NRF on a mirror).
        frow2: (E2,) row of F (the parent's scale) of every mirrored edge.
        gparent2, gchild2: (E2,) the edges' parent and child rows in the whole mirrored buffer.

    The emitting rows are not part of the plan (read from the graph on every call: a copied graph may
    change them, :func:`emitting_rows`).
    """

    sizes: list[int]
    offs: np.ndarray
    frow: torch.Tensor
    offs2: np.ndarray
    one_rows2: torch.Tensor
    parent2: list[torch.Tensor]
    child2: list[torch.Tensor]
    n_edges2: list[int]
    step_edges2: np.ndarray | None = None
    crow2: torch.Tensor | None = None
    frow2: torch.Tensor | None = None
    gparent2: torch.Tensor | None = None
    gchild2: torch.Tensor | None = None


def _step_edges(iv, nxt, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(parent row, child row, coefficient row, conjugating flag) of the split from ``iv`` (step n) into
    ``nxt``: plain edges by kind, conjugating edges by kind, then the recovery edges from the constant row
    (the order of :func:`dtoc.sim.pdg_rfsplit._split`)."""
    S = iv.n_states
    kind, par, child = nxt.edge_kind, nxt.edge_parent, nxt.edge_child
    cj = CONJ[kind]
    order = []
    for is_conj in (False, True):  # the order of pdg_rfsplit._groups / _split
        sel = np.where(cj == is_conj)[0]
        order.append(sel[np.argsort(kind[sel], kind="stable")])
    o = np.concatenate(order).astype(np.int64)
    at_eq = np.where(par == iv.eq_index)[0]
    return (
        np.concatenate([par[o], np.full(at_eq.size, S)]).astype(np.int64),
        np.concatenate([child[o], child[at_eq]]).astype(np.int64),
        (np.concatenate([kind[o], kind[at_eq]]) + 6 * n).astype(np.int64),
        np.concatenate([np.zeros(order[0].size, bool), np.ones(order[1].size, bool), np.zeros(at_eq.size, bool)]),
    )


def _split_tensor(arrs: list[np.ndarray], device) -> list[torch.Tensor]:
    """Per-step index arrays as views of one device tensor (one transfer instead of one per step)."""
    if not arrs:
        return []
    t = torch.as_tensor(np.concatenate(arrs), device=device)
    return list(torch.split(t, [a.size for a in arrs]))


def emitting_rows(graph, plan: FusedPlan, device) -> tuple[torch.Tensor, list[int]]:
    """(J_tot,) mirrored-buffer rows of the emitting states of all intervals (interval order) and their
    number per interval (0 where none emits: no ADC sample in the interval)."""
    rows, sizes = [], []
    for n, iv in enumerate(graph.intervals):
        e = iv.emit if (iv.emit.size and iv.adc_stop > iv.adc_start) else np.zeros(0, np.int64)
        rows.append(plan.offs2[n] + e)
        sizes.append(int(e.size))
    return torch.as_tensor(np.concatenate(rows).astype(np.int64), device=device), sizes


def fused_plan(graph, device) -> FusedPlan:
    """The :class:`FusedPlan` of ``graph`` on ``device`` (built once, cached on the graph)."""
    cache = graph.__dict__.setdefault("_torch_cache", {})
    key = ("fused2", str(device))
    if key in cache:
        return cache[key]
    ivs = graph.intervals
    NI = len(ivs)
    S = np.array([iv.n_states for iv in ivs], dtype=np.int64)
    sizes = S + 1
    offs = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    offs2 = 2 * offs
    soff = np.concatenate([[0], np.cumsum(S)]).astype(np.int64)
    n_rf = max(NI - 1, 1)
    frow = np.concatenate([np.concatenate([soff[n] + np.arange(S[n]), [soff[-1] + n]]) for n in range(NI)])
    par2, ch2, crow2, frow2, gpar2, gch2 = [], [], [], [], [], []
    for n in range(NI - 1):
        par, ch, crow, cj = _step_edges(ivs[n], ivs[n + 1], n)
        m, m1 = int(sizes[n]), int(sizes[n + 1])
        # main edge: x_c += w (x_p | conj(x_p)); its mirror: conj(x_c) += conj(w) (conj(x_p) | x_p)
        p2 = np.concatenate([par + m * cj, par + m * (~cj)])
        c2 = np.concatenate([ch, ch + m1])
        par2.append(p2)
        ch2.append(c2)
        crow2.append(np.concatenate([crow, crow + 6 * n_rf]))
        frow2.append(np.concatenate([offs[n] + par, offs[n] + par]))
        gpar2.append(offs2[n] + p2)
        gch2.append(offs2[n + 1] + c2)
    ones = np.concatenate([[offs2[n] + sizes[n] - 1, offs2[n] + 2 * sizes[n] - 1] for n in range(NI)])
    n_edges2 = [int(p.size) for p in par2]
    cat = lambda xs: torch.as_tensor(  # noqa: E731
        np.concatenate(xs).astype(np.int64) if xs else np.zeros(0, np.int64), device=device
    )
    plan = FusedPlan(
        sizes=sizes.tolist(),
        offs=offs,
        frow=torch.as_tensor(frow.astype(np.int64), device=device),
        offs2=offs2,
        one_rows2=torch.as_tensor(ones.astype(np.int64), device=device),
        parent2=_split_tensor(par2, device),
        child2=_split_tensor(ch2, device),
        n_edges2=n_edges2,
        step_edges2=np.concatenate([[0], np.cumsum(n_edges2)]).astype(np.int64),
        crow2=cat(crow2),
        frow2=cat(frow2),
        gparent2=cat(gpar2),
        gchild2=cat(gch2),
    )
    cache[key] = plan
    return plan


def coefficient_table(graph, ir, b1: torch.Tensor, cdtype, rf_coefficients) -> torch.Tensor:
    """(6 NRF, U) complex: the six edge coefficients of every RF pulse of the graph (time order); the same values as :func:`dtoc.sim.pdg_evolve.make_steps` (phase-free rows per flip times
    the pulse's phase factors)."""
    dev = b1.device
    rfs = [ir.rf[int(i)] for i in graph.rf_order[: len(graph.intervals) - 1]]
    if not rfs:
        return torch.zeros((6, b1.shape[0]), dtype=cdtype, device=dev)
    flips = sorted({float(r.flip_angle_rad) for r in rfs})
    base = torch.stack([rf_coefficients(f, 0.0, b1, cdtype) for f in flips])  # (F, 6, U)
    fidx = torch.as_tensor([flips.index(float(r.flip_angle_rad)) for r in rfs], device=dev)
    ph = np.array([r.phase_rad for r in rfs], dtype=np.float64)
    e1 = np.cos(ph) + 1j * np.sin(ph)
    e2 = np.cos(2 * ph) + 1j * np.sin(2 * ph)
    one = np.ones_like(e1)
    phase = np.stack([one, e2, e1.conj(), e1, e1, one], 1)  # (NRF, 6), as rf_coefficients' cached path
    return (base.index_select(0, fidx) * torch.as_tensor(phase, dtype=cdtype, device=dev)[:, :, None]).reshape(
        -1, b1.shape[0]
    )


def scale_rows(graph, bounds_t: np.ndarray, tis, b_all: torch.Tensor | None) -> torch.Tensor:
    """(sum S_n + NI, U) real: [fac of every state of every interval; rec of every interval] (see module doc).

    fac = exp(-b D - dt R) with R = 1/T2 for transverse and 1/T1 for longitudinal states, b the diffusion
    b-integral (``b_all``, (sum S_n,), None: no diffusion); rec = PD (1 - exp(-dt/T1)).  The same
    floating-point operations as :func:`dtoc.sim.pdg_evolve._factor` and :func:`make_steps`."""
    ivs = graph.intervals
    dev, rdt = tis.r1.device, tis.r1.dtype
    dt = np.diff(np.asarray(bounds_t, dtype=np.float64))
    S = [iv.n_states for iv in ivs]
    tr = np.concatenate([~iv.is_z for iv in ivs])
    dt_rows = np.repeat(dt, S)
    dt_t = torch.as_tensor(dt_rows, device=dev).to(rdt)[:, None]
    rate = torch.where(torch.as_tensor(tr, device=dev)[:, None], dt_t * tis.r2[None, :], dt_t * tis.r1[None, :])
    if b_all is None:
        fac = torch.exp(-rate)
    else:
        fac = (torch.outer(-b_all.to(rdt), tis.d) - rate).exp()
    rec = tis.pd[None, :] * (1.0 - torch.exp(-(torch.as_tensor(dt, device=dev).to(rdt)[:, None] * tis.r1[None, :])))
    return torch.cat([fac, rec], 0)


def _mirrored_weights(plan: FusedPlan, CT: torch.Tensor, F: torch.Tensor | None, n0: int, n1: int) -> torch.Tensor:
    """(E2, U) complex: the weight of every edge of the mirrored buffer of steps n0..n1-1 (step order, each
    step's main edges then their mirrors): its coefficient (conjugated on a mirror edge) times its parent
    row's real scale F (no F when ``F`` is None).  A handful of operations for all those steps."""
    assert plan.crow2 is not None and plan.frow2 is not None and plan.step_edges2 is not None
    e0, e1 = int(plan.step_edges2[n0]), int(plan.step_edges2[n1])
    W = torch.cat([CT, CT.conj()], 0).index_select(0, plan.crow2[e0:e1])
    return W if F is None else W * F.index_select(0, plan.frow2[e0:e1])


def _forward(plan: FusedPlan, A0: torch.Tensor, F: torch.Tensor, CT: torch.Tensor, n_steps: int, n0: int = 0):
    """The mirrored buffer (rows2, U) complex of the blocks n0..n0 + n_steps (see the module docstring),
    ``A0`` the amplitudes at the start of interval n0: per step one gather of the parents' rows, one product
    with the edges' weights (coefficient x parent scale, computed for all the steps at once), one
    scatter-add into the next block: three dispatched operations."""
    n1 = n0 + n_steps
    sizes2 = [2 * m for m in plan.sizes[n0 : n1 + 1]]
    o0 = int(plan.offs2[n0])
    S0, m0, U = A0.shape[0], plan.sizes[n0], A0.shape[1]
    buf = torch.zeros((sum(sizes2), U), dtype=A0.dtype, device=A0.device)
    buf[:S0] = A0
    buf[m0 : m0 + S0] = A0.conj()
    buf.index_fill_(0, plan.one_rows2[2 * n0 : 2 * (n1 + 1)] - o0 if o0 else plan.one_rows2[: 2 * (n1 + 1)], 1.0)
    blocks = torch.split(buf, sizes2, 0)
    W = torch.split(_mirrored_weights(plan, CT, F, n0, n1), plan.n_edges2[n0:n1], 0)
    for i, n in enumerate(range(n0, n1)):
        blocks[i + 1].index_add_(0, plan.child2[n], blocks[i].index_select(0, plan.parent2[n]).mul_(W[i]))
    return buf


class _FusedPropagate(torch.autograd.Function):
    """Emitting rows (J_tot, U) of all intervals, differentiable w.r.t. the row scales F (see module doc)."""

    @staticmethod
    def forward(ctx, F, A0, CT, plan, n_steps, emit_rows2):
        buf = _forward(plan, A0, F.detach(), CT, n_steps)
        ctx.plan, ctx.n_steps = plan, n_steps
        ctx.save_for_backward(F, CT, buf, emit_rows2)
        return buf.index_select(0, emit_rows2)

    @staticmethod
    def backward(ctx, gY):
        F, CT, buf, emit_rows2 = ctx.saved_tensors
        plan, n_steps = ctx.plan, ctx.n_steps
        assert plan.gparent2 is not None and plan.gchild2 is not None and plan.frow2 is not None
        lam = torch.zeros_like(buf).index_add_(0, emit_rows2, gY)
        lams = torch.split(lam, [2 * m for m in plan.sizes[: n_steps + 1]], 0)
        Wc = torch.split(_mirrored_weights(plan, CT, F, 0, n_steps).conj_physical_(), plan.n_edges2[:n_steps], 0)
        for n in range(n_steps - 1, -1, -1):  # the adjoint: L_n[parent] += conj(w) L_{n+1}[child]
            lams[n].index_add_(0, plan.parent2[n], lams[n + 1].index_select(0, plan.child2[n]).mul_(Wc[n]))
        # dL/dF of a row = sum over its edges e of Re(L[child_e] conj(c_e) conj(B[parent_e])), in chunks of
        # at most one buffer's worth of edges (a few chunks: the temporaries stay the buffer's size)
        dF = torch.zeros_like(F)
        E2 = int(plan.step_edges2[n_steps])
        Cc = torch.cat([CT.conj(), CT], 0)
        step = max(int(buf.shape[0]), 1)
        for a in range(0, E2, step):
            b = min(E2, a + step)
            h = lam.index_select(0, plan.gchild2[a:b]) * Cc.index_select(0, plan.crow2[a:b])
            dF.index_add_(0, plan.frow2[a:b], (h * buf.index_select(0, plan.gparent2[a:b]).conj()).real)
        return dF, None, None, None, None, None


def propagate_fused(graph, plan: FusedPlan, A0: torch.Tensor, F: torch.Tensor, CT: torch.Tensor) -> list:
    """Emitting rows per interval (list aligned with the intervals, None where none emits); differentiable
    w.r.t. ``F`` (:func:`scale_rows`) when it requires a gradient and autograd is on."""
    emit_rows, emit_sizes = emitting_rows(graph, plan, A0.device)
    emitting = [n for n, j in enumerate(emit_sizes) if j]
    if not emitting:
        return [None] * len(plan.sizes)
    n_steps = max(emitting)  # nothing after the last emitting interval is observed
    if torch.is_grad_enabled() and F.requires_grad:
        Y = _FusedPropagate.apply(F, A0, CT, plan, n_steps, emit_rows)
    else:
        with torch.no_grad():
            Y = _forward(plan, A0, F, CT, n_steps).index_select(0, emit_rows)
    parts = torch.split(Y, [emit_sizes[n] for n in emitting], 0)
    out: list = [None] * len(plan.sizes)
    for n, y in zip(emitting, parts):
        out[n] = y
    return out


def final_amplitudes(
    graph, plan: FusedPlan, A0: torch.Tensor, F: torch.Tensor, CT: torch.Tensor, max_bytes: float = float("inf")
) -> torch.Tensor:
    """(S_last, U) amplitudes at the END of the last interval, its T1 recovery added to the equilibrium state
    (the dummy trains' final state; no autograd), as :func:`dtoc.sim.pdg_evolve.propagate` with ``final_state``.

    The train runs in segments whose mirrored buffer and edge weights stay within ``max_bytes`` (at least one
    step each): the last block of a segment is the first of the next, so the amplitudes are the same."""
    NI = len(plan.sizes)
    per = A0.element_size() * A0.shape[1]
    A, n0 = A0, 0
    while n0 < NI - 1:
        n1, used = n0 + 1, per * (2 * plan.sizes[n0] + 2 * plan.sizes[n0 + 1] + plan.n_edges2[n0])
        while n1 < NI - 1 and used + per * (2 * plan.sizes[n1 + 1] + plan.n_edges2[n1]) <= max_bytes:
            used += per * (2 * plan.sizes[n1 + 1] + plan.n_edges2[n1])
            n1 += 1
        buf = _forward(plan, A, F, CT, n1 - n0, n0)
        o2 = int(plan.offs2[n1] - plan.offs2[n0])
        A, n0 = buf[o2 : o2 + plan.sizes[n1] - 1], n1
    o, S = int(plan.offs[NI - 1]), plan.sizes[NI - 1] - 1
    A_end = A * F[o : o + S]
    A_end[graph.intervals[-1].eq_index] += F[o + S].to(A_end.dtype)
    return A_end
