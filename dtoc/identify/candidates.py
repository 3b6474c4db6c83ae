"""The library of candidate effects and their linearised, cross-validated screening.

Every candidate is an effect appended to the current model (declared chain + effects found so far), acting
on that model's output P (realized gradient, mT/m); the eddy-current kinds are driven by the slew of the
demanded waveform g (docs/contracts.md §3) and add their field to P; ``slew_limit`` acts on the demanded input.
Screening fits the candidate's parameters to the current residual in the cheapest exact or linearised form
and scores it on held-out units (:func:`dtoc.identify.workspace.cross_validate`):

| kind | change of the prediction | screening |
|---|---|---|
| ``delay`` {seconds} | P(t - tau) - P(t) (PWL shift), one axis or all | grid of exact shifts around the linearised estimate |
| ``delay_bandlimited`` {seconds} | the same with a Fourier shift (smooth data) | as delay |
| ``gain`` {factor} | (factor - 1) * P_a | linear |
| ``offset`` {mT_per_m} | constant on axis a | linear |
| ``exp_eddy`` {alpha, tau_s} | -alpha * (dg_a/dt conv exp(-t/tau)) | linear in alpha on a log grid of tau, refined |
| ``cross_eddy`` {alpha, tau_s} | -alpha * (dg_i/dt conv exp(-t/tau)) on axis o | as exp_eddy |
| ``b0_eddy`` {alpha_uT_per_mT_per_m, tau_s} | B0 -= alpha * (dg_i/dt conv exp(-t/tau)) | as exp_eddy (needs measured b0) |
| ``lti`` {taps} | sum_j c_j P_a(t - (j + j0) dt) (FIR correction) | linear in the taps |
| ``slew_limit`` {max_slew_T_per_m_per_s}, all axes or one | model(limit(g)) - model(g) | grid of limits |
| ``time_base`` {ppm} (measurement clock) | P(t (1 + ppm 1e-6)) - P(t) | grid of exact values around the linearised estimate |
| ``resonance`` {f0_hz, q, amplitude, phase_rad} | A Re(e^{i phase} dg_a/dt conv e^{pt}) | f0 grid (10 %, then 1 %) x q grid, A cos / A sin linear |

The score is a held-out information criterion: the decrease of the cross-validated chi-square (each fold
fitted on the others) minus ``n_params * ln(n)`` (BIC penalty, n = measured samples).  Positive scores mean
the data support the effect; the search adds one only when the score exceeds a threshold (default 10,
"very strong" evidence on the Kass-Raftery scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dtoc.constants import AXES
from dtoc.identify.kinds import CANDIDATE_KINDS, effect_name
from dtoc.identify.workspace import Workspace, cross_validate


@dataclass
class Proposal:
    """A screened candidate: initial parameters and its held-out score."""

    kind: str
    axis: str | None
    input_axis: str | None
    params: dict
    n_params: int
    cv_chi2: float
    full_chi2: float
    score: float
    position: str = "post"  # "post": after the current chain; "pre": on the demanded input
    notes: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return effect_name(self)


@dataclass
class Context:
    """What candidates need besides the residual: the demanded input, the current output, the chain."""

    dt_s: float
    g: np.ndarray  # (M, 3, N) demanded, mT/m
    P: np.ndarray  # (M, 3, N) current prediction of the realized gradient, mT/m
    P_b0: np.ndarray | None = None  # (M, N) current prediction of B0, uT
    chain: object = None  # callable(g (M,3,N) ndarray) -> Prediction, the current full model
    slew_limit: object = None  # callable(g ndarray, max_slew) -> limited g ndarray
    shift: object = None  # callable(x (..., N) ndarray, tau_s) -> x(t - tau)
    cache: dict = field(default_factory=dict)  # per-round cache of exp columns on the coarse tau grid


def pwl_shift(x: np.ndarray, tau_s: float, dt_s: float) -> np.ndarray:
    """x(t - tau) at the sample times of a piecewise-linear waveform that is zero outside its samples
    (the convention of :class:`dtoc.hardware.effects.Delay`): linear interpolation, either sign of tau.

    Args:
        x: (..., N) samples.
        tau_s: delay, s (positive = late).
    """
    s = tau_s / dt_s
    i = math.floor(s)
    f = s - i
    N = x.shape[-1]

    def take(shift):  # out[n] = x[n - shift], zero-filled
        out = np.zeros_like(x)
        if 0 <= shift < N:
            out[..., shift:] = x[..., : N - shift]
        elif -N < shift < 0:
            out[..., : N + shift] = x[..., -shift:]
        return out

    return (1.0 - f) * take(i) + f * take(i + 1) if f > 0 else take(i)


def exp_columns(P_src: np.ndarray, dt_s: float, taus_s: np.ndarray) -> np.ndarray:
    """E_tau[P] = dP/dt conv H(t) exp(-t/tau) (exact for PWL P, zero before t = 0) for several tau.

    The same exact recursion as :func:`dtoc.hardware.recursion.exp_response` (e[0] = P[0];
    e[n+1] = a e[n] + b (P[n+1] - P[n]), a = exp(-dt/tau), b = (tau/dt)(1 - a)), evaluated as an IIR filter
    (:func:`pole_filter`) for speed; tests check the two agree.

    Args:
        P_src: (..., N) source waveform(s).
        taus_s: (K,) time constants, s.
    Returns:
        (K, ..., N) responses, in the unit of P.
    """
    P = np.asarray(P_src, dtype=np.float64)
    out = np.empty((len(taus_s),) + P.shape)
    for i, tau in enumerate(np.asarray(taus_s, dtype=np.float64)):
        out[i] = pole_filter(P, -dt_s / tau)
    return out


def pole_filter(x: np.ndarray, z: complex | float) -> np.ndarray:
    """The exact PWL recursion of :mod:`dtoc.hardware.recursion` (``r[0] = x[0]``,
    ``r[n+1] = a r[n] + b (x[n+1] - x[n])``, ``a = exp(z)``, ``b = (a - 1)/z``, ``z = p dt``) as an IIR filter
    (scipy.signal.lfilter) along the last axis; real for a real ``z`` (an exponential), complex otherwise."""
    from scipy.signal import lfilter

    if isinstance(z, complex):
        a, bb = np.exp(z), np.expm1(z) / z
    else:
        a, bb = math.exp(z), math.expm1(z) / z
    u = np.concatenate([x[..., :1].astype(type(a)), bb * np.diff(x, axis=-1)], axis=-1)
    return lfilter([1.0], [1.0, -a], u, axis=-1)


def _penalty(n_params: int, n: int) -> float:
    return n_params * math.log(max(n, 2))


def _finish(ws: Workspace, kind, axis, input_axis, params, n_params, res, position="post", notes=None) -> Proposal:
    c0 = float(ws.c_units.sum())
    score = (c0 - res.cv_chi2) - _penalty(n_params, ws.n_samples)
    return Proposal(
        kind, axis, input_axis, params, n_params, res.cv_chi2, res.full_chi2, float(score), position, notes or {}
    )


def _axis_index(axis):
    return AXES.index(axis)


# -- parametric linear candidates ---------------------------------------------------------------------
def screen_gain(ws: Workspace, ctx: Context, axis: str) -> Proposal:
    a = _axis_index(axis)

    def make(ms):
        return {a: ctx.P[ms, a][None]}, None

    A, b = ws.unit_stats(make, 1)
    res = cross_validate(A, b, ws.c_units, ws.folds, [[0]], free=True)
    return _finish(ws, "gain", axis, None, {"factor": 1.0 + float(res.theta[0])}, 1, res)


def screen_offset(ws: Workspace, ctx: Context, axis: str) -> Proposal:
    a = _axis_index(axis)

    def make(ms):
        return {a: np.ones((1, len(ms), ws.data.N))}, None

    A, b = ws.unit_stats(make, 1)
    res = cross_validate(A, b, ws.c_units, ws.folds, [[0]], free=True)
    return _finish(ws, "offset", axis, None, {"mT_per_m": float(res.theta[0])}, 1, res)


def _tau_grid(ws: Workspace) -> np.ndarray:
    T = ws.data.N * ws.data.dt_s
    lo, hi = 0.5 * ws.data.dt_s, max(2.0 * T, ws.data.dt_s * 4)
    return np.geomspace(lo, hi, 28)


def _screen_exp_family(ws: Workspace, ctx: Context, out_axis: int | None, in_axis: int):
    """Shared screening of exp/cross/b0 eddies: linear alpha on a coarse, then a fine tau grid.

    out_axis None means the B0 channel.  Returns (alpha, tau, OptionResult).
    """

    def stats(taus, cache_key=None):
        if cache_key is not None and cache_key not in ctx.cache:
            ctx.cache[cache_key] = -exp_columns(ctx.g[:, in_axis], ws.data.dt_s, taus)

        def make(ms):
            if cache_key is not None:
                E = ctx.cache[cache_key][:, ms]
            else:
                E = -exp_columns(ctx.g[ms, in_axis], ws.data.dt_s, taus)  # (K, Mc, N)
            if out_axis is None:
                return None, E
            return {out_axis: E}, None

        return ws.unit_stats(make, len(taus))

    coarse = _tau_grid(ws)
    A1, b1 = stats(coarse, ("exp_coarse", in_axis))
    r1 = cross_validate(A1, b1, ws.c_units, ws.folds, [[j] for j in range(len(coarse))], free=True)
    t_best = coarse[r1.option]
    step = math.log(coarse[1] / coarse[0])
    fine = t_best * np.exp(np.linspace(-step, step, 13))
    A2, b2 = stats(fine)
    taus = np.concatenate([coarse, fine])
    A = np.concatenate([A1, A2], axis=1)  # diagonal statistics: options are single columns
    b = np.concatenate([b1, b2], axis=1)
    res = cross_validate(A, b, ws.c_units, ws.folds, [[j] for j in range(len(taus))], free=True)
    return float(res.theta[0]), float(taus[res.option]), res


def screen_exp_eddy(ws: Workspace, ctx: Context, axis: str) -> Proposal:
    a = _axis_index(axis)
    alpha, tau, res = _screen_exp_family(ws, ctx, a, a)
    return _finish(ws, "exp_eddy", axis, None, {"alpha": alpha, "tau_s": tau}, 2, res)


#: Smallest ratio of the two time constants of a screened bi-exponential.
PAIR_MIN_RATIO = 5.0


def screen_exp_eddy_pair(ws: Workspace, ctx: Context, axis: str) -> Proposal | None:
    """Two exponentials on one axis at once (a bi-exponential eddy current): every pair of time constants of
    the coarse grid, both alphas linear (the full Gram of the coarse columns gives every pair's 2x2 system).
    Added as two ``exp_eddy`` effects; a single-step search would otherwise let a non-parametric ``lti``
    absorb the short term and part of the long one.  ``notes['second']`` holds the second term."""
    a = _axis_index(axis)
    coarse = _tau_grid(ws)
    key = ("exp_coarse", a)
    if key not in ctx.cache:
        ctx.cache[key] = -exp_columns(ctx.g[:, a], ws.data.dt_s, coarse)
    gkey = ("exp_coarse_gram", a)
    if gkey not in ctx.cache:  # the columns depend on the demanded g only: one Gram per identify and axis

        def make(ms):
            return {a: ctx.cache[key][:, ms]}, None

        ctx.cache[gkey] = ws.unit_stats(make, len(coarse), full=True)
    A, _ = ctx.cache[gkey]

    def make_b(ms):
        return {a: ctx.cache[key][:, ms]}, None

    _, b = ws.unit_stats(make_b, len(coarse))  # projections on the current residual
    K = len(coarse)
    # Time constants at least PAIR_MIN_RATIO apart: two close ones would only mimic one exponential between
    # the grid points (the single-exponential screen refines tau on a fine grid; the LM refit does too).
    step = max(1, math.ceil(math.log(PAIR_MIN_RATIO) / math.log(coarse[1] / coarse[0])))
    pairs = [[i, j] for i in range(K) for j in range(i + step, K)]
    if not pairs:
        return None
    res = cross_validate(A, b, ws.c_units, ws.folds, pairs, free=True)
    i, j = pairs[res.option]
    first = {"alpha": float(res.theta[0]), "tau_s": float(coarse[i])}
    second = {"alpha": float(res.theta[1]), "tau_s": float(coarse[j])}
    return _finish(ws, "exp_eddy", axis, None, first, 4, res, notes={"second": second})


def screen_cross_eddy(ws: Workspace, ctx: Context, axis: str, input_axis: str) -> Proposal:
    alpha, tau, res = _screen_exp_family(ws, ctx, _axis_index(axis), _axis_index(input_axis))
    return _finish(ws, "cross_eddy", axis, input_axis, {"alpha": alpha, "tau_s": tau}, 2, res)


def screen_b0_eddy(ws: Workspace, ctx: Context, input_axis: str) -> Proposal:
    alpha, tau, res = _screen_exp_family(ws, ctx, None, _axis_index(input_axis))
    return _finish(ws, "b0_eddy", None, input_axis, {"alpha_uT_per_mT_per_m": alpha, "tau_s": tau}, 2, res)


def resonance_columns(g_src: np.ndarray, dt_s: float, f0_hz: float, q: float) -> np.ndarray:
    """(2, ..., N) columns of a ``resonance`` at (f0, q): Re and -Im of ``dg/dt conv exp(p t)`` (exact for
    PWL g, :func:`pole_filter`, the recursion of :func:`dtoc.hardware.recursion.pole_response`); amplitude
    cos(phase) and amplitude sin(phase) are their coefficients."""
    w0 = 2.0 * math.pi * f0_hz
    p = complex(-w0 / (2.0 * q), w0 * math.sqrt(1.0 - 1.0 / (4.0 * q * q)))
    r = pole_filter(np.asarray(g_src, dtype=np.float64), p * dt_s)
    return np.stack([r.real, -r.imag])


#: Quality factors screened for a resonance (LM refines): light to strong ring-down.
RESONANCE_Q = (3.0, 10.0, 30.0, 100.0)


def screen_resonance(ws: Workspace, ctx: Context, axis: str) -> Proposal | None:
    """Damped resonance on one axis, driven by the demanded slew: f0 on a log grid (10 % steps, from 4 cycles
    per record to 0.4 / dt) at q = 30, then a 1 % grid over +-10 % around the best f0 for each q of
    :data:`RESONANCE_Q`; (amplitude cos, amplitude sin) linear (two columns per option)."""
    a = _axis_index(axis)
    dt = ws.data.dt_s
    T = ws.data.N * dt
    lo, hi = 4.0 / T, 0.4 / dt
    if hi <= lo:
        return None

    def evaluate(options):
        P = 2 * len(options)
        U = len(ws.folds.units)
        A = np.zeros((U, P, P))
        b = np.zeros((U, P))
        for j, (f0, q) in enumerate(options):

            def make(ms, f0=f0, q=q):
                return {a: resonance_columns(ctx.g[ms, a], dt, f0, q)}, None

            Aj, bj = ws.unit_stats(make, 2, chunk=max(1, ws.data.M), full=True)
            A[:, 2 * j : 2 * j + 2, 2 * j : 2 * j + 2] = Aj
            b[:, 2 * j : 2 * j + 2] = bj
        return cross_validate(A, b, ws.c_units, ws.folds, [[2 * j, 2 * j + 1] for j in range(len(options))], True)

    coarse = [(float(f), 30.0) for f in np.exp(np.arange(math.log(lo), math.log(hi), math.log(1.1)))]
    r1 = evaluate(coarse)
    f_best = coarse[r1.option][0]
    p1 = _finish(ws, "resonance", axis, None, {}, 4, r1)
    if p1.score <= 0:  # nothing resonant on this axis: the fine grid cannot make it significant
        c, s_ = float(r1.theta[0]), float(r1.theta[1])
        params = {"f0_hz": f_best, "q": 30.0, "amplitude": math.hypot(c, s_), "phase_rad": math.atan2(s_, c)}
        return _finish(ws, "resonance", axis, None, params, 4, r1)
    fine = [(float(f), q) for q in RESONANCE_Q for f in f_best * np.linspace(0.9, 1.1, 21)]
    r2 = evaluate(fine)
    best, opts = (r2, fine) if r2.full_chi2 <= r1.full_chi2 else (r1, coarse)
    f0, q = opts[best.option]
    c, s_ = float(best.theta[0]), float(best.theta[1])
    amp, ph = math.hypot(c, s_), math.atan2(s_, c)
    return _finish(ws, "resonance", axis, None, {"f0_hz": f0, "q": q, "amplitude": amp, "phase_rad": ph}, 4, best)


# -- delay --------------------------------------------------------------------------------------------
def fourier_shift(x: np.ndarray, tau_s: float, dt_s: float) -> np.ndarray:
    """x(t - tau) of a band-limited waveform zero outside its record (the convention of
    :class:`dtoc.hardware.effects.DelayBandlimited`): Fourier shift on a 2N zero-padded record."""
    N = x.shape[-1]
    f = np.fft.rfftfreq(2 * N, dt_s)
    return np.fft.irfft(np.fft.rfft(x, 2 * N, axis=-1) * np.exp(-2j * np.pi * f * tau_s), 2 * N, axis=-1)[..., :N]


def screen_delay(ws: Workspace, ctx: Context, axis: str | None, bandlimited: bool = False) -> Proposal:
    """Delay of one axis (or all axes when ``axis`` is None): exact shifts on a grid, piecewise-linear
    (``delay``) or band-limited (``delay_bandlimited``, Fourier shift)."""
    dt = ws.data.dt_s
    axes = [0, 1, 2] if axis is None else [_axis_index(axis)]
    if bandlimited:
        shift = lambda x, tau: fourier_shift(x, tau, dt)  # noqa: E731
    else:
        shift = ctx.shift or (lambda x, tau: pwl_shift(x, tau, dt))

    # Linearised estimate: r ~ -tau dP/dt.
    def make_lin(ms):
        return {a: -np.gradient(ctx.P[ms, a], dt, axis=-1)[None] for a in axes}, None

    A, b = ws.unit_stats(make_lin, 1)
    den = A[:, 0].sum()
    tau0 = float(b[:, 0].sum() / den) if den > 0 else 0.0
    tau0 = float(np.clip(tau0, -20 * dt, 20 * dt))

    def grid_stats(taus):
        def make(ms):
            return {a: np.stack([shift(ctx.P[ms, a], t) - ctx.P[ms, a] for t in taus]) for a in axes}, None

        return ws.unit_stats(make, len(taus))

    tau, res = _exact_grid_search(ws, grid_stats, tau0, max(0.5 * abs(tau0), 0.1 * dt), recentre=2)
    kind = "delay_bandlimited" if bandlimited else "delay"
    return _finish(ws, kind, axis, None, {"seconds": tau}, 1, res)


def _exact_grid_search(ws: Workspace, grid_stats, center: float, width: float, recentre: int):
    """Best of a set of exact, fixed changes (one parameter value each): an 11-point grid of +-``width``
    around ``center``, moved (``recentre`` times at most, doubling the width) while the optimum sits on its
    edge, then an 11-point grid of one step either side of the best value.

    Args:
        grid_stats: callable(values) -> per-unit statistics (A, b) of the changes at those values.
    Returns:
        (best value, :class:`OptionResult` of the fine grid).
    """
    vals = center + width * np.linspace(-1.0, 1.0, 11)
    for k in range(recentre + 1):
        A, b = grid_stats(vals)
        res = cross_validate(A, b, ws.c_units, ws.folds, [[j] for j in range(len(vals))], free=False)
        if 0 < res.option < len(vals) - 1 or k == recentre:
            break
        vals = vals[res.option] + width * np.linspace(-1.0, 1.0, 11)
        width *= 2.0
    fine = vals[res.option] + (vals[1] - vals[0]) * np.linspace(-1.0, 1.0, 11)
    A, b = grid_stats(fine)
    res = cross_validate(A, b, ws.c_units, ws.folds, [[j] for j in range(len(fine))], free=False)
    return float(fine[res.option]), res


# -- time base of the measurement (clock error) ------------------------------------------------------
def screen_time_base(ws: Workspace, ctx: Context) -> Proposal | None:
    """Clock error of the measuring device: the field sampled at t (1 + ppm 1e-6) on every axis, a delay
    growing linearly with time.  Linearised estimate (r ~ ppm 1e-6 t dP/dt), then a grid of exact values
    (:class:`dtoc.hardware.effects.TimeBase`) around it.  Position "meas": applied to the prediction of the
    measurement, never written into the hardware model."""
    import torch

    from dtoc.hardware.effects import TimeBase

    dt = ws.data.dt_s
    t = np.arange(ws.data.N) * dt

    def make_lin(ms):
        return {a: (1e-6 * t * np.gradient(ctx.P[ms, a], dt, axis=-1))[None] for a in range(3)}, None

    A, b = ws.unit_stats(make_lin, 1)
    den = A[:, 0].sum()
    if den <= 0:
        return None
    ppm0 = float(b[:, 0].sum() / den)

    def exact(ppm, ms):
        with torch.no_grad():
            P = torch.as_tensor(ctx.P[ms])
            out, _ = TimeBase(ppm)(P, torch.zeros(P.shape[0], P.shape[-1], dtype=P.dtype), dt)
        return out.numpy() - ctx.P[ms]

    def grid_stats(vals):
        def make(ms):
            d = np.stack([exact(v, ms) for v in vals])  # (p, Mc, 3, N)
            return {a: d[:, :, a] for a in range(3)}, None

        return ws.unit_stats(make, len(vals))

    ppm, res = _exact_grid_search(ws, grid_stats, ppm0, max(0.5 * abs(ppm0), 1e-3), recentre=0)
    return _finish(ws, "time_base", None, None, {"ppm": ppm}, 1, res, position="meas")


# -- lti (non-parametric FIR correction) -------------------------------------------------------------
def lti_layout(dt_s: float, n_taps: int | None = None, n_pre: int = 4) -> tuple[int, int]:
    """(number of taps, index of the first tap relative to zero lag) of the FIR correction."""
    if n_taps is None:
        n_taps = 48
    return n_taps, -n_pre


def screen_lti(ws: Workspace, ctx: Context, axis: str, n_taps: int | None = None) -> Proposal:
    a = _axis_index(axis)
    L, j0 = lti_layout(ws.data.dt_s, n_taps)
    N = ws.data.N

    def make(ms):
        x = ctx.P[ms, a]  # (Mc, N)
        dG = np.zeros((L, len(ms), N))
        for j in range(L):
            lag = j + j0
            if 0 <= lag < N:
                dG[j, :, lag:] = x[:, : N - lag]
            elif -N < lag < 0:
                dG[j, :, : N + lag] = x[:, -lag:]
        return {a: dG}, None

    if ws.data.k is None:  # G only: the columns change nothing else
        A, b = lti_stats_toeplitz(ws, ctx.P[:, a], a, [j + j0 for j in range(L)])
    else:
        A, b = ws.unit_stats(make, L, full=True)
    res = cross_validate(A, b, ws.c_units, ws.folds, [list(range(L))], free=True)
    taps = [float(v) for v in res.theta]
    dt = ws.data.dt_s
    return _finish(
        ws,
        "lti",
        axis,
        None,
        {"taps": taps, "dt_s": dt, "t0_s": j0 * dt},
        L,
        res,
        notes=lti_features(np.asarray(taps), j0, dt, excited_band_hz(ctx.P[:, a], dt)),
    )


def lti_stats_toeplitz(ws: Workspace, x: np.ndarray, a: int, lags: list) -> tuple[np.ndarray, np.ndarray]:
    """Per-unit Gram and projection of shifted copies x[n - lag] on the G channel of axis a, in O(p N).

    Column j is x(t - lag_j dt) (zero outside the record), whitened by sigma_G, restricted to the unit's
    samples; A[j, l] = sum_n x[n - lag_j] x[n - lag_l] is a range sum of the product sequence
    x[m] x[m - d] (d = lag_l - lag_j), taken from prefix sums.  Equal to :meth:`Workspace.unit_stats`
    with ``full=True`` for a G-only measurement (tests check it), without forming the p columns.
    """
    U = len(ws.folds.units)
    p = len(lags)
    lags = np.asarray(lags)
    N = x.shape[-1]
    s2 = ws.sigma["G"] ** 2
    A = np.zeros((U, p, p))
    b = np.zeros((U, p))
    for ui, u in enumerate(ws.folds.units):
        if not ws.data.axes_measured[u.m, a]:
            continue
        xm = x[u.m]
        z = ws.z["G"][u.m, a]
        for j, lag in enumerate(lags):  # b_j = sum_{n in unit} x[n - lag] z[n]
            lo, hi = max(u.n0, lag), min(u.n1, N + lag)
            if hi > lo:
                b[ui, j] = np.einsum("n,n->", xm[lo - lag : hi - lag], z[lo:hi])
        for d in range(p):  # pairs (j, j + d): lag_l - lag_j = d (consecutive lags)
            prod = np.zeros(N)
            prod[d:] = xm[d:] * xm[: N - d]  # prod[m] = x[m] x[m - d]
            C = np.concatenate([[0.0], np.cumsum(prod)])
            j = np.arange(p - d)
            lagj = lags[j]
            # n ranges over the unit; m = n - lag_j must lie in [d, N): m in [n0 - lag_j, n1 - lag_j)
            m_lo = np.clip(u.n0 - lagj, 0, N)
            m_hi = np.clip(u.n1 - lagj, 0, N)
            vals = np.where(m_hi > m_lo, C[m_hi] - C[m_lo], 0.0)
            A[ui, j, j + d] = vals
            A[ui, j + d, j] = vals
        b[ui] /= ws.sigma["G"]
        A[ui] /= s2
    return A, b


def excited_band_hz(x: np.ndarray, dt_s: float, db: float = 50.0) -> float:
    """Upper edge of the band the waveforms ``x`` (..., N) excite: the highest frequency at which their mean
    power spectrum (smoothed over ~2 % of the bins) is within ``db`` dB of its peak.  Above it a fitted
    filter is not constrained by the data (its response there is noise-fitting)."""
    from scipy.ndimage import uniform_filter1d

    x2 = np.asarray(x, dtype=np.float64).reshape(-1, np.shape(x)[-1])
    f = np.fft.rfftfreq(x2.shape[-1], dt_s)
    P = (np.abs(np.fft.rfft(x2, axis=-1)) ** 2).mean(0)
    if not np.any(P > 0):
        return float(f[-1])
    Ps = uniform_filter1d(P, max(1, len(P) // 50))
    idx = np.nonzero(Ps >= Ps.max() * 10.0 ** (-db / 10.0))[0]
    return float(f[idx.max()]) if idx.size else float(f[-1])


def lti_features(taps: np.ndarray, first_lag: int, dt_s: float, fmax_hz: float | None = None) -> dict:
    """Dominant features of an FIR correction dH(f) = sum_j taps[j] exp(-2 pi i f (j + first_lag) dt):
    peak |dH| and its frequency (searched up to ``fmax_hz``, the band the data excite, when given;
    default Nyquist), and the DC change (sum of taps).

    Physical names of the corrected response H = 1 + dH (the lti is additive, docs/contracts.md §3):
    ``dc_gain`` = H(0); ``delay_s`` = its group delay at low frequency, sum_j h_j t_j / sum_j h_j with
    h = delta + taps (the first moment: the delay a pure shift would have); ``bandwidth_hz`` = the lowest
    frequency where |H(f)| / |H(0)| falls below 1/sqrt(2) (None when it does not within the band searched,
    reported as "beyond" it)."""
    nfft = 4096
    taps = np.asarray(taps, dtype=np.float64).reshape(-1)
    f = np.fft.rfftfreq(nfft, dt_s)
    H = np.fft.rfft(taps, nfft) * np.exp(-2j * np.pi * f * first_lag * dt_s)
    band = np.ones(f.size, dtype=bool) if fmax_hz is None else (f <= fmax_hz)
    k = int(np.argmax(np.where(band, np.abs(H), -1.0)))
    out = {"peak_hz": float(f[k]), "peak_abs": float(np.abs(H[k])), "dc_change": float(np.real(H[0]))}
    dc = 1.0 + float(np.sum(taps))
    t = (np.arange(taps.size) + first_lag) * dt_s
    out["dc_gain"] = dc
    out["delay_s"] = float(np.sum(taps * t) / dc) if abs(dc) > 1e-9 else float("nan")
    full = np.abs(1.0 + H) / max(abs(dc), 1e-300)
    below = np.nonzero(band & (full < 1.0 / np.sqrt(2.0)))[0]
    out["bandwidth_hz"] = float(f[below[0]]) if below.size else None
    if fmax_hz is not None:
        out["band_hz"] = float(min(fmax_hz, f[-1]))
    return out


def lti_physical_text(ft: dict) -> str:
    """ "delay 1.23 us, DC gain 0.998, bandwidth (-3 dB) 9.1 kHz" of :func:`lti_features`' result."""
    bw = ft.get("bandwidth_hz")
    band = ft.get("band_hz")
    if bw is not None:
        bwt = f"bandwidth (-3 dB) {bw / 1e3:.3g} kHz"
    else:
        bwt = "no -3 dB point" + (f" within the excited band 0-{band / 1e3:.3g} kHz" if band else "")
    return f"delay {ft['delay_s'] * 1e6:+.3g} us (group delay at low frequency), DC gain {ft['dc_gain']:.4g}, {bwt}"


# -- slew limit (non-linear, on the demanded input) --------------------------------------------------
def screen_slew_limit(ws: Workspace, ctx: Context, axis: str | None = None) -> Proposal | None:
    """Slew-rate limit of the amplifier on one axis (``axis``) or one limit shared by all axes (None):
    a grid of limits between 0.2 and 0.98 of the demanded peak slew on those axes, refined."""
    if ctx.chain is None or ctx.slew_limit is None:
        return None
    dt = ws.data.dt_s
    sel = ctx.g if axis is None else ctx.g[:, _axis_index(axis) : _axis_index(axis) + 1]
    smax = float(np.max(np.abs(np.diff(sel, axis=-1)))) / dt  # mT/m/s
    if smax <= 0:
        return None
    base = ctx.P
    base_b0 = ctx.P_b0

    def stats(limits_T_per_m_per_s):
        def make(ms):
            dG = np.zeros((len(limits_T_per_m_per_s), len(ms), 3, ws.data.N))
            db0 = np.zeros((len(limits_T_per_m_per_s), len(ms), ws.data.N))
            for j, s in enumerate(limits_T_per_m_per_s):
                pred = ctx.chain(ctx.slew_limit(ctx.g[ms], s, axis))
                dG[j] = pred.G - base[ms]
                if pred.b0 is not None and base_b0 is not None:
                    db0[j] = pred.b0 - base_b0[ms]
            return {a: dG[:, :, a] for a in range(3)}, (db0 if base_b0 is not None else None)

        return ws.unit_stats(make, len(limits_T_per_m_per_s), chunk=max(1, ws.data.M))

    smax_T = smax * 1e-3
    coarse = smax_T * np.geomspace(0.2, 0.98, 9)
    A, b = stats(coarse)
    res = cross_validate(A, b, ws.c_units, ws.folds, [[j] for j in range(len(coarse))], free=False)
    j = res.option
    lo = coarse[max(j - 1, 0)]
    hi = coarse[min(j + 1, len(coarse) - 1)]
    fine = np.linspace(lo, hi, 7)
    A2, b2 = stats(fine)
    res2 = cross_validate(A2, b2, ws.c_units, ws.folds, [[j] for j in range(len(fine))], free=False)
    best = res2 if res2.full_chi2 <= res.full_chi2 else res
    val = fine[res2.option] if best is res2 else coarse[res.option]
    return _finish(ws, "slew_limit", axis, None, {"max_slew_T_per_m_per_s": float(val)}, 1, best, position="pre")


def _slew_dependent(ws: Workspace, ctx: Context, axis: str) -> bool:
    """Cheap pre-test for a per-axis slew-limit screen: does the residual power on ``axis`` grow with the
    demanded slew on that axis (top decile vs lower half, > 1.5x and z > 3)?  Without a measured G channel
    the screen always runs."""
    from dtoc.identify.diagnostics import power_growth

    if "G" not in ws.z:
        return True
    a = _axis_index(axis)
    x = np.abs(np.diff(ctx.g[:, a], axis=-1, prepend=ctx.g[:, a, :1]))
    m = np.broadcast_to(ws.data.axes_measured[:, a, None], x.shape)
    r = power_growth(x, ws.z["G"][:, a], m)
    return r is not None and r[0] > 1.5 and r[1] > 3.0


# -- the whole library -----------------------------------------------------------------------------
def screen_all(ws: Workspace, ctx: Context, kinds=None, exclude=()) -> list[Proposal]:
    """Screen every candidate of the library (optionally only ``kinds``); best score first.

    ``exclude``: names (:attr:`Proposal.name`) already in the model, not proposed again.
    """
    kinds = set(kinds) if kinds else set(CANDIDATE_KINDS)
    props: list[Proposal] = []
    measured_axes = [AXES[a] for a in range(3) if ws.data.axes_measured[:, a].any()]
    active_in = [AXES[a] for a in range(3) if np.any(ctx.P[:, a] != 0)]
    driven = [AXES[a] for a in range(3) if np.any(ctx.g[:, a] != 0)]  # demanded axes: sources of eddy terms
    for bl, name in ((False, "delay"), (True, "delay_bandlimited")):
        if name in kinds:
            if len(measured_axes) > 1:
                props.append(screen_delay(ws, ctx, None, bl))
            props += [screen_delay(ws, ctx, ax, bl) for ax in measured_axes]
    if "gain" in kinds:
        props += [screen_gain(ws, ctx, ax) for ax in measured_axes]
    if "offset" in kinds:
        props += [screen_offset(ws, ctx, ax) for ax in measured_axes]
    if "exp_eddy" in kinds:
        props += [screen_exp_eddy(ws, ctx, ax) for ax in measured_axes if ax in driven]
        props += [p for p in (screen_exp_eddy_pair(ws, ctx, ax) for ax in measured_axes if ax in driven) if p]
    if "cross_eddy" in kinds:
        props += [screen_cross_eddy(ws, ctx, o, i) for o in measured_axes for i in driven if i != o]
    if "b0_eddy" in kinds and ws.data.b0 is not None:
        props += [screen_b0_eddy(ws, ctx, i) for i in driven]
    if "resonance" in kinds:
        props += [p for p in (screen_resonance(ws, ctx, ax) for ax in measured_axes if ax in driven) if p is not None]
    if "time_base" in kinds:
        p = screen_time_base(ws, ctx)
        if p is not None:
            props.append(p)
    if "lti" in kinds:
        props += [screen_lti(ws, ctx, ax) for ax in measured_axes if ax in active_in]
    if "slew_limit" in kinds:  # one limit for all axes, and one per axis (amplifiers differ)
        dependent = [ax for ax in measured_axes if _slew_dependent(ws, ctx, ax)]
        shared = screen_slew_limit(ws, ctx, None) if dependent else None  # no slew-dependent residual: skip
        if shared is not None:
            props.append(shared)
        if len(measured_axes) > 1:
            props += [p for p in (screen_slew_limit(ws, ctx, ax) for ax in dependent) if p is not None]
    props = [p for p in props if p.name not in set(exclude)]
    props.sort(key=lambda p: -p.score)
    return props
