"""Windowed (period-by-period) optimization of long sequences, overlap-add convolution, hardware memory."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dtoc.hardware import convolution as C
from dtoc.hardware.effects import Delay, ExpEddy, Girf, SlewLimit
from dtoc.hardware.memory import is_affine, memory_s
from dtoc.hardware.model import HardwareModel


def _mprage_ir(shots: int = 2):
    import tempfile
    from pathlib import Path

    from dtoc.seq.load import load_sequence
    from tests.foreign.writers import mprage

    data = mprage(n=8, nz=2, tr=8e-3, ti=0.06, tr_shot=0.2, shots=shots)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "mp.seq"
        p.write_bytes(data)
        return load_sequence(p)


def test_memory_of_effects():
    m = HardwareModel([ExpEddy(0.01, 2e-3), Delay(4e-6)])
    causal, acausal = memory_s(m, tol=1e-6)
    assert causal == pytest.approx(2e-3 * math.log(0.01 / 1e-6) + 4e-6, rel=1e-12)
    assert acausal == 0.0
    h = np.zeros((3, 3, 101))
    h[[0, 1, 2], [0, 1, 2], 50] = 1.0
    causal, acausal = memory_s(HardwareModel([Girf(h, 1e-5, t0_s=-5e-4)]))
    assert (causal, acausal) == pytest.approx((5e-4, 5e-4), abs=1e-12)
    assert is_affine(m) and is_affine(None)
    assert not is_affine(HardwareModel([SlewLimit(100.0)]))


def test_overlap_add_equals_one_fft(monkeypatch):
    rng = np.random.default_rng(3)
    g = torch.as_tensor(rng.standard_normal((2, 3, 5000)))
    h = torch.as_tensor(rng.standard_normal((4, 3, 301)))
    ref = C.fft_convolve(g, h, -120)
    monkeypatch.setattr(C, "OLA_MIN", 1000)
    monkeypatch.setattr(C, "OLA_BLOCK", 512)
    ola = C.fft_convolve(g, h, -120)
    assert C.conv_length(5000, 301)[1] == 1024  # the blocked path ran
    np.testing.assert_allclose(ola.numpy(), ref.numpy(), rtol=0, atol=1e-11)


def test_projection_of_a_feasible_point_is_the_identity():
    from dtoc.optimize.limits import EdgeProjector, Limits

    rng = np.random.default_rng(0)
    e = np.cumsum(rng.uniform(-0.3, 0.3, (3, 400)), axis=1)
    e[:, 0] = e[:, -1] = 0
    free = np.ones_like(e, dtype=bool)
    free[:, [0, -1]] = False
    P = EdgeProjector(e, free, 1e-5, Limits(40.0, 200.0))
    x = P.project(e * 0.5, n_iter=60)
    assert P.is_feasible(x)
    assert np.array_equal(P.project(x, n_iter=60), x)


@pytest.fixture(scope="module")
def solved():
    """A 2-shot MPRAGE-like sequence (0.4 s) pre-compensated whole and period by period."""
    from dtoc.optimize import loss as L
    from dtoc.optimize import optimizer as O
    from dtoc.optimize.config import load_config
    from dtoc.optimize.limits import EdgeProjector
    from dtoc.optimize.run import free_edges, limits_and_sources
    from dtoc.optimize.twin import EdgeTwin
    from dtoc.optimize.windowed import windowed_warm_start

    ir = _mprage_ir()
    hw = HardwareModel([ExpEddy(0.01, 2e-3), Delay(4e-6)]).frozen()
    cfg = load_config(ir.kind, None).model_copy(update={"gmax_mT_per_m": 32, "smax_T_per_m_per_s": 130})
    lim, _ = limits_and_sources(ir, cfg)
    free = free_edges(ir)
    ctx = L.build_context(ir, lim)
    P = EdgeProjector(ir.edge_grad_mT_per_m, free, ir.raster_s, lim)
    twin = EdgeTwin(ir, hw, P)
    causal, acausal = memory_s(hw)
    e_win, st = windowed_warm_start(
        ir,
        hw,
        lim,
        free,
        cfg.weights,
        ctx,
        horizon_s=causal,
        lookahead_s=acausal,
    )
    e_whole = O.warm_start(twin, ctx, cfg.weights, 400)  # the fixed count this comparison was made with
    out = {"ir": ir, "P": P, "st": st, "ctx": ctx}
    with torch.no_grad():
        for name, e in (("base", P.base), ("win", e_win), ("whole", e_whole)):
            k = twin.forward_edges(torch.as_tensor(np.asarray(e)), moments=False).kspace_rad_per_m
            err = (k - ctx.k0_rad_per_m).abs().numpy() / ctx.dk_rad_per_m.numpy()[:, None]
            out[name] = float(np.nanmax(np.where(np.isfinite(err), err, 0)[:2]))
            out["e_" + name] = np.asarray(e)
    return out


@pytest.mark.slow
def test_windowed_matches_whole_sequence_solve(solved):
    s = solved
    assert s["P"].is_feasible(s["e_win"])
    assert s["base"] > 0.01  # the model moves k by a percent of dk or more
    assert s["win"] < 1e-3  # period by period reaches the whole solve's accuracy ...
    assert s["win"] <= max(3 * s["whole"], 1e-4)  # ... within a factor of it
    st = s["st"]
    assert st.windows == 2 * 8 + 1  # one per excitation (8 per shot) + the lead-in before the first
    assert st.structures < st.windows  # repeated periods share one Jacobian


@pytest.mark.slow
def test_windowed_changes_only_free_edges(solved):
    s = solved
    P = s["P"]
    assert np.array_equal(s["e_win"][~P.free], P.base[~P.free])


@pytest.mark.slow
def test_identical_periods_share_one_solve():
    """Three identical shots (one partition): each TR of shots 2 and 3 takes the solution of the same TR of shot 1
    (the manifest lists them as solved as one), and the result equals solving every window to 1e-3 mT/m."""
    import tempfile
    from pathlib import Path

    from dtoc.optimize import loss as L
    from dtoc.optimize.config import load_config
    from dtoc.optimize.limits import EdgeProjector
    from dtoc.optimize.run import free_edges, limits_and_sources
    from dtoc.optimize.windowed import windowed_warm_start
    from dtoc.seq.load import load_sequence
    from tests.foreign.writers import mprage

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "mp.seq"
        p.write_bytes(mprage(n=8, nz=1, tr=8e-3, ti=0.06, tr_shot=0.2, shots=3))
        ir = load_sequence(p)
    hw = HardwareModel([ExpEddy(0.01, 2e-3), Delay(4e-6)]).frozen()
    cfg = load_config(ir.kind, None).model_copy(update={"gmax_mT_per_m": 32, "smax_T_per_m_per_s": 130})
    lim, _ = limits_and_sources(ir, cfg)
    free = free_edges(ir)
    ctx = L.build_context(ir, lim)
    c, a = memory_s(hw)
    runs = {
        r: windowed_warm_start(ir, hw, lim, free, cfg.weights, ctx, horizon_s=c, lookahead_s=a, reuse=r)
        for r in (True, False)
    }
    e, st = runs[True]
    assert st.reused >= 14 and runs[False][1].reused == 0
    groups = st.as_dict()["solved_as_one"]
    assert {"windows": 3, "runs": [[1, 1], [9, 9], [17, 17]]} in groups  # TR 1 of each shot
    assert np.abs(e - runs[False][0]).max() < 1e-3
    assert EdgeProjector(ir.edge_grad_mT_per_m, free, ir.raster_s, lim).is_feasible(e)


@pytest.mark.parametrize("contiguous", [False, True])
def test_window_jacobian_equals_unit_perturbations(contiguous):
    """The impulse-response Jacobian (window_jacobian) against one forward per free edge through the window's
    residual: acausal taps, a cross term, an exponential, a delay, an offset; excitation, refocusing and an
    'undefined' pulse (which excites) among the ADC samples; fine samples that do not follow the edges.  Free edges
    scattered (most columns' taps partly held: the tap-by-tap path) or in one run per axis (the hat path's
    strided rows)."""
    from types import SimpleNamespace

    from dtoc.hardware.effects import CrossEddy, Lti, Offset
    from dtoc.optimize import window_jacobian as WJ
    from dtoc.optimize.windowed import window_residual

    rng = np.random.default_rng(5)
    dt, Ne = 5e-6, 601
    W = 2 * Ne - 1
    taps = np.zeros((3, 41))
    taps[:, :] = 0.02 * rng.standard_normal((3, 41))
    hw = HardwareModel(
        [Lti(taps, dt, t0_s=-20 * dt), CrossEddy(0.03, 1e-4, axis="y", input_axis="x"), ExpEddy(0.02, 3e-4),
         Delay(7e-6), Offset(0.1)]
    ).frozen()  # fmt: skip
    fr = np.zeros((3, Ne), dtype=bool)
    fr[:, 150:450] = True if contiguous else rng.random((3, 300)) < 0.5
    fmask = np.zeros((3, W), dtype=bool)
    fmask[:, ::2] = fr
    fmask[:, 1::2] = fr[:, 1:] | fr[:, :-1]
    fmask[1, 600:640] = False  # samples that keep the played value although an edge is free
    rf_c, rf_u = [0.4e-3, 1.6e-3, 2.3e-3, 2.9e-3], ["excitation", "refocusing", "undefined", "refocusing"]
    t_adc = np.sort(rng.uniform(0.0, (W - 1) * dt, 300))
    t_mom = np.array(rf_c[1:]) - 1e-9
    rfm = np.zeros(W, dtype=bool)
    rfm[300:340] = True
    sc = SimpleNamespace(
        k_axes=np.array([0, 2]), k=np.array([0.3, 0.5, 0.7]), m=np.array([0.2, 0.4, 0.6]), rf=1.3, reg=0.05
    )
    x = rng.standard_normal((3, Ne))
    fine = torch.as_tensor(rng.standard_normal((3, W)))
    g0 = torch.as_tensor(rng.standard_normal((3, W)))
    T = torch.as_tensor
    res = window_residual(
        hw, dt, T(fmask), fine, g0, t_adc, T(np.zeros((3, t_adc.size))), t_mom, T(np.zeros((3, t_mom.size))),
        rf_c, rf_u, rfm, sc, T(sc.k), T(sc.m),
    )  # fmt: skip
    idx = np.flatnonzero(fr.ravel())
    X = np.repeat(x[None], idx.size + 1, 0).reshape(idx.size + 1, -1)
    X[np.arange(1, idx.size + 1), idx] += 1.0
    with torch.no_grad():
        r = res(T(X.reshape(-1, 3, Ne))).numpy()
    J_ref = (r[1:] - r[0]).T
    R = WJ.impulse_responses(hw, dt, W)
    J = WJ.lti_jacobian(R, dt, fr, fmask, t_adc, t_mom, rf_c, rf_u, rfm, sc.k_axes, sc.k, sc.m, sc.rf)
    S = WJ.reg_rows(fr, fmask, sc.reg).toarray()
    full = np.concatenate([J, S], 0)
    assert full.shape == J_ref.shape
    assert np.abs(J_ref).max() > 1.0  # k rows: gamma * dt * scale is large
    np.testing.assert_allclose(full, J_ref, rtol=0, atol=1e-9 * np.abs(J_ref).max())


def test_report_span_and_trimmed_waveforms():
    """plotted_span counts exactly the fine samples the report's mask selected (t <= t_end + 1 ps) on the
    shipped EPI and GRE, and quality() with waveform_samples keeps that prefix of the whole-sequence
    waveforms, equal to the full arrays' prefix, with the k-space figures unchanged."""
    from pathlib import Path

    from dtoc.optimize.limits import EdgeProjector, Limits
    from dtoc.optimize.loss import build_context
    from dtoc.optimize.report import plotted_span
    from dtoc.optimize.run import free_edges, quality
    from dtoc.optimize.twin import EdgeTwin
    from dtoc.seq.load import load_sequence

    root = Path(__file__).resolve().parents[1]

    for name in ("epi_small.seq", "gre_small.seq"):
        ir = load_sequence(root / "sequences" / name)
        n, t_end = plotted_span(ir)
        assert n == int(np.sum(ir.t_fine_s <= t_end + 1e-12))
        assert 1 < n < ir.n_fine
    lim = Limits(40.0, 180.0)
    proj = EdgeProjector(ir.edge_grad_mT_per_m, free_edges(ir), ir.raster_s, lim)
    twin = EdgeTwin(ir, HardwareModel([ExpEddy(0.01, 2e-3), Delay(4e-6)]).frozen(), proj)
    ctx = build_context(ir, lim)
    full = quality(twin, None, ctx, ir.grad_mT_per_m)
    part = quality(twin, None, ctx, ir.grad_mT_per_m, waveform_samples=n)
    assert full["_G"].shape == (3, ir.n_fine) and part["_G"].shape == (3, n)
    assert np.array_equal(part["_G"], full["_G"][:, :n]) and np.array_equal(part["_g"], full["_g"][:, :n])
    assert part["_G"].base is None or part["_G"].base.shape == (3, n)  # not a view of the whole waveform
    assert part["kspace_max_dk"] == full["kspace_max_dk"] and np.array_equal(part["_k"], full["_k"])


