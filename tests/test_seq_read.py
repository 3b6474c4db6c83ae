"""Reader: played waveform on the fine grid, events, metadata, free mask, k-space vs pypulseq."""

from pathlib import Path

import numpy as np
import pytest

from dtoc.constants import GAMMA_HZ_PER_T, mT_per_m_from_hz_per_m
from dtoc.errors import InputError
from dtoc.seq.load import load_sequence
from dtoc.seq.read import from_pypulseq, quiet, read_seq, slice_axes

REPO = Path(__file__).resolve().parents[1]
SEQ = REPO / "sequences"


def _pp_kspace(seq):
    with quiet():
        k_adc, _, _, _, t_adc = seq.calculate_kspace()
    return k_adc, t_adc


@pytest.fixture(scope="module")
def epi():
    return read_seq(SEQ / "epi_esp081.seq")


@pytest.fixture(scope="module")
def gre():
    return read_seq(SEQ / "gre_paper.seq")


def test_epi_metadata_and_events(epi):
    assert epi.kind == "epi" and epi.readout_axis == 0 and epi.phase_axis == 1
    assert epi.fov_m == pytest.approx((0.25, 0.25, 0.003))
    assert epi.matrix[:2] == (64, 64)
    assert epi.raster_s == pytest.approx(10e-6)
    assert epi.grad_mT_per_m.shape == (3, 2 * round(epi.duration_s / 10e-6) + 1)
    assert len(epi.adc) == 64 and all(a.num_samples == 64 and a.dwell_s == pytest.approx(10e-6) for a in epi.adc)
    # echo spacing: ADC starts 0.81 ms apart
    starts = np.array([a.t_start_s for a in epi.adc])
    assert np.allclose(np.diff(starts), 0.81e-3, atol=1e-12)
    assert epi.meta["echo_spacing_s"] == pytest.approx(0.81e-3)
    (rf,) = epi.rf
    assert rf.use == "excitation" and rf.flip_angle_rad == pytest.approx(np.pi / 2, rel=2e-3)
    assert abs(rf.grad_at_center_mT_per_m[2]) > 1.0  # slice selection on z
    assert slice_axes(epi) == [2]


def test_epi_readout_amplitude_and_kspace_grid(epi):
    # readout on x: 1/(FOV * dwell) = 400 kHz/m on the flat, exactly
    t = epi.adc_times_s
    gx = np.interp(t, epi.t_fine_s, epi.grad_mT_per_m[0])
    g_ro = mT_per_m_from_hz_per_m(1 / (0.25 * 10e-6))
    assert np.allclose(np.abs(gx), g_ro, rtol=1e-6)
    k = epi.nominal_kspace_rad_per_m() / epi.dk_rad_per_m[:, None]
    kx = k[0].reshape(64, 64)
    ky = k[1].reshape(64, 64)
    idx = np.arange(64) - 32
    # even lines run -32..31, odd lines reversed; phase lines -32..31: within 2e-4 dk of the grid
    assert np.abs(kx[0::2] - idx[None, :]).max() < 2e-4
    assert np.abs(kx[1::2] - idx[None, ::-1]).max() < 2e-4
    assert np.abs(ky - idx[:, None]).max() < 2e-4
    assert np.abs(k[2]).max() < 1e-4  # slice rephased


def test_kspace_matches_pypulseq_calculate_kspace(epi, gre):
    for ir in (epi, gre):
        k_pp, t_pp = _pp_kspace(ir.source)
        assert np.allclose(t_pp, ir.adc_times_s, atol=1e-12)
        k_ir = ir.nominal_kspace_rad_per_m() / (2 * np.pi)  # 1/m, as pypulseq
        dk = 1 / np.array(ir.fov_m[:2])
        err = np.abs(k_pp[:2] - k_ir[:2]) / dk[:, None]
        assert err.max() < 1e-6, err.max()  # measured ~3e-9 dk


def _synthetic_seq(arbitrary_blips=True):
    """Trapezoid readout + arbitrary-gradient blips (raster-centre samples, with first/last)."""
    import pypulseq as pp

    sys_ = pp.Opts(max_grad=80, grad_unit="mT/m", max_slew=200, slew_unit="T/m/s", rf_dead_time=100e-6)
    seq = pp.Sequence(system=sys_)
    rf = pp.make_block_pulse(np.pi / 2, duration=500e-6, system=sys_, use="excitation", delay=100e-6)
    seq.add_block(rf)
    gx = pp.make_trapezoid("x", flat_area=32 / 0.2, flat_time=320e-6, system=sys_)
    adc = pp.make_adc(32, duration=320e-6, delay=gx.rise_time, system=sys_)
    shape = np.sin(np.pi * (np.arange(40) + 0.5) / 40)
    wave = 100.0 / (10e-6 * shape.sum()) * shape  # Hz/m, sum*raster = 100/m
    blip = (
        pp.make_arbitrary_grad("y", wave, first=0.0, last=0.0, system=sys_)
        if arbitrary_blips
        else pp.make_trapezoid("y", area=100.0, system=sys_)
    )
    for i in range(4):
        seq.add_block(pp.scale_grad(gx, (-1) ** i), adc)
        seq.add_block(blip)
    seq.set_definition("FOV", [0.2, 0.2, 0.005])
    return seq, wave


