"""Physics and contracts of the individual hardware-twin effects (dtoc.hardware.effects)."""

import math

import numpy as np
import pytest
import scipy.signal
import torch

from dtoc.errors import InputError
from dtoc.hardware.effects import (
    B0Eddy,
    CrossEddy,
    Delay,
    ExpEddy,
    Gain,
    Girf,
    Lti,
    Offset,
    Resonance,
    SlewLimit,
    TimeBase,
)
from dtoc.hardware.recursion import exp_response

F64 = torch.float64


def _b0(g):
    return torch.zeros(g.shape[0], g.shape[-1], dtype=g.dtype)


def trapezoid(T, dt, start_s, ramp_s, flat_s, amp):
    """PWL trapezoid sampled at n*dt (vertices on samples)."""
    t = np.arange(T) * dt
    up = np.clip((t - start_s) / ramp_s, 0, 1)
    down = np.clip((t - start_s - ramp_s - flat_s) / ramp_s, 0, 1)
    return amp * (up - down)


# ---------------------------------------------------------------- exponential eddy currents
@pytest.mark.parametrize("tau", [1e-3, 100e-3, 1.0])
def test_exp_eddy_step_response_exact(tau):
    dt, T, g0, alpha = 10e-6, 20001, 12.5, 0.1
    g = torch.full((1, 3, T), g0, dtype=F64)  # a step at t = 0 (zero before)
    G, _ = ExpEddy(alpha, tau)(g, _b0(g), dt)
    t = torch.arange(T, dtype=F64) * dt
    ref = g0 * (1 - alpha * torch.exp(-t / tau))
    assert torch.max(torch.abs(G[0] - ref) / g0) < 1e-6
    assert torch.max(torch.abs(G[0] - ref) / g0) < 1e-12  # the recursion is exact, not merely close


def test_exp_eddy_ramp_closed_form():
    """Ramp up at slope s for Tr, then flat: e = s tau (1 - exp(-t/tau)) then decays from its end value."""
    dt, tau, alpha, s = 10e-6, 0.4e-3, 0.2, 100.0  # s in mT/m/s per sample units -> mT/m per s
    T, nr = 400, 50
    t = np.arange(T) * dt
    g = np.minimum(t, nr * dt) * s
    G, _ = ExpEddy(alpha, tau, axis="y")(
        torch.as_tensor(g).expand(1, 3, T).contiguous(), torch.zeros(1, T, dtype=F64), dt
    )
    Tr = nr * dt
    e = np.where(t <= Tr, s * tau * (1 - np.exp(-t / tau)), s * tau * (1 - np.exp(-Tr / tau)) * np.exp(-(t - Tr) / tau))
    np.testing.assert_allclose(G[0, 1].detach().numpy(), g - alpha * e, rtol=0, atol=1e-12 * g.max())
    np.testing.assert_array_equal(G[0, 0].detach().numpy(), g)  # other axes untouched


@pytest.mark.parametrize("tau,dt", [(1e-3, 1e-6), (100e-3, 10e-6)])
def test_exp_eddy_exact_single_exponential_inverse(tau, dt):
    """Pre-emphasis alpha/(1-alpha), (1-alpha) tau (sign: adds) followed by the eddy current restores g."""
    alpha = 0.1
    T = int(round(4e-3 / dt)) + 1
    g = trapezoid(T, dt, 5 * dt, 200e-6, 2e-3, 20.0)
    gt = torch.as_tensor(g).expand(1, 3, T).contiguous()
    pre = ExpEddy(-alpha / (1 - alpha), (1 - alpha) * tau)
    eddy = ExpEddy(alpha, tau)
    p, b = pre(gt, _b0(gt), dt)
    G, _ = eddy(p, b, dt)
    assert torch.max(torch.abs(G - gt)) / 20.0 < 1e-6
    G_plain, _ = eddy(gt, _b0(gt), dt)
    assert torch.max(torch.abs(G_plain - gt)) / 20.0 > 1e-2  # without pre-emphasis the error is large


