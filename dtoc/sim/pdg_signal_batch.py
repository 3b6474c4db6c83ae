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
(tests/test_sim_perf_equivalence.py).  With ``PDGConfig.fused_signal_adjoint`` (default) the weights,
kernels and products of a batch are one autograd node with a hand-written adjoint
(:class:`_BatchedGemm`); otherwise torch's generic chain (the reference in
tests/test_sim_perf_equivalence.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import torch

from dtoc.sim import pdg_signal as _sig
from dtoc.sim.pdg_rfsplit import add_rows_, take_rows
from dtoc.sim.pdg_signal import _DIFF_TAYLOR_MAX, _decay_phase, _time_factor, _time_key, voxel_factor
from dtoc.util.cplx import cexp, cis


def cat_views(pieces: list[torch.Tensor], dim: int = 0) -> torch.Tensor:
    """``torch.cat(pieces, dim)``, with every run of consecutive pieces that are the successive views of one
    tensor along its first axis (``x.unbind(0)``, or ``torch.split(x, sizes, 0)`` when ``dim`` is 0) taken as
    one view of that tensor instead: the same values (data movement either way), but one autograd node per
    run where a cat's backward slices every piece (an operation per interval for the per-interval pieces
    of a batched pass).  Without a gradient to carry, the plain cat (one operation)."""
    if not (torch.is_grad_enabled() and any(p.requires_grad for p in pieces)):
        return torch.cat(pieces, dim)
    out, i = [], 0
    while i < len(pieces):
        i, blk = _view_run(pieces, i, dim)
        out.append(blk)
    return out[0] if len(out) == 1 else torch.cat(out, dim)


def _view_run(pieces: list[torch.Tensor], i: int, dim: int) -> tuple[int, torch.Tensor]:
    """(end of the run of views starting at ``i``, the run as one view of their base) (see :func:`cat_views`)."""
    p, base = pieces[i], pieces[i]._base
    if base is None or base.dim() == 0 or base.stride(0) <= 0 or base.device != p.device:
        return i + 1, p
    st = base.stride(0)
    k0, rem = divmod(int(p.storage_offset()) - int(base.storage_offset()), st)
    if rem or k0 < 0:
        return i + 1, p
    unbound = base.dim() == p.dim() + 1 and base.shape[1:] == p.shape and base.stride()[1:] == p.stride()
    split = dim == 0 and base.dim() == p.dim() and base.shape[1:] == p.shape[1:] and base.stride() == p.stride()
    if not (unbound or split):
        return i + 1, p
    j, nxt = i + 1, p.storage_offset() + st * (1 if unbound else p.shape[0])
    while j < len(pieces):
        q = pieces[j]
        same = q._base is base and q.stride() == p.stride() and q.storage_offset() == nxt
        if not same or (q.shape != p.shape if unbound else q.shape[1:] != p.shape[1:]):
            break
        nxt += st * (1 if unbound else q.shape[0])
        j += 1
    n = (nxt - p.storage_offset()) // st
    if j == i + 1 or k0 + n > base.shape[0]:
        return i + 1, p
    blk = base.narrow(0, k0, n)
    return j, (blk.movedim(0, dim).flatten(dim, dim + 1) if unbound else blk)


def taylor_orders(xs: np.ndarray, tol: float) -> np.ndarray:
    """Vectorised :func:`dtoc.sim.pdg_signal.taylor_order`: smallest R with x^(R+1) / (R+1)! <= tol (at most 30)."""
    xs = np.asarray(xs, dtype=np.float64)
    if xs.size == 0:
        return np.zeros(0, dtype=np.int64)
    terms = np.cumprod(xs[:, None] / np.arange(1, 31)[None, :], axis=1)  # (J, 30): x^(R+1)/(R+1)!, R = 0..29
    ok = terms <= tol
    return np.where(ok.any(1), ok.argmax(1), 30).astype(np.int64)


def _time_factors(dtt: np.ndarray, dtr: torch.Tensor, sgn: float, vox) -> tuple[list, bool]:
    """Per interval g, the (T, V) kernel time factor exp(-dt (1/T2 + sgn/T2' + i omega)) of T2' class sign
    ``sgn`` (cached per simulate call, :func:`dtoc.sim.pdg_signal._time_factor`; computed per interval when
    the cache is full), and whether every interval has the same sample times (then all entries are the
    same factor)."""
    G = dtt.shape[0]
    rate = vox.r2 + (sgn * vox.r2d if vox.has_t2d else 0.0)
    keys = [_time_key(dtt[g], sgn if vox.has_t2d else 0.0) for g in range(G)]
    # cached factors read without indexing dtr (no operation per interval when every key is cached)
    tfs = [vox.cache.get(("tf", k)) for k in keys]
    tfs = [tf if tf is not None else _time_factor(dtr[g], rate, vox, k) for g, (k, tf) in enumerate(zip(keys, tfs))]
    if any(t is None for t in tfs):  # cache full: compute per interval
        tfs = [_decay_phase(dtr[g], rate, vox.omega) for g in range(G)]
    return tfs, all(k == keys[0] for k in keys)


def _tau_factor(utau_t: torch.Tensor, sgn: float, vox) -> torch.Tensor:
    """(U, V) exp(-tau (sgn / T2' + i omega)) for the distinct dephasing times ``utau_t`` (s) of the emitting states."""
    mag = (
        torch.clamp(-sgn * utau_t[:, None] * vox.r2d[None], max=80.0)
        if vox.has_t2d
        else torch.zeros((utau_t.shape[0], vox.n), dtype=utau_t.dtype, device=utau_t.device)
    )
    return cexp(mag, -utau_t[:, None] * vox.omega[None])


