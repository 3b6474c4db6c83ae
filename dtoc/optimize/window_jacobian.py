"""The exact Jacobian of a window's residual for a time-invariant affine hardware chain, from impulse responses.

The windowed warm start (:mod:`dtoc.optimize.windowed`) needs, for every excitation-period structure, the
Jacobian of its residual vector (k at the ADC samples, moments before RF pulses, G during RF) with respect
to the free raster-edge samples.  Every chain of :data:`dtoc.hardware.memory.AFFINE_KINDS` is linear and
time-invariant on the fine grid (convolutions, recursions started at rest, delays, gains; offsets cancel),
so the response to a unit change of one fine sample is one impulse response per input axis, shifted:

* ``R[a, b, m]``: realized axis ``b`` for a unit fine sample on demanded axis ``a`` at index ``W`` of a
  ``2 W``-sample zero waveform (``W``: the window's fine length), minus the response to zero (the affine
  offset).  A change at window index ``n`` moves ``G_b[p]`` by ``R[a, b, p - n + W]`` -- exactly what the
  chain gives on the window itself, whose waveform is zero outside its samples (truncation included);
* a raster edge ``j`` moves fine samples ``2j`` (weight 1) and ``2j +- 1`` (weight 1/2) where they follow
  the edges (:meth:`dtoc.optimize.limits.EdgeProjector.fine_free_mask`);
* k at a query time is a fixed combination of running integrals ``I(t) = int_0^t G`` at the query and at
  the RF events before it (:func:`dtoc.seq.kspace.kspace_at`: an excitation resets, a refocusing negates):
  ``k(t) = gamma (I(t) + sum_e A[t, e] I(t_e))``; the running integral of a shifted impulse response is a
  shifted lookup in the exact PWL cumulative integral of ``R`` (:func:`dtoc.seq.kspace.pwl_integral_at`).

Cost: three forwards of ``2 W`` samples and ``O(rows x columns)`` copies, instead of one forward of the
window per column: an edge whose three fine taps all follow it moves the realized waveform by one *hat* response
(``R`` convolved with the taps' weights), so its column is a stride-2 run of the hat's PWL integral, read as one
strided row copy per query (:func:`_shifted_rows`); only the scored output axes are evaluated.  The change penalty's rows (one per free fine sample, two or three non-zeros each) are
not built: :func:`reg_rows` gives the sparse matrix.  Units: mT/m, s, rad/m.
"""

from __future__ import annotations

import numpy as np
import scipy.fft
import scipy.sparse as sp
import torch

from dtoc.constants import GAMMA_RAD_PER_S_PER_MT

#: the RF uses kspace_at acts on (excitation and undefined reset, refocusing negates)
_K_EVENTS = ("excitation", "undefined", "refocusing")


def impulse_responses(hardware, dt_s: float, W: int, dtype=torch.float64, device="cpu") -> np.ndarray:
    """(3, 3, 2W) float64: ``R[a, b]`` realized axis b for a unit fine sample of axis a at index W."""
    x = torch.zeros((4, 3, 2 * W), dtype=dtype, device=device)
    for a in range(3):
        x[a, a, W] = 1.0
    with torch.no_grad():
        G = x if hardware is None else hardware(x, dt_s)[0]
    return (G[:3] - G[3:4]).cpu().double().numpy()


