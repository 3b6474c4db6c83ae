"""Certificates of unreachable k: a lower bound, proven by a small linear programme, on the k error that any
waveform within the limits leaves on a group of ADC samples (docs/optimize.md, "Unreachable samples").

For an affine, time-invariant hardware chain (:data:`dtoc.hardware.memory.AFFINE_KINDS`) the realized k at an ADC
sample is affine in the demanded raster edges, and the limits are linear inequalities (the amplitude and
reachability envelopes ``lo <= x <= hi`` of :class:`~dtoc.optimize.limits.EdgeProjector`, which fold in the held
edges, and the slew bounds ``dlo <= x[n+1] - x[n] <= dhi`` between free neighbours).  For a *group* ``G`` of
samples (the worst one and its neighbours in time) the smallest achievable worst error

    t* = min over x within the limits of  max over j in G, encoded axis b of |k_jb(x) - k0_jb| / dk_b

is an LP.  It is solved on a *window* of edges only, as a relaxation (so ``t*`` of the window is <= the whole
problem's):

* the window reaches the chain's causal support ``L_c`` before the group's first sample and its acausal support
  ``L_a`` after its last one, and ``L_c`` before any RF pulse inside it;
* every edge outside the window is free of every limit; its effect on the group is then, up to the chain's response
  beyond ``L_c`` / ``L_a`` (its *tail*), a change of the running integral common to every sample of the group: one
  free offset per axis (signed as the RF pulses in the window sign k: :func:`~dtoc.optimize.window_jacobian.k_coefficients`);
* the slew bound between the window's first (last) edge and the one before (after) it is dropped.

The tail is bounded, not neglected: an edge outside the window moves by at most ``hi - lo <= 2 gmax``, so the
group's k moves beyond the common offset by at most ``gamma 2 gmax sum |tail|`` per axis (``tail_dk``).  The bound
``lower_bound_dk = t* - tail_dk - LP_SLACK_DK`` holds for every waveform within the limits: if it is above the
tolerance, no waveform dtoc may write puts every sample of the group within it (*proven*).  The error dtoc reports
is the 2-norm over the encoded axes, >= the max over them, so the bound holds for it too.

A single sample is never proven unreachable this way when the edges before it are free: the area before it can move
its k anywhere; what the limits forbid is a whole readout line's shape.  So a certificate names a group and proves
that one of its samples is at least ``lower_bound_dk`` from its target.

Which limit: the LP is solved again without the slew bounds and without the amplitude bounds; a limit whose removal
brings ``t*`` within the tolerance is named as binding, with the number of its constraints active at the optimum
(nonzero dual).  When neither removal does, both together are tried; when even the LP without limits misses, the
cause is what dtoc may not change (held edges, RF blocks) and the chain.

Units: mT/m (edges), s, dk (errors).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog

from dtoc.constants import AXES, GAMMA_RAD_PER_S_PER_MT
from dtoc.optimize import window_jacobian as WJ

#: the worst this many groups of samples above the tolerance are certified, one LP (up to four) each
CERTIFY_GROUPS = 4
#: a group: the worst sample not yet in a group and up to this many ADC samples before and after it (in time order)
GROUP_HALF = 32
#: the window reaches the chain's support before and after the group: the shortest lags whose bounded tail
#: (:func:`tail_sums`) is within this share of the tolerance
TAIL_SHARE = 0.05
#: the longest support tried, s (a chain still ringing beyond it: its tail is bounded as it is)
SUPPORT_MAX_S = 40e-3
#: the LPs' own variables: the edges within this time before the group's first sample and after its last, s
#: (a rule of ours: a GIRF's fast part; the edges further in the window enter the bound as a bounded remainder)
NEAR_S = 2e-3
#: the witness keeps at most this many other ADC samples of its window no worse (evenly spaced; the witness is
#: checked on the whole waveform after)
KEEP_MAX = 16
#: the most simplex iterations of one LP (deterministic, unlike a time limit): beyond it the LP counts as unsolved
#: (no bound, no witness)
LP_MAXITER = 20000
#: subtracted from the LP's optimum for the solver's tolerances (dk)
LP_SLACK_DK = 1e-6


@dataclass
class Certificate:
    """One group's lower bound (module doc).

    Attributes:
        samples: the group's ADC sample indices; worst: its worst sample at the solver's stop.
        error_dk: the worst sample's error at the stop.
        lower_bound_dk: proven: every waveform within the limits leaves a sample of the group at least this far.
        lp_dk: the window LP's optimum ``t*``; tail_dk: the bound on what the edges outside the window add.
        without_slew_dk / without_amplitude_dk / without_limits_dk: ``t*`` with those limits removed (nan: not solved).
        binding: the limits named binding ('slew', 'amplitude', 'slew and amplitude', or 'held edges' when even
            no limit leaves the group above the tolerance).
        active: per limit kind and axis, the constraints active at the optimum ('slew x': 12, ...).
        window_ms: the window's first and last edge times, ms.
        proven: ``lower_bound_dk > tol``.
    """

    samples: np.ndarray
    worst: int
    error_dk: float
    lower_bound_dk: float
    lp_dk: float
    tail_dk: float
    without_slew_dk: float = math.nan
    without_amplitude_dk: float = math.nan
    without_limits_dk: float = math.nan
    binding: str = ""
    active: dict = field(default_factory=dict)
    window_ms: tuple[float, float] = (math.nan, math.nan)
    far_remainder_dk: float = 0.0
    witness_dk: float = math.nan
    _tol: float = 0.0
    witness_change: tuple | None = None  # (edge indices, axes, change in mT/m) of the witness
    witness_max_dk: float = math.nan  # every sample's largest error with the witness applied (set by the caller)
    stop_max_dk: float = math.inf  # every sample's largest error at the stop (set by the caller)
    proven: bool = False

    def as_dict(self) -> dict:
        def f(v):
            return None if not math.isfinite(v) else float(v)

        return {
            "samples": [int(self.samples[0]), int(self.samples[-1])],
            "worst_sample": int(self.worst),
            "error_dk": float(self.error_dk),
            "proven": bool(self.proven),
            "lower_bound_dk": float(self.lower_bound_dk),
            "lp_optimum_dk": float(self.lp_dk),
            "tail_dk": float(self.tail_dk),
            "without_slew_dk": f(self.without_slew_dk),
            "without_amplitude_dk": f(self.without_amplitude_dk),
            "without_limits_dk": f(self.without_limits_dk),
            "binding": self.binding or None,
            "active": dict(self.active),
            "window_ms": [float(self.window_ms[0]), float(self.window_ms[1])],
            "far_remainder_dk": float(self.far_remainder_dk),
            "witness_dk": f(self.witness_dk),
            "witness_max_dk": f(self.witness_max_dk),
            "status": self.status,
        }

    @property
    def status(self) -> str:
        """'proven' (no waveform within the limits puts the group within the tolerance), 'reachable' (the witness
        does: the solver stopped short) or 'not proven'."""
        if self.proven:
            return "proven"
        whole = not (self.witness_max_dk > self.stop_max_dk)  # nan: the whole sequence not checked (the group only)
        return "reachable" if self.witness_dk <= self._tol and whole else "not proven"

    def line(self) -> str:
        what = f"samples {int(self.samples[0])}-{int(self.samples[-1])} (worst {self.worst} at {self.error_dk:.3g} dk)"
        held = f"with every other edge held and no net area change the group reaches {self.witness_dk:.3g} dk" + (
            "" if math.isnan(self.witness_max_dk) else f" (every sample then within {self.witness_max_dk:.3g} dk)"
        )
        if self.proven:
            return (
                f"{what}: proven, one of them stays >= {self.lower_bound_dk:.3g} dk within the limits "
                f"({self.binding} binding)"
            )
        if self.status == "reachable":
            return f"{what}: reachable, {held}"
        why = (
            f"the chain's response beyond {1e3 * NEAR_S:g} ms could move them by up to "
            f"{self.far_remainder_dk + self.tail_dk:.3g} dk"
            if self.far_remainder_dk + self.tail_dk > self._tol
            else f"lower bound {max(self.lower_bound_dk, 0.0):.3g} dk"
        )
        return f"{what}: not proven ({why}); {held}"


def tail_sums(R: np.ndarray, W: int, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Per output axis and lag ``L`` (fine samples), the bound on the running integral that every fine sample more
    than ``L`` before (``causal``, (3, W)) or after (``acausal``) a query adds beyond its final value (before) or
    zero (after), per mT/m of change of each, summed over the input axes and over the lags: ``dt sum_{m >= L}
    max(|S(m)|, |S(m + 1)|)`` with ``S(m) = sum_{i >= W + m} R`` (causal; the PWL integral of a query between fine
    samples lies between two such sums) and ``S(m) = sum_{i <= W - m} R`` (acausal).  ``R``: (3, 3, 2W)
    :func:`~dtoc.optimize.window_jacobian.impulse_responses`.  Units: s (rad/m per (mT/m) without gamma)."""
    after = np.cumsum(R[..., ::-1], -1)[..., ::-1][..., W:]  # (3, 3, W): S(m) = sum_{i >= W + m} R
    before = np.cumsum(R, -1)[..., W::-1]  # (3, 3, W + 1): sum_{i <= W - m} R
    out = []
    for S in (after, before[..., :W]):
        nxt = np.concatenate([S[..., 1:], np.zeros(S.shape[:-1] + (1,))], -1)
        dev = np.maximum(np.abs(S), np.abs(nxt)).sum(0)  # (3, W): summed over the input axes
        out.append(dt_s * np.cumsum(dev[:, ::-1], -1)[:, ::-1])  # [b, L] = dt sum_{m >= L} dev[b, m]
    return out[0], out[1]


