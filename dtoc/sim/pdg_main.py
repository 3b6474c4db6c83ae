"""The PDG main pass (torch): state amplitudes per voxel, realized k, signal of emitting states.

See :mod:`dtoc.sim.pdg_graph` for the state model and docs/simulator.md for the physics.  Amplitudes
``A`` (S, V) carry PD, RF mixing (flip scaled by B1), T1/T2 relaxation, T1 recovery and diffusion;
the spatial pattern ``exp(-i (k . r + omega tau))`` and the T2' factor ``exp(-|tau| / T2')`` are
applied only when a state is observed (ADC sample, or the final Mz of a dummy train).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dtoc.errors import InputError
from dtoc.seq.ir import SequenceIR
from dtoc.sim.pdg_config import PDGConfig
from dtoc.sim.pdg_evolve import make_steps, propagate, run_propagation
from dtoc.sim.pdg_fused import coefficient_table, final_amplitudes, fused_plan, propagate_fused, scale_rows
from dtoc.sim.pdg_graph import IntervalGraph, PDGGraph, build_graph
from dtoc.sim.pdg_moments import Moments, compute_moments
from dtoc.sim.pdg_rfsplit import rf_coefficients, rf_split
from dtoc.sim.pdg_rows import CONJ
from dtoc.sim.pdg_signal import VoxelData, emit_signal, signal_method
from dtoc.sim.pdg_signal_batch import EmitItem, cat_views, emit_signal_batched


def complex_dtype(dtype: torch.dtype) -> torch.dtype:
    if dtype == torch.float32:
        return torch.complex64
    if dtype == torch.float64:
        return torch.complex128
    raise InputError(f"simulate: dtype must be torch.float32 or torch.float64, got {dtype}")


@dataclass(frozen=True)
class MainPass:
    """Everything the main pass of one simulation works on, validated by :func:`prepare`.

    Attributes:
        ir: the sequence; graph: its PDG; vox: the phantom's voxels (:class:`VoxelData`);
        mom: realized gradient moments at interval bounds and ADC samples (:class:`Moments`);
        bounds_t: (NI + 1,) interval boundaries, s; cfg: simulator settings; dtype, device: precision, device.
    """

    ir: SequenceIR
    graph: PDGGraph
    vox: VoxelData
    mom: Moments
    bounds_t: np.ndarray
    cfg: PDGConfig
    dtype: torch.dtype
    device: torch.device | str


def prepare(
    ir: SequenceIR,
    phantom,
    graph: PDGGraph | None,
    cfg: PDGConfig,
    grad: torch.Tensor | np.ndarray | None,
    b0_uT: torch.Tensor | None,
    initial_mz: torch.Tensor | None,
    dtype: torch.dtype,
    device: torch.device | str,
    final_z: bool = False,
) -> MainPass:
    """Validate the inputs of one simulation and compute the realized moments (see :class:`MainPass`);
    builds the graph when ``graph`` is None (``final_z``: with the final Mz observed, for dummy trains)."""
    if phantom is None:
        raise InputError("simulate: a phantom is required")
    if graph is None:
        graph = build_graph(ir, cfg, phantom, final_z_readout=final_z)
    if graph.n_fine != ir.n_fine or graph.adc_times_s.size != ir.n_adc_samples or len(graph.rf_order) != len(ir.rf):
        raise InputError(
            f"simulate: graph was built for a sequence with {graph.n_fine} fine samples, {len(graph.rf_order)} RF, "
            f"{graph.adc_times_s.size} ADC samples; this one has {ir.n_fine}, {len(ir.rf)}, {ir.n_adc_samples}"
        )
    vox = VoxelData.from_phantom(phantom, initial_mz, dtype, device, cfg)
    if graph.tau_ignored and (vox.has_b0 or vox.has_t2d):
        raise InputError(
            "simulate: graph was built for a phantom without B0 and T2' (tau merged); rebuild it for this phantom"
        )
    if grad is None:
        grad = torch.as_tensor(ir.grad_mT_per_m, dtype=torch.float64, device=device)
    else:
        if not isinstance(grad, torch.Tensor):
            grad = torch.as_tensor(np.asarray(grad, dtype=np.float64))
        if tuple(grad.shape) != tuple(ir.grad_mT_per_m.shape):
            raise InputError(
                f"simulate: grad_mT_per_m has shape {tuple(grad.shape)}, expected {tuple(ir.grad_mT_per_m.shape)} (3, 2N+1)"
            )
        grad = grad.to(device)
    if b0_uT is not None:
        b0_uT = torch.as_tensor(b0_uT, device=device)
        if b0_uT.reshape(-1).shape[0] != ir.n_fine:
            raise InputError(f"simulate: b0_uT has {b0_uT.numel()} samples, expected {ir.n_fine} (2N+1)")
    bounds_t = np.array([iv.t_start_s for iv in graph.intervals] + [graph.intervals[-1].t_end_s])
    mom = compute_moments(grad, b0_uT, ir.dt_fine_s, bounds_t, graph.adc_times_s, vox.has_diffusion)
    return MainPass(ir, graph, vox, mom, bounds_t, cfg, dtype, device)


def _evolve(
    iv: IntervalGraph,
    A: torch.Tensor,
    K: torch.Tensor,
    mom: Moments,
    n: int,
    vox: VoxelData,
    dt: float,
    tr_t: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Free evolution over interval n: relaxation, diffusion, dephasing of transverse states.

    Returns the amplitudes at the interval end *without* the T1 recovery of the equilibrium state,
    and that recovery term (V,) separately (it is added where the equilibrium state is read, in
    :func:`_apply_rf` / at the end), which saves a full copy of the (S, V) amplitudes per interval.
    States are ordered transverse first (the graph's key order), so relaxation is two row blocks.
    """
    E1 = torch.exp(-dt * vox.r1)
    E2 = torch.exp(-dt * vox.r2)
    nT = int(tr_t.sum())
    K_end, b = _k_and_b(iv, K, mom, n, vox, dt, tr_t)
    if b is not None:
        facT = E2[None, :] * torch.exp(-b[:nT, None] * vox.d[None, :])
        facZ = E1[None, :] * torch.exp(-b[nT:, None] * vox.d[None, :])
    else:
        facT, facZ = E2[None, :], E1[None, :]
    S, V = A.shape
    if nT == S:
        fac = facT
    elif nT == 0:
        fac = facZ
    else:  # one (S, V) factor: slicing A would cost two (S, V) zero-filled gradients in backward
        fac = torch.cat([facT.expand(nT, V), facZ.expand(S - nT, V)], 0)
    A_end = A * fac
    rec = vox.pd * (1.0 - E1)
    return A_end, K_end, rec


