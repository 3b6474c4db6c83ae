"""State-amplitude propagation of the PDG main pass as ONE autograd function with a hand-written adjoint.

The amplitudes ``A_n`` (S_n, V) of interval n (at its start) evolve as

    A_end = A_n * fac_n,        fac_n[s, v] = E(v) exp(-b_n[s] D(v))   (E = exp(-dt/T2) for transverse rows,
                                                                         exp(-dt/T1) for longitudinal rows)
    A_{n+1} = Split_n(A_end) + (T1 recovery of the equilibrium state through its RF edges),

with ``Split_n`` the linear RF split (:mod:`dtoc.sim.pdg_rfsplit`) and ``b_n`` (S_n,) the diffusion
b-integral of every state over the interval (a function of the realized k: the only way the
gradient waveform reaches the amplitudes).  The outputs are the emitting rows ``Y_n = A_n[emit_n]``
of every interval with ADC samples (the signal is evaluated from them afterwards).

Under generic autograd every interval records ~30 nodes and saves ~8 (S, V) tensors; here the forward
runs without autograd, saves only ``A_end`` (and ``fac`` unless recomputing), and the backward is the
adjoint recursion (torch's convention for complex gradients, grad = dL/dRe + i dL/dIm):

    mu_n = Split_n^T(lambda_{n+1})                          (dL/dA_end)
    dL/db_n[s] = -sum_v D(v) Re(mu_n[s, v] conj(A_end[s, v]))
    lambda_n = fac_n * mu_n + scatter(dL/dY_n at emit_n)     (dL/dA_n; fac is real)

The T1 recovery does not depend on A or b, so it has no adjoint term.  Exactly the same numbers as
the generic path up to rounding (tests/test_sim_perf_equivalence.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dtoc.sim.pdg_rfsplit import _groups, _split, _split_adjoint, add_rows_
from dtoc.sim.pdg_rows import CONJ


@dataclass
class Step:
    """Everything interval n needs, precomputed once per simulate call.

    Attributes:
        S: number of states of the interval.
        nT: number of transverse states (ordered first).
        E1, E2: (V,) real relaxation factors over the interval; dt (s), r1, r2 (V,) 1/s: the same as rates.
        emit: (J,) long tensor of the emitting rows, or None (no ADC / no signal wanted).
        coefs: (6, V) complex RF edge coefficients of the pulse ending the interval (None: last interval).
        groups: edge groups of that pulse (:func:`dtoc.sim.pdg_rfsplit._groups`).
        n_next: number of states of the next interval.
        eq_edges: (kind rows (E_eq,), children (E_eq,)) of the equilibrium state's edges, or None.
        eq_index: index of the equilibrium state (receives the T1 recovery at the very end).
    """

    S: int
    nT: int
    E1: torch.Tensor
    E2: torch.Tensor
    dt: float
    r1: torch.Tensor
    r2: torch.Tensor
    emit: torch.Tensor | None
    coefs: torch.Tensor | None
    groups: list | None
    n_next: int
    eq_edges: tuple | None
    eq_index: int


def _factor(step: Step, b: torch.Tensor | None, D: torch.Tensor | None, S: int) -> torch.Tensor:
    """(S, V) real fac_n (expanded view when there is no diffusion)."""
    V = step.E1.shape[0]
    if b is None:
        if step.nT == S:
            return step.E2[None].expand(S, V)
        if step.nT == 0:
            return step.E1[None].expand(S, V)
        return torch.cat([step.E2[None].expand(step.nT, V), step.E1[None].expand(S - step.nT, V)], 0)
    # exp(-b D + log E) in place: three passes over (S, V), no concatenated E
    assert D is not None, "a b-integral without diffusion coefficients"
    x = torch.outer(-b, D)
    x[: step.nT] -= step.dt * step.r2[None, :]
    x[step.nT :] -= step.dt * step.r1[None, :]
    return x.exp_()


def _rf(step: Step, A_end: torch.Tensor, rec: torch.Tensor) -> torch.Tensor:
    assert step.coefs is not None, "RF split after the last interval"
    A = _split(A_end, step.coefs, step.groups, step.n_next)
    if step.eq_edges is not None:
        rows, child = step.eq_edges
        add_rows_(A, child, step.coefs.index_select(0, rows) * rec.to(A.dtype)[None, :])
    return A


def propagate(
    steps: list[Step], A0: torch.Tensor, bs: list, D, rec: list, final_state: bool, save: str = "none", sink=None
):
    """Forward recursion (no autograd).  Returns (emitting rows per interval (None where none), final A, saved).

    ``save``: 'none', 'full' (A_end and fac per interval) or 'recompute' (A_n only; fac and A_end
    recomputed in the backward).  ``sink(n, Y)``: called with each interval's emitting rows instead of
    keeping them (streaming, forward only).
    """
    A = A0
    Ys: list = []
    saved: list = []
    NI = len(steps)
    for n, st in enumerate(steps):
        Y = A.index_select(0, st.emit) if st.emit is not None else None
        if sink is not None and Y is not None:
            sink(n, Y)
            Y = None
        Ys.append(Y)
        if n == NI - 1 and not final_state:
            break
        S = A.shape[0]
        fac = _factor(st, bs[n], D, S)
        if save == "recompute":
            saved.append(A)
        A_end = A * fac
        if save == "full":
            saved.append((A_end, fac))
        if n == NI - 1:
            A_end[st.eq_index] += rec[n].to(A_end.dtype)
            A = A_end
            break
        A = _rf(st, A_end, rec[n])
    return Ys, A, saved


class _Propagate(torch.autograd.Function):
    @staticmethod
    def forward(ctx, plan, A0, D, *bs):
        steps, rec, recompute = plan
        need = any(ctx.needs_input_grad[3:])
        save = ("recompute" if recompute else "full") if need else "none"
        Ys, _, saved = propagate(steps, A0, list(bs) if bs else [None] * len(steps), D, rec, False, save)
        ctx.plan, ctx.saved, ctx.mode, ctx.nb = plan, saved, save, len(bs)
        ctx.save_for_backward(D, *bs)
        emit_n = [n for n, y in enumerate(Ys) if y is not None]
        ctx.emit_n = emit_n
        return tuple(Ys[n] for n in emit_n)

    @staticmethod
    def backward(ctx, *G):
        steps, rec, _ = ctx.plan
        D, *bs = ctx.saved_tensors
        grads_b = [None] * ctx.nb
        if ctx.mode == "none":
            return (None, None, None, *grads_b)
        Gn = dict(zip(ctx.emit_n, G))
        lam = None
        last = max(ctx.emit_n) if ctx.emit_n else -1
        for n in range(last, -1, -1):
            st = steps[n]
            if lam is not None:
                if ctx.mode == "full":
                    A_end, fac = ctx.saved[n]
                else:
                    A_n = ctx.saved[n]
                    fac = _factor(st, bs[n], D, A_n.shape[0])
                    A_end = A_n * fac
                mu = _split_adjoint(lam, st.coefs, st.groups, A_end.shape[0])
                if bs:
                    grads_b[n] = -((mu.real * A_end.real + mu.imag * A_end.imag) @ D)
                lam = mu * fac
            g = Gn.get(n)
            if g is not None:
                if lam is None:
                    lam = torch.zeros((st.S, g.shape[1]), dtype=g.dtype, device=g.device)
                add_rows_(lam, st.emit, g)
        return (None, None, None, *grads_b)


def make_steps(graph, ir, vox, bounds_t, cdtype, with_signal: bool, rf_coefficients) -> tuple[list[Step], list]:
    """Per-interval :class:`Step` list and T1 recovery terms (V,) of the equilibrium state."""

    dev = vox.pd.device
    steps, rec = [], []
    coef_cache: dict = {}
    e_cache: dict = {}
    NI = len(graph.intervals)
    for n, iv in enumerate(graph.intervals):
        dt = float(bounds_t[n + 1] - bounds_t[n])
        ek = round(dt * 1e15)
        if ek not in e_cache:
            E1 = torch.exp(-dt * vox.r1)
            e_cache[ek] = (E1, torch.exp(-dt * vox.r2), vox.pd * (1.0 - E1))
        E1, E2, rc = e_cache[ek]
        nT = int((~iv.is_z).sum())
        if iv.is_z[:nT].any():
            raise RuntimeError("PDG graph states must be ordered transverse first")
        emit = None
        if with_signal and iv.emit.size and iv.adc_stop > iv.adc_start:
            emit = torch.as_tensor(iv.emit, device=dev)
        coefs = groups = eq_edges = None
        n_next = 0
        if n < NI - 1:
            rf = ir.rf[graph.rf_order[n]]
            key = (rf.flip_angle_rad, rf.phase_rad)
            coefs = coef_cache.get(key)
            if coefs is None:
                coefs = coef_cache[key] = rf_coefficients(rf.flip_angle_rad, rf.phase_rad, vox.b1, cdtype, coef_cache)
            nxt = graph.intervals[n + 1]
            # edge groups depend on the graph only: built once per graph and device (private cache on the graph)
            cache = graph.__dict__.setdefault("_torch_cache", {})
            ck = ("edges", str(dev), n)
            if ck not in cache:
                at_eq = np.where(nxt.edge_parent == iv.eq_index)[0]
                cache[ck] = (
                    _groups(nxt.edge_kind, nxt.edge_parent, nxt.edge_child, CONJ, dev),
                    (
                        torch.as_tensor(nxt.edge_kind[at_eq], device=dev),
                        torch.as_tensor(nxt.edge_child[at_eq], device=dev),
                    )
                    if at_eq.size
                    else None,
                )
            groups, eq_edges = cache[ck]
            n_next = nxt.n_states
        steps.append(
            Step(iv.n_states, nT, E1, E2, dt, vox.r1, vox.r2, emit, coefs, groups, n_next, eq_edges, iv.eq_index)
        )
        rec.append(rc)
    return steps, rec


def run_propagation(steps, rec, A0, bs, D, recompute: bool):
    """Emitting rows per interval (list aligned with ``steps``, None where no signal), differentiable w.r.t. ``bs``."""
    if not torch.is_grad_enabled() or not any(b is not None and b.requires_grad for b in bs):
        with torch.no_grad():
            Ys, _, _ = propagate(steps, A0, bs, D, rec, False, "none")
        return Ys
    outs = _Propagate.apply((steps, rec, recompute), A0, D, *bs)
    it = iter(outs)
    return [next(it) if st.emit is not None else None for st in steps]