def test_exp_eddy_multi_term_is_sum_of_terms():
    dt, T = 5e-6, 20001
    g = torch.as_tensor(trapezoid(T, dt, 1e-4, 1e-4, 1e-2, 10.0)).expand(1, 3, T).contiguous()
    two = ExpEddy([0.1, 0.05], [1e-3, 1.0])(g, _b0(g), dt)[0]
    one_a = ExpEddy(0.1, 1e-3)(g, _b0(g), dt)[0]
    one_b = ExpEddy(0.05, 1.0)(g, _b0(g), dt)[0]
    torch.testing.assert_close(two, one_a + one_b - g, rtol=0, atol=1e-12)


def test_exp_response_matches_direct_loop():
    rng = np.random.default_rng(1)
    g = rng.standard_normal(300)
    dt, tau = 10e-6, 37e-6
    e = exp_response(torch.as_tensor(g), dt, torch.tensor(tau, dtype=F64)).numpy()
    a, b = math.exp(-dt / tau), tau / dt * (1 - math.exp(-dt / tau))
    ref = np.empty_like(g)
    ref[0] = g[0]
    for n in range(1, g.size):
        ref[n] = a * ref[n - 1] + b * (g[n] - g[n - 1])
    np.testing.assert_allclose(e, ref, rtol=1e-12, atol=1e-12)


def test_cross_and_b0_eddy_route_and_sign():
    dt, T = 10e-6, 500
    g = torch.zeros(1, 3, T, dtype=F64)
    g[0, 0] = 10.0  # step on x from t = 0
    t = torch.arange(T, dtype=F64) * dt
    G, b0 = CrossEddy(0.02, 1e-3, axis="z", input_axis="x")(g, _b0(g), dt)
    torch.testing.assert_close(G[0, 2], -0.2 * torch.exp(-t / 1e-3), rtol=0, atol=1e-12)
    torch.testing.assert_close(G[0, :2], g[0, :2])
    G, b0 = B0Eddy(0.5, 2e-3, input_axis="x")(g, _b0(g), dt)
    torch.testing.assert_close(b0[0], -5.0 * torch.exp(-t / 2e-3), rtol=0, atol=1e-12)
    torch.testing.assert_close(G, g)
    with pytest.raises(InputError):
        CrossEddy(0.1, 1e-3, axis="x", input_axis=None)
    with pytest.raises(InputError):
        ExpEddy(0.1, -1e-3)


def test_gain_offset_axes():
    g = torch.randn(2, 3, 50, dtype=F64)
    G, _ = Gain(0.9, axis="y")(g, _b0(g), 1e-5)
    torch.testing.assert_close(G[:, 1], 0.9 * g[:, 1])
    torch.testing.assert_close(G[:, [0, 2]], g[:, [0, 2]])
    G, _ = Offset(0.3)(g, _b0(g), 1e-5)
    torch.testing.assert_close(G, g + 0.3)


# ---------------------------------------------------------------- delay
def test_delay_is_exact_for_pwl_and_zero_padded():
    dt, T = 10e-6, 200
    g_np = trapezoid(T, dt, 20 * dt, 10 * dt, 30 * dt, 5.0)
    g = torch.as_tensor(g_np).expand(1, 3, T).contiguous()
    for d in (3.0, 2.3, -1.7, 0.25):
        G, _ = Delay(d * dt, axis="x")(g, _b0(g), dt)
        ref = np.interp(np.arange(T) - d, np.arange(T), g_np, left=0.0, right=0.0)
        np.testing.assert_allclose(G[0, 0].detach().numpy(), ref, atol=1e-13)
        torch.testing.assert_close(G[0, 1:], g[0, 1:])
    G, _ = Delay(5e-3)(g, _b0(g), dt)  # longer than the waveform: all zero
    assert float(G.detach().abs().max()) == 0.0


# ---------------------------------------------------------------- slew limit
def _slew_reference(x, s):
    y = np.empty_like(x)
    y[0] = x[0]
    for n in range(1, x.size):
        y[n] = y[n - 1] + np.clip(x[n] - y[n - 1], -s, s)
    return y