def _apply_rf(
    nxt: IntervalGraph,
    A_end: torch.Tensor,
    rec: torch.Tensor,
    eq_prev: int,
    K_end: torch.Tensor,
    coefs: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Split the states at an RF pulse into the next interval's states.

    One gather, one multiply by the per-edge coefficient rows and one scatter-add for the plain
    edges and the same for the conjugating ones (not one per edge kind), with a hand-written adjoint
    (:mod:`dtoc.sim.pdg_rfsplit`); the T1 recovery ``rec``
    of the equilibrium state enters through its (at most three) edges separately, so the (S, V)
    amplitudes are never copied to add it.
    """
    dev = A_end.device
    kind, par, child = nxt.edge_kind, nxt.edge_parent, nxt.edge_child
    A_new = rf_split(A_end, coefs, kind, par, child, CONJ, nxt.n_states)  # fresh tensor: in place below is safe
    at_eq = np.where(par == eq_prev)[0]
    if at_eq.size:  # rec is real: conjugation does not change it
        cf = coefs.index_select(0, torch.as_tensor(kind[at_eq], device=dev))
        A_new.index_add_(0, torch.as_tensor(child[at_eq], device=dev), cf * rec.to(A_end.dtype)[None, :])
    rep = nxt.rep_parent
    sgn = np.where(rep < 0, 0.0, np.where(nxt.rep_conj, -1.0, 1.0))
    K_new = (
        K_end.index_select(0, torch.as_tensor(np.maximum(rep, 0), device=dev))
        * torch.as_tensor(sgn, dtype=K_end.dtype, device=dev)[:, None]
    )
    return A_new, K_new


def _k_and_b(
    iv: IntervalGraph,
    K: torch.Tensor,
    mom: Moments,
    n: int,
    vox: VoxelData,
    dt: float,
    tr_t: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """k at the interval end (S, 4) and the diffusion b-integral of every state over interval n (S,) (None without diffusion)."""
    dM = (mom.I_bound[n + 1] - mom.I_bound[n]).to(K.dtype)
    K_end = K + tr_t[:, None].to(K.dtype) * dM[None, :]
    if not vox.has_diffusion:
        return K_end, None
    assert mom.J1_bound is not None and mom.J2_bound is not None  # computed when the phantom diffuses
    b = _b_integral(
        K[:, :3],
        mom.I_bound[n][:3][None, :],
        mom.J1_bound[n + 1] - mom.J1_bound[n],
        mom.J2_bound[n + 1] - mom.J2_bound[n],
        dt,
        tr_t,
    )
    return K_end, b.to(vox.r1.dtype)


def _b_integral(k3, I_start, dJ1, dJ2, dt, tr):
    """Diffusion b-integral of states over an interval (S,): int |k(t)|^2 dt, with k(t) = k3 + I(t) - I_start
    for transverse states (dJ1 = int I dt, dJ2 = int |I|^2 dt over the interval, I the moment since the
    sequence start; so int |u + I|^2 = |u|^2 dt + 2 u . dJ1 + dJ2 with u = k3 - I_start) and |k3|^2 dt for
    longitudinal ones (k frozen); broadcasting over states."""
    u = k3 - I_start
    b_tr = (u * u).sum(-1) * dt + 2.0 * (u * dJ1).sum(-1) + dJ2
    b_z = (k3 * k3).sum(-1) * dt
    return torch.where(tr, b_tr, b_z)


_K_PATH_MAX_ELEMS = 2 * 10**7  # largest (all states x intervals) path matrix; longer graphs use the recursion


def _k_path_matrix(graph: PDGGraph):
    """(sum_n S_n, NI) matrix C with K_n[s] = sum_m C[s, m] dM_m (numpy, cached on the graph), or None if too large.

    A state's k at the start of interval n is the signed sum of the interval moment increments
    dM_m = I(t_{m+1}) - I(t_m) along its representative parents (+1 while transverse, conjugation
    flips the sign of everything before), so the recursion K_{n+1} = sgn (K_n[rep] + tr dM_n) unrolls
    into one fixed matrix with entries in {-1, 0, 1}.
    """
    cache = graph.__dict__.setdefault("_torch_cache", {})
    if "kpath" not in cache:
        ivs = graph.intervals
        NI = len(ivs)
        if sum(iv.n_states for iv in ivs) * NI > _K_PATH_MAX_ELEMS:
            cache["kpath"] = None
        else:
            Cs = [np.zeros((ivs[0].n_states, NI))]
            for n in range(NI - 1):
                Cend = Cs[n].copy()
                Cend[~ivs[n].is_z, n] += 1.0
                rep = ivs[n + 1].rep_parent
                sgn = np.where(rep < 0, 0.0, np.where(ivs[n + 1].rep_conj, -1.0, 1.0))
                Cs.append(Cend[np.maximum(rep, 0)] * sgn[:, None])
            cache["kpath"] = np.concatenate(Cs, 0)
    return cache["kpath"]


def _k_jumps(graph: PDGGraph) -> tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Pointer jumping over the representative parents (numpy, graph only, cached on the graph).

    A state's start-of-interval k is affine in its representative parent's, ``K_s = a_s K_rep(s) + c_s dM_(n-1)``
    (a = c = +-1 through a plain or conjugating edge while the parent is transverse, a = +-1, c = 0 while it
    is longitudinal, a = c = 0 for a state without parent and in the first interval).  Composing the maps
    in rounds (``v += a_r v[ptr_r]``, ``a_(r+1) = a_r a_r[ptr_r]``, ``ptr_(r+1) = ptr_r[ptr_r]``) reaches every
    root in ceil(log2 NI) rounds.  Returns (c (S_tot,), the dM row of each state (S_tot,), [(a_r, ptr_r)])."""
    cache = graph.__dict__.setdefault("_torch_cache", {})
    if "kjumps" in cache:
        return cache["kjumps"]
    ivs = graph.intervals
    soff = np.concatenate([[0], np.cumsum([iv.n_states for iv in ivs])]).astype(np.int64)
    a = np.zeros(soff[-1])
    c = np.zeros(soff[-1])
    ptr = np.arange(soff[-1], dtype=np.int64)
    row = np.zeros(soff[-1], dtype=np.int64)
    for n in range(1, len(ivs)):
        rep, sl = ivs[n].rep_parent, slice(soff[n], soff[n + 1])
        sgn = np.where(rep < 0, 0.0, np.where(ivs[n].rep_conj, -1.0, 1.0))
        a[sl] = sgn
        c[sl] = sgn * (~ivs[n - 1].is_z[np.maximum(rep, 0)])
        ptr[sl] = np.where(rep < 0, np.arange(soff[n], soff[n + 1]), soff[n - 1] + np.maximum(rep, 0))
        row[sl] = n - 1
    rounds = []
    while np.any(a != 0):
        rounds.append((a, ptr))
        a, ptr = a * a[ptr], ptr[ptr]
    cache["kjumps"] = (c, row, rounds)
    return cache["kjumps"]


def _k_by_jumps(graph: PDGGraph, dM: torch.Tensor) -> torch.Tensor:
    """(S_tot, 4) start-of-interval k of all states without the path matrix (:func:`_k_jumps`): ~3 operations
    per round, ceil(log2 NI) rounds; the same sums as :func:`_k_path_matrix` in another order (rounding)."""
    c, row, rounds = _k_jumps(graph)
    dev = dM.device
    v = dM.index_select(0, torch.as_tensor(row, device=dev)) * torch.as_tensor(c, dtype=dM.dtype, device=dev)[:, None]
    if rounds:  # one transfer for all rounds
        A = torch.as_tensor(np.stack([r[0] for r in rounds]), dtype=dM.dtype, device=dev)
        P = torch.as_tensor(np.stack([r[1] for r in rounds]), device=dev)
        for r in range(len(rounds)):
            v = v + A[r][:, None] * v.index_select(0, P[r])
    return v


def _k_and_b_all(
    graph: PDGGraph, C, mom: Moments, vox: VoxelData, bounds_t: np.ndarray, final_state: bool
) -> tuple[list, list, torch.Tensor | None, torch.Tensor | None]:
    """Vectorised k recursion: start-of-interval k (list of (S_n, 4)), diffusion b-integrals (list, None where
    unused), with ``final_state`` the k at the end of the last interval, and the b-integrals of all states
    concatenated (None without diffusion); same values as :func:`_k_and_b`.  ``C``: the path matrix
    (:func:`_k_path_matrix`), or None: by pointer jumping (:func:`_k_by_jumps`)."""
    ivs = graph.intervals
    NI = len(ivs)
    dev = mom.I_bound.device
    sizes = [iv.n_states for iv in ivs]
    dM = mom.I_bound[1:] - mom.I_bound[:-1]  # (NI, 4)
    K_all = (  # (S_tot, 4)
        torch.as_tensor(C, dtype=dM.dtype, device=dev) @ dM if C is not None else _k_by_jumps(graph, dM)
    )
    Ks = list(torch.split(K_all, sizes, 0))
    K_fin = None
    if final_state:
        tr = torch.as_tensor(~ivs[-1].is_z, device=dev)
        K_fin = Ks[-1] + tr[:, None].to(dM.dtype) * dM[-1][None, :]
    if not vox.has_diffusion:
        return Ks, [None] * NI, K_fin, None
    assert mom.J1_bound is not None and mom.J2_bound is not None  # computed when the phantom diffuses
    own = torch.as_tensor(np.repeat(np.arange(NI), sizes), device=dev)
    tr_all = torch.as_tensor(np.concatenate([~iv.is_z for iv in ivs]), device=dev)
    dt = torch.as_tensor(np.diff(np.asarray(bounds_t, dtype=np.float64)), device=dev).index_select(0, own)
    b = _b_integral(
        K_all[:, :3],
        mom.I_bound[:-1, :3].index_select(0, own),
        (mom.J1_bound[1:] - mom.J1_bound[:-1]).index_select(0, own),
        (mom.J2_bound[1:] - mom.J2_bound[:-1]).index_select(0, own),
        dt,
        tr_all,
    )
    b_r = b.to(vox.r1.dtype)
    bs: list[torch.Tensor | None] = list(torch.split(b_r, sizes, 0))
    if not final_state:
        bs[-1] = None
    return Ks, bs, K_fin, b_r


def _next_k(nxt: IntervalGraph, K_end: torch.Tensor) -> torch.Tensor:
    rep = nxt.rep_parent
    dev = K_end.device
    sgn = np.where(rep < 0, 0.0, np.where(nxt.rep_conj, -1.0, 1.0))
    return (
        K_end.index_select(0, torch.as_tensor(np.maximum(rep, 0), device=dev))
        * torch.as_tensor(sgn, dtype=K_end.dtype, device=dev)[:, None]
    )


def _emit_view(iv: IntervalGraph) -> IntervalGraph:
    """Shallow copy of ``iv`` whose states are its emitting states only (emit = 0..J-1)."""
    import copy

    sub = copy.copy(iv)
    sub.tau_s = iv.tau_s[iv.emit]
    sub.emit = np.arange(iv.emit.size)
    return sub


def main_loop(p: MainPass, with_signal: bool, final_state: bool, probe: dict | None = None, fused: bool | None = None):
    """Main loop: k recursion (autograd, (S, 4) per interval), amplitudes by :mod:`dtoc.sim.pdg_fused`
    (or :mod:`dtoc.sim.pdg_evolve`; one autograd node with a hand-written adjoint), then the signal of
    every emitting interval.

    Returns ``(pieces, A, K)``: with ``final_state`` the final amplitudes (S, V) and k (S, 4) and no
    pieces; else the signal pieces ``[(first ADC index, (C, T) signal)]`` and None, None.

    ``fused``: use the fused propagation (:mod:`dtoc.sim.pdg_fused`) where its buffers fit; None: with
    the 'batched' schedule (``PDGConfig.schedule``; by default off the CPU, where the per-interval path's
    one-interval working set is faster).
    """
    ir, graph, vox, mom, bounds_t, cfg, dtype, device = (
        p.ir,
        p.graph,
        p.vox,
        p.mom,
        p.bounds_t,
        p.cfg,
        p.dtype,
        p.device,
    )
    cdtype = complex_dtype(dtype)
    tis = _tissue_classes(vox, cfg)
    NI = len(graph.intervals)
    iv0 = graph.intervals[0]
    A0 = torch.zeros((iv0.n_states, tis.n), dtype=cdtype, device=device)
    A0[iv0.eq_index] = tis.mz0.to(cdtype)
    C = _k_path_matrix(graph)
    b_all = None
    use_fused = cfg.batched(device) if fused is None else fused
    # the batched schedule (a GPU): a constant number of launches per interval; a dummy train (final state,
    # no autograd) in segments of bounded buffers, so only its row scales F need to fit.  On the CPU the
    # per-interval path stays (its working set is one interval; the fused buffers were 1.15x slower on
    # the paper GRE's fwd+bwd and 3x on a long strict dummy train there: memory-bound)
    fits = use_fused and (
        _fused_fits(graph, tis.n, cdtype, cfg)
        if not final_state
        else (tis.n * 8 * (graph.n_states_total + NI) <= cfg.checkpoint_bytes)
    )
    # all intervals at once: a handful of autograd nodes instead of ~15 per interval (with the batched
    # schedule also above the path matrix's size, by pointer jumping: the long dummy trains)
    if C is not None or fits:
        Ks, bs, K, b_all = _k_and_b_all(graph, C, mom, vox, bounds_t, final_state)
        if fits:
            if not final_state:
                return _main_loop_fused(p, tis, A0, Ks, b_all, probe), None, None
            with torch.no_grad():
                plan = fused_plan(graph, A0.device)
                CT = coefficient_table(graph, ir, tis.b1, cdtype, rf_coefficients)
                F = scale_rows(graph, bounds_t, tis, b_all).index_select(0, plan.frow)
                A_end = final_amplitudes(graph, plan, A0, F, CT, max_bytes=cfg.checkpoint_bytes)
                return [], tis.expand(A_end), K
    steps, rec = make_steps(graph, ir, tis, bounds_t, cdtype, with_signal, rf_coefficients)
    if C is None:
        K = torch.zeros((iv0.n_states, 4), dtype=torch.float64, device=device)
        Ks, bs = [], []
        for n, iv in enumerate(graph.intervals):
            Ks.append(K)
            if n == NI - 1 and not final_state:
                bs.append(None)
                break
            dt = float(bounds_t[n + 1] - bounds_t[n])
            K_end, b = _k_and_b(iv, K, mom, n, vox, dt, torch.as_tensor(~iv.is_z, device=device))
            bs.append(b)
            K = K_end if n == NI - 1 else _next_k(graph.intervals[n + 1], K_end)
    if final_state:
        with torch.no_grad():
            _, A, _ = propagate(steps, A0, bs, tis.d, rec, True, "none")
        return [], tis.expand(A), K
    batcher = _SignalBatcher(graph, steps, _emitting_k(Ks, steps), mom, vox, bounds_t, cfg, tis.expand, probe)
    if not torch.is_grad_enabled() or not any(b is not None and b.requires_grad for b in bs):
        # amplitudes do not depend on the gradient waveform (no diffusion, or no autograd): stream,
        # each interval's emitting rows go to the signal batcher as they are reached
        with torch.no_grad():
            propagate(steps, A0, bs, tis.d, rec, False, "none", sink=batcher.add)
    else:
        est = tis.n * (24 if cdtype == torch.complex128 else 12) * sum(iv.n_states for iv in graph.intervals)
        Ys = run_propagation(steps, rec, A0, bs, tis.d, recompute=est > cfg.checkpoint_bytes)
        for n, Y in enumerate(Ys):
            if Y is not None:
                batcher.add(n, Y)
    return batcher.finish(), None, None


def _fused_fits(graph: PDGGraph, U: int, cdtype: torch.dtype, cfg: PDGConfig) -> bool:
    """Whether the fused propagation's buffers fit ``cfg.checkpoint_bytes``: the mirrored amplitudes of all
    intervals (2 S x U complex) and the weights of the mirrored edges (2 E x U complex); with autograd also
    the adjoint, the conjugated weights and the chunked temporaries of dL/dF (about three buffers more;
    the per-interval path keeps ~1 buffer and can recompute instead)."""
    per = 16 if cdtype == torch.complex128 else 8
    grad = torch.is_grad_enabled()
    rows2 = 2 * (graph.n_states_total + len(graph.intervals))
    edges2 = 2 * sum(int(iv.edge_parent.size) for iv in graph.intervals[1:])
    return per * U * (rows2 * (5 if grad else 1) + edges2 * (2 if grad else 1)) <= cfg.checkpoint_bytes


def _main_loop_fused(p: MainPass, tis, A0: torch.Tensor, Ks: list, b_all, probe: dict | None) -> list:
    """Signal pieces of the main pass by :mod:`dtoc.sim.pdg_fused` (a constant number of operations per
    interval, all intervals' emitting rows at once); the same values as the per-interval path."""
    graph, cfg = p.graph, p.cfg
    plan = fused_plan(graph, A0.device)
    CT = coefficient_table(graph, p.ir, tis.b1, A0.dtype, rf_coefficients)
    F = scale_rows(graph, p.bounds_t, tis, b_all).index_select(0, plan.frow)
    Ys = propagate_fused(graph, plan, A0, F, CT)
    emit_t = _split_rows(graph, [n for n, y in enumerate(Ys) if y is not None], A0.device)
    steps = [_EmitStep(e) for e in emit_t]
    batcher = _SignalBatcher(
        graph, steps, _emitting_k(Ks, steps, graph), p.mom, p.vox, p.bounds_t, cfg, tis.expand, probe
    )
    batcher.plan_batches([(n, int(Y.shape[0])) for n, Y in enumerate(Ys) if Y is not None], A0.device)
    for n, Y in enumerate(Ys):
        if Y is not None:
            batcher.add(n, Y)
    return batcher.finish()


def _split_rows(graph: PDGGraph, emitting: list[int], device) -> list:
    """Per interval, its emitting rows as a long tensor on ``device`` (None where none is listed): one
    transfer for all intervals."""
    out: list = [None] * len(graph.intervals)
    if not emitting:
        return out
    arrs = [graph.intervals[n].emit for n in emitting]
    for n, t in zip(
        emitting, torch.split(torch.as_tensor(np.concatenate(arrs), device=device), [a.size for a in arrs])
    ):
        out[n] = t
    return out


@dataclass(frozen=True)
class _EmitStep:
    """The emitting rows of one interval (what :func:`_emitting_k` reads of a step)."""

    emit: torch.Tensor | None


class TissueClasses:
    """The voxels' distinct (T1, T2, D, B1, initial Mz / PD) tuples: the amplitudes depend on nothing else.

    Relaxation, diffusion and the RF split act per voxel only through T1, T2, D and B1, and the
    amplitudes are linear in (initial Mz, PD) with the T1 recovery proportional to PD, so every voxel's
    amplitudes are PD(v) x those of its tuple propagated with PD 1 and initial Mz = Mz0(v)/PD(v).
    The propagation runs on the U distinct tuples instead of the V voxels (exact, no tolerance; the
    built-in brain phantom without B1 map: 589 -> 225 (32x32), 2247 -> 262 (64x64), 34581 -> 96
    (256x256)) and the emitting rows are expanded to voxels for the signal.  With ``compress`` False
    (or when every voxel is distinct) the tuples are the voxels themselves.

    A smooth B1 map, or an initial Mz from dummy cycles (which carries the voxel-scale pattern of the
    dephased longitudinal pathways), makes every voxel distinct.  ``quantum`` > 0 rounds B1 and
    Mz0/PD to multiples of it for every voxel (an approximation: relative flip-angle error <= quantum/2,
    initial-Mz error <= quantum/2 x PD), after which voxels of the same tissue share a tuple again.
    """

    def __init__(self, vox, compress: bool, quantum: float = 0.0):
        dev = vox.pd.device
        ratio = vox.mz0 / vox.pd
        b1 = vox.b1
        if quantum > 0:
            b1 = torch.round(b1 / quantum) * quantum
            ratio = torch.round(ratio / quantum) * quantum
        inv = None
        if compress and vox.n > 1:
            h = vox.host
            if h and all(k in h for k in ("r1", "r2", "d", "b1", "pd", "mz0")):
                # the same values on the host (numpy copies of the tensors): no device synchronisation
                hb1, hratio = h["b1"], h["mz0"] / h["pd"]
                if quantum > 0:
                    hb1 = np.round(hb1 / quantum) * quantum
                    hratio = np.round(hratio / quantum) * quantum
                key = np.stack([h["r1"], h["r2"], h["d"], hb1, hratio], 1)
            else:
                key = torch.stack([vox.r1, vox.r2, vox.d, b1, ratio], 1).detach().cpu().numpy()
            uniq, first, inv_np = np.unique(key, axis=0, return_index=True, return_inverse=True)
            if uniq.shape[0] < vox.n:
                sel = torch.as_tensor(first, device=dev)
                inv = torch.as_tensor(inv_np.reshape(-1), device=dev)
        if inv is None:
            self.r1, self.r2, self.d, self.b1, self.pd = vox.r1, vox.r2, vox.d, b1, vox.pd
            self.mz0 = vox.mz0 if quantum <= 0 else ratio * vox.pd
        else:
            pick = lambda t: t.index_select(0, sel)  # noqa: E731
            self.r1, self.r2, self.d, self.b1, self.mz0 = pick(vox.r1), pick(vox.r2), pick(vox.d), pick(b1), pick(ratio)
            self.pd = torch.ones_like(self.r1)
            self.scale = vox.pd
        self.inv = inv

    @property
    def n(self) -> int:
        return int(self.r1.shape[0])

    def expand(self, A: torch.Tensor) -> torch.Tensor:
        """(R, U) tuple amplitudes -> (R, V) voxel amplitudes."""
        if self.inv is None:
            return A
        return A.index_select(1, self.inv) * self.scale.to(A.dtype)[None, :]


def _tissue_classes(vox, cfg) -> TissueClasses:
    return TissueClasses(vox, cfg.compress_tissues, cfg.tissue_quantum)


_BATCH_ELEMS = 2**21
_GPU_BATCHES = (
    1  # the 'batched' schedule: at most this many signal batches per ADC sample count (PDGConfig.signal_batches)
)


def _emitting_k(Ks, steps, graph: PDGGraph | None = None):
    """k of the emitting states of every interval (list, None where none emits): one gather from the
    concatenated k of all intervals (one autograd node instead of one per interval; the row indices
    from the graph in numpy when ``graph`` is given, one transfer)."""
    if not Ks:
        return []
    emit_n = [n for n, st in enumerate(steps) if n < len(Ks) and st.emit is not None]
    out: list[torch.Tensor | None] = [None] * len(Ks)
    if not emit_n:
        return out
    offs = np.concatenate([[0], np.cumsum([k.shape[0] for k in Ks])])
    if graph is not None:
        idx = torch.as_tensor(
            np.concatenate([graph.intervals[n].emit + int(offs[n]) for n in emit_n]).astype(np.int64),
            device=Ks[0].device,
        )
    else:
        idx = torch.cat([steps[n].emit + int(offs[n]) for n in emit_n])
    K_emit = cat_views(Ks, 0).index_select(0, idx)  # K_all itself when Ks are its split
    for n, Kj in zip(emit_n, torch.split(K_emit, [int(steps[n].emit.numel()) for n in emit_n], 0)):
        out[n] = Kj
    return out


class _SignalBatcher:
    """Collects the emitting amplitudes of the intervals and evaluates their signals: 'gemm' intervals
    batched by their number of ADC samples (:mod:`dtoc.sim.pdg_signal_batch`), in batches bounded by
    the kernels (G x C x T x V) and weights (sum of J x V) they form (2**21 elements); 'direct' /
    'separable' intervals and very large kernels one by one."""

    def __init__(self, graph, steps, Kjs, mom, vox, bounds_t, cfg, expand=None, probe: dict | None = None):
        """``Kjs``: per interval, the k (J, 4) of its emitting states (see :func:`_emitting_k`);
        ``probe``: if a dict, the batched path records there the per-state peak |signal| (interval ->
        (J,) array, see :func:`emission_peaks`)."""
        self.graph, self.steps, self.Kjs, self.mom, self.vox, self.bounds_t, self.cfg = (
            graph,
            steps,
            Kjs,
            mom,
            vox,
            bounds_t,
            cfg,
        )
        self.probe = probe
        self.expand = expand or (lambda A: A)
        self.budget = 4 * cfg.chunk_elems  # larger kernels: per-interval path (chunked, checkpointed)
        # batches of ~2M complex elements: large enough to amortise the per-operation overhead, small
        # enough to stay cache-friendly (16M-element batches were 1.8x slower on the 64x64 GRE)
        self.batch_elems = min(self.budget, _BATCH_ELEMS)
        self.batch_for: dict = {}  # T -> batch size (elements) from plan_batches
        self.pieces: list = []
        self.pending: dict = {}  # T -> (items, used)

    def plan_batches(self, emitting: list[tuple[int, int]], device) -> None:
        """With every interval's number of emitting rows known up front ((n, J) pairs): size the batches of
        each sample count T so that there are at most ``PDGConfig.signal_batches`` of them with the 'batched'
        schedule (a constant number of operations however long the sequence; default 1: as few as the kernel budget allows), else no limit
        (cache-sized 2**21-element batches), never below 2**21 elements nor above the kernel budget."""
        vox = self.vox
        total: dict = {}
        largest: dict = {}
        for n, J in emitting:
            iv = self.graph.intervals[n]
            T = iv.adc_stop - iv.adc_start
            cost = vox.n_coils * vox.n * (T + J)
            total[T] = total.get(T, 0) + cost
            largest[T] = max(largest.get(T, 0), cost)
        n_max = (self.cfg.signal_batches or _GPU_BATCHES) if self.cfg.batched(device) else 0
        for T, tot in total.items():
            # greedy filling (:meth:`add`) closes a batch only above ``want - largest``: at most n_max batches
            want = (-(-tot // n_max) + (largest[T] if n_max > 1 else 0)) if n_max > 0 else self.batch_elems
            self.batch_for[T] = min(self.budget, max(self.batch_elems, want))

    def add(self, n: int, Y: torch.Tensor) -> None:
        iv, vox, cfg = self.graph.intervals[n], self.vox, self.cfg
        Kj = self.Kjs[n]
        T = iv.adc_stop - iv.adc_start
        method = signal_method(cfg, T, iv.emit.size)
        # a 3D phantom: per interval (the batched kernels' fused spatial phase is x-y only)
        if method != "gemm" or vox.n_coils * T * vox.n > self.budget or vox.z is not None:
            self.pieces.append(
                (
                    iv.adc_start,
                    emit_signal(_emit_view(iv), self.expand(Y), Kj, self.mom, n, vox, self.graph, self.bounds_t, cfg),
                )
            )
            return
        cost = vox.n_coils * vox.n * (T + Y.shape[0])
        items, used = self.pending.get(T, ([], 0))
        if items and used + cost > self.batch_for.get(T, self.batch_elems):
            self._flush(items)
            items, used = [], 0
        items.append(EmitItem(n, _emit_view(iv), Y, Kj))  # Y per tissue tuple: expanded to voxels once per batch
        self.pending[T] = (items, used + cost)

    def _flush(self, items) -> None:
        for (_n, ivv, _, _), s in zip(
            items,
            emit_signal_batched(
                items, self.mom, self.vox, self.graph, self.bounds_t, self.cfg, self.expand, probe=self.probe
            ),
        ):
            self.pieces.append((ivv.adc_start, s))

    def finish(self) -> list:
        for items, _ in self.pending.values():
            if items:
                self._flush(items)
        self.pending = {}
        return self.pieces


def run_main_pass(
    ir: SequenceIR,
    phantom,
    graph: PDGGraph | None,
    cfg: PDGConfig,
    grad: torch.Tensor | None,
    b0_uT: torch.Tensor | None,
    initial_mz: torch.Tensor | None,
    dtype: torch.dtype,
    device: torch.device | str,
) -> torch.Tensor:
    """Signal (n_coils, N_adc) complex in IR ADC order (see :func:`dtoc.sim.pdg.simulate`)."""
    p = prepare(ir, phantom, graph, cfg, grad, b0_uT, initial_mz, dtype, device)
    cdtype = complex_dtype(dtype)
    N = p.graph.adc_times_s.size
    graph = p.graph
    pieces, _, _ = main_loop(p, True, False)
    sig = torch.zeros((p.vox.n_coils, N), dtype=cdtype, device=device)
    if pieces:  # one scatter for all pieces (ADC indices from numpy, one transfer)
        idx = np.concatenate([np.arange(start, start + s.shape[1]) for start, s in pieces])
        sig = sig.index_add(1, torch.as_tensor(idx, device=device), cat_views([s for _, s in pieces], 1))
    if N:
        ph = torch.as_tensor(np.exp(-1j * graph.adc_phase_rad), dtype=cdtype, device=device)
        sig = sig * ph[None, :]
        inv = np.empty(N, dtype=np.int64)
        inv[graph.adc_order] = np.arange(N)
        sig = sig.index_select(1, torch.as_tensor(inv, device=device))
    return sig
