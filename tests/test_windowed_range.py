"""A window's residual realized only where its rows read (dtoc.optimize.window_jacobian.RangeRealizer): the same
realized gradient as the chain on the whole window, the same window figures."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dtoc.hardware.effects import Delay, ExpEddy, Gain, Girf, Offset
from dtoc.hardware.memory import memory_s
from dtoc.hardware.model import HardwareModel
from dtoc.optimize.window_jacobian import RangeRealizer

DT = 5e-6


def _chain() -> HardwareModel:
    """A GIRF-like 3x3 kernel (dt 10 us, -0.5 .. +3 ms: an acausal dip, a causal eddy-like tail, 3 % and 1 % cross
    terms x <-> y and y -> z) and a gain."""
    dt = 1e-5
    t = np.arange(-50, 301) * dt
    tail = np.where(t < 0, -0.01 * np.exp(t / 1.5e-4) / 1.5e-4, 0.05 * np.exp(-t / 1e-3) / 1e-3) * dt
    h = np.zeros((3, 3, t.size))
    for a in range(3):
        h[a, a] = tail
        h[a, a, 50] += 1.0
    h[0, 1] = h[1, 0] = 0.03 * np.roll(tail, 7)
    h[2, 1] = 0.01 * tail
    return HardwareModel([Gain(0.98), Girf(h, dt, float(t[0]))]).frozen()


def test_the_range_realizer_gives_the_chain_on_the_window():
    """Any range of the window's fine samples, at its start, inside, at its end and the whole: the chain's realized
    gradient of the waveform alone (zero outside it), to round-off."""
    hw = _chain()
    r = RangeRealizer.for_chain(hw, DT, 3000)
    assert r is not None and r.n_taps < 3000  # the chain's memory (~4 ms) is shorter than the window (15 ms)
    rng = np.random.default_rng(3)
    for T in (3000, 2501):
        g = torch.as_tensor(np.cumsum(rng.normal(size=(2, 3, T)), axis=-1))  # two waveforms, all axes
        with torch.no_grad():
            G = hw(g, DT)[0]
        scale = float(G.abs().max())
        for lo, hi in ((0, 2), (0, 300), (1200, 1500), (T - 100, T), (0, T)):
            err = float((r(g, lo, hi) - G[..., lo:hi]).abs().max())
            assert err <= 1e-12 * scale, (T, lo, hi, err / scale)


def test_the_range_realizer_is_made_only_for_shift_invariant_chains_with_a_short_memory():
    assert RangeRealizer.for_chain(None, DT, 3000) is None  # ideal hardware: nothing to realize
    assert RangeRealizer.for_chain(HardwareModel([]), DT, 3000) is None
    assert RangeRealizer.for_chain(HardwareModel([Offset(0.1), Delay(3e-6)]), DT, 3000) is None  # affine offset
    # an eddy current's recursion starts at the record's first sample (not one response, shifted)
    assert RangeRealizer.for_chain(HardwareModel([ExpEddy(0.02, 1e-4)]), DT, 3000) is None
    # two effects with memory: the chain cuts the first one's output at the window's edges
    assert RangeRealizer.for_chain(HardwareModel([*_chain().effects, Delay(3e-6)]), DT, 3000) is None
    h = np.zeros((3, 3, 801))
    h[[0, 1, 2], [0, 1, 2], 400] = 1.0
    h[0, 0] += 1e-3 / 801
    assert RangeRealizer.for_chain(HardwareModel([Girf(h, 1e-5, -4e-3)]), DT, 1200) is None  # a response longer than W
    assert RangeRealizer.for_chain(HardwareModel([Delay(3e-6)]), DT, 3000) is not None


def test_a_window_residual_on_its_rows_range_equals_the_whole_window_one():
    """The residual rows (k at ADC samples and moments after the window's excitation, G during a later pulse, the
    change penalty) with the gradient realized only from that excitation to the last row: the rows of the chain on
    the whole window, with a refocusing pulse before the excitation (dropped: k restarts there) and one after it
    (kept); a query before every reset realizes the whole window."""
    from types import SimpleNamespace

    from dtoc.optimize.windowed import window_residual

    hw = _chain()
    Ne = 1201  # 12 ms of raster edges, 2401 fine samples
    T = 2 * Ne - 1
    r = RangeRealizer.for_chain(hw, DT, T)
    assert r is not None
    rng = np.random.default_rng(5)
    x = np.cumsum(rng.normal(size=(3, Ne)), axis=1)
    fr = np.zeros((3, Ne), dtype=bool)
    fr[:, 500:700] = True
    fmask = np.zeros((3, T), dtype=bool)
    fmask[:, 999:1400] = True
    fine = np.cumsum(rng.normal(size=(3, T)), axis=1)
    late, early = np.zeros(T, dtype=bool), np.zeros(T, dtype=bool)
    late[1765:1886] = True  # G-during-RF rows under the last pulse (9.12 ms +- 0.3 ms): past the last query
    early[1700:1760] = True  # or before it (the last query ends the range)
    sc = SimpleNamespace(k_axes=np.array([0, 1, 2]), rf=0.3, reg=0.01)
    t_adc = 1e-3 * np.array([5.2, 5.5, 6.01, 7.3])
    # pulses off the fine grid (k restarts within a sample)
    t_mom = 1e-3 * np.array([9.12349])
    rf_c, rf_u = [1e-3, 4.20237e-3, 6.5e-3, 9.1235e-3], ["refocusing", "excitation", "refocusing", "excitation"]
    T_ = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    xe = T_(x)[None]
    real_call = RangeRealizer.__call__
    calls = []

    def counted(self, g, n_lo, n_hi):
        calls.append(n_hi - n_lo)
        return real_call(self, g, n_lo, n_hi)

    cases = ((t_adc, late), (t_adc, early), (np.r_[0.5e-3, t_adc], early))  # the last: a query before the reset
    for t_a, rfm in cases:
        rows = (torch.as_tensor(fmask), T_(fine), T_(0.9 * fine), t_a, T_(rng.normal(size=(3, t_a.size))), t_mom,
                T_(rng.normal(size=(3, 1))), rf_c, rf_u, rfm, sc, T_([1.0, 2.0, 3.0]), T_([0.5, 0.5, 0.5]))  # fmt: skip
        with torch.no_grad():
            want = window_residual(hw, DT, *rows)(xe)
            RangeRealizer.__call__ = counted
            try:
                got = window_residual(hw, DT, *rows, r)(xe)
            finally:
                RangeRealizer.__call__ = real_call
        np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=0, atol=1e-11 * float(want.abs().max()))
    assert len(calls) == 2  # the query before every reset: the whole window by the chain
    assert calls[0] < T / 2  # from the excitation at 4.2 ms to the last pulse's G-during-RF samples at 9.4 ms


@pytest.mark.slow
def test_windows_realized_on_their_rows_range_give_the_whole_window_figures(monkeypatch):
    """A 3D GRE (16 periods, each cut into parts: parts carry k from a reference) solved period by period with the
    GIRF-like chain, twice: the residuals realized only on the fine samples their rows read give the window k errors
    and the edges of the residuals realized on the whole window.  The residuals agree to round-off; ADMM, stopped at
    its tolerance, carries that round-off into the committed edges and through them into the later windows, so the
    runs agree to that tolerance (the CLI's 3D FLASH cut: 1.5e-4 mT/m, k figures to 7 digits)."""
    import tempfile
    from pathlib import Path

    from dtoc.optimize import loss as L
    from dtoc.optimize.config import load_config
    from dtoc.optimize.run import free_edges, limits_and_sources
    from dtoc.optimize.windowed import windowed_warm_start
    from dtoc.seq.load import load_sequence
    from tests.foreign.writers import gre3d

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "g.seq"
        p.write_bytes(gre3d(n=8, nz=2))
        ir = load_sequence(p)
    hw = _chain()
    cfg = load_config(ir.kind, None).model_copy(update={"gmax_mT_per_m": 32, "smax_T_per_m_per_s": 130})
    lim, _ = limits_and_sources(ir, cfg)
    free = free_edges(ir)
    ctx = L.build_context(ir, lim)
    causal, acausal = memory_s(hw)
    calls = []
    real_call = RangeRealizer.__call__

    def counted(self, g, n_lo, n_hi):
        calls.append((g.shape[-1], n_hi - n_lo))
        return real_call(self, g, n_lo, n_hi)

    monkeypatch.setattr(RangeRealizer, "__call__", counted)
    out = {}
    for on in (True, False):
        out[on] = windowed_warm_start(
            ir, hw, lim, free, cfg.weights, ctx, horizon_s=causal, lookahead_s=acausal, k_tol_dk=0.01,
            realize_range=on, dense_max=1200, part_max=600,
        )  # fmt: skip
    (e1, s1), (e0, s0) = out[True], out[False]
    assert s1.windows > 2 * 16  # parts
    assert len(calls) >= s1.windows // 2 and all(m < T for T, m in calls)  # the range, for most windows
    assert np.abs(e0 - ir.edge_grad_mT_per_m).max() > 1.0  # the chain needs a change of the edges (mT/m)
    assert np.nanmax(s0.unconstrained_adc_dk) > 1e-6  # and the figures compared are not all zero
    # dk: 1e-3 of the run's tolerance (the runs differ by ~1.5e-6 dk here, ADMM's slack; a row read outside the range
    # would be off by the chain's whole effect on k)
    for a, b in ((s1.window_adc_dk, s0.window_adc_dk), (s1.window_moment_dk, s0.window_moment_dk)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)
    np.testing.assert_allclose(s1.unconstrained_adc_dk, s0.unconstrained_adc_dk, rtol=0, atol=1e-5)
    assert np.abs(e1 - e0).max() <= 1e-3  # mT/m
