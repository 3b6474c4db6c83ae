"""Windows whose core is a part of an excitation period (long echo trains: TSE, HASTE, long EPI periods), and the
TSE sequence kind."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dtoc.hardware.effects import Delay, ExpEddy
from dtoc.hardware.memory import memory_s
from dtoc.hardware.model import HardwareModel


def _load(data: bytes):
    import tempfile
    from pathlib import Path

    from dtoc.seq.load import load_sequence

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "s.seq"
        p.write_bytes(data)
        return load_sequence(p)


@pytest.fixture(scope="module")
def tse16():
    """A CPMG TSE, 16 lines, 4 echoes per excitation (10 ms spacing): periods of ~7,460 free variables
    (> DENSE_MAX = 6000), and an eddy-current + delay chain."""
    from foreign.writers import tse

    from dtoc.optimize.run import free_edges

    ir = _load(tse(n=16, etl=4))
    hw = HardwareModel([ExpEddy(0.02, 1e-3), Delay(6e-6)]).frozen()
    return ir, hw, free_edges(ir)


def test_long_periods_are_cut_into_parts_after_pulses(tse16):
    from dtoc.optimize.windowed import (
        DENSE_MAX,
        PART_MAX,
        core_blocks,
        core_free_counts,
        period_free_counts,
        period_starts,
        plan_windows,
    )

    ir, hw, free = tse16
    assert period_free_counts(ir, free).max() > DENSE_MAX  # the case: a period too large to solve densely
    cores = core_blocks(ir, free)
    n = core_free_counts(ir, free)
    assert n.max() <= PART_MAX
    # the cores tile the blocks; every period begins a core, which says so; parts end right after a pulse
    assert cores[0][0] == 0 and cores[-1][1] == len(ir.block_edges_s) - 1
    assert all(a[1] == b[0] for a, b in zip(cores, cores[1:]))
    starts = set(period_starts(ir))
    assert {c[0] for c in cores if c[2]} == starts and not any(c[0] in starts for c in cores if not c[2])
    rf_blocks = {r.block for r in ir.rf}
    cut = [c for c, d in zip(cores, cores[1:]) if not d[2]]  # parts followed by a part of the same period
    assert len(cut) >= 4 * 4  # 4 periods of 4 echoes
    # a part ends right after a pulse, or holds none (then it ends where it is full)
    assert all(e - 1 in rf_blocks or not rf_blocks & set(range(s, e)) for s, e, _ in cut)
    assert sum(e - 1 in rf_blocks for s, e, _ in cut) >= 4 * 3
    assert n.sum() == period_free_counts(ir, free).sum()  # nothing lost or counted twice
    # a period that fits stays one core: the plan of periods is unchanged (README job, goldens)
    c, a = memory_s(hw)
    old = plan_windows(ir, c, a)
    big = plan_windows(ir, c, a, free, dense_max=10**9)
    assert [(w.core, w.sub, w.adc, w.rf, w.moment_rf, w.rfterm_rf) for w in old] == [
        (w.core, w.sub, w.adc, w.rf, w.moment_rf, w.rfterm_rf) for w in big
    ]
    # a part's terms: its own pulses' moments and G during RF (the last part: the next excitation's too), no
    # excitation of its own
    parts = [w for w in plan_windows(ir, c, a, free) if not w.starts_period]
    assert parts and all(
        ir.rf[i].use == "refocusing" or (ir.rf[i].excites and ir.rf[i].block == w.core[1])
        for w in parts
        for i in w.moment_rf
    )


def test_carried_k_follows_the_refocusing_pulses(tse16):
    """The k carried into each part (the committed realized k at its reference time, chained part by part) equals
    the realized k of the whole sequence there: through 16 refocusing pulses, each of which negates k (a carry
    that ignored the negation is off by 2|k|, > 16 dk here)."""
    from dtoc.optimize.windowed import PAD_S, active_edges, carried_k, carry_sign, part_reference_s, plan_windows

    ir, hw, free = tse16
    c, a = memory_s(hw)
    ws = plan_windows(ir, c, a, free, part_max=1200)  # parts of about half an echo: chains of carries
    base_fine = np.asarray(ir.grad_mT_per_m, dtype=np.float64)
    edges = np.array(ir.edge_grad_mT_per_m, dtype=np.float64)
    act = active_edges(ir, PAD_S)
    with torch.no_grad():
        G = hw(torch.as_tensor(base_fine)[None], ir.dt_fine_s)[0][0]
    be = ir.block_edges_s
    dk = float(ir.dk_rad_per_m[0])
    k = np.zeros(3)
    t_ref = 0.0
    got, want, crossed = [], [], 0
    for w in ws:
        if w.starts_period:
            exc = [i for i in w.rf if ir.rf[i].excites and ir.rf[i].block == w.core[0]]
            t_ref, k = ir.rf[exc[0]].t_center_s, np.zeros(3)
            continue
        t_from, k_from = t_ref, k
        t_ref = part_reference_s(ir, w, a, t_from)
        k = carried_k(
            ir, hw, edges, base_fine, free, act, t_from, t_ref, k_from, round(be[w.core[0]] / ir.raster_s), c, a
        )
        ref = ir.kspace_rad_per_m(G, times_s=np.array([t_ref]))[:, 0].numpy()
        got.append(k)
        want.append(ref)
        between = [r for r in ir.rf if t_from <= r.t_center_s < t_ref and r.use == "refocusing"]
        crossed += bool(between) and abs(k_from[0]) > dk
    got, want = np.array(got), np.array(want)
    assert crossed >= 8  # chains that carry |k_x| > 1 dk through a refocusing pulse
    assert np.abs(got - want)[:, :2].max() < 1e-3 * dk  # readout and phase axes, to 0.001 dk
    assert np.abs(got - want).max() < 1e-6 * np.abs(want).max() + 1e-3 * dk
    # the sign rule itself: -1 per refocusing pulse passed, 0 after an excitation
    s = carry_sign(np.array([0.0, 1.0, 2.0, 3.0]), [0.5, 1.5, 2.5], ["refocusing", "refocusing", "excitation"])
    assert s.tolist() == [1.0, -1.0, 1.0, 0.0]


@pytest.mark.slow
def test_sub_period_windows_match_the_whole_solve(tse16):
    """The TSE solved part by part (cores of at most 1,200 free variables, 9 per 4-echo period) reaches the k
    errors of the whole-sequence solve within 1e-3 dk (a tenth of the default k tolerance), from 0.157 dk: measured
    1.4e-4 dk in parts, 4.1e-6 dk whole (400 iterations), 7.2e-4 dk with whole-period windows."""
    from dtoc.optimize import loss as L
    from dtoc.optimize import optimizer as O
    from dtoc.optimize.config import load_config
    from dtoc.optimize.limits import EdgeProjector
    from dtoc.optimize.run import limits_and_sources
    from dtoc.optimize.twin import EdgeTwin
    from dtoc.optimize.windowed import windowed_warm_start

    ir, hw, free = tse16
    cfg = load_config(ir.kind, None).model_copy(update={"gmax_mT_per_m": 32, "smax_T_per_m_per_s": 130})
    lim, _ = limits_and_sources(ir, cfg)
    ctx = L.build_context(ir, lim)
    P = EdgeProjector(ir.edge_grad_mT_per_m, free, ir.raster_s, lim)
    twin = EdgeTwin(ir, hw, P)
    c, a = memory_s(hw)
    e_parts, st = windowed_warm_start(ir, hw, lim, free, cfg.weights, ctx, horizon_s=c, lookahead_s=a, part_max=1200)
    e_whole = O.warm_start(twin, ctx, cfg.weights, 400)

    def err(e):
        with torch.no_grad():
            k = twin.forward_edges(torch.as_tensor(np.asarray(e)), moments=False).kspace_rad_per_m
        er = ((k - ctx.k0_rad_per_m).abs() / ctx.dk_rad_per_m[:, None]).numpy()
        return float(np.nanmax(np.where(np.isfinite(er), er, 0)[:2]))

    assert st.windows > 4 * 4 and st.max_free <= 1200  # parts, not periods
    assert P.is_feasible(e_parts)
    assert np.array_equal(e_parts[~P.free], P.base[~P.free])
    base, parts, whole = err(P.base), err(e_parts), err(e_whole)
    assert base > 0.05
    assert parts < 1e-3, (parts, whole)  # a tenth of the solver's default tolerance (0.01 dk)
    assert abs(parts - whole) < 1e-3, (parts, whole)


def test_a_spin_echo_train_is_a_tse(tse16):
    from foreign.writers import se_epi, tse

    from dtoc.optimize.config import KIND_DEFAULTS, load_config
    from dtoc.optimize.run import why_not_windowed

    ir, hw, free = tse16
    assert ir.kind == "tse"
    assert any("kind guessed from the readout pattern: tse" in n for n in ir.meta.get("notes", []))
    assert _load(tse(n=16, single_shot=True)).kind == "tse"  # HASTE: one excitation, one train
    assert _load(se_epi(n=16)).kind == "epi"  # one refocusing pulse, then an EPI train: not a TSE
    cfg = load_config("tse", None)
    assert cfg.iters == 0 and cfg.weights.image > 0 and KIND_DEFAULTS["tse"]["iters"] == 0
    # its long periods are windowed in parts, by 'auto' too; a long period of another kind only when asked for
    # (windowed: on)
    assert why_not_windowed(ir, hw, cfg.model_copy(update={"windowed": "on"}), free) is None
    assert why_not_windowed(ir, hw, cfg, free) is None
    ir.kind = "epi"
    try:
        assert "windowed: on solves them in parts" in (why_not_windowed(ir, hw, cfg, free) or "")
    finally:
        ir.kind = "tse"


def _two_sided_girf(acausal_s: float = 5e-3, causal_s: float = 10e-3):
    """A GIRF-like kernel (3x3, dt 10 us) with memory on both sides: a unit tap, a -1 % acausal tail over
    ``acausal_s`` / 3 and a +5 % causal one of 3 ms (an eddy current), no cross terms; and a 6 us delay."""
    from dtoc.hardware.effects import Girf

    dt = 1e-5
    t = np.arange(-round(acausal_s / dt), round(causal_s / dt) + 1) * dt
    tail = np.where(t < 0, -0.01 * np.exp(t / (acausal_s / 3)) / (acausal_s / 3), 0.0)
    tail += np.where(t > 0, 0.05 * np.exp(-t / 3e-3) / 3e-3, 0.0)
    h = np.zeros((3, 3, t.size))
    for a in range(3):
        h[a, a] = tail * dt
        h[a, a, np.argmin(np.abs(t))] += 1.0
    return HardwareModel([Girf(h, dt, float(t[0])), Delay(6e-6)]).frozen()


def test_a_part_window_holds_the_memory_of_what_it_integrates(tse16):
    """A part integrates its k from its reference (its acausal memory before the core), so its window must hold the
    causal memory before that reference: then the realized gradient of the window's waveform alone equals the whole
    sequence's from the reference to the core's end, and so does its k.  A window whose history started at the
    core's start - horizon (before this change) misses the waveform before it: with this two-sided chain the part's
    k was off by 0.073 dk (now 7e-15; with the measured KCL 7 T GIRF on this TSE, windows that saw 1e-4 dk ended at
    0.07 dk)."""
    from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
    from dtoc.optimize.windowed import part_reference_s, plan_windows

    ir, _, free = tse16
    hw = _two_sided_girf()
    c, a = memory_s(hw)
    assert a >= 4e-3 and c >= 9e-3  # memory on both sides (the case)
    base_fine = torch.as_tensor(np.asarray(ir.grad_mT_per_m, dtype=np.float64))
    with torch.no_grad():
        G = hw(base_fine[None], ir.dt_fine_s)[0][0].numpy()
    be, dtf = ir.block_edges_s, ir.dt_fine_s
    dk = float(ir.dk_rad_per_m[0])
    worst, n = 0.0, 0
    t_ref = 0.0
    for w in plan_windows(ir, c, a, free, part_max=1200):
        if w.starts_period:
            t_ref = be[w.core[0]]
            continue
        t_ref = part_reference_s(ir, w, a, t_ref)
        m0, m1 = round(be[w.sub[0]] / dtf), round(be[w.sub[1]] / dtf)
        with torch.no_grad():
            Gw = hw(base_fine[None, :, m0 : m1 + 1], dtf)[0][0].numpy()
        r0, r1 = round(t_ref / dtf), round(be[w.core[1]] / dtf)
        dG = Gw[:2, r0 - m0 : r1 - m0] - G[:2, r0:r1]  # readout and phase axes
        worst = max(worst, float(np.abs(np.cumsum(dG, axis=1)).max()) * dtf * GAMMA_RAD_PER_S_PER_MT / dk)
        n += 1
    assert n >= 16
    assert worst < 1e-3, worst  # k from the reference to the core's end, dk
