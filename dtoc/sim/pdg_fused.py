"""The PDG amplitude propagation as a fixed, small number of tensor operations per RF interval.

Same recursion as :mod:`dtoc.sim.pdg_evolve` (read its docstring first), rewritten so that everything
that does not depend on the previous interval's amplitudes is computed for ALL intervals at once, and
each interval is a handful of operations (scale, gather, conjugate a slice, scale, scatter-add) on one
preallocated buffer:

* The amplitudes of interval n are a block of S_n + 1 rows ``[A_n; 1]`` of the buffer; the constant row
  carries the T1 recovery of the equilibrium state (scaled by the interval's ``rec_n``, it enters
  through the equilibrium state's RF edges, as in :func:`dtoc.sim.pdg_evolve._rf`).
* ``F_n = [fac_n; rec_n]`` (relaxation x diffusion factors of all intervals, and the recovery) is one
  (sum of rows, U) real tensor computed with a handful of operations (the only place where the gradient
  waveform enters, through the diffusion b-integrals).
* Step n:  ``E = B_n * F_n``;  ``G = E[parent]``;  ``G[conjugating edges] = conj(G[...])`` (one slice:
  edges ordered plain by kind, conjugating by kind, then the recovery edges, the order of
  :func:`dtoc.sim.pdg_rfsplit._split`);  ``G *= coef[row]``;  ``B_{n+1} += scatter(child, G)``.  So every
  amplitude is the same floating-point sum as in :mod:`dtoc.sim.pdg_evolve` (c conj(x) = conj(conj(c) x)).
* The emitting rows of every interval are gathered from the buffer at the end (one gather).

The backward is the adjoint recursion (torch's convention grad = dL/dRe + i dL/dIm; for y = c conj(x),
grad_x = conj(conj(c) g)):  ``h = L_{n+1}[child] conj(coef)``, conjugated on the conjugating slice;
``gE = scatter(parent, h)``;  ``dL/dF_n = Re(gE conj(B_n))``;  ``L_n += gE F_n``.  Per interval a constant
number of operations, independent of the number of edges, states or voxels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dtoc.sim.pdg_graph import CONJ


@dataclass
class FusedPlan:
    """Index arrays of the buffer propagation (graph only; cached per graph and device).

    Attributes:
        sizes: (NI,) rows of each interval's block (S_n + 1).
        offs: (NI + 1,) block offsets in the buffer.
        one_rows: (NI,) long tensor: the constant row of each block.
        parent, child, crow: per step n (0..NI-2) long tensors: source row in block n, target row in
            block n + 1, row of the coefficient table (pulse * 6 + kind).
        conj: per step, the (start, stop) slice of its conjugating edges.
        frow: (sum of rows,) long tensor: row of ``[fac of all states; rec of all intervals]`` that
            scales each buffer row.

    The emitting rows are not part of the plan (read from the graph on every call: a copied graph may
    change them, :func:`emitting_rows`).
    """

    sizes: list[int]
    offs: np.ndarray
    one_rows: torch.Tensor
    parent: list[torch.Tensor]
    child: list[torch.Tensor]
    crow: list[torch.Tensor]
    conj: list[tuple[int, int]]
    frow: torch.Tensor
    gparent: torch.Tensor | None = None
    conj_sign: torch.Tensor | None = None


def _step_edges(iv, nxt, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    """(parent row, child row, coefficient row, conjugating slice) of the split from ``iv`` (step n) into ``nxt``."""
    S = iv.n_states
    kind, par, child = nxt.edge_kind, nxt.edge_parent, nxt.edge_child
    cj = CONJ[kind]
    order = []
    for is_conj in (False, True):  # the order of pdg_rfsplit._groups / _split
        sel = np.where(cj == is_conj)[0]
        order.append(sel[np.argsort(kind[sel], kind="stable")])
    o = np.concatenate(order).astype(np.int64)
    at_eq = np.where(par == iv.eq_index)[0]
    a = int(order[0].size)
    return (
        np.concatenate([par[o], np.full(at_eq.size, S)]).astype(np.int64),
        np.concatenate([child[o], child[at_eq]]).astype(np.int64),
        (np.concatenate([kind[o], kind[at_eq]]) + 6 * n).astype(np.int64),
        (a, a + int(order[1].size)),
    )


def _split_tensor(arrs: list[np.ndarray], device) -> list[torch.Tensor]:
    """Per-step index arrays as views of one device tensor (one transfer instead of one per step)."""
    if not arrs:
        return []
    t = torch.as_tensor(np.concatenate(arrs), device=device)
    return list(torch.split(t, [a.size for a in arrs]))


def emitting_rows(graph, plan: FusedPlan, device) -> tuple[torch.Tensor, list[int]]:
    """(J_tot,) buffer rows of the emitting states of all intervals (interval order) and their number per
    interval (0 where none emits: no ADC sample in the interval)."""
    rows, sizes = [], []
    for n, iv in enumerate(graph.intervals):
        e = iv.emit if (iv.emit.size and iv.adc_stop > iv.adc_start) else np.zeros(0, np.int64)
        rows.append(plan.offs[n] + e)
        sizes.append(int(e.size))
    return torch.as_tensor(np.concatenate(rows).astype(np.int64), device=device), sizes


def fused_plan(graph, device) -> FusedPlan:
    """The :class:`FusedPlan` of ``graph`` on ``device`` (built once, cached on the graph)."""
    cache = graph.__dict__.setdefault("_torch_cache", {})
    key = ("fused", str(device))
    if key in cache:
        return cache[key]
    ivs = graph.intervals
    NI = len(ivs)
    S = np.array([iv.n_states for iv in ivs], dtype=np.int64)
    sizes = S + 1
    offs = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    soff = np.concatenate([[0], np.cumsum(S)]).astype(np.int64)
    edges = [_step_edges(ivs[n], ivs[n + 1], n) for n in range(NI - 1)]
    frow = np.concatenate([np.concatenate([soff[n] + np.arange(S[n]), [soff[-1] + n]]) for n in range(NI)])
    plan = FusedPlan(
        sizes=sizes.tolist(),
        offs=offs,
        one_rows=torch.as_tensor(offs[1:] - 1, device=device),
        parent=_split_tensor([e[0] for e in edges], device),
        child=_split_tensor([e[1] for e in edges], device),
        crow=_split_tensor([e[2] for e in edges], device),
        conj=[e[3] for e in edges],
        frow=torch.as_tensor(frow.astype(np.int64), device=device),
    )
    # all steps' parent rows in the buffer, and -1 on the conjugating edges (:func:`_edge_scales`)
    gpar = [offs[n] + e[0] for n, e in enumerate(edges)]
    sign = [np.where((np.arange(e[0].size) >= e[3][0]) & (np.arange(e[0].size) < e[3][1]), -1.0, 1.0) for e in edges]
    plan.gparent = torch.as_tensor(
        np.concatenate(gpar).astype(np.int64) if gpar else np.zeros(0, np.int64), device=device
    )
    plan.conj_sign = torch.as_tensor(np.concatenate(sign) if sign else np.zeros(0), device=device)
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


def _edge_coefficients(plan: FusedPlan, CT: torch.Tensor) -> list[torch.Tensor]:
    """Per step, the (E_n, U) complex coefficient of every edge: one gather for all steps."""
    if not plan.crow:
        return []
    return list(torch.split(CT.index_select(0, torch.cat(plan.crow)), [c.shape[0] for c in plan.crow], 0))


def _edge_scales(plan: FusedPlan, F: torch.Tensor, n_steps: int) -> list[torch.Tensor]:
    """Per step, the (E_n, 2 U) real factor of every edge in the real view: its parent row's scale F,
    negated on the imaginary half of the conjugating edges (so that x F, conjugated, is one product:
    (xr F, xi (-F)) = conj(x F) exactly).  A handful of operations for all steps."""
    if not n_steps:
        return []
    assert plan.gparent is not None and plan.conj_sign is not None  # set by fused_plan
    U = F.shape[1]
    sizes = [plan.parent[n].shape[0] for n in range(n_steps)]
    E = sum(sizes)
    FS = F.index_select(0, plan.gparent[:E])[:, :, None].repeat(1, 1, 2)  # (E, U, 2)
    FS[:, :, 1].mul_(plan.conj_sign[:E, None])
    return list(torch.split(FS.view(E, 2 * U), sizes, 0))


def _forward(plan: FusedPlan, A0: torch.Tensor, F: torch.Tensor, CT: torch.Tensor, n_steps: int):
    """The buffer of all blocks (rows, U) complex (see the module docstring).

    Per step, in the real view: one gather of the parents' rows, one product with the edges' real scales
    (:func:`_edge_scales`: the parent's F, the conjugation as a sign; the same products as scaling the
    block and conjugating the slice), the edge coefficients multiplied, one scatter-add into the next
    block: six dispatched operations (two of them views)."""
    R, U = int(plan.offs[-1]), A0.shape[1]
    buf = torch.zeros((R, U), dtype=A0.dtype, device=A0.device)
    buf[: A0.shape[0]] = A0
    buf.index_fill_(0, plan.one_rows, 1.0)
    blocks2 = torch.split(torch.view_as_real(buf).view(R, 2 * U), plan.sizes, 0)
    W = _edge_coefficients(plan, CT)
    FS = _edge_scales(plan, F, n_steps)
    for n in range(n_steps):
        Gr = blocks2[n].index_select(0, plan.parent[n]).mul_(FS[n])
        torch.view_as_complex(Gr.view(-1, U, 2)).mul_(W[n])
        blocks2[n + 1].index_add_(0, plan.child[n], Gr)
    return buf


class _FusedPropagate(torch.autograd.Function):
    """Emitting rows (J_tot, U) of all intervals, differentiable w.r.t. the row scales F (see module doc)."""

    @staticmethod
    def forward(ctx, F, A0, CT, plan, n_steps, emit_rows):
        buf = _forward(plan, A0, F.detach(), CT, n_steps)
        ctx.plan, ctx.n_steps = plan, n_steps
        ctx.save_for_backward(F, CT, buf, emit_rows)
        return buf.index_select(0, emit_rows)

    @staticmethod
    def backward(ctx, gY):
        F, CT, buf, emit_rows = ctx.saved_tensors
        plan, n_steps = ctx.plan, ctx.n_steps
        R, U = buf.shape
        lam = torch.zeros_like(buf)
        lam2 = torch.view_as_real(lam).view(R, 2 * U)
        lam2.index_add_(0, emit_rows, torch.view_as_real(gY.contiguous()).reshape(-1, 2 * U))
        lams = torch.split(lam, plan.sizes, 0)
        lams2 = torch.split(lam2, plan.sizes, 0)
        Fs = torch.split(F, plan.sizes, 0)
        Wc = _edge_coefficients(plan, CT.conj().resolve_conj())
        gE_all = torch.zeros((int(plan.offs[n_steps]), U), dtype=buf.dtype, device=buf.device)
        gEs = torch.split(gE_all, plan.sizes[:n_steps], 0)
        gEs2 = torch.split(torch.view_as_real(gE_all).view(-1, 2 * U), plan.sizes[:n_steps], 0)
        for n in range(n_steps - 1, -1, -1):
            hr = lams2[n + 1].index_select(0, plan.child[n])
            h = torch.view_as_complex(hr.view(-1, U, 2))
            h.mul_(Wc[n])
            a, b = plan.conj[n]
            if b > a:
                h[a:b].conj_physical_()
            gEs2[n].index_add_(0, plan.parent[n], hr)
            lams[n].addcmul_(gEs[n], Fs[n])
        # dL/dF = Re(gE conj(B)) for all blocks at once (zero beyond the last step)
        dF = torch.zeros_like(F)
        nr = int(plan.offs[n_steps])
        dF[:nr] = (gE_all * buf[:nr].conj()).real
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


def final_amplitudes(graph, plan: FusedPlan, A0: torch.Tensor, F: torch.Tensor, CT: torch.Tensor) -> torch.Tensor:
    """(S_last, U) amplitudes at the END of the last interval, its T1 recovery added to the equilibrium state
    (the dummy trains' final state; no autograd), as :func:`dtoc.sim.pdg_evolve.propagate` with ``final_state``."""
    NI = len(plan.sizes)
    buf = _forward(plan, A0, F, CT, NI - 1)
    o, S = int(plan.offs[NI - 1]), plan.sizes[NI - 1] - 1
    A_end = buf[o : o + S] * F[o : o + S]
    A_end[graph.intervals[-1].eq_index] += F[o + S].to(A_end.dtype)
    return A_end