def _class_rows(cls, far, orders, own_np):
    """Per T2' kernel class c (0: all samples tau + dt >= 0, 1: all < 0, 2: crossing zero) with its kernel
    signs, the expanded (not far) state rows, sorted by (interval, descending Taylor order) so that the rows
    of order >= r are a prefix of each interval's block."""
    expanded = ~far
    for c, signs in ((0, (1.0,)), (1, (-1.0,)), (2, (1.0, -1.0))):
        in_c = np.where((cls == c) & expanded)[0]
        if in_c.size:
            yield c, signs, in_c[np.lexsort((-orders[in_c], own_np[in_c]))]


@dataclass
class TaylorBlock:
    """The rows of one Taylor order r of one plan step (diffusion expansion exp(-D delta) ~ sum_r (-D delta)^r / r!).

    Attributes:
        sizes: number of consecutive rows per interval block.
        ivs: interval (batch item) of each block.
        fact: r!.
        mask: class-2 sign mask of the rows (None: all rows count; the batched schedule sets it on order 0 only).
        pos_t, rows_t, dr, kix: the per-order schedule's (the CPU's) row bookkeeping: positions of the rows
            within the step, the same rows as indices into the batch's emitting states, (V,) (D / Dmax)^r
            (None for r = 0) and the kernel row of each block; None / empty in the batched schedule.
    """

    sizes: list[int]
    ivs: list[int]
    fact: float
    mask: torch.Tensor | None = None
    pos_t: Any = None
    rows_t: Any = None
    dr: Any = None
    kix: list[int] = field(default_factory=list)


@dataclass
class PlanStep:
    """The states of one kernel class and sign: their rows, T2'-per-tau factors and Taylor orders.

    Two schedules (``GemmPlan.per_block``).  Per order (the CPU's): order by order, the order-r rows
    (``TaylorBlock.pos_t``) scaled by (D / Dmax)^r and multiplied block by block (one interval each) by
    their kernels: no padding, no copies, many small operations.  Batched (off the CPU): all orders of a
    step together, the order-r rows (``pos`` within the step, order ``r``) scaled by (D / Dmax)^r, laid out
    in ``nb`` padded blocks of ``mx`` rows, one per interval, multiplied by their kernels in one batched
    product per bucket, and weighted by ndl^r / r! (x mask): a constant number of operations.

    Attributes:
        rows: the step's rows (into the batch's emitting states); sgn: kernel sign; Pt: (rows, V) T2' x tau factors.
        orders: per Taylor order, its blocks (with the per-order schedule's row bookkeeping).
        max_order: highest Taylor order of the step.
        src, brow, r: (npad,) per slot of the batched schedule's padded layout: its row in the step, its row
            in the batch (for ndl and the cotangent) and its order (padding: the zero row of ``GemmPlan.DR``).
        mask: (npad, T) class-2 sign mask of every slot (None: all count); valid: (npad,) 1 / 0 (padding).
        npad: slots; buckets: (first slot, blocks nb, rows per block mx, kernel rows (nb,) long tensor) of
            each batched product: blocks (intervals) of similar size share one, so the padding stays below
            ~1.6x the rows (numpy interval ids until the kernels are known).
    """

    rows: torch.Tensor
    sgn: float
    Pt: torch.Tensor
    orders: list[TaylorBlock]
    max_order: int
    src: Any = None
    brow: Any = None
    r: Any = None
    mask: torch.Tensor | None = None
    npad: int = 0
    buckets: list = field(default_factory=list)
    valid: torch.Tensor | None = None


@dataclass
class GemmPlan:
    """What :class:`_BatchedGemm` needs besides its tensors: voxel constants, kernels in use, the steps."""

    vox: Any
    Co: int
    tfs: dict
    used: dict
    steps: list[PlanStep]
    per_block: bool  # the per-order schedule (CPU), else the batched one (see PlanStep)
    DR: Any = None  # batched schedule: (R + 2, V) real: (D / Dmax)^r, r = 0..R, then a zero row (padding)
    fact: Any = None  # batched schedule: (R + 2,) r!


class EmitItem(NamedTuple):
    """One interval of a batch: index ``n``, emitting view ``iv`` of its graph interval (emit = 0..J-1),
    emitting amplitudes ``Y`` (J, V) complex (or per tissue tuple, (J, U)) and their k ``Kj`` (J, 4) float64."""

    n: int
    iv: Any
    Y: torch.Tensor
    Kj: torch.Tensor


@dataclass
class _Batch:
    """The constants of one batch of intervals, shared by its evaluation steps."""

    items: list[EmitItem]
    G: int  # intervals in the batch
    Co: int  # coils
    T: int  # ADC samples per interval
    rdt: torch.dtype
    cdt: torch.dtype
    dev: torch.device
    own: torch.Tensor  # (J,) interval of each emitting state
    own_np: np.ndarray
    mom: Any
    vox: Any
    graph: Any
    bounds_t: np.ndarray
    cfg: Any


