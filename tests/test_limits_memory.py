"""The limits of a long sequence without whole-length copies (issue 32 point 2): the reachability envelopes computed
piece by piece are the whole-sequence sweep's bit for bit, and a projector that only checks feasibility (a windowed
run's export) holds nothing of the sequence's length beyond its masks."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from dtoc.errors import LimitError
from dtoc.optimize import limits as L
from dtoc.optimize.limits import EdgeProjector, Limits

RASTER = 10e-6
LIM = Limits(gmax_mT_per_m=32.0, smax_T_per_m_per_s=130.0)


def _case(seed: int, n: int, p_free: float):
    """A random walk within the limits, its samples held with probability ``1 - p_free`` (axis y all free)."""
    rng = np.random.default_rng(seed)
    S = LIM.step_max_mT_per_m(RASTER)
    e = np.clip(np.cumsum(rng.uniform(-S, S, size=(3, n)), axis=1), -25.0, 25.0)
    free = rng.random((3, n)) < p_free
    free[1] = True
    return e, free


def _brute_envelopes(e, free):
    """The definition: hi[n] = min(G, min over held j of e_j + S |n - j|), lo likewise (O(n x held))."""
    G, S = LIM.gmax_eff_mT_per_m, LIM.step_max_mT_per_m(RASTER)
    n = e.shape[1]
    lo, hi = np.full(e.shape, -G), np.full(e.shape, G)
    for a in range(3):
        j = np.flatnonzero(~free[a])
        if j.size:
            dist = S * np.abs(np.arange(n)[:, None] - j[None, :])
            hi[a] = np.minimum(G, (e[a, j][None, :] + dist).min(axis=1))
            lo[a] = np.maximum(-G, (e[a, j][None, :] - dist).max(axis=1))
        lo[a, j], hi[a, j] = e[a, j], e[a, j]
    return lo, hi


@pytest.mark.parametrize("seed,p_free", [(0, 0.95), (1, 0.5), (2, 0.995)])
def test_envelopes_in_pieces_are_the_whole_sweep_bit_for_bit(monkeypatch, seed, p_free):
    """Pieces of 1, 7 and 64 edges (carries across many borders, held samples on them) give the one-piece envelopes
    bit for bit, which are the definition's to rounding; feasibility and the projection are the same."""
    e, free = _case(seed, 1500, p_free)
    whole = EdgeProjector(e, free, RASTER, LIM)
    lo, hi = whole.lo.copy(), whole.hi.copy()
    blo, bhi = _brute_envelopes(e, free)
    assert np.allclose(lo, blo, rtol=0, atol=1e-9) and np.allclose(hi, bhi, rtol=0, atol=1e-9)
    assert (hi - lo).min() >= 0 and np.ptp(hi[0]) > 1.0  # tight near the held samples, not the box everywhere
    x = e + np.random.default_rng(seed).normal(scale=0.2, size=e.shape)
    for chunk in (1, 7, 64):
        monkeypatch.setattr(L, "CHECK_CHUNK", chunk)
        P = EdgeProjector(e, free, RASTER, LIM)
        assert P.is_feasible(x, tol=0.0) == whole.is_feasible(x, tol=0.0)
        assert P.is_feasible(e, tol=0.0) and whole.is_feasible(e, tol=0.0)
        assert P.lo.tobytes() == lo.tobytes() and P.hi.tobytes() == hi.tobytes()
        assert P.project(x).tobytes() == whole.project(x).tobytes()


def test_empty_envelope_names_the_same_sample_in_pieces(monkeypatch):
    """Held samples no waveform can join (a jump of 40 steps in 10): the same LimitError, found piece by piece."""
    S = LIM.step_max_mT_per_m(RASTER)
    e = np.zeros((3, 400))
    free = np.ones((3, 400), dtype=bool)
    for a, (i, j) in ((1, (100, 110)), (2, (50, 60))):
        e[a, j] = 40 * S * 0.5
        free[a, [i, j]] = False
    msgs = []
    for chunk in (1 << 18, 7):
        monkeypatch.setattr(L, "CHECK_CHUNK", chunk)
        with pytest.raises(LimitError) as ex:
            EdgeProjector(e, free, RASTER, LIM)
        msgs.append(str(ex.value))
    assert (
        msgs[0] == msgs[1] and " y " in msgs[0] and "t=0.960 ms" in msgs[0]
    )  # 20 steps to climb in 10: empty from edge 96


