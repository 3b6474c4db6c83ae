"""Reading long files without expanding what need not be (issue 36: CEST protocols, 2 s saturation pulses at
1 us, read for 30 s and 4 GB): pypulseq's RF decoding is done once per pulse shape and shared by the events
that differ in frequency and phase offsets only, and no fine time axis is built to look gradients up; the
IR is the one a decoding per event gives.  The file comes from our own pypulseq script (a CEST-like train)."""

from __future__ import annotations

import numpy as np
import pytest

from dtoc.seq import read as R
from dtoc.seq.ir import interp_fine


def _cest_like(tmp_path, n_offsets: int = 5):
    from foreign.writers import _bytes, _system

    from dtoc.seq.pulseq import import_pypulseq

    pp = import_pypulseq()
    sys = _system(pp)
    seq = pp.Sequence(sys)
    sat = {}
    for k, ppm in enumerate(np.linspace(-4, 4, n_offsets)):
        f = ppm * 1e-6 * sys.gamma * sys.B0
        sat = pp.make_block_pulse(flip_angle=np.pi * 4, duration=50e-3, freq_offset=f, system=sys, use="saturation")
        seq.add_block(sat)
        seq.add_block(pp.make_trapezoid("x", area=400, duration=2e-3, system=sys))
        exc = pp.make_block_pulse(flip_angle=np.pi / 18, duration=0.5e-3, system=sys, use="excitation")
        seq.add_block(exc)
        seq.add_block(pp.make_trapezoid("y", area=50 * (k - 2), duration=1e-3, system=sys))
        seq.add_block(
            pp.make_adc(16, duration=1.6e-3, system=sys),
            pp.make_trapezoid("x", flat_area=320, flat_time=1.6e-3, system=sys),
        )
        seq.add_block(pp.make_delay(5e-3))
    p = tmp_path / "cest.seq"
    p.write_bytes(_bytes(seq))
    return p


def test_rf_decoded_once_per_shape_and_the_ir_unchanged(tmp_path, monkeypatch):
    """Five 50 ms saturation pulses at five offsets and five excitations: the block pass decodes two pulses
    (one per amplitude and shape), not ten; the IR equals the one decoded event by event."""
    from dtoc.seq.pulseq import import_pypulseq

    p = _cest_like(tmp_path)
    seq_cls = import_pypulseq().Sequence
    orig = seq_cls.rf_from_lib_data
    calls: list[int] = []
    monkeypatch.setattr(seq_cls, "rf_from_lib_data", lambda self, d, use="": (calls.append(1), orig(self, d, use))[1])
    ir = R.read_seq(p)
    shared = len(calls)
    monkeypatch.setattr(R, "_shared_rf_decoding", _no_sharing)
    ir0 = R.read_seq(p)
    each = len(calls) - shared
    assert each - shared == 10 - 2  # (pypulseq's own read decodes as before in both)
    sat = [r for r in ir.rf if r.duration_s > 10e-3]
    assert len(sat) == 5 and len({r.freq_offset_hz for r in sat}) == 5
    assert all(abs(r.flip_angle_rad - 4 * np.pi) < 1e-3 for r in sat)
    assert [r.__dict__ for r in ir.rf] == [r.__dict__ for r in ir0.rf]
    assert np.array_equal(ir.grad_mT_per_m, ir0.grad_mT_per_m)


class _no_sharing:
    def __init__(self, seq, cache):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


def test_interp_fine_is_np_interp_on_the_fine_axis():
    rng = np.random.default_rng(1)
    for n in (2, 3, 257):
        g, dtf = rng.normal(size=(3, n)), 5e-6
        t = np.concatenate([rng.random(500) * (n - 1) * dtf, np.arange(n) * dtf, [-1e-6, (n - 1) * dtf + 1e-6]])
        ref = np.array([np.interp(t, np.arange(n) * dtf, g[a]) for a in range(3)])
        assert np.array_equal(interp_fine(g, t, dtf), ref)