def test_slew_limit_matches_recursive_clamp():
    dt, smax = 10e-6, 180.0  # T/m/s -> 1.8 mT/m per 10 us
    rng = np.random.default_rng(3)
    x = np.concatenate(
        [np.zeros(5), np.full(20, 30.0), np.zeros(10), -np.linspace(0, 40, 8), rng.normal(0, 3, 60).cumsum()]
    )
    g = torch.as_tensor(x).expand(1, 3, x.size).contiguous()
    G, _ = SlewLimit(smax, axis="z")(g, _b0(g), dt)
    ref = _slew_reference(x, smax * 1e3 * dt)
    np.testing.assert_allclose(G[0, 2].detach().numpy(), ref, rtol=0, atol=1e-12)
    assert np.max(np.abs(np.diff(G[0, 2].detach().numpy()))) <= smax * 1e3 * dt * (1 + 1e-9)
    torch.testing.assert_close(G[0, :2], g[0, :2])
    # a waveform within the limit passes unchanged
    ok = torch.as_tensor(trapezoid(300, dt, 1e-4, 2e-4, 1e-3, 30.0)).expand(1, 3, 300).contiguous()
    torch.testing.assert_close(SlewLimit(smax)(ok, _b0(ok), dt)[0], ok)


# ---------------------------------------------------------------- GIRF / LTI
def _smooth_kernel(t, delay=4e-6, width=15e-6):
    return np.exp(-0.5 * ((t - delay) / width) ** 2)


def test_girf_equals_direct_convolution_with_t0():
    rng = np.random.default_rng(0)
    dt, T, L, s0 = 10e-6, 700, 61, -30
    h = rng.normal(0, 0.05, (3, 3, L))
    h0 = rng.normal(0, 0.01, (3, L))
    g = rng.normal(0, 10, (2, 3, T))
    eff = Girf(h, dt, s0 * dt, h0)
    G, b0 = eff(torch.as_tensor(g), torch.zeros(2, T, dtype=F64), dt)
    for b in range(2):
        for o in range(3):
            full = sum(scipy.signal.convolve(g[b, i], h[o, i]) for i in range(3))  # index m <-> time (m + s0) dt
            ref = full[-s0 : -s0 + T]
            np.testing.assert_allclose(G[b, o].detach().numpy(), ref, rtol=0, atol=1e-9 * np.abs(ref).max())
        full0 = sum(scipy.signal.convolve(g[b, i], h0[i]) for i in range(3))
        np.testing.assert_allclose(
            b0[b].detach().numpy(), full0[-s0 : -s0 + T], rtol=0, atol=1e-9 * np.abs(full0).max()
        )


