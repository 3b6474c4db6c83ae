"""'gemm' signal evaluation batched over all intervals with the same number of ADC samples (torch).

Same mathematics as :func:`dtoc.sim.pdg_signal.emit_signal_gemm` (read its docstring first): for an
emitting state j of interval n and a sample at dt = t - t_n,

    s_j(t) = vf_j(t) sum_v W_j(v) Kern_n(t, v) exp(-D(v) delta_j(t)),
    W_j(v)  = A_j(v) exp(-i (kx_j x_v + ky_j y_v)) exp(-tau_j (i omega_v + sgn / T2'(v))) exp(-D(v) b_j(t_mid)),
    Kern_n(t, v) = exp(-i (mx_n(t) x_v + my_n(t) y_v)) exp(-dt (1/T2(v) + sgn / T2'(v) + i omega_v)),

with the in-window diffusion change delta_j(t) = b_j(t) - b_j(t_mid) Taylor-expanded per state
(order chosen for ``taylor_tol``; states with D |delta| > 0.5 evaluated exactly) and the T2' sign
classes (tau + dt >= 0 / <= 0 / crossing inside the window).  What changes is the bookkeeping: instead
of ~60 small torch operations per interval, every elementwise step runs once on the emitting states of
ALL intervals (weights, voxel factors, Taylor coefficients, kernels), and only the matrix products
remain per interval (one per interval, kernel class and Taylor order, over a contiguous block of
rows: states are sorted by (class, interval, descending order)).  The spatial exponentials are
separable on the voxel grid, the tau factor is evaluated once per distinct tau, and the time factor
exp(-dt (...)) of the kernel, which depends on the fixed ADC times only, is shared by all intervals
with the same sample times.  Equal to the per-interval evaluation up to rounding
(tests/test_sim_perf_signal.py).
"""

from __future__ import annotations

import numpy as np
import torch

from dtoc.sim import pdg_signal as _sig
from dtoc.sim.pdg_signal import _DIFF_TAYLOR_MAX, _time_factor, _time_key, voxel_factor


def _taylor_orders(xs: np.ndarray, tol: float) -> np.ndarray:
    """Vectorised :func:`dtoc.sim.pdg_signal._taylor_order`: smallest R with x^(R+1) / (R+1)! <= tol (at most 30)."""
    xs = np.asarray(xs, dtype=np.float64)
    if xs.size == 0:
        return np.zeros(0, dtype=np.int64)
    terms = np.cumprod(xs[:, None] / np.arange(1, 31)[None, :], axis=1)  # (J, 30): x^(R+1)/(R+1)!, R = 0..29
    ok = terms <= tol
    return np.where(ok.any(1), ok.argmax(1), 30).astype(np.int64)