def support(tail: np.ndarray, scale: np.ndarray, limit: float) -> int:
    """The smallest lag whose tail ``(3, W)`` times ``scale`` (3,) is within ``limit`` on every axis (the last
    lag if none is)."""
    ok = np.flatnonzero(((tail * scale[:, None]) <= limit).all(0))
    return int(ok[0]) if ok.size else tail.shape[1] - 1


def _groups(err: np.ndarray, t_adc: np.ndarray, tol: float, n_groups: int, half: int) -> list[np.ndarray]:
    """The worst ``n_groups`` groups: each the worst sample above ``tol`` not yet grouped and its ``half``
    neighbours either side in time order (cut at a gap of more than 4 sample spacings: another readout)."""
    order = np.argsort(t_adc, kind="stable")
    pos = np.empty_like(order)
    pos[order] = np.arange(order.size)
    taken = np.zeros(err.size, dtype=bool)
    out: list[np.ndarray] = []
    for j in np.argsort(-err, kind="stable"):
        if len(out) >= n_groups or err[j] <= tol:
            break
        if taken[j]:
            continue
        p = int(pos[j])
        lo, hi = max(p - half, 0), min(p + half, order.size - 1)
        ts = t_adc[order[lo : hi + 1]]
        step = np.diff(ts)
        if step.size:
            typ = float(np.median(step))
            gap = np.flatnonzero(step > 4 * typ + 1e-12)
            c = p - lo
            left = gap[gap < c]
            right = gap[gap >= c]
            lo2 = lo + (int(left[-1]) + 1 if left.size else 0)
            hi2 = lo + (int(right[0]) if right.size else hi - lo)
            lo, hi = lo2, hi2
        g = order[lo : hi + 1]
        taken[g] = True
        out.append(np.sort(g))
    return out