def test_arbitrary_gradient_played_through_first_centres_last():
    seq, wave = _synthetic_seq()
    ir = from_pypulseq(seq)
    b = 2  # first blip block (0: RF, 1: readout)
    m0 = int(round(ir.block_edges_s[b] / ir.dt_fine_s))
    gy = ir.grad_mT_per_m[1, m0 : m0 + 2 * len(wave) + 1]
    assert gy[0] == 0.0 and gy[-1] == 0.0  # first / last
    assert np.allclose(gy[1::2], mT_per_m_from_hz_per_m(wave), rtol=1e-12)  # raster centres
    # played area of the PWL through first, centres, last: sum*raster minus the two corner triangles
    area = np.trapezoid(gy, dx=ir.dt_fine_s) * 1e-3 * GAMMA_HZ_PER_T
    corner = (wave[0] + wave[-1]) * 10e-6 / 4  # two half-raster triangles lost vs sum*raster
    assert area == pytest.approx(100.0 - corner, rel=1e-9)


def test_trapezoid_vertices_on_raster_edges_and_exact_area():
    seq, _ = _synthetic_seq(arbitrary_blips=False)
    ir = from_pypulseq(seq)
    b = 2
    m0, m1 = (int(round(x / ir.dt_fine_s)) for x in ir.block_edges_s[b : b + 2])
    area = np.trapezoid(ir.grad_mT_per_m[1, m0 : m1 + 1], dx=ir.dt_fine_s) * 1e-3 * GAMMA_HZ_PER_T
    assert area == pytest.approx(100.0, rel=1e-6)  # no corner loss: vertices on even samples


@pytest.mark.parametrize("arb", [True, False])
def test_synthetic_kspace_vs_pypulseq(arb):
    seq, _ = _synthetic_seq(arb)
    ir = from_pypulseq(seq)
    k_pp, _ = _pp_kspace(seq)
    k_ir = ir.nominal_kspace_rad_per_m() / (2 * np.pi)
    # pypulseq integrates the same PWL waveform; agreement to 1e-6 of dk = 5/m
    assert np.abs(k_pp - k_ir).max() < 5e-6


def test_free_mask_defaults(epi, gre):
    # EPI: z (slice axis) fixed everywhere; nothing free inside the RF block; first/last fixed
    assert not epi.free_mask[2].any()
    rf_end = int(round(epi.block_edges_s[1] / epi.dt_fine_s))
    assert not epi.free_mask[:, : rf_end + 1].any()
    assert epi.free_mask[:2, rf_end + 1 : -1].all()
    # GRE: the 2 ms RF block of every TR is fixed on all axes, the rest free on x, y (no slice axis)
    tr_m = int(round(10e-3 / gre.dt_fine_s))
    rf_m = int(round(2e-3 / gre.dt_fine_s))
    for j in range(32):
        assert not gre.free_mask[:, j * tr_m : j * tr_m + rf_m + 1].any()
        assert gre.free_mask[:2, j * tr_m + rf_m + 1 : (j + 1) * tr_m].all()
    assert not gre.free_mask[2].any()  # z plays nothing in this GRE: fixed unless asked
    assert read_seq(SEQ / "gre_paper.seq", free_unused_axes=True).free_mask[2, rf_m + 1 : tr_m].all()
    free_z = read_seq(SEQ / "epi_esp081.seq", free_slice_axis=True)
    assert free_z.free_mask[2, rf_end + 1 : -1].all()
    pulse = read_seq(SEQ / "gre_paper.seq", rf_guard="pulse")
    assert pulse.free_mask[0, 1] and not pulse.free_mask[0, int(round(1.0e-3 / gre.dt_fine_s))]


def test_load_sequence_accepts_spec_and_seq(tmp_path):
    a = load_sequence(SEQ / "epi_small.yaml")
    b = load_sequence(SEQ / "epi_small.seq")
    assert np.array_equal(a.grad_mT_per_m, b.grad_mT_per_m)
    assert a.definitions == b.definitions
    with pytest.raises(InputError, match="expected a .seq file or a spec"):
        p = tmp_path / "x.txt"
        p.write_text("hello")
        load_sequence(p)
