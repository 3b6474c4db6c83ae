"""Exact integration of piecewise-linear (PWL) gradient waveforms and k-space at arbitrary times.

Every waveform in dtoc is a set of samples ``g[..., m]`` at ``t_m = m * dt`` (s) joined by straight
lines, which is exactly how a Pulseq interpreter plays trapezoids, extended trapezoids and arbitrary
gradients when ``dt`` is half the gradient raster (see docs/conventions.md).  The functions here
integrate such a waveform exactly (no quadrature error) and are differentiable in torch.

k-space convention (rad/m): ``k(t) = GAMMA_RAD_PER_S_PER_MT * integral G [mT/m] dt [s]`` counted from
the centre of the last excitation pulse; a refocusing pulse negates k (as pypulseq's
``calculate_kspace``); other pulses leave it unchanged.  Before the first excitation, k counts from t=0.
"""

from __future__ import annotations

from collections.abc import Sequence as _Seq

import numpy as np
import torch

from dtoc.constants import GAMMA_RAD_PER_S_PER_MT


def _as_tensor(g) -> torch.Tensor:
    if isinstance(g, torch.Tensor):
        return g
    return torch.as_tensor(np.asarray(g, dtype=np.float64))


def pwl_cumulative(g, dt: float) -> torch.Tensor:
    """Running integral of a PWL waveform at its own sample times.

    Args:
        g: (..., M) samples at t_m = m*dt.
        dt: sample spacing, s.
    Returns:
        (..., M) tensor C with C[..., m] = integral_0^{t_m} g dt (units of g times s).
    """
    g = _as_tensor(g)
    inc = 0.5 * dt * (g[..., 1:] + g[..., :-1])
    zero = torch.zeros(g.shape[:-1] + (1,), dtype=g.dtype, device=g.device)
    return torch.cat([zero, inc.cumsum_(dim=-1)], dim=-1)  # in place: one whole-length temporary fewer


#: a waveform longer than this many samples (and not part of an autograd graph) is integrated in chunks of it:
#: the running integral is never held whole (same numbers bit for bit: each chunk's cumulative sum starts from
#: the last one's end, added to its first increment, the order a whole cumulative sum adds in)
CUMULATIVE_CHUNK = 1 << 20


def _chunked(g: torch.Tensor) -> bool:
    return g.shape[-1] > CUMULATIVE_CHUNK + 1 and not g.requires_grad


def cumulative_at(g, dt: float, m: np.ndarray) -> torch.Tensor:
    """``pwl_cumulative(g, dt)[..., m]`` without the whole running integral when ``g`` is long and needs no
    gradient (:data:`CUMULATIVE_CHUNK`): (..., len(m)), the same numbers bit for bit."""
    g = _as_tensor(g)
    m = np.asarray(m, dtype=np.int64)
    if not _chunked(g):
        return pwl_cumulative(g, dt)[..., torch.as_tensor(m, device=g.device)]
    out = torch.zeros(g.shape[:-1] + (len(m),), dtype=g.dtype, device=g.device)
    order = np.argsort(m, kind="stable")
    ms = m[order]
    carry = torch.zeros(g.shape[:-1], dtype=g.dtype, device=g.device)
    M = g.shape[-1]
    for s in range(0, M - 1, CUMULATIVE_CHUNK):
        e = min(s + CUMULATIVE_CHUNK, M - 1)  # increments s..e-1: C[s + 1 .. e]
        inc = 0.5 * dt * (g[..., s + 1 : e + 1] + g[..., s:e])
        inc[..., 0] += carry
        inc.cumsum_(dim=-1)
        a, b = np.searchsorted(ms, [s + 1, e + 1])
        if b > a:
            sel = torch.as_tensor(ms[a:b] - (s + 1), device=g.device)
            out[..., torch.as_tensor(order[a:b], device=g.device)] = inc[..., sel]
        carry = inc[..., -1].clone()
    return out