def test_rf_mask_by_bisection_equals_the_comparison():
    """rf_mask_fine (one bisection per pulse, linear in the duration) marks exactly the fine samples with
    t_start - 1 ps <= t <= t_end + 1 ps of some pulse, as the whole-array comparison per pulse did."""
    from dtoc.optimize.loss import rf_mask_fine

    ir = _mprage_ir(shots=3)
    t = ir.t_fine_s
    want = np.zeros(t.shape, dtype=bool)
    for r in ir.rf:
        want |= (t >= r.t_start_s - 1e-12) & (t <= r.t_start_s + r.duration_s + 1e-12)
    got = rf_mask_fine(ir)
    assert len(ir.rf) > 20 and want.sum() > 100
    assert np.array_equal(got, want)


def _idle_gre_ir(reps: int, idle_edges: int = 8000, r_s: float = 1e-4, n: int = 16, fov_m: float = 0.032):
    """``reps`` identical spoiled-GRE periods on a ``r_s`` raster (0.1 ms: RF 2 ms, prewinder, ``n``-sample readout
    of dwell ``r_s``, spoiler), each followed by an idle delay of ``idle_edges`` rasters (0.8 s): a long sequence
    whose whole-sequence arrays are large and whose windows and period structures are small."""
    from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
    from dtoc.seq.ir import ADCEvent, RFEvent, SequenceIR, edges_to_fine

    per = 84 + n + idle_edges
    gr = 2 * np.pi / fov_m / (GAMMA_RAD_PER_S_PER_MT * r_s)
    e = np.zeros((3, per * reps + 1))
    rf, adc, edges_s = [], [], []
    for r in range(reps):
        o = r * per
        e[0, o + 21 : o + 25] = -(n // 2 + 1) * gr / 4.0
        e[0, o + 25 : o + 26 + n] = gr
        e[0, o + 26 + n : o + 36 + n] = 17.6
        e[1, o + 21 : o + 25] = 2 * gr / 4.0
        e[1, o + 26 + n : o + 30 + n] = -2 * gr / 4.0
        rf.append(RFEvent(3 * r, o * r_s, o * r_s + 10 * r_s, 20 * r_s, np.deg2rad(15), 0.0, 0.0, "excitation"))
        adc.append(ADCEvent(block=3 * r + 1, t_start_s=o * r_s + 25 * r_s, num_samples=n, dwell_s=r_s))
        edges_s += [o * r_s, o * r_s + 20 * r_s, (o + 84 + n) * r_s]
    edges_s.append(per * reps * r_s)
    free = np.zeros((3, 2 * e.shape[1] - 1), bool)
    fe = (np.arange(e.shape[1]) % per) >= 20
    fe[-1] = False
    free[:2, ::2] = fe
    return SequenceIR(
        raster_s=r_s, grad_mT_per_m=edges_to_fine(e), block_edges_s=np.array(edges_s), rf=rf, adc=adc,
        free_mask=free, fov_m=(fov_m, fov_m, fov_m), matrix=(n, n), kind="gre", readout_axis=0, phase_axis=1,
    )  # fmt: skip


def _solve_peak_bytes(reps: int) -> tuple[int, int, object]:
    """(tracemalloc peak of the windowed solve beyond what existed before it, bytes of its result, the IR) of
    :func:`_idle_gre_ir` (numpy allocations; the solve's torch work is per window)."""
    import tracemalloc

    from dtoc.hardware.effects import Lti
    from dtoc.optimize import loss as L
    from dtoc.optimize.config import load_config
    from dtoc.optimize.run import free_edges, limits_and_sources
    from dtoc.optimize.windowed import windowed_warm_start

    ir = _idle_gre_ir(reps)
    taps = -0.05 * np.exp(-np.arange(40) / 8.0)[None].repeat(3, 0)  # an eddy-like 2 ms tail, applied by FFT
    hw = HardwareModel([Lti(taps, 5e-5), Delay(4e-6)]).frozen()
    cfg = load_config(ir.kind, None).model_copy(update={"gmax_mT_per_m": 32, "smax_T_per_m_per_s": 130})
    lim, _ = limits_and_sources(ir, cfg)
    free = free_edges(ir)
    ctx = L.build_context(ir, lim)
    c, a = memory_s(hw)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        before = tracemalloc.get_traced_memory()[0]
        e, st = windowed_warm_start(ir, hw, lim, free, cfg.weights, ctx, horizon_s=c, lookahead_s=a)
        peak = tracemalloc.get_traced_memory()[1] - before
    finally:
        tracemalloc.stop()
    assert st.windows == reps and st.structures <= 4
    return peak, e.nbytes, ir


def test_windowed_solve_memory_does_not_grow_with_the_duration():
    """A 4x longer sequence (12 identical 0.81 s periods against 3, the same period structures) is solved within
    1.2x the peak memory of the solve, its result (the (3, N+1) edges, 24 bytes per raster step) left out: the
    solve holds one window, the per-structure matrices and the recent solutions, not a copy of the whole waveform
    (the played waveform is 48 bytes per raster step, 0.39 MB a period here; the solve that kept one: 1.26x)."""
    _solve_peak_bytes(1)  # first-call allocations (lazy imports, caches) out of the comparison
    p1, r1, ir1 = _solve_peak_bytes(3)
    p4, r4, ir4 = _solve_peak_bytes(12)
    assert ir4.duration_s == pytest.approx(4 * ir1.duration_s, rel=1e-9)
    assert r4 > 3.9 * r1
    extra1, extra4 = p1 - r1, p4 - r4
    assert extra1 > 0
    assert extra4 <= 1.2 * extra1, (extra1, extra4)


def test_a_window_admm_leaves_above_the_tolerance_runs_on_to_it(monkeypatch):
    """The windows' ADMM stops on a relative residual; where that leaves a window's own k error (an ADC sample or
    an RF pulse's moment) above half the run's k tolerance, the window runs on from there until it is within.
    Made visible with a deliberately loose ADMM tolerance (0.3) on a 1-shot MPRAGE-like base at 60 T/m/s (every
    window limit-bound): without the k tolerance a moment is left at ~0.03 dk, with it every window ends within
    0.005 dk and the windows that ran on are counted."""
    import dtoc.optimize.windowed as W
    from dtoc.optimize import loss as L
    from dtoc.optimize.config import load_config
    from dtoc.optimize.run import free_edges, limits_and_sources

    ir = _mprage_ir(shots=1)
    hw = HardwareModel([ExpEddy(0.01, 2e-3), Delay(4e-6)]).frozen()
    cfg = load_config(ir.kind, None).model_copy(update={"gmax_mT_per_m": 32, "smax_T_per_m_per_s": 60})
    lim, _ = limits_and_sources(ir, cfg)
    free, ctx = free_edges(ir), L.build_context(ir, lim)
    causal, acausal = memory_s(hw)
    monkeypatch.setattr(W, "ADMM_TOL", 0.3)
    worst = {}
    for tol in (None, 0.01):
        _, st = W.windowed_warm_start(
            ir, hw, lim, free, cfg.weights, ctx, horizon_s=causal, lookahead_s=acausal, k_tol_dk=tol
        )
        assert st.window_adc_dk is not None and st.window_moment_dk is not None
        worst[tol] = max(np.nanmax(st.window_adc_dk), np.nanmax(st.window_moment_dk))
        assert (st.refined > 0) == (tol is not None)
    assert worst[None] > 0.01  # the loose stop is visible
    assert worst[0.01] <= W.REFINE_SHARE * 0.01
