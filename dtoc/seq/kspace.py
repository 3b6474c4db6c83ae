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
    M = g.shape[-1]
    C = pwl_cumulative(g, dt) if cumulative is None else cumulative
    t = np.clip(np.asarray(t_s, dtype=np.float64), 0.0, (M - 1) * dt)
    m = np.clip(np.floor(t / dt + 1e-9).astype(np.int64), 0, max(M - 2, 0))
    tau = torch.as_tensor(t - m * dt, dtype=g.dtype, device=g.device)
    mi = torch.as_tensor(m, device=g.device)
    g0 = g[..., mi]
    g1 = g[..., mi + 1] if M > 1 else g0
    return C[..., mi] + tau * g0 + 0.5 * tau * tau * (g1 - g0) / dt


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
    C = pwl_cumulative(g, dt)
    integ = pwl_integral_at(g, dt, t, cumulative=C)  # (..., 3, Q)
    # 'undefined' excites, as in pypulseq's calculate_kspace and Pulseq's calcKspace
    events = [(tc, u) for tc, u in zip(rf_centres_s, rf_uses) if u in ("excitation", "undefined", "refocusing")]
    if not events:
        return GAMMA_RAD_PER_S_PER_MT * integ
    tc = np.array([e[0] for e in events], dtype=np.float64)
    i_rf = pwl_integral_at(g, dt, tc, cumulative=C)  # (..., 3, E)
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
    seg = np.searchsorted(tc, t, side="right") - 1  # -1: before first event
    out = GAMMA_RAD_PER_S_PER_MT * integ
    after = seg >= 0
    if after.any():
        idx = torch.as_tensor(np.where(after)[0], device=g.device)
        sj = torch.as_tensor(seg[after], device=g.device)
        val = GAMMA_RAD_PER_S_PER_MT * (integ[..., idx] - i_rf[..., sj]) + k_after_t[..., sj]
        out = out.index_copy(-1, idx, val)
    return out