def k_coefficients(t_s: np.ndarray, rf_c: list[float], rf_u: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(event times (E,), A (Q, E)): ``k(t_q) = gamma (I(t_q) + A[q] @ I(t_events))`` as in ``kspace_at``."""
    ev = [(t, u) for t, u in zip(rf_c, rf_u) if u in _K_EVENTS]
    E = len(ev)
    te = np.array([e[0] for e in ev], dtype=np.float64)
    after = np.zeros((E, E))  # row s: k right after event s, as coefficients of I(t_e)
    for s in range(E):
        before = np.zeros(E)
        before[s] = 1.0
        if s > 0:
            before[s - 1] -= 1.0
            before += after[s - 1]
        after[s] = -before if ev[s][1] == "refocusing" else 0.0
    t = np.asarray(t_s, dtype=np.float64)
    A = np.zeros((t.size, E))
    if E:
        seg = np.searchsorted(te, t, side="right") - 1
        on = np.flatnonzero(seg >= 0)
        A[on] = after[seg[on]]
        A[on, seg[on]] -= 1.0
    return te, A


def _edge_taps(fr_a: np.ndarray, fmask_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fine indices (n_a, 3) and weights (n_a, 3) that the free edges of one axis move (0 weight: none)."""
    W = fmask_a.size
    j = np.flatnonzero(fr_a)
    n = 2 * j[:, None] + np.array([-1, 0, 1])[None, :]
    w = np.broadcast_to(np.array([0.5, 1.0, 0.5]), n.shape).copy()
    ok = (n >= 0) & (n < W)
    n = np.clip(n, 0, W - 1)
    w[~(ok & fmask_a[n])] = 0.0
    return n, w


def _integrals(R_a: np.ndarray, C_a: np.ndarray, W: int, dt: float, t_s: np.ndarray, n, w) -> np.ndarray:
    """(3, Q, n_a): ``int_0^t`` of each column's realized change at the query times (window-relative), tap by tap
    (any columns; :func:`_hat_rows` is the fast path for the columns whose three taps all follow their edge)."""
    m, tau = _query_steps(t_s, W, dt)
    tau = tau[None, :, None, None]
    idx = m[:, None, None] + W - n[None]  # (Q, n_a, 3) into the 2W grid
    g0 = R_a[:, idx]
    val = C_a[:, idx] + tau * g0 + 0.5 * tau * tau * (R_a[:, idx + 1] - g0) / dt
    val = val - C_a[:, W - n][:, None]  # integrals counted from the window's start
    return (val * w[None, None]).sum(-1)


def _query_steps(t_s: np.ndarray, W: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(fine step m (Q,), offset tau (Q,) s) of query times clipped to the window: ``t = m dt + tau``."""
    t = np.clip(np.asarray(t_s, dtype=np.float64), 0.0, (W - 1) * dt)
    m = np.clip(np.floor(t / dt + 1e-9).astype(np.int64), 0, max(W - 2, 0))
    return m, t - m * dt


def _hat(X: np.ndarray) -> np.ndarray:
    """``0.5 X[i + 1] + X[i] + 0.5 X[i - 1]`` along the last axis (zero beyond the ends): the response to one raster
    edge whose three fine taps (weights 1/2, 1, 1/2) all follow it, from the response to one fine sample."""
    out = X.copy()
    out[..., 1:] += 0.5 * X[..., :-1]
    out[..., :-1] += 0.5 * X[..., 1:]
    return out


def _shifted_rows(X: np.ndarray, i0: np.ndarray, j: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(Q, len(j)) ``X[i0[q] - 2 j]`` (into ``out`` if given): per query a reversed stride-2 run of ``X``, read as
    one strided row copy per query (no element gather); ``j`` ascending, every index within ``X``."""
    if not (i0.size and j.size):
        return np.empty((i0.size, j.size)) if out is None else out
    if out is None:
        return _shifted_rows(X, i0, j, np.empty((i0.size, j.size)))
    j0, j1 = int(j[0]), int(j[-1]) + 1
    Xr = np.ascontiguousarray(X[::-1])  # Xr[L - 1 - i] = X[i]
    s = Xr.strides[0]
    n_rows = Xr.size - 2 * (j1 - j0 - 1)
    V = np.lib.stride_tricks.as_strided(Xr, (n_rows, j1 - j0), (s, 2 * s), writeable=False)
    start = Xr.size - 1 - i0 + 2 * j0  # V[start, j - j0] = Xr[start + 2 (j - j0)] = X[i0 - 2 j]
    if j1 - j0 == j.size:
        out[:] = V[start]
        return out
    # edges in runs with gaps between (a long window: a spoiler and a readout 100,000 edges apart): run by run, never
    # the gaps (``V[start][:, j - j0]`` held queries x (j1 - j0): 1.8 GB on a 4.9 min MPRAGE's longest window)
    cut = np.flatnonzero(np.diff(j) != 1) + 1
    for s0, s1 in zip(np.r_[0, cut].tolist(), np.r_[cut, j.size].tolist()):
        out[:, s0:s1] = V[start, int(j[s0]) - j0 : int(j[s1 - 1]) + 1 - j0]
    return out


def _hat_rows(Ch, Rh, W: int, dt: float, t_s: np.ndarray, j: np.ndarray) -> np.ndarray:
    """(Q, len(j)) ``int_0^t`` at the query times of one realized axis' change for a unit change of the raster
    edges ``j`` (all three taps following them): :func:`_integrals` on the hat responses ``Ch`` (integral) and ``Rh``
    (:func:`_hat`), the exact PWL integral ``C[i] + tau R[i] + tau^2 / (2 dt) (R[i + 1] - R[i])``, ``i = m + W - 2j``,
    minus its value at the window's start."""
    m, tau = _query_steps(t_s, W, dt)
    i0 = m + W
    b = 0.5 * tau * tau / dt
    val = _shifted_rows(Ch, i0, j)
    tmp = _shifted_rows(Rh, i0, j)
    tmp *= (tau - b)[:, None]
    val += tmp
    _shifted_rows(Rh, i0 + 1, j, out=tmp)
    tmp *= b[:, None]
    val += tmp
    val -= Ch[W - 2 * j][None, :]
    return val


def lti_jacobian(
    R: np.ndarray,
    dt_s: float,
    fr: np.ndarray,
    fmask: np.ndarray,
    t_adc: np.ndarray,
    t_mom: np.ndarray,
    rf_c: list[float],
    rf_u: list[str],
    rfm: np.ndarray,
    k_axes: np.ndarray,
    k_scale: np.ndarray,
    m_scale: np.ndarray,
    rf_scale: float,
) -> np.ndarray:
    """Rows of the window's residual other than the change penalty, as :func:`windowed.window_residual` orders
    them (k: k-axes x ADC samples; moments: k-axes x pulses; G during RF: 3 x RF samples), by free edge.

    A column whose edge moves all three of its fine taps is one shifted copy of the hat response per (input,
    output) axis pair: its rows are read as strided runs of the hat's integral (:func:`_hat_rows`); the few
    columns at the ends of a free run (a tap held) go tap by tap (:func:`_integrals`).  Only the scored output
    axes are evaluated.  Cost ~ rows x columns copies, no (rows x columns x taps) gathers.

    Args:
        R: (3, 3, 2W) :func:`impulse_responses`.  dt_s: fine spacing, s.
        fr: (3, Ne) free edges; fmask: (3, W) fine samples that follow the edges.
        t_adc, t_mom: window-relative query times, s.  rf_c, rf_u: window-relative RF centres and uses.
        rfm: (W,) fine samples under the RF pulses whose G-during-RF counts.
        k_axes: axes scored in k; k_scale, m_scale: (3,) row weights (1/dk and term weights), ``k_scale`` also
            (3, len(t_adc)) per row; rf_scale.
    Returns:
        (rows, n_free) float64, columns in ``np.flatnonzero(fr.ravel())`` order.
    """
    W = fmask.shape[1]
    C = np.concatenate([np.zeros(R.shape[:2] + (1,)), np.cumsum(0.5 * dt_s * (R[..., 1:] + R[..., :-1]), -1)], -1)
    Rh, Ch = _hat(R), _hat(C)
    te, A_adc = k_coefficients(t_adc, rf_c, rf_u)
    _, A_mom = k_coefficients(t_mom, rf_c, rf_u)
    ka = np.asarray(k_axes, dtype=np.int64)
    p_rf = np.flatnonzero(rfm)
    k_terms = [(np.asarray(tq), A, np.asarray(sc)) for tq, A, sc in ((t_adc, A_adc, k_scale), (t_mom, A_mom, m_scale))]
    n_rows = sum(ka.size * tq.size for tq, _, _ in k_terms) + 3 * p_rf.size
    J = np.empty((n_rows, int(fr.sum())))
    c0 = 0
    full = np.array([0.5, 1.0, 0.5])
    for a in range(3):
        n, w = _edge_taps(fr[a], fmask[a])
        if n.shape[0] == 0:
            continue
        cols = slice(c0, c0 + n.shape[0])
        c0 += n.shape[0]
        j = np.flatnonzero(fr[a])
        hat = (w == full).all(1)
        tap = np.flatnonzero(~hat)

        def integrals(tq, b, a=a, n=n, w=w, j=j, hat=hat, tap=tap):
            if not tap.size:
                return _hat_rows(Ch[a, b], Rh[a, b], W, dt_s, tq, j)
            out = np.empty((tq.size, j.size))
            out[:, hat] = _hat_rows(Ch[a, b], Rh[a, b], W, dt_s, tq, j[hat])
            out[:, tap] = _integrals(R[a, b : b + 1], C[a, b : b + 1], W, dt_s, tq, n[tap], w[tap])[0]
            return out

        r0 = 0
        I_ev = {int(b): integrals(te, b) for b in ka} if te.size else {}
        for tq, A, sc_ in k_terms:
            for b in ka:
                out = integrals(tq, b)
                if te.size:
                    out += A @ I_ev[int(b)]
                out *= GAMMA_RAD_PER_S_PER_MT * (sc_[b][:, None] if sc_.ndim == 2 else sc_[b])
                J[r0 : r0 + tq.size, cols] = out
                r0 += tq.size
        for b in range(3) if p_rf.size else ():
            out = np.empty((p_rf.size, j.size))
            out[:, hat] = _shifted_rows(Rh[a, b], p_rf + W, j[hat])
            if tap.size:
                idx = p_rf[:, None, None] - n[tap][None] + W  # (P, n_tap, 3)
                out[:, tap] = (R[a, b][idx] * w[tap][None]).sum(-1)
            J[r0 : r0 + p_rf.size, cols] = rf_scale * out
            r0 += p_rf.size
    return J


def reg_rows(fr: np.ndarray, fmask: np.ndarray, scale: float) -> sp.csr_matrix:
    """The change penalty's rows ``scale * (g - g0)[fmask]`` (row-major over (axis, fine sample)) as a
    sparse (fmask.sum(), n_free) matrix of the free edges."""
    W = fmask.shape[1]
    row_of = np.full(fmask.size, -1, dtype=np.int64)
    row_of[np.flatnonzero(fmask.ravel())] = np.arange(int(fmask.sum()))
    rows, cols, vals = [], [], []
    c0 = 0
    for a in range(3):
        n, w = _edge_taps(fr[a], fmask[a])
        cc = c0 + np.broadcast_to(np.arange(n.shape[0])[:, None], n.shape)
        keep = w > 0
        rows.append(row_of[a * W + n[keep]])
        cols.append(cc[keep])
        vals.append(scale * w[keep])
        c0 += n.shape[0]
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(int(fmask.sum()), c0)
    )


#: effect kinds whose response to a waveform that is zero outside its samples is one impulse response, shifted (zero-
#: padded convolutions, zero-filled delays, gains: no affine offset, no wrap-around, no start-up at the record's first
#: sample as the eddy currents' recursions have): :class:`RangeRealizer` may replace a chain of them that has one effect
#: with memory (two would not do: the chain cuts the first one's output at the window's edges, which the second then
#: delays into the window -- one shifted response of the whole chain differs there)
_SHIFT_INVARIANT_KINDS = frozenset({"girf", "lti", "delay", "gain"})
#: taps of the impulse response below this share of its largest are the FFT's round-off beyond the kernel's extent
SUPPORT_REL = 1e-15


class RangeRealizer:
    """The realized gradient of a window on a range of its fine samples only, for a linear, shift-invariant chain.

    ``G[b, p] = sum_a sum_n g[a, n] R[a, b, p - n]`` (the chain on the window, whose waveform is zero outside its
    samples, :func:`impulse_responses`); the impulse response's support ``[l_min, l_max]`` (taps above
    :data:`SUPPORT_REL` of its largest) is measured once.  The outputs ``[n_lo, n_hi)`` need the inputs
    ``[n_lo - l_max, n_hi - l_min)``: one circular (overlap-save) FFT convolution of at least ``M + L - 1`` samples
    (``M`` outputs, ``L`` taps; a 5-smooth length) instead of the chain's linear one over the whole window (a power
    of two of at least ``T + L - 1``).
    Same figures as the chain up to the FFTs' round-off and the dropped taps (below :data:`SUPPORT_REL`).
    """

    def __init__(self, R: np.ndarray, W: int, dtype=torch.float64, device="cpu"):
        m = np.abs(R).max(axis=(0, 1))
        nz = np.flatnonzero(m > SUPPORT_REL * max(float(m.max()), 1e-300))
        lo, hi = (int(nz[0]), int(nz[-1])) if nz.size else (W, W)
        self.l_min, self.l_max = lo - W, hi - W
        self.taps = torch.as_tensor(np.ascontiguousarray(R[:, :, lo : hi + 1]), dtype=dtype, device=device)
        self._spec: dict[int, torch.Tensor] = {}

    @classmethod
    def for_chain(cls, hardware, dt_s: float, W: int, dtype=torch.float64, device="cpu") -> RangeRealizer | None:
        """The realizer of ``hardware`` for windows of at most ``W`` fine samples, or None where the chain is not one
        effect of :data:`_SHIFT_INVARIANT_KINDS` with memory and gains (ideal hardware included: nothing to gain) or its
        response is not shorter than ``W`` (no saving)."""
        inner = getattr(hardware, "hardware", None) if hasattr(hardware, "R") else hardware  # a RotatedChain's model
        kinds = [getattr(e, "kind", None) for e in getattr(inner, "effects", None) or [None]]
        if hardware is None or not set(kinds) <= _SHIFT_INVARIANT_KINDS or len(kinds) - kinds.count("gain") != 1:
            return None
        r = cls(impulse_responses(hardware, dt_s, W, dtype, device), W, dtype, device)
        return r if r.n_taps < W else None

    @property
    def n_taps(self) -> int:
        return int(self.taps.shape[-1])

    def __call__(self, g: torch.Tensor, n_lo: int, n_hi: int) -> torch.Tensor:
        """(B, 3, n_hi - n_lo) the realized gradient on the fine samples ``[n_lo, n_hi)`` of ``g`` (B, 3, T)."""
        M, L, T = n_hi - n_lo, self.n_taps, g.shape[-1]
        N = scipy.fft.next_fast_len(M + L - 1, real=True)
        spec = self._spec.get(N)
        if spec is None:
            spec = self._spec[N] = torch.fft.rfft(self.taps, n=N)  # (a, b, F)
        n_a = n_lo - self.l_max  # the input sample that meets tap l_max at output n_lo
        a0, a1 = max(n_a, 0), min(n_a + M + L - 1, T)
        x = torch.zeros(g.shape[:-1] + (N,), dtype=g.dtype, device=g.device)
        if a1 > a0:
            x[..., a0 - n_a : a1 - n_a] = g[..., a0:a1]
        Y = (torch.fft.rfft(x).unsqueeze(-2) * spec).sum(-3)  # (B, a, 1, F) * (a, b, F) summed over a
        return torch.fft.irfft(Y, n=N)[..., L - 1 : L - 1 + M]