def emit_signal_batched(items, mom, vox, graph, bounds_t, cfg) -> list:
    """Signals of several intervals with the same number T of ADC samples.

    Args:
        items: list of (n, iv_view, Y, Kj): interval index, emitting view of its graph (emit = 0..J-1,
            tau_s of the emitting states), emitting amplitudes (J, V) complex, their k (J, 4) float64.
        mom, vox, graph, bounds_t, cfg: as for :func:`dtoc.sim.pdg_signal.emit_signal_gemm`.
    Returns:
        list of (C, T) complex signals, one per item (before the ADC phase).
    """
    dev = vox.pd.device
    rdt = vox.x.dtype
    Co = vox.n_coils
    V = vox.n
    G = len(items)
    ns = [it[0] for it in items]
    lo = [it[1].adc_start for it in items]
    T = items[0][1].adc_stop - lo[0]
    cdt = items[0][2].dtype
    Js = [it[2].shape[0] for it in items]
    own_np = np.repeat(np.arange(G), Js)
    J = int(own_np.size)
    Y = torch.cat([it[2] for it in items], 0) if G > 1 else items[0][2]
    Kj = torch.cat([it[3] for it in items], 0) if G > 1 else items[0][3]
    tau = np.concatenate([it[1].tau_s for it in items])
    own = torch.as_tensor(own_np, device=dev)
    nb = torch.as_tensor(np.asarray(ns), device=dev)
    sel_adc = torch.as_tensor(np.stack([np.arange(a, a + T) for a in lo]).reshape(-1), device=dev)
    mt = (mom.I_adc.index_select(0, sel_adc).reshape(G, T, 4) - mom.I_bound.index_select(0, nb)[:, None, :])  # (G, T, 4) f64
    dtt = np.stack([graph.adc_times_s[a:a + T] - bounds_t[n] for a, n in zip(lo, ns)])  # (G, T)
    dtt_own = dtt[own_np]  # (J, T)
    plus = (tau[:, None] + dtt_own) >= 0
    if vox.has_t2d:
        allp, allm = plus.all(1), (~plus).all(1)
        cls = np.where(allp, 0, np.where(allm, 1, 2))
    else:
        cls = np.zeros(J, dtype=np.int64)
    mt_own = mt.index_select(0, own)  # (J, T, 4)
    vf = voxel_factor(Kj[:, None, :] + mt_own, vox)  # (J, T) complex

    # diffusion: b_j(t) = b_j(t_mid) + delta_j(t)
    orders = np.zeros(J, dtype=np.int64)
    far = np.zeros(J, dtype=bool)
    bm = ndl = None
    Dmax = max(float(vox.d.max()), 1e-300) if vox.has_diffusion else 1.0
    if vox.has_diffusion and T:
        dtt_t = torch.as_tensor(dtt, dtype=torch.float64, device=dev)
        u = Kj[:, :3] - mom.I_bound.index_select(0, nb)[:, :3].index_select(0, own)
        dJ1 = (mom.J1_adc.index_select(0, sel_adc).reshape(G, T, 3) - mom.J1_bound.index_select(0, nb)[:, None, :]).index_select(0, own)
        dJ2 = (mom.J2_adc.index_select(0, sel_adc).reshape(G, T) - mom.J2_bound.index_select(0, nb)[:, None]).index_select(0, own)
        b = (u * u).sum(1)[:, None] * dtt_t.index_select(0, own) + 2.0 * (u[:, None, :] * dJ1).sum(-1) + dJ2  # (J, T)
        bm = b[:, T // 2]
        delta = b - bm[:, None]
        xs = Dmax * delta.detach().abs().amax(1).cpu().numpy()
        far = xs > _DIFF_TAYLOR_MAX
        orders = _taylor_orders(xs, cfg.taylor_tol)
        orders[far] = -1
        ndl = (-Dmax * delta).to(rdt).to(cdt)  # (J, T), |.| <= _DIFF_TAYLOR_MAX for the expanded states

    # weights common to both kernel classes: A exp(-i k.r) exp(-D b_mid)
    W = Y * vox.spatial_phase(Kj[:, 0].to(rdt), Kj[:, 1].to(rdt))
    if bm is not None:
        W = W * torch.exp(-bm.to(rdt)[:, None] * vox.d[None, :])
    utau, tinv = np.unique(tau, return_inverse=True)
    utau_t = torch.as_tensor(utau, dtype=rdt, device=dev)
    tinv_t = torch.as_tensor(tinv.reshape(-1), device=dev)

    # kernels per interval: separable spatial part x cached time factor (per class sign), coils folded in
    SP = vox.spatial_phase(mt[:, :, 0].to(rdt), mt[:, :, 1].to(rdt))  # (G, T, V)
    dtr = torch.as_tensor(dtt, dtype=rdt, device=dev)

    def kernel(sgn):
        rate = vox.r2 + (sgn * vox.r2d if vox.has_t2d else 0.0)
        keys = [_time_key(dtt[g], sgn if vox.has_t2d else 0.0) for g in range(G)]
        tfs = [_time_factor(dtr[g], rate, vox, k) for g, k in enumerate(keys)]
        if any(t is None for t in tfs):  # cache full: compute per interval
            tfs = [torch.exp(torch.complex(torch.clamp(-dtr[g][:, None] * rate[None], max=80.0), -dtr[g][:, None] * vox.omega[None]))
                   for g in range(G)]
        if all(k == keys[0] for k in keys):
            K = SP * tfs[0][None]
        else:
            K = SP * torch.stack(tfs, 0)
        if vox.coil is not None:
            K = (vox.coil[None, :, None, :] * K[:, None]).reshape(G, Co * T, V)
        return K.unbind(0)  # G x (Co*T, V); unbind: one autograd node (indexing would zero-fill per interval)

    kern_cache = {}
    out = torch.zeros((J, Co, T), dtype=cdt, device=dev)
    expanded = ~far
    for c, signs in ((0, (1.0,)), (1, (-1.0,)), (2, (1.0, -1.0))):
        in_c = np.where((cls == c) & expanded)[0]
        if not in_c.size:
            continue
        # sort by (interval, descending Taylor order): rows with order >= r are a prefix of each interval's block
        in_c = in_c[np.lexsort((-orders[in_c], own_np[in_c]))]
        rows_c = torch.as_tensor(in_c, device=dev)
        Wc = W.index_select(0, rows_c)
        for sgn in signs:
            Pt = torch.exp(torch.complex(torch.clamp(-sgn * utau_t[:, None] * vox.r2d[None], max=80.0) if vox.has_t2d
                                         else torch.zeros((utau.size, V), dtype=rdt, device=dev),
                                         -utau_t[:, None] * vox.omega[None]))  # (U, V)
            C = Wc * Pt.index_select(0, tinv_t.index_select(0, rows_c))
            if sgn not in kern_cache:
                kern_cache[sgn] = kernel(sgn)
            Kern = kern_cache[sgn]
            s_c = None
            dn = vox.d / Dmax
            dr = None
            for r in range(int(orders[in_c].max(initial=0)) + 1):
                pos = np.where(orders[in_c] >= r)[0]  # positions within in_c (still grouped by interval)
                if not pos.size:
                    break
                if r == 0:
                    Cr = C
                else:
                    dr = dn if dr is None else dr * dn
                    Cr = C.index_select(0, torch.as_tensor(pos, device=dev)) * dr[None, :]
                ow = own_np[in_c[pos]]
                cuts = np.flatnonzero(np.diff(ow)) + 1
                starts = np.concatenate([[0], cuts])
                ends = np.concatenate([cuts, [ow.size]])
                blocks = torch.split(Cr, (ends - starts).tolist(), 0)  # one autograd node (slices would zero-fill each)
                Gr = torch.cat([blk @ Kern[int(ow[a])].T for blk, a in zip(blocks, starts)], 0)  # (n_r, Co*T)
                Gr = Gr.reshape(-1, Co, T)
                if r > 0:
                    w = ndl.index_select(0, torch.as_tensor(in_c[pos], device=dev)) ** r / float(np.prod(np.arange(1, r + 1)))
                    Gr = Gr * w[:, None, :]
                if r == 0:
                    s_c = Gr
                else:
                    s_c = s_c.index_add(0, torch.as_tensor(pos, device=dev), Gr)
            if c == 2:
                m = plus[in_c] if sgn > 0 else ~plus[in_c]
                s_c = s_c * torch.as_tensor(m, device=dev).to(rdt)[:, None, :]
            out = out.index_add(0, rows_c, s_c)
    out = out * vf[:, None, :]
    sig = torch.zeros((G, Co, T), dtype=cdt, device=dev).index_add(0, own, out)
    res = list(sig.unbind(0))
    if far.any():
        import copy

        for g, (n, ivv, Yg, Kg) in enumerate(items):
            f = far[own_np == g]
            if f.any():
                sub = copy.copy(ivv)
                sub.emit = ivv.emit[f]
                res[g] = res[g] + _sig.emit_signal_direct(sub, Yg, Kg, mom, n, vox, graph, bounds_t, cfg)
    return res