def test_fov_definition_in_millimetres_is_read_as_such(tmp_path):
    """A FOV definition over 2 m (Pulseq MATLAB demos of 2018-2020 and JEMRIS wrote millimetres) is read as mm,
    with a note saying it is assumed: the same image grid as the file stating metres (a radial file: 2 pi /
    FOV from the definition), not a 31002 x 31002 grid refused for memory."""
    from foreign.writers import _sign, _unsigned, radial

    from dtoc.seq.load import load_sequence

    base = _unsigned(radial(n=16, spokes=8))
    grids = {}
    for name, fov in (("m", b"FOV 0.22 0.22 0.005"), ("mm", b"FOV 220 220 5")):
        p = tmp_path / f"r_{name}.seq"
        p.write_bytes(_sign(base.replace(b"[DEFINITIONS]\n", b"[DEFINITIONS]\n" + fov + b"\n", 1)))
        ir = load_sequence(p)
        grids[name] = (ir.fov_m, ir.matrix)
        said = [n for n in ir.meta.get("notes", []) if "read as millimetres" in n]
        assert bool(said) == (name == "mm")
    assert np.allclose(grids["m"][0], grids["mm"][0], rtol=1e-12) and grids["m"][1] == grids["mm"][1]
    assert grids["m"][1] is not None and max(grids["m"][1]) < 64


def test_the_readout_guess_interpolates_the_adc_gradient_in_pieces(tmp_path, monkeypatch):
    """A file without axis definitions: the readout axis is guessed from the mean |g| over its ADC samples, read
    piece by piece (a 5-minute 3D file has 5.8 M ADC samples: no (3, N_adc) temporaries); the means are those of
    the whole interpolation bit for bit, whatever the piece, and the guess is their largest."""
    from foreign.writers import gre

    p = tmp_path / "gre.seq"
    p.write_bytes(gre(n=16))
    ir = R.read_seq(p)
    whole = np.array([np.abs(ir.grad_at(ir.adc_times_s)[a]).mean() for a in range(3)])
    assert ir.n_adc_samples == 256 and whole.max() > 0
    for piece in (7, 100, 1 << 18):
        monkeypatch.setattr(R, "ADC_PIECE", piece)
        assert np.array_equal(R.mean_abs_grad_at_adc(ir), whole)
    assert ir.meta.get("axes_guessed") and ir.readout_axis == int(np.argmax(whole))


@pytest.mark.parametrize("chunk", [None, 64])
def test_the_nominal_k_of_many_adc_samples_is_computed_in_pieces_bit_for_bit(tmp_path, monkeypatch, chunk):
    """More ADC samples than ``NOMINAL_K_PIECE``: the nominal k piece by piece (no per-sample temporaries of the
    whole acquisition) equals the whole computation bit for bit, with excitations and refocusing pulses (a TSE:
    k is negated at each refocusing centre) and with the waveform's running integral whole or in chunks."""
    from foreign.writers import tse

    import dtoc.seq.ir as I
    import dtoc.seq.kspace as K

    p = tmp_path / "tse.seq"
    p.write_bytes(tse(n=16, etl=4))
    ir = R.read_seq(p)
    assert any(r.refocuses for r in ir.rf) and ir.n_adc_samples == 256
    if chunk is not None:
        monkeypatch.setattr(K, "CUMULATIVE_CHUNK", chunk)
    whole = ir.kspace_rad_per_m().numpy()
    assert np.abs(whole).max() > 100  # rad/m: encoded
    whole_k = ir.kspace_rad_per_m
    asked: list[int] = []

    def recorded(*a, times_s=None, **k):
        asked.append(ir.n_adc_samples if times_s is None else len(times_s))
        return whole_k(*a, times_s=times_s, **k)

    monkeypatch.setattr(ir, "kspace_rad_per_m", recorded)
    for piece in (37, 256, 1 << 20):
        monkeypatch.setattr(I, "NOMINAL_K_PIECE", piece)
        asked.clear()
        assert np.array_equal(ir.nominal_kspace_rad_per_m(), whole)
        assert max(asked) == min(piece, 256) and len(asked) == -(-256 // piece)  # no query longer than a piece