class _Query:
    """Where query times fall on a PWL waveform of ``M`` samples spaced ``dt``: each time's interval ``m`` (numpy,
    clamped to the waveform) and its offset ``tau`` into it (s), with their tensors made once per device and dtype
    (a repeated query moves nothing from the host)."""

    def __init__(self, M: int, dt: float, t_s):
        t = np.clip(np.asarray(t_s, dtype=np.float64), 0.0, (M - 1) * dt)
        self.M, self.dt = M, dt
        self.m = np.clip(np.floor(t / dt + 1e-9).astype(np.int64), 0, max(M - 2, 0))
        self.tau = t - self.m * dt
        self._on: dict = {}

    def tensors(self, dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(tau, m, m + 1) on ``device`` (m + 1 = m for a one-sample waveform); tau in ``dtype``."""
        key = (dtype, str(device))
        if key not in self._on:
            mi = torch.as_tensor(self.m, device=device)
            self._on[key] = (torch.as_tensor(self.tau, dtype=dtype, device=device), mi, mi + 1 if self.M > 1 else mi)
        return self._on[key]

    def starts(self, C: torch.Tensor) -> torch.Tensor:
        """(..., Q) the running integral ``C`` (..., M) (:func:`pwl_cumulative`) at the query intervals' starts."""
        return C[..., self.tensors(C.dtype, C.device)[1]]

    def integral(self, g: torch.Tensor, Cm: torch.Tensor) -> torch.Tensor:
        """(..., Q) integrals of ``g`` (..., M) to the query times; ``Cm``: the running integral at the intervals'
        starts (:meth:`starts`, or :func:`cumulative_at` for a long waveform)."""
        tau, mi, mi1 = self.tensors(g.dtype, g.device)
        g0, g1 = g[..., mi], g[..., mi1]
        return Cm + tau * g0 + 0.5 * tau * tau * (g1 - g0) / self.dt


def pwl_integral_at(g, dt: float, t_s, cumulative: torch.Tensor | None = None) -> torch.Tensor:
    """Exact integral_0^t of a PWL waveform at arbitrary query times.

    Args:
        g: (..., M) samples at t_m = m*dt.
        dt: sample spacing, s.
        t_s: (Q,) query times, s, within [0, (M-1)*dt] (clamped outside).
        cumulative: optional precomputed :func:`pwl_cumulative` of ``g``.
    Returns:
        (..., Q) integrals (units of g times s), differentiable w.r.t. ``g``.
    """
    g = _as_tensor(g)
    q = _Query(g.shape[-1], dt, t_s)
    if cumulative is None and _chunked(g):  # a long waveform without a graph: its running integral by chunks
        return q.integral(g, cumulative_at(g, dt, q.m))
    return q.integral(g, q.starts(pwl_cumulative(g, dt) if cumulative is None else cumulative))


def kspace_at(g_mT_per_m, dt: float, t_s, rf_centres_s: _Seq[float] = (), rf_uses: _Seq[str] = ()) -> torch.Tensor:
    """k-space (rad/m) of a PWL gradient at query times, with excitation resets and refocusing.

    Args:
        g_mT_per_m: (..., 3, M) gradient samples at t_m = m*dt, mT/m.
        dt: sample spacing, s.
        t_s: (Q,) query times, s.
        rf_centres_s: times of the RF pulse centres (instantaneous rotations), s, ascending.
        rf_uses: Pulseq ``use`` of each pulse: 'excitation' and 'undefined' reset k to 0 (as pypulseq and
            Pulseq do), 'refocusing' negates it, others are ignored.
    Returns:
        (..., 3, Q) k in rad/m, differentiable w.r.t. the gradient.
    """
    g = _as_tensor(g_mT_per_m)
    t = np.asarray(t_s, dtype=np.float64)
    events = _k_events(rf_centres_s, rf_uses)
    t_rf = np.array([e[0] for e in events], dtype=np.float64)
    if _chunked(g):  # long and without a graph: one pass of its running integral by chunks for both sets of times
        both = pwl_integral_at(g, dt, np.concatenate([t, t_rf]))
        integ, i_rf = both[..., : len(t)], (both[..., len(t) :] if events else None)
        return kspace_from_integrals(integ, i_rf, t, rf_centres_s, rf_uses)
    return KspacePlan(g.shape[-1], dt, t, rf_centres_s, rf_uses)(g)


class KspacePlan:
    """:func:`kspace_at` for fixed query times and RF events on waveforms of ``M`` samples spaced ``dt``: the index
    arithmetic done once on the host and its tensors made once per device and dtype, so that a call runs torch
    operations alone (no host data moves, nothing waits for the device: a CUDA graph can hold it).  The same
    numbers as :func:`kspace_at` bit for bit (which uses it); a long waveform without a graph is integrated by
    chunks as there."""

    def __init__(self, M: int, dt: float, t_s, rf_centres_s: _Seq[float] = (), rf_uses: _Seq[str] = ()):
        self.M, self.dt = M, dt
        self.t = np.asarray(t_s, dtype=np.float64)
        self.rf_centres_s, self.rf_uses = list(rf_centres_s), list(rf_uses)
        events = _k_events(rf_centres_s, rf_uses)
        self.q = _Query(M, dt, self.t)
        self.q_rf = _Query(M, dt, np.array([e[0] for e in events], dtype=np.float64)) if events else None
        self.resets = _Resets(self.t, events)

    def __call__(self, g) -> torch.Tensor:
        """(..., 3, Q) k in rad/m of ``g`` (..., 3, M) mT/m, differentiable."""
        g = _as_tensor(g)
        if g.shape[-1] != self.M:
            raise ValueError(f"KspacePlan of {self.M} samples applied to a waveform of {g.shape[-1]}")
        if _chunked(g):
            return kspace_at(g, self.dt, self.t, self.rf_centres_s, self.rf_uses)
        C = pwl_cumulative(g, self.dt)
        integ = self.q.integral(g, self.q.starts(C))  # (..., 3, Q)
        i_rf = None if self.q_rf is None else self.q_rf.integral(g, self.q_rf.starts(C))
        return self.resets.apply(integ, i_rf)


def _k_events(rf_centres_s, rf_uses) -> list:
    # 'undefined' excites, as in pypulseq's calculate_kspace and Pulseq's calcKspace
    return [(tc, u) for tc, u in zip(rf_centres_s, rf_uses) if u in ("excitation", "undefined", "refocusing")]


def kspace_from_integrals(
    integ: torch.Tensor, i_rf: torch.Tensor | None, t_s, rf_centres_s: _Seq[float] = (), rf_uses: _Seq[str] = ()
) -> torch.Tensor:
    """:func:`kspace_at` from the integrals it needs: ``integ`` (..., 3, Q) of the gradient from 0 to each query
    time ``t_s`` and ``i_rf`` (..., 3, E) to each RF event that resets or negates k (excitation, undefined,
    refocusing, in the order given; None when there is none)."""
    return _Resets(np.asarray(t_s, dtype=np.float64), _k_events(rf_centres_s, rf_uses)).apply(integ, i_rf)


class _Resets:
    """The RF events' action on k at fixed query times ``t`` (s): which event each time follows (index tensors made
    once per device)."""

    def __init__(self, t: np.ndarray, events: list):
        self.events = events
        self._on: dict = {}
        if events:
            tc = np.array([e[0] for e in events], dtype=np.float64)
            seg = np.searchsorted(tc, t, side="right") - 1  # -1: before first event
            after = seg >= 0
            self.idx, self.sj = np.where(after)[0], seg[after]

    def apply(self, integ: torch.Tensor, i_rf: torch.Tensor | None) -> torch.Tensor:
        events = self.events
        if not events:
            return GAMMA_RAD_PER_S_PER_MT * integ
        assert i_rf is not None
        # k right after event j: k_j; k(t) = gamma*(I(t) - I(t_j)) + k_j for t in [t_j, t_{j+1}).
        if all(u != "refocusing" for _, u in events):
            k_after_t = torch.zeros_like(i_rf)  # every event excites: k restarts at 0 (no loop over the events)
        else:
            k_after = []
            k_prev = None  # k just before the current event
            for j, (_, use) in enumerate(events):
                if j == 0:
                    k_before = GAMMA_RAD_PER_S_PER_MT * i_rf[..., 0]
                else:
                    k_before = GAMMA_RAD_PER_S_PER_MT * (i_rf[..., j] - i_rf[..., j - 1]) + k_prev
                k_prev = -k_before if use == "refocusing" else torch.zeros_like(k_before)
                k_after.append(k_prev)
            k_after_t = torch.stack(k_after, dim=-1)  # (..., 3, E)
        out = GAMMA_RAD_PER_S_PER_MT * integ
        if self.idx.size:
            key = str(integ.device)
            if key not in self._on:
                self._on[key] = (
                    torch.as_tensor(self.idx, device=integ.device),
                    torch.as_tensor(self.sj, device=integ.device),
                )
            idx, sj = self._on[key]
            val = GAMMA_RAD_PER_S_PER_MT * (integ[..., idx] - i_rf[..., sj]) + k_after_t[..., sj]
            out = out.index_copy(-1, idx, val)
        return out


def kspace_at_streamed(chunks, n: int, dt: float, t_s, rf_centres_s: _Seq[float] = (), rf_uses: _Seq[str] = ()):
    """:func:`kspace_at` of a waveform of ``n`` samples given piece by piece, never whole: ``chunks`` yields
    ``(s, w)`` in time order, ``w`` (..., 3, L) its samples ``s .. s + L - 1``, each piece starting on the last
    sample of the one before (``s`` = 0 first, the last ending at sample ``n - 1``).  Same formulas; a waveform in
    one piece gives the numbers of :func:`kspace_at` bit for bit."""
    t = np.asarray(t_s, dtype=np.float64)
    events = _k_events(rf_centres_s, rf_uses)
    tq = np.concatenate([t, np.array([e[0] for e in events], dtype=np.float64)])
    tq = np.clip(tq, 0.0, (n - 1) * dt)
    m = np.clip(np.floor(tq / dt + 1e-9).astype(np.int64), 0, max(n - 2, 0))
    order = np.argsort(m, kind="stable")
    ms = m[order]
    out: torch.Tensor | None = None
    carry = torch.zeros(())
    for s, w in chunks:
        if out is None:
            out = torch.zeros(w.shape[:-1] + (len(tq),), dtype=w.dtype, device=w.device)
            carry = torch.zeros(w.shape[:-1], dtype=w.dtype, device=w.device)
        L = w.shape[-1]
        inc = 0.5 * dt * (w[..., 1:] + w[..., :-1])
        inc[..., 0] += carry
        C = torch.cat([carry[..., None], inc.cumsum_(dim=-1)], dim=-1)  # C[s .. s + L - 1]
        a, b = np.searchsorted(ms, [s, s + L - 1])  # queries whose interval [m, m + 1] lies in this piece
        if b > a:
            q = order[a:b]
            mi = torch.as_tensor(ms[a:b] - s, device=w.device)
            tau = torch.as_tensor(tq[q] - ms[a:b] * dt, dtype=w.dtype, device=w.device)
            g0, g1 = w[..., mi], w[..., mi + 1]
            out[..., torch.as_tensor(q, device=w.device)] = C[..., mi] + tau * g0 + 0.5 * tau * tau * (g1 - g0) / dt
        carry = C[..., -1].clone()
    assert out is not None
    nq = len(t)
    return kspace_from_integrals(out[..., :nq], out[..., nq:] if events else None, t, rf_centres_s, rf_uses)
