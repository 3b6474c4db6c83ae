"""Slice groups (dtoc.sim.slices): a 2D multi-slice sequence's slices are different spins.

A small 2-slice spin-echo sequence written here with pypulseq: each slice a slice-selective sinc 90 and 180
(crushers) at its own frequency offset, then a few Cartesian readout lines.  The simulation of the 2-slice file at
each slice's samples equals that of the file in which only that slice's pulses play (the other's blocks keep their
gradients and timing); the old simulation, every pulse on one sheet, differs.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dtoc.seq.load import load_sequence
from dtoc.sim import pdg_graph, pdg_main
from dtoc.sim.pdg import GroupedGraph, PDGConfig, PDGGraph, build_graph, simulate
from dtoc.sim.phantom import phantom_for
from dtoc.sim.slices import slice_groups

pp = pytest.importorskip("pypulseq")

FOV = 0.2
N = 16
THK = 3e-3


def _write(path, slices_played=(0, 1), offsets_m=(-THK, THK), fatsat=False):
    """2-slice SE: per slice [fat sat], 90 (slice-selective), 180 with crushers, N/4 readout lines of N samples;
    the pulses of a slice not in ``slices_played`` are left out (their blocks keep gradients and durations)."""
    sys = pp.Opts(max_grad=32, grad_unit="mT/m", max_slew=130, slew_unit="T/m/s", rf_dead_time=100e-6)
    seq = pp.Sequence(sys)
    rf90, gz90, gzr = pp.make_sinc_pulse(
        flip_angle=math.pi / 2,
        duration=2e-3,
        slice_thickness=THK,
        time_bw_product=4,
        system=sys,
        return_gz=True,
        delay=100e-6,
    )
    rf180, gz180, _ = pp.make_sinc_pulse(
        flip_angle=math.pi, duration=2e-3, slice_thickness=THK, time_bw_product=4, system=sys, return_gz=True,
        phase_offset=math.pi / 2, use="refocusing", delay=100e-6,
    )  # fmt: skip
    crush = pp.make_trapezoid("z", area=4 / THK, system=sys)
    gx = pp.make_trapezoid("x", flat_area=N / FOV, flat_time=1.6e-3, system=sys)
    gxp = pp.make_trapezoid("x", area=gx.area / 2, duration=1e-3, system=sys)
    adc = pp.make_adc(N, duration=gx.flat_time, delay=gx.rise_time, system=sys)
    spoil = pp.make_trapezoid("z", area=10 / THK, system=sys)
    sat = pp.make_gauss_pulse(
        flip_angle=math.radians(110), duration=8e-3, bandwidth=420, freq_offset=-420, system=sys, delay=100e-6
    )
    for s, z in enumerate(offsets_m):
        play = s in slices_played
        if fatsat:
            seq.add_block(sat) if play else seq.add_block(pp.make_delay(pp.calc_duration(sat)))
            seq.add_block(spoil)
        rf90.freq_offset = gz90.amplitude * z
        rf180.freq_offset = gz180.amplitude * z
        seq.add_block(rf90, gz90) if play else seq.add_block(gz90)
        seq.add_block(gzr, pp.make_delay(5e-3))
        seq.add_block(crush)
        seq.add_block(rf180, gz180) if play else seq.add_block(gz180)
        seq.add_block(crush)
        for line in range(N // 4):
            gy = pp.make_trapezoid("y", area=(line - N // 8) / FOV, duration=1e-3, system=sys)
            seq.add_block(gxp, gy)
            seq.add_block(gx, adc)
            seq.add_block(pp.scale_grad(gy, -1), pp.scale_grad(gxp, -1))
        seq.add_block(spoil)
    seq.set_definition("FOV", [FOV, FOV, THK])
    seq.write(str(path))
    return path


def _signal(ir, ph):
    return simulate(ir, ph, dtype=torch.float64)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("slices")
    return {
        "both": load_sequence(_write(d / "both.seq")),
        0: load_sequence(_write(d / "s0.seq", slices_played=(0,))),
        1: load_sequence(_write(d / "s1.seq", slices_played=(1,))),
    }


def test_groups_of_a_two_slice_spin_echo(files):
    ir = files["both"]
    sg = slice_groups(ir)
    assert len(ir.rf) == 4 and all(r.bandwidth_hz is not None for r in ir.rf)
    # time-bandwidth 4 over 2 ms: 2 kHz (an unapodised sinc's FWHM is 4 % narrower); the slab: bandwidth / (gamma G)
    assert ir.rf[0].bandwidth_hz == pytest.approx(2000.0, rel=0.05)
    assert sg.groups == ((0, 1), (2, 3)) and not sg.inert and not sg.trivial
    assert sg.adc == (tuple(range(0, N // 4)), tuple(range(N // 4, N // 2)))
    # one slice played: one group, the plain simulation
    assert slice_groups(files[0]).trivial and isinstance(build_graph(files[0]), PDGGraph)
    assert isinstance(build_graph(ir), GroupedGraph)


def test_each_slice_equals_its_single_slice_simulation(files):
    ir = files["both"]
    ph = phantom_for(ir, "brain", size=N)
    sig = _signal(ir, ph)[0].numpy()
    n = ir.n_adc_samples // 2
    for s in (0, 1):
        alone = _signal(files[s], ph)[0].numpy()[s * n : (s + 1) * n]
        mine = sig[s * n : (s + 1) * n]
        assert np.abs(alone).max() > 0.1  # a signal, not zeros (units of PD x voxels; the echo peaks between lines)
        np.testing.assert_allclose(mine, alone, rtol=0, atol=1e-9 * np.abs(alone).max())
    # the two slices are the same phantom: the same echo
    np.testing.assert_allclose(sig[n:], sig[:n], rtol=0, atol=1e-9 * np.abs(sig).max())
    # every pulse on one sheet (the simulator before slice groups): slice 1's 90 and 180 act on slice 0's spins too
    cfg = PDGConfig()
    g = pdg_graph.build_graph(ir, cfg, ph)
    old = pdg_main.run_main_pass(ir, ph, g, cfg, None, None, None, torch.float64, "cpu")[0].numpy()
    np.testing.assert_allclose(old[:n], sig[:n], rtol=0, atol=1e-9 * np.abs(sig).max())  # before slice 1 plays
    assert np.linalg.norm(old[n:] - sig[n:]) > 0.05 * np.linalg.norm(sig[n:])


def test_fat_saturation_acts_on_no_spin_of_the_sheet(files, tmp_path):
    """A spectrally selective pulse (no gradient, water outside its band) is a no-op on the phantom (water only)."""
    with_sat = load_sequence(_write(tmp_path / "fs.seq", slices_played=(0,), fatsat=True))
    sg = slice_groups(with_sat)
    assert sg.inert == (0,) and sg.kinds == ("inert", "selective", "selective") and len(sg.groups) == 1
    ph = phantom_for(files["both"], "brain", size=N)
    n = with_sat.n_adc_samples // 2
    a = _signal(with_sat, ph)[0].numpy()[:n]
    b = _signal(files[0], ph)[0].numpy()[:n]  # the same slice without the saturation blocks, the plain path
    # from equilibrium, the saturation block only delays the excitation: the same echo
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * np.abs(b).max())
    # played as before (on every spin), the 110 degree pulse and its spoiler leave less for the 90 to excite
    cfg = PDGConfig()
    old = pdg_main.run_main_pass(
        with_sat, ph, pdg_graph.build_graph(with_sat, cfg, ph), cfg, None, None, None, torch.float64, "cpu"
    )[0].numpy()[:n]
    assert np.linalg.norm(old) < 0.8 * np.linalg.norm(a)


def test_steady_state_per_slice_group(files):
    """The dummy train of a multi-slice file: one per group, each that of the file where only its pulses play."""
    from dtoc.sim.pdg import steady_state_mz

    ir = files["both"]
    ph = phantom_for(ir, "brain", size=N)
    mz = steady_state_mz(ir, ph, 3).numpy()
    assert mz.shape == (2, *ph.pd.shape)
    for s in (0, 1):
        alone = steady_state_mz(files[s], ph, 3).numpy()
        np.testing.assert_allclose(mz[s], alone, rtol=0, atol=1e-12 * np.abs(ph.pd).max())
    assert np.abs(mz[0] - ph.pd).max() > 0.05 * np.abs(ph.pd).max()  # the train did act
    # the stacked result is what simulate takes per group
    sig = simulate(ir, ph, initial_mz=torch.as_tensor(mz), dtype=torch.float64)[0].numpy()
    n = ir.n_adc_samples // 2
    one = simulate(files[1], ph, initial_mz=torch.as_tensor(mz[1]), dtype=torch.float64)[0].numpy()[n:]
    np.testing.assert_allclose(sig[n:], one, rtol=0, atol=1e-9 * np.abs(one).max())


def test_the_simulation_estimate_reads_every_slice_groups_graph(files):
    """dtoc.util.cost.emission_cost (the report image's estimate) on a grouped graph: the groups' work summed (it
    read ``graph.intervals`` of one graph and failed on a multi-slice file: an internal error on spiral_v15)."""
    from dtoc.util.cost import emission_cost

    g = build_graph(files["both"])
    assert isinstance(g, GroupedGraph) and len(g.graphs) == 2
    mem, sec, per = emission_cost(g, 256)
    parts = [emission_cost(gg, 256) for gg in g.graphs]
    assert sec > 0 and sec == pytest.approx(sum(p[1] for p in parts), rel=1e-12)
    assert mem == pytest.approx(max(p[0] for p in parts), rel=1e-12)  # the groups run one after the other
    assert per > 0


def test_the_bandwidth_of_a_long_saturation_pulse_is_read_in_bounded_memory():
    """A 2 s block pulse at 1 us (a CEST saturation train's length): its spectrum's FWHM is 1.21 / 2 s, read without
    zero-padding it to 64x its duration (2^27 points, ~6 GB at the read: the APTw files stopped at the bench's cap)."""
    import tracemalloc

    from dtoc.seq.read import BANDWIDTH_FFT_MAX, rf_bandwidth_hz

    t = np.arange(2_000_000) * 1e-6
    tracemalloc.start()
    bw = rf_bandwidth_hz(t, np.ones(t.size))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert bw == pytest.approx(1.2067 / 2.0, rel=0.05)
    assert peak < 16 * 4 * (1 << 21)  # a few complex arrays of the waveform's own power-of-two length
    # a slice-selective pulse keeps its 64x zero-padding: 2 ms sinc, time-bandwidth 4 -> ~2 kHz
    ts = np.arange(200) * 1e-5
    x = np.linspace(-2, 2, ts.size)
    assert 64 * 2e-3 / 1e-5 < BANDWIDTH_FFT_MAX
    assert rf_bandwidth_hz(ts, np.sinc(x)) == pytest.approx(2000.0 * 0.96, rel=0.05)