def test_waveform_extremes_in_pieces(monkeypatch):
    rng = np.random.default_rng(5)
    g = rng.normal(size=(3, 1001)) * 10
    ref = {"gmax_mT_per_m": np.abs(g).max(axis=1).tolist(),
           "smax_T_per_m_per_s": (np.abs(np.diff(g, axis=1)).max(axis=1) / 5e-6 * 1e-3).tolist()}  # fmt: skip
    for chunk in (1, 3, 1 << 18):
        monkeypatch.setattr(L, "EXTREMES_CHUNK", chunk)
        assert L.waveform_extremes(g, 5e-6) == ref


def test_a_checking_projector_holds_no_whole_length_arrays():
    """A 2 M-edge sequence (20 s of raster): the projector, built and asked whether a waveform is feasible, holds
    under 8 bytes per edge (its masks: free and free pairs), not the envelopes (48) nor Dykstra's reordered copies
    (~150); its construction's temporaries are a piece's.  A projection then builds them (and is unchanged)."""
    n = 2_000_001
    e = np.zeros((3, n))
    free = np.ones((3, n), dtype=bool)
    free[:, ::5000] = False  # held samples (RF blocks) every 50 ms
    e[0, 1::5000] = 1.0
    tracemalloc.start()
    try:
        P = EdgeProjector(e, free, RASTER, LIM)
        assert P.is_feasible(e)
        held, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert held / n < 8.0, held / n
    assert peak / n < 40.0, peak / n
    x = e.copy()
    x[0, 7] = 40.0  # beyond gmax: projected
    y = P.project(x)
    assert P.is_feasible(y, tol=1e-9) and abs(y[0, 7]) <= LIM.gmax_eff_mT_per_m


def test_the_write_check_compares_in_pieces_and_names_the_first_difference():
    """The written text's read-back is compared with the waveform piece by piece (no whole-length difference
    array); a text that plays another gradient is still refused naming the axis and the time of the largest
    difference."""
    from pathlib import Path

    from dtoc.errors import DtocError
    from dtoc.seq.load import load_sequence
    from dtoc.seq.write import output_version, seq_bytes_of, verify_written

    ir = load_sequence(Path(__file__).resolve().parents[1] / "sequences" / "epi_esp081.seq")
    v = output_version(ir)
    data = seq_bytes_of(ir, verify=False)
    verify_written(ir, data, v)  # the text plays ir: passes
    g = ir.grad_mT_per_m.copy()
    m = int(np.flatnonzero(ir.free_mask[1])[100])
    g[1, m] += 1.0  # 1 mT/m more than the text plays, at one fine sample on y
    with pytest.raises(DtocError, match=rf"axis y at {m * ir.dt_fine_s * 1e3:.4f} ms"):
        verify_written(ir.with_grad(g), data, v)


def _sine_case(n: int):
    """A slow sine (in the set with room) on x and y, held in blocks of 200 edges every 5000 (RF), z held at 0."""
    t = np.arange(n)
    e = np.zeros((3, n))
    e[:2] = 10.0 * np.sin(t / 300.0)[None]
    free = np.ones((3, n), dtype=bool)
    for s in range(1000, n, 5000):
        free[:, s : s + 200] = False
    free[2] = False
    return e, free