def test_girf_resampled_10us_kernel_on_5us_waveform():
    """A smooth continuous GIRF sampled at 10 us, applied to a 5 us waveform, matches its 5 us sampling."""

    def kernel(dt, L):
        t0 = -(L // 2) * dt
        t = t0 + np.arange(L) * dt
        h = np.zeros((3, 3, L))
        for i in range(3):
            h[i, i] = _smooth_kernel(t, delay=3e-6 * (i + 1)) * dt
            h[(i + 1) % 3, i] = 0.02 * _smooth_kernel(t, delay=20e-6, width=30e-6) * dt
        h /= h[0, 0].sum()
        return h, t0

    h10, t10 = kernel(10e-6, 41)
    h5, t5 = kernel(5e-6, 81)
    dt, T = 5e-6, 2000
    t = np.arange(T) * dt
    g = np.stack([20 * np.exp(-0.5 * ((t - 4e-3) / 0.3e-3) ** 2) * np.sin(2 * np.pi * 2e3 * t + p) for p in (0, 1, 2)])
    gt = torch.as_tensor(g)[None]
    G10, _ = Girf(h10, 10e-6, t10)(gt, torch.zeros(1, T, dtype=F64), dt)
    G5, _ = Girf(h5, 5e-6, t5)(gt, torch.zeros(1, T, dtype=F64), dt)
    rel = float((G10 - G5).detach().abs().max() / G5.detach().abs().max())
    assert rel < 1e-3, rel
    # and the same kernel on an odd grid (the 2023 KCL file has 10.0067 us taps) also agrees
    Godd, _ = Girf(h10, 10.0067e-6, t10 * 1.00067)(gt, torch.zeros(1, T, dtype=F64), dt)
    assert float((Godd - G5).detach().abs().max() / G5.detach().abs().max()) < 2e-3


def test_girf_resampling_keeps_dc_gain():
    from dtoc.hardware.convolution import resample_kernel

    rng = np.random.default_rng(5)
    h = torch.as_tensor(rng.normal(0, 1, (2, 100)))
    for dt in (5e-6, 10e-6, 20e-6, 10.0067e-6):
        hr, _ = resample_kernel(h, 10e-6, -3.3e-6, dt)
        torch.testing.assert_close(hr.sum(-1), h.sum(-1), rtol=1e-12, atol=1e-12)


def test_lti_zero_taps_is_identity_and_matches_convolution():
    rng = np.random.default_rng(2)
    dt, T = 10e-6, 300
    g = torch.as_tensor(rng.normal(0, 1, (1, 3, T)))
    torch.testing.assert_close(Lti(np.zeros((3, 9)), dt)(g, _b0(g), dt)[0], g)
    taps = rng.normal(0, 0.1, 9)
    G, _ = Lti(taps, dt, -4 * dt, axis="y")(g, _b0(g), dt)
    ref = g[0, 1].numpy() + scipy.signal.convolve(g[0, 1].numpy(), taps)[4 : 4 + T]
    np.testing.assert_allclose(G[0, 1].detach().numpy(), ref, atol=1e-12)
    torch.testing.assert_close(G[0, [0, 2]], g[0, [0, 2]])


# ---------------------------------------------------------------- dtype, gradcheck
def _all_effects(dt):
    rng = np.random.default_rng(7)
    L = 7
    return [
        Gain(1.05, axis="x"),
        Offset(0.2),
        Delay(1.37 * dt),
        Delay(-0.4 * dt, axis="z"),
        ExpEddy([0.1, 0.05], [3 * dt, 40 * dt]),
        ExpEddy(0.1, 5 * dt, axis="y"),
        CrossEddy(0.03, 4 * dt, axis="y", input_axis="x"),
        B0Eddy(0.2, 6 * dt, input_axis="z"),
        Girf(
            np.eye(3)[:, :, None] * np.array([0.2, 0.5, 0.2, 0.1, 0, 0, 0]) + rng.normal(0, 0.01, (3, 3, L)),
            dt,
            -2 * dt,
            rng.normal(0, 0.01, (3, L)),
        ),
        Girf(rng.normal(0, 0.1, (3, 3, L)), 0.7 * dt, -1.3 * dt),  # resampled path
        Lti(rng.normal(0, 0.05, (3, 5)), dt, -dt),
        SlewLimit(2.0),
        Resonance(3.1e3, 12.0, 0.05, -0.7, axis="y"),
        TimeBase(3000.0),
    ]


@pytest.mark.parametrize("idx", range(14))
def test_gradcheck_every_effect(idx):
    dt = 1e-5
    eff = _all_effects(dt)[idx]
    rng = np.random.default_rng(idx)
    T = 24
    # a waveform with clear slew violations for slew_limit (limit 2 T/m/s = 0.02 mT/m per sample)
    g = torch.as_tensor(rng.normal(0, 1.0, (2, 3, T)), dtype=F64).requires_grad_(True)
    b0 = torch.as_tensor(rng.normal(0, 0.1, (2, T)), dtype=F64).requires_grad_(True)
    params = [p for p in eff.parameters()]
    assert params, "every effect exposes parameters"
    names = [n for n, _ in eff.named_parameters()]

    # parameters are passed normalised by their magnitude (time constants ~1e-5 s would make a
    # fixed finite-difference step meaningless); the chain rule through a constant scale is exact
    scales = [p.detach().abs().max().clamp_min(1e-3) for p in params]

    def fn(g_, b0_, *qs):
        ps = {n: q * sc for n, q, sc in zip(names, qs, scales)}
        return torch.func.functional_call(eff, ps, (g_, b0_, dt))

    inputs = [g, b0] + [(p.detach() / sc).clone().requires_grad_(True) for p, sc in zip(params, scales)]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-7, atol=1e-6, rtol=1e-5, fast_mode=True)