def emit_signal_batched(items, mom, vox, graph, bounds_t, cfg, expand=None, probe: dict | None = None) -> list:
    """Signals of several intervals with the same number T of ADC samples.

    Args:
        items: list of :class:`EmitItem` (n, iv_view, Y, Kj): interval index, emitting view of its graph
            (emit = 0..J-1, tau_s of the emitting states), emitting amplitudes (J, V) complex, their k (J, 4) float64.
        mom, vox, graph, bounds_t, cfg: as for :func:`dtoc.sim.pdg_signal.emit_signal_gemm`.
        expand: optional map (R, U) -> (R, V) applied once to the concatenated amplitudes (the items'
            Y are then per-tissue-tuple rows (J, U); one gather for the batch instead of one per interval).
        probe: optional dict; receives {interval n: (J,) peak |signal| of each emitting state} (the
            exactly evaluated far states: +inf); see :func:`dtoc.sim.pdg_calibrate.emission_peaks`.
    Returns:
        list of (C, T) complex signals, one per item (before the ADC phase).
    """
    dev = vox.pd.device
    rdt = vox.x.dtype
    Co = vox.n_coils
    V = vox.n
    G = len(items)
    ns = [it.n for it in items]
    lo = [it.iv.adc_start for it in items]
    T = items[0].iv.adc_stop - lo[0]
    cdt = items[0].Y.dtype
    Js = [it.Y.shape[0] for it in items]
    own_np = np.repeat(np.arange(G), Js)
    J = int(own_np.size)
    Y = cat_views([it.Y for it in items], 0) if G > 1 else items[0].Y
    if expand is not None:
        Y = expand(Y)
    Kj = cat_views([it.Kj for it in items], 0) if G > 1 else items[0].Kj
    tau = np.concatenate([it.iv.tau_s for it in items])
    own = torch.as_tensor(own_np, device=dev)
    batch = _Batch(items, G, Co, T, rdt, cdt, dev, own, own_np, mom, vox, graph, bounds_t, cfg)
    nb = torch.as_tensor(np.asarray(ns), device=dev)
    sel_adc = torch.as_tensor(np.stack([np.arange(a, a + T) for a in lo]).reshape(-1), device=dev)
    mt = (
        mom.I_adc.index_select(0, sel_adc).reshape(G, T, 4) - mom.I_bound.index_select(0, nb)[:, None, :]
    )  # (G, T, 4) f64
    dtt = np.stack([graph.adc_times_s[a : a + T] - bounds_t[n] for a, n in zip(lo, ns)])  # (G, T)
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
    bm: Any = None
    ndl: Any = None
    bfull: Any = None
    Dmax = max(vox.d_max, 1e-300) if vox.has_diffusion else 1.0
    if vox.has_diffusion and T:
        dtt_t = torch.as_tensor(dtt, dtype=torch.float64, device=dev)
        u = Kj[:, :3] - mom.I_bound.index_select(0, nb)[:, :3].index_select(0, own)
        dJ1 = (
            mom.J1_adc.index_select(0, sel_adc).reshape(G, T, 3) - mom.J1_bound.index_select(0, nb)[:, None, :]
        ).index_select(0, own)
        dJ2 = (
            mom.J2_adc.index_select(0, sel_adc).reshape(G, T) - mom.J2_bound.index_select(0, nb)[:, None]
        ).index_select(0, own)
        b = (u * u).sum(1)[:, None] * dtt_t.index_select(0, own) + 2.0 * (u[:, None, :] * dJ1).sum(-1) + dJ2  # (J, T)
        bfull = b
        bm = b[:, T // 2]
        delta = b - bm[:, None]
        xs = Dmax * delta.detach().abs().amax(1).cpu().numpy()
        far = xs > _DIFF_TAYLOR_MAX
        orders = taylor_orders(xs, cfg.taylor_tol)
        orders[far] = -1
        ndl = (-Dmax * delta).to(rdt)  # (J, T) real, |.| <= _DIFF_TAYLOR_MAX for the expanded states

    if getattr(cfg, "fused_signal_adjoint", False):
        out = _fused_products(batch, Y, Kj, bm, mt, ndl, dtt, tau, cls, far, orders, plus, Dmax)
        return _finish(batch, out, vf, (Y, Kj, mt_own, dtt_own, tau, bfull), far, probe)

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
        tfs, shared = _time_factors(dtt, dtr, sgn, vox)
        if shared:
            K = SP * tfs[0][None]
        else:
            K = SP * torch.stack(tfs, 0)
        if vox.coil is not None:
            K = (vox.coil[None, :, None, :] * K[:, None]).reshape(G, Co * T, V)
        return K.unbind(0)  # G x (Co*T, V); unbind: one autograd node (indexing would zero-fill per interval)

    kern_cache = {}
    out = torch.zeros((J, Co, T), dtype=cdt, device=dev)
    for c, signs, in_c in _class_rows(cls, far, orders, own_np):
        rows_c = torch.as_tensor(in_c, device=dev)
        Wc = W.index_select(0, rows_c)
        for sgn in signs:
            Pt = _tau_factor(utau_t, sgn, vox)  # (U, V)
            C = Wc * Pt.index_select(0, tinv_t.index_select(0, rows_c))
            if sgn not in kern_cache:
                kern_cache[sgn] = kernel(sgn)
            Kern = kern_cache[sgn]
            s_c: torch.Tensor | None = None
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
                    w = ndl.index_select(0, torch.as_tensor(in_c[pos], device=dev)) ** r / float(
                        np.prod(np.arange(1, r + 1))
                    )
                    Gr = Gr * w[:, None, :]
                if s_c is None:  # r == 0
                    s_c = Gr
                else:
                    s_c = s_c.index_add(0, torch.as_tensor(pos, device=dev), Gr)
            assert s_c is not None
            if c == 2:
                m = plus[in_c] if sgn > 0 else ~plus[in_c]
                s_c = s_c * torch.as_tensor(m, device=dev).to(rdt)[:, None, :]
            out = out.index_add(0, rows_c, s_c)
    return _finish(batch, out, vf, (Y, Kj, mt_own, dtt_own, tau, bfull), far, probe)


def _finish(b: _Batch, out, vf, exact, far, probe=None) -> list:
    """Voxel factor, sum of the states per interval, exact evaluation of the far (strong-diffusion) states."""
    items, own, own_np, G, Co, T = b.items, b.own, b.own_np, b.G, b.Co, b.T
    out = out * vf[:, None, :]
    if probe is not None:
        peak = (
            out.detach().abs().reshape(out.shape[0], -1).amax(1).double().cpu().numpy() if T else np.zeros(out.shape[0])
        )
        peak[far] = np.inf
        for g, it in enumerate(items):
            probe[it.n] = peak[own_np == g]
    sig = torch.zeros((G, Co, T), dtype=b.cdt, device=b.dev).index_add(0, own, out)
    if far.any():
        sig = sig.index_add(0, torch.as_tensor(own_np[far], device=b.dev), _far_exact(b, vf, exact, far))
    return list(sig.unbind(0))


def _far_exact(b: _Batch, vf, exact, far) -> torch.Tensor:
    """(J_far, Co, T) exact signal of the far states of all intervals of the batch at once
    (:func:`dtoc.sim.pdg_signal.emit_signal_direct` with :class:`~dtoc.sim.pdg_signal.ExactStates`)."""
    Y, Kj, mt_own, dtt_own, tau, bfull = exact
    dev, rdt = b.dev, b.rdt
    fi = np.where(far)[0]
    F = torch.as_tensor(fi, device=dev)
    st = _sig.ExactStates(
        kt=(Kj.index_select(0, F)[:, None, :] + mt_own.index_select(0, F)).to(rdt),
        tau=torch.as_tensor(tau[fi][:, None] + dtt_own[fi], dtype=rdt, device=dev),
        dt=torch.as_tensor(dtt_own[fi], dtype=rdt, device=dev),
        bD=None if bfull is None else bfull.index_select(0, F).to(rdt),
        A=Y.index_select(0, F),
        vf=vf.index_select(0, F),
    )
    return _sig.emit_signal_direct(_FarView(fi), None, None, b.mom, None, b.vox, b.graph, b.bounds_t, b.cfg, st)


class _FarView(NamedTuple):
    """What the exact path reads of its interval argument when given :class:`ExactStates`: the states."""

    emit: np.ndarray


def _fused_products(b: _Batch, Y, Kj, bm, mt, ndl, dtt, tau, cls, far, orders, plus, Dmax):
    """(J, Co, T) products of the expanded states through :class:`_BatchedGemm` (same terms and order as the generic path).

    The 'per_interval' schedule (``PDGConfig.schedule``, the CPU's default) multiplies per order and block
    (no padded flops, no copies; faster there), the 'batched' one (any other device) per bucket of similar
    blocks, all orders at once (a constant number of operations; :class:`PlanStep`)."""
    own_np, vox, Co, rdt = b.own_np, b.vox, b.Co, b.rdt
    dev = Y.device
    empty = torch.zeros(0, dtype=rdt, device=dev)
    utau, tinv = np.unique(tau, return_inverse=True)
    utau_t = torch.as_tensor(utau, dtype=rdt, device=dev)
    tinv = tinv.reshape(-1)
    dtr = torch.as_tensor(dtt, dtype=rdt, device=dev)
    tfs = {}
    for sgn in (1.0, -1.0) if vox.has_t2d else (1.0,):
        tl, shared = _time_factors(dtt, dtr, sgn, vox)
        tfs[sgn] = tl[0].T[:, None, :] if shared else torch.stack(tl, 0).permute(2, 0, 1)  # (V, 1|G, T)
    per_block = not b.cfg.batched(dev)
    dn = vox.d / Dmax
    steps: list[PlanStep] = []
    step_blocks: list[np.ndarray] = []  # intervals of every step (kernels in use)
    for c, signs, in_c in _class_rows(cls, far, orders, own_np):
        rows_c = torch.as_tensor(in_c, device=dev)
        for sgn in signs:
            if not vox.has_t2d:
                sgn = 1.0
            Pt = _tau_factor(utau_t, sgn, vox)
            Pt_rows = Pt.index_select(0, torch.as_tensor(tinv[in_c], device=dev))
            m_np = None if c != 2 else (plus[in_c] if sgn > 0 else ~plus[in_c])
            if per_block:
                st = _per_order_step(rows_c, sgn, Pt_rows, in_c, orders, own_np, m_np, dn, rdt)
                step_blocks.append(np.unique(np.concatenate([rr.ivs for rr in st.orders])))
            else:
                st, ivs_u = _batched_step(rows_c, sgn, Pt_rows, in_c, orders, own_np, m_np, rdt)
                step_blocks.append(ivs_u)
            steps.append(st)
    # kernels only for the intervals with states of each sign; block interval -> kernel row
    used = {sg: sorted({int(g) for st, ivu in zip(steps, step_blocks) if st.sgn == sg for g in ivu}) for sg in tfs}
    used = {sg: u for sg, u in used.items() if u}
    plan = GemmPlan(vox=vox, Co=Co, tfs={sg: tfs[sg] for sg in used}, used=used, steps=steps, per_block=per_block)
    for st in steps:
        row = {g: i for i, g in enumerate(used[st.sgn])}
        for rr in st.orders:
            rr.kix = [row[g] for g in rr.ivs]
        st.buckets = [
            (lo, nb, mx, torch.as_tensor([row[int(g)] for g in gs], device=dev)) for lo, nb, mx, gs in st.buckets
        ]
    if not per_block:
        Rmax = max((st.max_order for st in steps), default=0)
        drs = [torch.ones_like(dn)]
        for _ in range(Rmax):
            drs.append(drs[-1] * dn)  # (D / Dmax)^r by repeated products, as the per-order evaluation
        drs.append(torch.zeros_like(dn))  # row Rmax + 1: the padding slots
        plan.DR = torch.stack(drs, 0)
        plan.fact = torch.as_tensor([float(math.factorial(q)) for q in range(Rmax + 2)], dtype=rdt, device=dev)
        for st in steps:
            r_np = np.where(st.r < 0, Rmax + 1, st.r)
            st.r = torch.as_tensor(r_np, device=dev)
            st.valid = torch.as_tensor(r_np <= Rmax, device=dev).to(rdt)
    bm_r = empty if bm is None else bm.to(rdt)
    ndl_r = empty if ndl is None else ndl
    return _BatchedGemm.apply(
        Y, Kj[:, 0].to(rdt), Kj[:, 1].to(rdt), bm_r, mt[:, :, 0].to(rdt), mt[:, :, 1].to(rdt), ndl_r, plan
    )


def _order_blocks(ow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First position and size of every run of equal intervals in ``ow`` (the rows grouped by interval)."""
    cuts = np.flatnonzero(np.diff(ow)) + 1
    starts = np.concatenate([[0], cuts]).astype(np.int64)
    ends = np.concatenate([cuts, [ow.size]]).astype(np.int64)
    return starts, ends - starts


def _per_order_step(rows_c, sgn, Pt_rows, in_c, orders, own_np, m_np, dn, rdt) -> PlanStep:
    """A :class:`PlanStep` of the per-order schedule (the CPU's)."""
    dev = rows_c.device
    mask_c = None if m_np is None else torch.as_tensor(m_np, device=dev).to(rdt)
    ords: list[TaylorBlock] = []
    dr = None
    for r in range(int(orders[in_c].max(initial=0)) + 1):
        pos = np.where(orders[in_c] >= r)[0]
        if not pos.size:
            break
        if r > 0:
            dr = dn if dr is None else dr * dn
        ow = own_np[in_c[pos]]
        starts, sizes = _order_blocks(ow)
        pos_t = torch.as_tensor(pos, device=dev)
        ords.append(
            TaylorBlock(
                sizes=sizes.tolist(),
                ivs=[int(ow[a]) for a in starts],
                fact=float(np.prod(np.arange(1, r + 1))),
                mask=None if mask_c is None else (mask_c if r == 0 else mask_c.index_select(0, pos_t)),
                pos_t=pos_t,
                rows_t=torch.as_tensor(in_c[pos], device=dev),
                dr=dr,
            )
        )
    return PlanStep(rows=rows_c, sgn=sgn, Pt=Pt_rows, orders=ords, max_order=len(ords) - 1)


def _batched_step(rows_c, sgn, Pt_rows, in_c, orders, own_np, m_np, rdt) -> tuple[PlanStep, np.ndarray]:
    """A :class:`PlanStep` of the batched schedule (off the CPU) and the intervals of its blocks."""
    dev = rows_c.device
    oc = orders[in_c]
    # every (order r, position) pair with orders[pos] >= r, ordered by r then position (the
    # summation order of the per-order evaluation); blocks by interval for the batched product
    R = int(oc.max(initial=0))
    pos_l = [np.where(oc >= r)[0] for r in range(R + 1)]
    pos = np.concatenate(pos_l)
    rr_ = np.repeat(np.arange(R + 1), [q.size for q in pos_l])
    ow = own_np[in_c[pos]]
    ivs_u, blk = np.unique(ow, return_inverse=True)
    blk = blk.reshape(-1)
    counts = np.bincount(blk, minlength=ivs_u.size)
    buckets, pad, npad = _pad_buckets(counts, blk)
    taylor = []
    for r in range(R + 1):
        o = own_np[in_c[pos_l[r]]]
        starts, sizes = _order_blocks(o)
        taylor.append(TaylorBlock(sizes=sizes.tolist(), ivs=[int(o[q]) for q in starts], fact=float(math.factorial(r))))
    src = np.zeros(npad, dtype=np.int64)  # step row of every slot (padding: row 0, scaled by 0)
    src[pad] = pos
    r_slot = np.full(npad, -1, dtype=np.int64)  # order of every slot (padding: -1 -> the zero row)
    r_slot[pad] = rr_
    mask = None
    if m_np is not None:
        taylor[0].mask = torch.as_tensor(m_np, device=dev).to(rdt)
        mask = torch.as_tensor(m_np[src], device=dev).to(rdt)
    st = PlanStep(
        rows=rows_c,
        sgn=sgn,
        Pt=Pt_rows,
        orders=taylor,
        max_order=R,
        src=torch.as_tensor(src, device=dev),
        brow=torch.as_tensor(in_c[src], device=dev),
        r=r_slot,  # numpy until the zero row's index is known
        mask=mask,
        npad=npad,
        buckets=[(lo, nb, mx, ivs_u[sel]) for lo, nb, mx, sel in buckets],
    )
    return st, ivs_u


_PAD_GROWTH = 1.6  # blocks whose row counts differ by less than this factor share one batched product


def _pad_buckets(counts: np.ndarray, blk: np.ndarray) -> tuple[list, np.ndarray, int]:
    """Padded layout of a step's rows: blocks (intervals) with row counts ``counts`` grouped into buckets of
    similar size (a bucket's blocks are padded to its largest: < 1.6x the rows plus rounding), each bucket
    one contiguous (nb, mx) region.  Returns [(first slot, nb, mx, block ids)], the slot of every row
    (``blk``: its block, rows of a block in order) and the total number of slots."""
    key = np.ceil(np.log(np.maximum(counts, 1)) / np.log(_PAD_GROWTH)).astype(np.int64)
    buckets = []
    base = np.zeros(counts.size, dtype=np.int64)  # first slot of every block
    lo = 0
    for k in np.unique(key):
        sel = np.where(key == k)[0]
        mx = int(counts[sel].max())
        base[sel] = lo + mx * np.arange(sel.size)
        buckets.append((lo, int(sel.size), mx, sel))
        lo += mx * int(sel.size)
    srt = np.argsort(blk, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.empty(blk.size, dtype=np.int64)
    slot[srt] = np.arange(blk.size) - np.repeat(starts, counts)
    return buckets, base[blk] + slot, lo


def _block_major(K: torch.Tensor, CT: int) -> torch.Tensor:
    """(nK, V, CT) contiguous copy of the voxel-major (V, nK CT) complex kernels: one interval's kernel per
    leading index, so a bucket's kernels are a row gather (or a slice) of it."""
    V = K.shape[0]
    Kr = torch.view_as_real(K).view(V, -1, 2 * CT).transpose(0, 1).contiguous()
    return torch.view_as_complex(Kr.view(Kr.shape[0], V, CT, 2))


def _bucket_kernels(Kbm: torch.Tensor, kix: torch.Tensor) -> torch.Tensor:
    """(nb, V, CT) kernels of a bucket's blocks from the block-major kernels (no copy when they are all)."""
    nK = Kbm.shape[0]
    if kix.shape[0] == nK:  # every interval of this sign, in order (kix is sorted and distinct)
        return Kbm
    Kr = torch.view_as_real(Kbm).reshape(nK, -1).index_select(0, kix)
    return torch.view_as_complex(Kr.view(kix.shape[0], Kbm.shape[1], Kbm.shape[2], 2))


def _slot_rows(st: PlanStep, C: torch.Tensor, DR: torch.Tensor, zero_padding: bool) -> torch.Tensor:
    """(npad, V) C[src] (D / Dmax)^r of every slot; padding rows exactly 0 with ``zero_padding`` (else left
    as copies of a row: row-wise products never mix them into kept results)."""
    P = take_rows(C, st.src)
    if st.max_order > 0:
        return P.mul_(DR.index_select(0, st.r))  # the zero row of DR for the padding
    if zero_padding:
        assert st.valid is not None  # set with the plan
        return P.mul_(st.valid[:, None])
    return P


def _step_products(st: PlanStep, P: torch.Tensor, Kbm: torch.Tensor, Co: int, T: int) -> torch.Tensor:
    """(npad, Co T) raw products P_slot @ K_interval of the batched schedule: one batched matrix product per
    bucket of blocks."""
    CT = Co * T
    Z = torch.empty((st.npad, CT), dtype=P.dtype, device=P.device)
    for lo, nb, mx, kix in st.buckets:
        torch.bmm(
            P[lo : lo + nb * mx].view(nb, mx, -1), _bucket_kernels(Kbm, kix), out=Z[lo : lo + nb * mx].view(nb, mx, CT)
        )
    return Z


def _step_weights(st: PlanStep, ndl: torch.Tensor, fact: torch.Tensor) -> torch.Tensor | None:
    """(npad, T) Taylor weights ndl^r / r! (x the class-2 mask) of every slot; None: all 1."""
    w = st.mask
    if st.max_order > 0:
        nd = ndl.index_select(0, st.brow)
        wr = nd ** st.r.to(nd.dtype)[:, None] / fact.index_select(0, st.r)[:, None]
        w = wr if w is None else w * wr
    return w


class _BatchedGemm(torch.autograd.Function):
    """The state x kernel products of :func:`emit_signal_batched` as one autograd node (hand-written adjoint).

    Inputs (differentiable): Y (J, V) complex amplitudes; kx, ky (J,) rad/m (state k); bm (J,) s/m^2
    (b at the window centre; empty: no diffusion); mtx, mty (G, T) rad/m (in-interval k of the
    samples); ndl (J, T) real (-Dmax delta_j(t), the Taylor variable; empty: no diffusion).
    ``plan`` (:class:`GemmPlan`, not differentiable) holds the voxel constants and the row bookkeeping.
    Output: (J, Co, T) complex, sum over voxels of W_j(v) Kern_n(t, v) exp(-D(v) delta_j(t)) per class,
    exactly as the generic path (same terms, same order of the products).

    Adjoint (torch's convention, G = dL/dRe + i dL/dIm, real inputs get Re(conj(G) dz/dx)):
    with W = Y E, E = exp(-i (kx x + ky y)) exp(-bm D): dL/dY = G_W conj(E),
    dL/dkx = sum_v x Im(conj(G_W) W), dL/dbm = -sum_v D Re(conj(G_W) W); for the kernel
    K = coil exp(-i (mx x + my y)) tf: dL/dmx = sum_v x Im(sum_coils conj(G_K) K) (same for y);
    the products Z = Cr @ K^T give G_Cr = G_Z @ conj(K), G_K = G_Z^T @ conj(Cr); the Taylor weights
    w = ndl^r / r! (times the class-2 mask m) give dL/dndl = m r ndl^(r-1)/r! Re(sum_coils G_Z conj(Z_raw)).
    Saved: W, E, the kernels per sign in voxel-major layout (V, nK * Co * T; only the nK intervals
    with states of that sign) and the raw products of orders >= 1 (J x Co x T); C = W Pt and the
    order-r rows are recomputed (one pass each) instead of saved.  The backward carries conjugated
    cotangents so no conjugated copy of a kernel or weight array is formed.
    """

    @staticmethod
    def forward(ctx, Y, kx, ky, bm, mtx, mty, ndl, plan):
        vox = plan.vox
        E = vox.spatial_phase(kx, ky)
        if bm.numel():
            E = E * torch.exp(-bm[:, None] * vox.d[None, :])
        W = Y * E
        G, T = mtx.shape
        Co = plan.Co
        # kernels in voxel-major layout KT (V, nK * Co * T) = exp(-i (mx x + my y)) tf (coil): the
        # per-axis factors are gathered by voxel rows (no transposed copy); interval k's kernel is the
        # column block [k Co T, (k + 1) Co T), a strided (V, Co T) operand of the products
        SPT = (
            take_rows(cis(-vox.xg[:, None] * mtx.reshape(1, -1)), vox.ix_t())
            * take_rows(cis(-vox.yg[:, None] * mty.reshape(1, -1)), vox.iy_t())
        ).reshape(-1, G, T)
        Ks = {}
        signs = list(plan.tfs)
        for i, sgn in enumerate(signs):
            u, tfT = plan.used[sgn], plan.tfs[sgn]  # tfT (V, 1 or G, T)
            if len(u) == G:
                K = SPT.mul_(tfT) if (i == len(signs) - 1 and vox.coil is None) else SPT * tfT
            else:
                ut = torch.as_tensor(u, device=SPT.device)
                K = SPT.index_select(1, ut) * (tfT if tfT.shape[1] == 1 else tfT.index_select(1, ut))
            if vox.coil is not None:
                K = vox.coil.T[:, None, :, None] * K[:, :, None, :]  # (V, nK, Co, T)
            Ks[sgn] = K.reshape(K.shape[0], -1)
        J = W.shape[0]
        out = torch.zeros((J, Co, T), dtype=W.dtype, device=W.device)
        raws: list[torch.Tensor] = []
        # per-interval kernels, contiguous, for the batched products (off the CPU); the CPU's per-order
        # schedule multiplies block by block from the voxel-major kernels
        Kbm = {} if plan.per_block else {sg: _block_major(K, Co * T) for sg, K in Ks.items()}
        for st in plan.steps:
            C = take_rows(W, st.rows) * st.Pt
            if plan.per_block:
                add_rows_(out, st.rows, _orders_forward(st, C, Ks[st.sgn], ndl, Co, T, raws))
                continue
            Z = _step_products(st, _slot_rows(st, C, plan.DR, False), Kbm[st.sgn], Co, T)
            w = _step_weights(st, ndl, plan.fact)
            if st.max_order > 0:
                raws.append(Z)
            if st.max_order == 0:  # padding rows of Z are copies (not zero): weight them 0
                assert st.valid is not None
                w = st.valid[:, None] if w is None else w * st.valid[:, None]
            Gr = Z.view(-1, Co, T) if w is None else Z.view(-1, Co, T) * w[:, None, :]
            s_c = torch.zeros((st.rows.shape[0], Co, T), dtype=W.dtype, device=W.device)
            add_rows_(s_c, st.src, Gr)  # per row: order 0 first, then the higher orders (slot order)
            add_rows_(out, st.rows, s_c)
        ctx.plan, ctx.Ks, ctx.Kbm, ctx.GT = plan, Ks, Kbm, (G, T)
        ctx.save_for_backward(W, E, ndl, *raws)
        return out

    @staticmethod
    def backward(ctx, gout):
        # conjugated cotangents throughout (gKc = conj(G_K), gWc = conj(G_W)): the products need no
        # conjugated copies of the (G, Co*T, V) kernels or the (J, V) weights
        plan, Ks, Kbm = ctx.plan, ctx.Ks, ctx.Kbm
        W, E, ndl, *raws = ctx.saved_tensors
        vox = plan.vox
        Co = plan.Co
        J, V = W.shape
        G, T = ctx.GT
        need_y, need_kx, need_ky, need_bm, need_mx, need_my, need_ndl = ctx.needs_input_grad[:7]
        need_k = need_mx or need_my
        goutc = gout.conj() if plan.per_block else gout.conj().resolve_conj().contiguous()
        gWc = torch.zeros_like(W)
        gKcs = {s: torch.zeros_like(K) for s, K in Ks.items()} if need_k else {}  # conj(G_K), voxel-major
        gndl = torch.zeros_like(ndl) if need_ndl else None
        ri = 0
        for st in plan.steps:
            C = take_rows(W, st.rows) * st.Pt
            K = Ks[st.sgn]
            gKc = gKcs.get(st.sgn)
            if plan.per_block:
                gCc, ri = _orders_backward(st, C, K, gKc, goutc, ndl, gndl, raws, ri, Co, T)
                add_rows_(gWc, st.rows, gCc * st.Pt)
                continue
            GZ = take_rows(goutc, st.brow)  # (npad, Co, T) conj(G_out) of every slot
            w = _step_weights(st, ndl, plan.fact)
            if st.max_order > 0:
                raw = raws[ri].view(-1, Co, T)
                ri += 1
                if need_ndl:
                    nd = ndl.index_select(0, st.brow)
                    rf = st.r.to(nd.dtype)[:, None] * st.valid[:, None]
                    dw = (
                        rf
                        * nd ** (st.r - 1).clamp(min=0).to(nd.dtype)[:, None]
                        / plan.fact.index_select(0, st.r)[:, None]
                    )
                    if st.mask is not None:
                        dw = dw * st.mask
                    gndl.index_add_(0, st.brow, (GZ * raw).real.sum(1) * dw)  # Re(conj(G) raw); order 0: dw = 0
            GZ.mul_((st.valid[:, None] if w is None else w * st.valid[:, None])[:, None, :])  # padding rows 0
            GZ = GZ.view(st.npad, Co * T)
            Pd = _slot_rows(st, C, plan.DR, True)  # (npad, V), padding rows 0
            gCp = torch.empty_like(Pd)
            for lo, nb, mx, kix in st.buckets:
                Kb = _bucket_kernels(Kbm[st.sgn], kix)  # (nb, V, Co T)
                gz = GZ[lo : lo + nb * mx].view(nb, mx, Co * T)
                torch.bmm(gz, Kb.transpose(1, 2), out=gCp[lo : lo + nb * mx].view(nb, mx, V))
                if gKc is not None:
                    gKb = torch.bmm(Pd[lo : lo + nb * mx].view(nb, mx, V).transpose(1, 2), gz)  # (nb, V, Co T)
                    gKc.view(V, -1, Co * T).index_add_(1, kix, gKb.transpose(0, 1))
            gCp.mul_(plan.DR.index_select(0, st.r))  # padding rows -> 0
            gCc = torch.zeros_like(C)
            add_rows_(gCc, st.src, gCp)
            add_rows_(gWc, st.rows, gCc * st.Pt)
        gY = (gWc * E).conj() if need_y else None
        gkx = gky = gbm = None
        if need_kx or need_ky or need_bm:
            P = gWc * W
            if need_kx or need_ky:
                q = P.imag
                gkx = q @ vox.x if need_kx else None
                gky = q @ vox.y if need_ky else None
            if need_bm:
                gbm = -(P.real @ vox.d)
        gmx = gmy = None
        if need_k:
            Q = None  # (V, G, T): sum over signs and coils of conj(G_K) K
            for s_, K in sorted(Ks.items(), key=lambda kv: -kv[1].shape[1]):  # full kernels first
                q = gKcs[s_].mul_(K).reshape(V, -1, Co, T)
                q = q[:, :, 0] if Co == 1 else q.sum(2)
                u = plan.used[s_]
                if len(u) == G:
                    Q = q if Q is None else Q.add_(q)
                else:
                    if Q is None:
                        Q = torch.zeros((V, G, T), dtype=q.dtype, device=q.device)
                    Q.index_add_(1, torch.as_tensor(u, device=q.device), q)
            if Q is None:  # no expanded state (all evaluated exactly)
                Q = torch.zeros((V, G, T), dtype=W.dtype, device=W.device)
            xy = torch.stack([vox.x, vox.y], 0).to(Q.dtype)  # (2, V)
            m = (xy @ Q.reshape(V, G * T)).imag.reshape(2, G, T)
            gmx = m[0].contiguous() if need_mx else None
            gmy = m[1].contiguous() if need_my else None
        return gY, gkx, gky, gbm, gmx, gmy, gndl, None


def _orders_forward(st: PlanStep, C, K, ndl, Co: int, T: int, raws: list) -> torch.Tensor:
    """(rows, Co, T) products of one step in the per-order schedule (the CPU's): order by order, block by
    block (one interval each) from the voxel-major kernels ``K``; the raw products of orders >= 1 are
    appended to ``raws`` (saved for the backward)."""
    CT = Co * T
    s_c: Any = None
    for r, rr in enumerate(st.orders):
        Cr = C if r == 0 else take_rows(C, rr.pos_t) * rr.dr[None, :]
        blocks = torch.split(Cr, rr.sizes, 0)
        Gr = torch.cat([blk @ K[:, g * CT : (g + 1) * CT] for blk, g in zip(blocks, rr.kix)], 0).reshape(-1, Co, T)
        w = rr.mask
        if r > 0:
            raws.append(Gr)
            wr = ndl.index_select(0, rr.rows_t) ** r / rr.fact
            w = wr if w is None else w * wr
        if w is not None:
            Gr = Gr * w[:, None, :]
        s_c = Gr if r == 0 else add_rows_(s_c, rr.pos_t, Gr)  # s_c: a fresh product, not saved
    return s_c


def _orders_backward(st: PlanStep, C, K, gKc, goutc, ndl, gndl, raws, ri: int, Co: int, T: int):
    """The adjoint of :func:`_orders_forward`: (conj(G_C) of the step's rows, next raw index); accumulates
    conj(G_K) into ``gKc`` and dL/dndl into ``gndl`` (where not None)."""
    CT = Co * T
    g_c = take_rows(goutc, st.rows)  # conj(G_out) of the step's rows
    gCc = torch.empty_like(C)  # every row written by the order-0 products
    for r, rr in enumerate(st.orders):
        g_r = g_c if r == 0 else take_rows(g_c, rr.pos_t)
        w = rr.mask
        if r > 0:
            raw = raws[ri]
            ri += 1
            nd = ndl.index_select(0, rr.rows_t)
            if gndl is not None:
                dw = (r * nd ** (r - 1)) / rr.fact
                if w is not None:
                    dw = dw * w
                gndl.index_add_(0, rr.rows_t, (g_r * raw).real.sum(1) * dw)  # Re(conj(G) raw) = Re(G conj(raw))
            wr = nd**r / rr.fact
            w = wr if w is None else w * wr
        if w is not None:
            g_r = g_r * w[:, None, :]
        gz = g_r.reshape(g_r.shape[0], CT)
        Cr = C if r == 0 else take_rows(C, rr.pos_t) * rr.dr[None, :]
        a = 0
        parts = []
        for n_b, g in zip(rr.sizes, rr.kix):
            b = gz[a : a + n_b]
            if r == 0:
                torch.mm(b, K[:, g * CT : (g + 1) * CT].T, out=gCc[a : a + n_b])
            else:
                parts.append(b @ K[:, g * CT : (g + 1) * CT].T)
            if gKc is not None:
                gKc[:, g * CT : (g + 1) * CT].addmm_(Cr[a : a + n_b].T, b)
            a += n_b
        if r > 0:
            add_rows_(gCc, rr.pos_t, torch.cat(parts, 0) * rr.dr[None, :])
    return gCc, ri
