"""Windowed pre-compensation of long sequences: cost linear in duration, memory bounded by one window.

The warm start's objective (:func:`dtoc.optimize.optimizer.linear_objective`: k at every ADC sample, the
moment before every RF pulse, G during RF, a small change penalty) is a sum over excitation periods, and a
period's terms depend on the demanded waveform only within the hardware's memory
(:func:`dtoc.hardware.memory.memory_s`).  So the sequence is solved one excitation period (the *core*) at a
time, in time order (receding horizon):

* the window is ``[core start - horizon, core end + lookahead]`` (block boundaries; the lookahead reaches at
  least the next period's excitation): the committed waveform before the core (history) and the base
  waveform after it are fixed, only the core's free edges move;
* the core's terms: its ADC samples (exact k: the core begins with an excitation, which resets k), the
  moment and the G-during-RF of every pulse after its own excitation up to the next period's excitation,
  the change penalty on its own samples -- each term counted in exactly one window, with the whole
  sequence's normalisation, so that the windows' objectives add up to the whole-sequence objective;
* with an affine hardware chain the residual vector is ``r0 + J d`` exactly; ``J`` depends only on the
  period's timing (not on the gradient amplitudes), so periods of one structure (every TR of a train)
  share one Jacobian and one Cholesky factor of ``J^T J``, computed once ("kernel" of the repeated block).
  The unconstrained minimiser is one back-substitution; when it leaves the limits, projected FISTA on the
  exact quadratic (dense ``J^T J``) finishes it.

Edges in long idle stretches (more than ``pad_s`` from any non-zero base gradient or ADC sample) are held
at the base value (zero): a delay of a second adds no variables.  The difference to the whole-sequence
solve (the part of the hardware's memory beyond the horizon, the future periods that cannot answer back)
is measured in docs/benchmarks.md ("Long sequences").  Units: mT/m, s, rad/m.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from dtoc.optimize.limits import EdgeProjector, Limits, edges_to_played
from dtoc.seq.ir import SequenceIR, edges_to_fine
from dtoc.seq.kspace import kspace_at

#: a period with more free variables than this is not solved densely (the whole-sequence path is used)
DENSE_MAX = 6000


@dataclass
class Window:
    """One excitation period (core) and its context, as block indices ``[b0, b1)``."""

    core: tuple[int, int]
    sub: tuple[int, int]
    adc: list[int]  # indices into ir.adc
    rf: list[int]  # indices into ir.rf kept in the window (k resets, moments)
    moment_rf: list[int]  # RF pulses whose moment counts here
    rfterm_rf: list[int]  # RF pulses whose G-during-RF counts here


@dataclass
class WindowStats:
    windows: int = 0
    structures: int = 0
    constrained: int = 0
    fista_iters: int = 0
    max_free: int = 0
    horizon_s: float = 0.0
    lookahead_s: float = 0.0
    times_s: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {
            "windows": self.windows,
            "distinct_structures": self.structures,
            "windows_at_limits": self.constrained,
            "fista_iterations": self.fista_iters,
            "max_free_variables_per_window": self.max_free,
            "horizon_s": self.horizon_s,
            "lookahead_s": self.lookahead_s,
            "times_s": {k: round(v, 3) for k, v in self.times_s.items()},
        }


def plan_windows(ir: SequenceIR, horizon_s: float, lookahead_s: float) -> list[Window]:
    """Cores = excitation periods (from the block of one exciting pulse to the next's); their windows."""
    edges = ir.block_edges_s
    nb = len(edges) - 1
    exc_blocks = sorted({r.block for r in ir.rf if r.excites})
    starts = [0] + [b for b in exc_blocks if b > 0]
    out = []
    for j, b0 in enumerate(starts):
        b1 = starts[j + 1] if j + 1 < len(starts) else nb
        t0, t1 = edges[b0], edges[b1]
        sb0 = int(max(0, np.searchsorted(edges, t0 - horizon_s, side="right") - 1))
        # the next period's excitation (its moment and G-during-RF depend on this core)
        nxt = [i for i, r in enumerate(ir.rf) if r.block == b1 and r.excites] if b1 < nb else []
        t_end = t1 + lookahead_s
        if nxt:
            t_end = max(t_end, edges[b1 + 1])
        sb1 = int(min(nb, np.searchsorted(edges, t_end - 1e-12, side="left")))
        sb1 = max(sb1, b1)
        in_core = [i for i, r in enumerate(ir.rf) if b0 <= r.block < b1]
        first = in_core[0] if (in_core and j > 0 and ir.rf[in_core[0]].excites) else None
        rf_idx = in_core + nxt[:1]
        own = [i for i in rf_idx if i != first]
        moment = [i for i in own if i > 0]  # the sequence's first pulse has no moment term
        adc = [i for i, a in enumerate(ir.adc) if b0 <= a.block < b1]
        out.append(Window((b0, b1), (sb0, sb1), adc, rf_idx, moment, own))
    return out


def active_edges(ir: SequenceIR, pad_s: float) -> np.ndarray:
    """(N+1,) bool: raster edges within ``pad_s`` of a non-zero base gradient (any axis) or an ADC sample."""
    e = ir.edge_grad_mT_per_m
    busy = np.any(e != 0, axis=0)
    n = busy.size
    for a in ir.adc:
        i0 = int(np.floor(a.t_start_s / ir.raster_s))
        i1 = int(np.ceil((a.t_start_s + a.num_samples * a.dwell_s) / ir.raster_s))
        busy[max(i0, 0) : min(i1, n - 1) + 1] = True
    pad = int(math.ceil(pad_s / ir.raster_s))
    c = np.concatenate([[0], np.cumsum(busy)])
    lo = np.clip(np.arange(n) - pad, 0, n)
    hi = np.clip(np.arange(n) + pad + 1, 0, n)
    return (c[hi] - c[lo]) > 0


def period_free_counts(ir: SequenceIR, free: np.ndarray, pad_s: float = 2e-3) -> np.ndarray:
    """Free variables of every excitation period (core) in windowed mode (cheap: no window is built)."""
    f = (free & active_edges(ir, pad_s)[None, :]).sum(axis=0)
    c = np.concatenate([[0], np.cumsum(f)])
    edges = ir.block_edges_s
    nb = len(edges) - 1
    starts = [0] + sorted({r.block for r in ir.rf if r.excites} - {0}) + [nb]
    e = np.round(edges[starts] / ir.raster_s).astype(int)
    return c[e[1:]] - c[e[:-1]]


class _Scales:
    """Per-term residual weights with the whole sequence's normalisation (see loss.py)."""

    def __init__(self, ir: SequenceIR, weights, dk: np.ndarray, rf_mask_full: np.ndarray):
        n_adc = max(ir.n_adc_samples, 1)
        n_mom = max(len(ir.rf) - 1, 1)
        n_rf = max(int(rf_mask_full.sum()), 1)
        gref = float(np.abs(ir.grad_mT_per_m).max()) or 1.0
        inv = np.where(np.isfinite(dk), 1.0 / dk, 0.0)
        self.k = math.sqrt(weights.kspace / n_adc) * inv
        self.m = math.sqrt(weights.moment / n_mom) * inv
        self.rf = math.sqrt(weights.rf / n_rf) / gref
        self.reg = math.sqrt(weights.reg / (3 * ir.n_fine)) / gref
        self.k_axes = np.flatnonzero(inv > 0)


def windowed_warm_start(
    ir: SequenceIR,
    hardware,
    limits: Limits,
    free: np.ndarray,
    weights,
    dk_rad_per_m: np.ndarray,
    rf_mask_full: np.ndarray,
    *,
    horizon_s: float,
    lookahead_s: float,
    pad_s: float = 2e-3,
    iters: int = 300,
    dtype: torch.dtype = torch.float64,
    device: str = "cpu",
    progress: Callable | None = None,
) -> tuple[np.ndarray, WindowStats]:
    """Solve the warm start's objective period by period (module doc).

    Args:
        ir: the base sequence; hardware: an affine chain (:func:`dtoc.hardware.memory.is_affine`).
        free: (3, N+1) optimizable edges (as :func:`dtoc.optimize.run.free_edges`).
        weights: :class:`~dtoc.optimize.config.LossWeights` (image, amplitude, slew ignored).
        dk_rad_per_m: (3,) k unit per axis (inf: axis not scored); rf_mask_full: (2N+1,) RF samples.
        horizon_s / lookahead_s: history kept before / base waveform kept after each core.
        iters: CG + FISTA iterations per window (half each at most, as the whole-sequence warm start).
    Returns:
        (3, N+1) edges within the limits, and :class:`WindowStats`.
    Raises:
        ValueError: a period has more than :data:`DENSE_MAX` free variables.
    """
    import time

    t_all = time.time()
    st = WindowStats(horizon_s=horizon_s, lookahead_s=lookahead_s)
    windows = plan_windows(ir, horizon_s, lookahead_s)
    st.windows = len(windows)
    dtf = ir.dt_fine_s
    sc = _Scales(ir, weights, np.asarray(dk_rad_per_m, dtype=np.float64), rf_mask_full)
    base_fine = np.asarray(ir.grad_mT_per_m, dtype=np.float64)
    k0_full = ir.nominal_kspace_rad_per_m()
    adc_start = np.concatenate([[0], np.cumsum([a.num_samples for a in ir.adc])]).astype(int)
    t_mom_all = np.array([r.t_center_s - 1e-9 for r in ir.rf])
    m0_full = ir.kspace_rad_per_m(times_s=t_mom_all).numpy() if len(ir.rf) else np.zeros((3, 0))
    free = free & active_edges(ir, pad_s)[None, :]
    edges = np.array(ir.edge_grad_mT_per_m, dtype=np.float64)  # committed as we go
    played = base_fine.copy()
    cache: dict[str, dict] = {}
    n_cg = iters // 2
    n_fista = iters - n_cg
    tt = {"setup": 0.0, "jacobian": 0.0, "residual": 0.0, "solve": 0.0}
    for wi, w in enumerate(windows):
        t0 = time.time()
        be = ir.block_edges_s
        m0 = int(round(be[w.sub[0]] / dtf))
        m1 = int(round(be[w.sub[1]] / dtf))
        e0, e1 = m0 // 2, m1 // 2
        ec0, ec1 = int(round(be[w.core[0]] / ir.raster_s)), int(round(be[w.core[1]] / ir.raster_s))
        fr = np.zeros((3, e1 - e0 + 1), dtype=bool)
        fr[:, ec0 - e0 : ec1 - e0] = free[:, ec0:ec1]
        n_free = int(fr.sum())
        st.max_free = max(st.max_free, n_free)
        if n_free == 0:
            continue
        if n_free > DENSE_MAX:
            raise ValueError(f"excitation period {wi} has {n_free} free variables (> {DENSE_MAX})")
        tsub = be[w.sub[0]]
        x_sub = edges[:, e0 : e1 + 1].copy()
        fine_sub = played[:, m0 : m1 + 1].copy()
        P = EdgeProjector(x_sub, fr, ir.raster_s, limits)
        fmask = P.fine_free_mask()
        rf_c = [ir.rf[i].t_center_s - tsub for i in w.rf]
        rf_u = [ir.rf[i].use for i in w.rf]
        t_adc = np.concatenate([ir.adc[i].sample_times_s for i in w.adc]) - tsub if w.adc else np.zeros(0)
        sel_adc: np.ndarray | list[int] = (
            np.concatenate([np.arange(adc_start[i], adc_start[i + 1]) for i in w.adc]) if w.adc else []
        )
        k0 = k0_full[:, sel_adc] if w.adc else np.zeros((3, 0))
        t_mom = t_mom_all[w.moment_rf] - tsub
        mom0 = m0_full[:, w.moment_rf]
        rfm = np.zeros(m1 - m0 + 1, dtype=bool)
        tf = np.arange(m1 - m0 + 1) * dtf
        for i in w.rfterm_rf:
            r = ir.rf[i]
            rfm |= (tf >= r.t_start_s - tsub - 1e-12) & (tf <= r.t_start_s + r.duration_s - tsub + 1e-12)
        g0_sub = base_fine[:, m0 : m1 + 1]

        def T(a):
            return torch.as_tensor(a, dtype=dtype, device=device)

        residual = _residual_fn(
            hardware, dtf, torch.as_tensor(fmask), T(fine_sub), T(g0_sub), t_adc, T(k0), t_mom, T(mom0),
            rf_c, rf_u, rfm, sc, T(sc.k), T(sc.m),
        )  # fmt: skip

        tt["setup"] += time.time() - t0
        t0 = time.time()
        with torch.no_grad():
            r0 = residual(T(x_sub)[None])[0]
        tt["residual"] += time.time() - t0
        tc = be[w.core[0]] - tsub  # the core's start in the window; the Jacobian does not depend on the history
        key = _structure_key(
            fr[:, ec0 - e0 :],
            fmask[:, 2 * (ec0 - e0) :],
            t_adc - tc,
            [c_ - tc for c_ in rf_c],
            rf_u,
            t_mom - tc,
            rfm[2 * (ec0 - e0) :],
            m1 - 2 * ec1,
        )
        c = cache.get(key)
        if c is None:
            t0 = time.time()
            c = _factor(residual, x_sub, fr, r0, dtype, device)
            cache[key] = c
            tt["jacobian"] += time.time() - t0
        t0 = time.time()
        idx = np.flatnonzero(fr.ravel())
        x_p, its = _solve(c["H"], c["J"].T @ r0, x_sub, idx, P, c["lam"], n_cg, n_fista, dtype, device)
        st.fista_iters += its
        st.constrained += int(its > 0)
        tt["solve"] += time.time() - t0
        edges[:, e0 : e1 + 1] = x_p
        played[:, m0 : m1 + 1] = edges_to_played(x_p, fine_sub, fmask)
        if progress is not None:
            progress("windows", wi + 1, len(windows), float((r0**2).sum()))
    st.structures = len(cache)
    tt["total"] = time.time() - t_all
    st.times_s = tt
    return edges, st


def _residual_fn(hardware, dtf, fmask_t, fine_t, g0_t, t_adc, k0_t, t_mom, mom0_t, rf_c, rf_u, rfm, sc, sk_t, sm_t):
    """The window's weighted residual vector as a function of edge arrays: (B, 3, Ne) -> (B, R)."""
    ka = torch.as_tensor(sc.k_axes)

    def residual(xe: torch.Tensor) -> torch.Tensor:
        g = torch.where(fmask_t, edges_to_fine(xe), fine_t)
        G = g if hardware is None else hardware(g, dtf)[0]
        parts = []
        if t_adc.size and ka.numel():
            k = kspace_at(G, dtf, t_adc, rf_c, rf_u)
            parts.append(((k - k0_t) * sk_t[:, None])[:, ka].flatten(1))
        if t_mom.size and ka.numel():
            mm = kspace_at(G, dtf, t_mom, rf_c, rf_u)
            parts.append(((mm - mom0_t) * sm_t[:, None])[:, ka].flatten(1))
        if rfm.any():
            parts.append(((G - g0_t)[..., rfm] * sc.rf).flatten(1))
        parts.append((g - g0_t)[:, fmask_t] * sc.reg)  # only samples that can change: the rest is a constant
        return torch.cat(parts, dim=1)

    return residual


def _structure_key(*parts) -> str:
    h = hashlib.sha256()
    for p in parts:
        if isinstance(p, np.ndarray):
            a = np.round(p, 10) if p.dtype.kind == "f" else p
            h.update(str(a.shape).encode())
            h.update(np.ascontiguousarray(a).tobytes())
        elif isinstance(p, (list, tuple)):
            h.update(repr([round(v, 10) if isinstance(v, float) else v for v in p]).encode())
        else:
            h.update(repr(p).encode())
    return h.hexdigest()


def _factor(residual, x_sub: np.ndarray, fr: np.ndarray, r0: torch.Tensor, dtype, device) -> dict:
    """Jacobian J of the affine residual w.r.t. the free edges (unit perturbations), H = J^T J, its largest
    eigenvalue."""
    idx = np.flatnonzero(fr.ravel())
    cols = []
    chunk = int(np.clip((1 << 22) // (2 * x_sub.shape[1]), 4, 128))  # batch memory ~ chunk x window length
    xt = torch.as_tensor(x_sub, dtype=dtype, device=device)
    with torch.no_grad():
        for s in range(0, idx.size, chunk):
            ii = idx[s : s + chunk]
            X = xt.expand(ii.size, *xt.shape).clone().reshape(ii.size, -1)
            X[torch.arange(ii.size), torch.as_tensor(ii)] += 1.0
            cols.append(residual(X.reshape(ii.size, *xt.shape)) - r0)
    J = torch.cat(cols, 0).T.contiguous()  # (R, n)
    H = J.T @ J
    return {"J": J, "H": H, "lam": _power(H)}


def _power(H: torch.Tensor, n: int = 30) -> float:
    v = torch.ones(H.shape[0], dtype=H.dtype, device=H.device)
    lam = 0.0
    for _ in range(n):
        w = H @ v
        lam = float(w.norm())
        v = w / max(lam, 1e-300)
    return 1.05 * lam


def _solve(H, b, x_sub, idx, P: EdgeProjector, lam, n_cg, n_fista, dtype, device, rel_tol=1e-7):
    """The warm start's algorithm (:func:`dtoc.optimize.optimizer.warm_start`) on the window's exact quadratic
    ``q(d) = d^T H d + 2 b^T d`` (d: change of the free edges): CG from d = 0 (its early stop regularises),
    exact projection, projected FISTA with adaptive restart; never worse than the base (d = 0).
    Returns (edges, FISTA iterations)."""
    shape = x_sub.shape
    xb = x_sub.ravel()[idx]

    def d_of(x):
        return torch.as_tensor(x.ravel()[idx] - xb, dtype=dtype, device=device)

    def q(d):
        return float(d @ (H @ d) + 2.0 * (b @ d))

    def put(x, d):
        z = x.ravel().copy()
        z[idx] = xb + d.cpu().numpy()
        return z.reshape(shape)

    d = torch.zeros_like(b)
    r = -b.clone()
    p = r.clone()
    rr = rr0 = float(r @ r)
    for _ in range(n_cg):
        if rr <= 1e-12 * max(rr0, 1e-300):
            break
        Hp = H @ p
        pHp = float(p @ Hp)
        if pHp <= 0:
            break
        a = rr / pHp
        d = d + a * p
        r = r - a * Hp
        rr_new = float(r @ r)
        p = r + (rr_new / rr) * p
        rr = rr_new
    x = P.project(put(x_sub, d), n_iter=60, exact=True)
    step = 1.0 / (1.2 * 2.0 * max(lam, 1e-300))
    y, x_prev, t = x.copy(), x.copy(), 1.0
    f0 = q(d_of(x))
    f_prev = math.inf
    j = 0
    for j in range(1, n_fista + 1):
        dy = d_of(y)
        gy = (2.0 * (H @ dy + b)).cpu().numpy()
        z = y.ravel().copy()
        z[idx] -= step * gy
        x_new = P.project(z.reshape(shape), n_iter=8, exact=False)
        if float(((y - x_new) * (x_new - x_prev)).sum()) > 0:
            t = 1.0
        t_new = 0.5 * (1 + math.sqrt(1 + 4 * t * t))
        y = x_new + ((t - 1) / t_new) * (x_new - x_prev)
        x_prev, t = x_new, t_new
        if j > 20 and j % 20 == 1:
            fy = q(dy)
            if f_prev - fy <= max(rel_tol * abs(fy), 1e-6 * abs(f0)):
                break
            f_prev = fy
    x = P.project(x_prev, n_iter=60, exact=True)
    if q(d_of(x)) > 0.0:  # worse than leaving the window as it is
        return x_sub.copy(), j
    return x, j