def test_float32_and_dtype_preserved():
    dt = 1e-5
    g = torch.as_tensor(np.random.default_rng(11).normal(0, 1, (1, 3, 64)), dtype=torch.float32)
    with torch.no_grad():
        for eff in _all_effects(dt):
            G, b0 = eff(g, torch.zeros(1, 64), dt)
            assert G.dtype == torch.float32 and b0.dtype == torch.float32 and G.shape == g.shape
            G64, _ = eff(g.double(), torch.zeros(1, 64, dtype=F64), dt)
            assert float((G.double() - G64).abs().max()) < 1e-4 * max(1.0, float(G64.abs().max()))


def test_resonance_step_response_is_a_damped_cosine():
    """A step of height dG at t = 0 rings as amplitude dG exp(-w0 t / 2Q) cos(w_d t + phase), exactly."""
    dt, f0, q, amp, ph = 1e-5, 1.7e3, 20.0, 0.04, 0.6
    T = 2000
    g = torch.zeros(1, 3, T, dtype=F64)
    g[:, 2] = 5.0
    G, _ = Resonance(f0, q, amp, ph, axis="z")(g, torch.zeros(1, T, dtype=F64), dt)
    t = np.arange(T) * dt
    w0 = 2 * math.pi * f0
    wd = w0 * math.sqrt(1 - 1 / (4 * q * q))
    ring = amp * 5.0 * np.exp(-w0 * t / (2 * q)) * np.cos(wd * t + ph)
    np.testing.assert_allclose(G[0, 2].detach().numpy() - 5.0, ring, atol=1e-12)
    np.testing.assert_array_equal(G[0, :2].detach().numpy(), 0.0)


def test_resonance_of_a_trapezoid_matches_quadrature():
    """Independent check on a ramp: Re(e^{i phase} int g'(s) e^{p (t - s)} ds) by fine numerical quadrature."""
    dt, f0, q, amp, ph = 1e-5, 2.3e3, 8.0, 0.1, -1.1
    g = np.concatenate([np.linspace(0, 10, 21), np.full(30, 10.0), np.linspace(10, 0, 21), np.zeros(60)])
    G, _ = Resonance(f0, q, amp, ph)(torch.as_tensor(g[None, None].repeat(3, 1)), torch.zeros(1, g.size, dtype=F64), dt)
    w0 = 2 * math.pi * f0
    p = complex(-w0 / (2 * q), w0 * math.sqrt(1 - 1 / (4 * q * q)))
    sub = 400
    ts = np.arange((g.size - 1) * sub + 1) * dt / sub
    slope = np.repeat(np.diff(g) / dt, sub)  # g' on each sub-step
    mid = ts[:-1] + 0.5 * dt / sub
    for n in (25, 50, 70, 100, 130):
        tn = n * dt
        m = mid < tn
        val = np.sum(slope[m] * np.exp(p * (tn - mid[m]))) * dt / sub
        ref = amp * (np.exp(1j * ph) * val).real
        assert abs(float(G[0, 0, n].detach()) - g[n] - ref) < 2e-5 * 10 * amp + 1e-9


def test_time_base_scales_the_time_axis():
    """A clock running ppm fast samples a ramp c t at t (1 + ppm 1e-6): exact for a PWL ramp; zero after the end."""
    dt, T, ppm = 1e-5, 500, 2000.0
    c = 0.01
    g = torch.zeros(1, 3, T, dtype=F64)
    g[:, 1] = c * torch.arange(T, dtype=F64)
    G, _ = TimeBase(ppm, axis="y")(g, torch.zeros(1, T, dtype=F64), dt)
    n = np.arange(T)
    pos = n * (1 + ppm * 1e-6)
    inside = pos <= T - 1
    np.testing.assert_allclose(G[0, 1].detach().numpy()[inside], (c * pos)[inside], rtol=0, atol=1e-12)
    assert np.all(G[0, 1].detach().numpy()[~inside] == 0)
