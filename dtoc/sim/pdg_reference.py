"""Reference main loop of the PDG simulator under generic autograd, one interval at a time.

This is the path that :mod:`dtoc.sim.pdg_evolve` (amplitudes as one autograd node with a hand-written
adjoint) and the batched signal replaced; it is kept only as the reference the equivalence tests
compare them against (``tests/test_sim_perf_equivalence.py``) and is not called by dtoc itself.
"""

from __future__ import annotations

import torch

from dtoc.sim.pdg_main import MainPass, _apply_rf, _evolve, complex_dtype
from dtoc.sim.pdg_rfsplit import rf_coefficients
from dtoc.sim.pdg_signal import emit_signal


def main_loop_autograd(p: MainPass, with_signal: bool, final_state: bool, probe: dict | None = None):
    """Reference main loop under generic autograd (the path before :mod:`dtoc.sim.pdg_evolve`); same results
    as :func:`dtoc.sim.pdg_main.main_loop` (``probe`` is not supported)."""
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
    iv0 = graph.intervals[0]
    A = torch.zeros((iv0.n_states, vox.n), dtype=cdtype, device=device)
    A = A.index_add(0, torch.tensor([iv0.eq_index], device=device), vox.mz0.to(cdtype)[None, :])
    K = torch.zeros((iv0.n_states, 4), dtype=torch.float64, device=device)
    pieces = []
    coef_cache: dict = {}
    NI = len(graph.intervals)
    # autograd memory estimate: ~8 saved (S, V) tensors per interval
    est = 8 * vox.n * (16 if cdtype == torch.complex128 else 8) * sum(iv.n_states for iv in graph.intervals)
    ckpt = torch.is_grad_enabled() and est > cfg.checkpoint_bytes
    if ckpt:
        from torch.utils.checkpoint import checkpoint
    for n, iv in enumerate(graph.intervals):
        if with_signal and iv.emit.size and iv.adc_stop > iv.adc_start:
            pieces.append((iv.adc_start, emit_signal(iv, A, K, mom, n, vox, graph, bounds_t, cfg)))
        if n == NI - 1 and not final_state:
            break
        dt = float(bounds_t[n + 1] - bounds_t[n])
        nT = int((~iv.is_z).sum())
        if iv.is_z[:nT].any():
            raise RuntimeError("PDG graph states must be ordered transverse first")
        tr_t = torch.as_tensor(~iv.is_z, device=device)
        if n == NI - 1:
            A, K, rec = _evolve(iv, A, K, mom, n, vox, dt, tr_t)
            eq = torch.tensor([iv.eq_index], device=device)
            A = A.index_add(0, eq, rec.to(A.dtype)[None, :])
            break
        rf = ir.rf[graph.rf_order[n]]
        key = (rf.flip_angle_rad, rf.phase_rad)
        coefs = coef_cache.get(key)
        if coefs is None:
            coefs = coef_cache[key] = rf_coefficients(rf.flip_angle_rad, rf.phase_rad, vox.b1, cdtype)
        if ckpt:
            # keep only the interval's input amplitudes; relaxation and RF split are recomputed in backward
            def step(A_, K_, iv=iv, n=n, dt=dt, tr_t=tr_t, coefs=coefs):
                A2, K2, rec2 = _evolve(iv, A_, K_, mom, n, vox, dt, tr_t)
                return _apply_rf(graph.intervals[n + 1], A2, rec2, iv.eq_index, K2, coefs)

            A, K = checkpoint(step, A, K, use_reentrant=False)
            continue
        A, K, rec = _evolve(iv, A, K, mom, n, vox, dt, tr_t)
        A, K = _apply_rf(graph.intervals[n + 1], A, rec, iv.eq_index, K, coefs)
    return pieces, A, K