def test_a_waveform_outside_the_set_in_a_few_places_is_projected_there_only(monkeypatch):
    """A long waveform in the set but for a few places (a windowed solve's: its windows' envelopes round by ~5e-10
    mT/m against the whole sequence's at millions of edges; here also real excesses) is projected span by span: the
    whole projection's result bit for bit here, within the limits, and neither the whole envelopes (48 bytes per
    edge) nor Dykstra's whole layout (~150) are made (the 64 s bench.long run: 7.5 GB and 5 minutes for that
    projection, 2026-11-27).  Many places: the whole is projected, as before."""
    monkeypatch.setattr(L, "CHECK_CHUNK", 4096)  # 15 pieces
    monkeypatch.setattr(L, "LOCAL_MIN_EDGES", 8192)
    n = 60_001
    e, free = _sine_case(n)
    P = EdgeProjector(e, free, RASTER, LIM)
    assert P.is_feasible(e, tol=0.0)
    x = e.copy()
    x[0, [7_000, 31_337, 52_001]] += [30.0, -25.0, 3.0]  # beyond gmax / the slew limit
    lo, hi = P._box_range(1201, 1202, {})  # the free edge after a held block: on its envelope (the slew cone)
    x[1, 1201] = hi[1, 0] + 1e-10
    assert not P.is_feasible(x, tol=0.0)
    y = P.project(x, n_iter=60)
    assert P._lohi is None and P._layout_made is None
    whole = EdgeProjector(e, free, RASTER, LIM)
    whole._local = False
    assert y.tobytes() == whole.project(x, n_iter=60).tobytes()
    assert whole._layout_made is not None
    assert P.is_feasible(y) and y[1, 1201] <= hi[1, 0] + 1e-12
    moved = np.flatnonzero((y != x).any(axis=0))
    near = np.abs(moved[:, None] - np.array([1201, 7_000, 31_337, 52_001])[None, :]).min(axis=1)
    assert moved.size and near.max() <= L.LOCAL_MARGIN
    many = e.copy()
    many[0, 50::300] += 5.0  # 200 places: their spans cover the sequence
    Q = EdgeProjector(e, free, RASTER, LIM)
    assert Q._bad_spans(many) is None
    assert Q.project(many, n_iter=60).tobytes() == whole.project(many, n_iter=60).tobytes()


def test_the_limits_at_their_bound_in_pieces(monkeypatch):
    """The masks that name an active limit (the solver's report) are the whole envelopes' ones, in pieces, without
    making the envelopes whole."""
    e, free = _case(4, 3001, 0.9)
    x = EdgeProjector(e, free, RASTER, LIM).project(e + np.random.default_rng(4).normal(scale=3.0, size=e.shape))
    whole = EdgeProjector(e, free, RASTER, LIM)
    t = 1e-6 * whole.step
    amp_ref = whole.free & ((x >= whole.hi - t) | (x <= whole.lo + t))
    slew_ref = whole.pair_free & (np.abs(np.diff(x, axis=1)) >= whole.step * (1 - 1e-6))
    assert amp_ref.sum() > 10 and slew_ref.sum() > 10
    monkeypatch.setattr(L, "CHECK_CHUNK", 256)
    P = EdgeProjector(e, free, RASTER, LIM)
    amp, slew = P.at_limits(x)
    assert np.array_equal(amp, amp_ref) and np.array_equal(slew, slew_ref)
    assert P._lohi is None


def test_the_writer_finds_the_changed_blocks_in_pieces(monkeypatch):
    """The blocks the writer rewrites are found piece by piece: the same blocks, with temporaries of a piece (a
    (3, 2N+1) bool mask, 3 bytes per fine sample), not two whole-length float arrays (48)."""
    from pathlib import Path

    from dtoc.seq import write as W
    from dtoc.seq.load import load_sequence

    ir = load_sequence(Path(__file__).resolve().parents[1] / "sequences" / "epi_esp081.seq")
    g = ir.grad_mT_per_m.copy()
    idx = np.flatnonzero(ir.free_mask[0])
    g[0, idx[:: max(1, idx.size // 7)]] += 0.01
    out = ir.with_grad(g)
    whole = W.changed_blocks(out)
    assert len(whole) >= 5
    monkeypatch.setattr(W, "_PIECE", 256)
    n = g.shape[1]
    assert n > 20 * 256
    tracemalloc.start()
    try:
        got = W.changed_blocks(out)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert got == whole
    assert peak / n < 8.0, peak / n