def certify(
    hardware,
    dt_fine_s: float,
    P,
    x: np.ndarray,
    k_now: np.ndarray,
    k0: np.ndarray,
    dk: np.ndarray,
    t_adc: np.ndarray,
    rf_c: list[float],
    rf_u: list[str],
    err: np.ndarray,
    tol: float,
    n_groups: int = CERTIFY_GROUPS,
    half: int = GROUP_HALF,
) -> list[Certificate]:
    """Certificates for the worst ``n_groups`` groups of ADC samples above ``tol`` (module doc).

    Args:
        hardware: the affine chain (``hardware(g, dt) -> (G, ...)``, (B, 3, M) fine samples).  dt_fine_s: its spacing.
        P: the run's :class:`~dtoc.optimize.limits.EdgeProjector`; x: (3, N+1) the solver's edges (within the limits).
        k_now / k0: (3, N_adc) the realized k at ``x`` and the target, rad/m.  dk: (3,) rad/m (inf: not encoded).
        t_adc: (N_adc,) sample times, s.  rf_c / rf_u: every RF pulse's centre (s) and use.
        err: (N_adc,) the errors at ``x``, dk (the groups' order).
    """
    dk = np.asarray(dk, dtype=np.float64)
    ka = np.flatnonzero(np.isfinite(dk) & (dk > 0))
    groups = _groups(np.asarray(err, dtype=np.float64), np.asarray(t_adc, dtype=np.float64), tol, n_groups, half)
    if not groups or not ka.size:
        return []
    ras = P.raster_s
    W_r = max(8, int(round(2 * SUPPORT_MAX_S / dt_fine_s)))
    R = WJ.impulse_responses(hardware, dt_fine_s, W_r)
    tc, ta = tail_sums(R, W_r, dt_fine_s)
    # every fine sample outside the window moves by at most 2 gmax (within the amplitude limit before and after)
    scale = np.zeros(3)
    scale[ka] = GAMMA_RAD_PER_S_PER_MT * 2 * P.limits.gmax_eff_mT_per_m / dk[ka]
    Lc, La = support(tc, scale, TAIL_SHARE * tol), support(ta, scale, TAIL_SHARE * tol)
    tail_dk = float((tc[:, Lc] * scale).max() + (ta[:, La] * scale).max())
    ev_t = np.array([t for t, u in zip(rf_c, rf_u) if u in ("excitation", "undefined", "refocusing")])
    out = []
    n_e = P.free.shape[1]
    for g in groups:
        t_q = np.asarray(t_adc, dtype=np.float64)[g]
        t_start = float(t_q.min()) - max(Lc * dt_fine_s, NEAR_S)
        L = Lc * dt_fine_s
        while t_start > 0:  # every RF event in the window at least the causal support after its start
            near = ev_t[(ev_t >= t_start) & (ev_t < t_start + L - 1e-12) & (ev_t <= t_q.max())]
            if not near.size or float(near.min()) - L >= t_start:
                break
            t_start = float(near.min()) - L
        a = max(int(math.floor(t_start / ras)), 0)
        b = min(int(math.ceil((float(t_q.max()) + max(La * dt_fine_s, NEAR_S)) / ras)) + 1, n_e - 1)
        out.append(
            _certify_group(hardware, dt_fine_s, P, x, k_now, k0, dk, ka, t_adc, rf_c, rf_u, err, tol, g, a, b, tail_dk)
        )
    return out


def _certify_group(hardware, dt_fine_s, P, x, k_now, k0, dk, ka, t_adc, rf_c, rf_u, err, tol, g, a, b, tail_dk):
    """One group's two LPs on the window of edges ``a..b`` (module doc): the bound (the edges within :data:`NEAR_S`
    of the group its variables, the others in the window a remainder bounded row by row, the ones outside a free
    common offset plus the bounded tail ``tail_dk``) and the witness (the same variables, every other edge at ``x``)."""
    from dtoc.optimize.limits import fine_free_mask

    ras = P.raster_s
    t0 = a * ras
    width = b - a + 1
    fr = np.asarray(P.free[:, a : b + 1], dtype=bool)
    xw = np.asarray(x[:, a : b + 1], dtype=np.float64)
    tq = np.asarray(t_adc, dtype=np.float64)[g] - t0
    inwin = [(tc - t0, u) for tc, u in zip(rf_c, rf_u) if t0 <= tc <= b * ras]
    rc, ru = [c for c, _ in inwin], [u for _, u in inwin]
    fmask = fine_free_mask(fr)
    R = WJ.impulse_responses(hardware, dt_fine_s, fmask.shape[1])
    k_scale = np.where(np.isfinite(dk) & (dk > 0), 1.0 / np.where(dk > 0, dk, 1.0), 0.0)
    J = WJ.lti_jacobian(
        R, dt_fine_s, fr, fmask, tq, np.zeros(0), rc, ru, np.zeros(fmask.shape[1], dtype=bool), ka, k_scale,
        np.zeros(3), 0.0,
    )  # fmt: skip
    # the out-of-window edges' common running integral enters k with the sign the window's pulses give it
    _, A = WJ.k_coefficients(tq, rc, ru)
    s_q = 1.0 + A.sum(1) if A.size else np.ones(tq.size)
    tail = tail_dk * (1.0 + (np.abs(A).sum(1).max() if A.size else 0.0))
    r0 = ((np.asarray(k_now)[:, g] - np.asarray(k0)[:, g]) * k_scale[:, None])[ka].ravel()  # rows: axis-major
    n_c = ka.size if a > 0 else 0  # the window from the sequence's start: no edge before it, no offset
    Cm = np.zeros((r0.size, n_c))
    for i in range(n_c):
        Cm[i * tq.size : (i + 1) * tq.size, i] = s_q
    cols = np.flatnonzero(fr.ravel())
    col_ax, col_e = cols // width, cols % width
    lo_w, hi_w = P._box(slice(a, b + 1))
    xf = xw[col_ax, col_e]
    lo_d = np.minimum(np.asarray(lo_w)[col_ax, col_e] - xf, 0.0)
    hi_d = np.maximum(np.asarray(hi_w)[col_ax, col_e] - xf, 0.0)
    n0 = max(int(math.floor((float(tq.min()) - NEAR_S) / ras)), 0)
    n1 = min(int(math.ceil((float(tq.max()) + NEAR_S) / ras)), width - 1)
    near = (col_e >= n0) & (col_e <= n1)
    # the far edges of the window, each within its envelope: beyond the common offset (free c) they move each row by
    # at most sum_n |F'_rn| D_n (F' = F less its offset part)
    Fw = J[:, ~near] * np.maximum(-lo_d[~near], hi_d[~near])[None, :]
    if n_c:
        Q, _ = np.linalg.qr(Cm)
        Fw = Fw - Q @ (Q.T @ Fw)
    e_row = np.abs(Fw).sum(1)
    Jn = J[:, near]
    n_x = Jn.shape[1]
    # slew rows between free neighbours both among the variables; a free neighbour outside: a bound in the witness
    col_of = np.full(fr.shape, -1, dtype=np.int64)
    col_of[col_ax[near], col_e[near]] = np.arange(n_x)
    pr = (col_of[:, 1:] >= 0) & (col_of[:, :-1] >= 0) & fr[:, 1:] & fr[:, :-1]
    ax, n = np.nonzero(pr)
    dlo_w = np.broadcast_to(P.dlo, (3, P.free.shape[1] - 1))[:, a:b]
    dhi_w = np.broadcast_to(P.dhi, (3, P.free.shape[1] - 1))[:, a:b]
    step = xw[ax, n + 1] - xw[ax, n]
    m = ax.size
    s_hi, s_lo = np.maximum(dhi_w[ax, n] - step, 0.0), np.minimum(dlo_w[ax, n] - step, 0.0)
    lo_n, hi_n = lo_d[near].copy(), hi_d[near].copy()

    def lp(K: np.ndarray, slack: np.ndarray, lo_v, hi_v, free_extra: int, slew: bool = True, eq=None, keep=None):
        """min t: |r0 + K v| <= t + slack, the first n_x of v within [lo_v, hi_v] and the slew rows, the rest free;
        ``eq``: rows E with E v = 0 on the first n_x; ``keep``: (Jo, ro, cap) rows with |ro + Jo v| <= cap."""
        nv = K.shape[1] + 1
        one = np.ones((r0.size, 1))
        A_ub = sp.csr_matrix(np.vstack([np.hstack([K, -one]), np.hstack([-K, -one])]))
        b_ub = np.r_[slack - r0, slack + r0]
        if slew and m:
            D = sp.csr_matrix(
                (np.r_[np.ones(m), -np.ones(m)], (np.r_[np.arange(m), np.arange(m)], np.r_[col_of[ax, n + 1], col_of[ax, n]])),
                shape=(m, nv),
            )  # fmt: skip
            A_ub, b_ub = sp.vstack([A_ub, D, -D]).tocsr(), np.r_[b_ub, s_hi, -s_lo]
        if keep is not None and keep[0].size:
            Jo = np.hstack([keep[0], np.zeros((keep[0].shape[0], nv - keep[0].shape[1]))])
            A_ub = sp.vstack([A_ub, sp.csr_matrix(Jo), sp.csr_matrix(-Jo)]).tocsr()
            b_ub = np.r_[b_ub, keep[2] - keep[1], keep[2] + keep[1]]
        c_obj = np.zeros(nv)
        c_obj[-1] = 1.0
        bounds = np.column_stack(
            [np.r_[lo_v, np.full(free_extra, -np.inf), 0.0], np.r_[hi_v, np.full(free_extra, np.inf), np.inf]]
        )
        A_eq = None if eq is None else np.hstack([eq, np.zeros((eq.shape[0], nv - eq.shape[1]))])
        b_eq = None if eq is None else np.zeros(eq.shape[0])
        res = linprog(
            c_obj, A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=b_eq, bounds=bounds, method="highs",
            options={"maxiter": LP_MAXITER},
        )  # fmt: skip
        return (float(res.fun) if res.status == 0 else math.nan), res

    Kb = np.hstack([Jn, Cm])
    val, res = lp(Kb, e_row, lo_n, hi_n, n_c)

    def fixed_neighbours(lo_v, hi_v, fixed):
        """``lo_v``/``hi_v`` narrowed by the slew bound to every neighbour in ``fixed`` (3, width) (held at x)."""
        lo_v, hi_v = lo_v.copy(), hi_v.copy()
        ia, ie = col_ax[near], col_e[near]
        for side in (-1, 1):
            e_out = ie + side
            ok = (e_out >= 0) & (e_out < width)
            ok[ok] &= fixed[ia[ok], e_out[ok]]
            j, i_, e, o = np.flatnonzero(ok), ia[ok], ie[ok], e_out[ok]
            seg = np.minimum(e, o)
            d = (xw[i_, e] - xw[i_, o]) * -side  # the step across the segment, forward in time
            # side -1: x[e] - x[o] in [dlo, dhi] -> delta in [dlo - d, dhi - d]; side +1: x[o] - x[e] -> [d - dhi, d - dlo]
            lo_b = np.where(side < 0, dlo_w[i_, seg] - d, d - dhi_w[i_, seg])
            hi_b = np.where(side < 0, dhi_w[i_, seg] - d, d - dlo_w[i_, seg])
            lo_v[j] = np.maximum(lo_v[j], np.minimum(lo_b, 0.0))
            hi_v[j] = np.minimum(hi_v[j], np.maximum(hi_b, 0.0))
        return lo_v, hi_v

    # the witness: every edge outside the variables held at x
    lo_wt, hi_wt = fixed_neighbours(lo_n, hi_n, col_of < 0)
    # ... and the k of every sample after the chain's response to the window unchanged: no net area change per
    # encoded axis (an edge moves its fine taps, 1/2, 1, 1/2, where they follow it; each by the chain's DC gain)
    ia, ie = col_ax[near], col_e[near]
    taps = np.zeros(n_x)
    for off, wt in ((-1, 0.5), (0, 1.0), (1, 0.5)):
        f = 2 * ie + off
        ok = (f >= 0) & (f < fmask.shape[1])
        taps[ok] += wt * fmask[ia[ok], f[ok]]
    dc = R.sum(-1)  # (3 in, 3 out)
    area = np.stack([dc[ia, bb] * taps for bb in ka])
    # ... and every other ADC sample in the window no worse than the stop's largest error (or its own, if larger)
    t_all = np.asarray(t_adc, dtype=np.float64)
    o = np.flatnonzero((t_all >= t0 + n0 * ras) & (t_all <= t0 + n1 * ras))
    o = o[~np.isin(o, g)]
    o = o[:: max(1, -(-o.size // KEEP_MAX))] if KEEP_MAX > 0 else o[:0]  # a subset (the whole is checked after)
    keep = None
    if o.size:
        Jo = WJ.lti_jacobian(
            R, dt_fine_s, fr, fmask, t_all[o] - t0, np.zeros(0), rc, ru, np.zeros(fmask.shape[1], dtype=bool), ka,
            k_scale, np.zeros(3), 0.0,
        )[:, near]  # fmt: skip
        ro = ((np.asarray(k_now)[:, o] - np.asarray(k0)[:, o]) * k_scale[:, None])[ka].ravel()
        keep = (Jo, ro, np.maximum(float(np.max(err)) / math.sqrt(ka.size), np.abs(ro)))
    wv, wres = lp(Jn, np.zeros(r0.size), lo_wt, hi_wt, 0, eq=area, keep=keep)
    witness, change = math.nan, None
    if math.isfinite(wv):
        change = (a + ie, ia, wres.x[:n_x].copy())  # (edge, axis, change), mT/m
        rw = (r0 + Jn @ wres.x[:n_x]).reshape(ka.size, tq.size)
        witness = float(np.sqrt((rw**2).sum(0)).max())
    cert = Certificate(
        samples=np.asarray(g), worst=int(g[np.argmax(err[g])]), error_dk=float(err[g].max()),
        lower_bound_dk=(val - tail - LP_SLACK_DK) if math.isfinite(val) else -math.inf, lp_dk=val, tail_dk=tail,
        window_ms=(1e3 * (a + n0) * ras, 1e3 * (a + n1) * ras), far_remainder_dk=float(e_row.max(initial=0.0)),
        witness_dk=witness, _tol=tol, witness_change=change,
    )  # fmt: skip
    cert.proven = bool(cert.lower_bound_dk > tol)
    if not cert.proven:
        return cert
    # which limit: the constraints active at the optimum (nonzero dual), and the optimum without each kind
    act: dict[str, int] = {}
    if m:
        marg = np.abs(np.asarray(res.ineqlin.marginals)[2 * r0.size :])
        on = (marg[:m] > 1e-12) | (marg[m:] > 1e-12)
        for i in range(3):
            if c := int((on & (ax == i)).sum()):
                act[f"slew {AXES[i]}"] = c
    bm = np.abs(np.asarray(res.lower.marginals)[:n_x]) + np.abs(np.asarray(res.upper.marginals)[:n_x])
    for i in range(3):
        if c := int(((bm > 1e-12) & (col_ax[near] == i)).sum()):
            act[f"amplitude {AXES[i]}"] = c
    cert.active = act
    # without the slew bound: the amplitude limit alone; without the amplitude limit: the slew bounds alone, to the
    # free neighbours (rows) and to the held ones (the envelopes fold both in)
    gm = P.limits.gmax_eff_mT_per_m
    x_n = xw[col_ax[near], col_e[near]]
    big = np.full(n_x, 4 * gm)
    cert.without_slew_dk = lp(Kb, e_row, np.minimum(-gm - x_n, 0.0), np.maximum(gm - x_n, 0.0), n_c, slew=False)[0]
    cert.without_amplitude_dk = lp(Kb, e_row, *fixed_neighbours(-big, big, ~fr), n_c)[0]
    names = [
        k for k, v in (("slew", cert.without_slew_dk), ("amplitude", cert.without_amplitude_dk)) if v - tail <= tol
    ]
    if not names:
        cert.without_limits_dk = lp(Kb, e_row, -big, big, n_c, slew=False)[0]
        names = ["slew and amplitude together"] if cert.without_limits_dk - tail <= tol else ["held edges"]
    cert.binding = " or ".join(names)
    return cert
