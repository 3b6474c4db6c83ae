"""What dtoc says about a file it did not write is true (tests/foreign/writers_truth.py): the RF use of a pre-1.5
file detected from its pulses as the reference tools do, overridable, stated per pulse."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cli_helpers import run_cli
from foreign.writers_truth import se_epi_v14

from dtoc.errors import InputError
from dtoc.seq.load import load_sequence


@pytest.fixture(scope="module")
def se14(tmp_path_factory):
    p = tmp_path_factory.mktemp("truth") / "se_epi_v14.seq"
    p.write_bytes(se_epi_v14())
    return p


def _pypulseq_kspace(path, detect):
    """pypulseq's own k at the ADC samples, with its RF use detection on or off."""
    from dtoc.seq.pulseq import import_pypulseq, quiet

    pp = import_pypulseq()
    seq = pp.Sequence()
    with quiet():
        seq.read(str(path), detect_rf_use=detect)
        k_adc = seq.calculate_kspace()[0]
    return np.asarray(k_adc) * 2 * math.pi  # 1/m -> rad/m


def test_pre15_spin_echo_epi_detects_the_refocusing_pulse_and_centres_k(se14):
    ir = load_sequence(se14)
    assert [r.use for r in ir.rf] == ["excitation", "refocusing"]
    k = ir.nominal_kspace_rad_per_m()
    # the readout runs symmetric about k = 0 (taking the 180 as an excitation put it at +670..+1480 rad/m)
    assert k[0].min() == pytest.approx(-k[0].max(), rel=0.02) and k[0].max() > 300
    assert abs(k[1].min() + k[1].max()) < 0.1 * k[1].max()
    geo = ir.geometry
    assert geo is not None and geo.matrix_readout_phase == (32, 32)  # a Cartesian grid, not a non-uniform DFT
    assert ir.meta.get("recon") != "ndft" and ir.kind == "epi"
    assert geo.fov_m[1] == pytest.approx(0.22, rel=1e-4)
    table = {e["id"]: e for e in ir.meta["rf_use"]}
    assert table[1]["use"] == "excitation" and table[2]["use"] == "refocusing"
    assert table[2]["how"] == "detected" and table[2]["flip_deg"] == pytest.approx(180, abs=0.1)
    notes = " ".join(ir.meta["notes"])
    assert "format 1.4.1 states no RF use" in notes and "RF 2 (180 deg, 3 ms, x1): refocusing (detected)" in notes
    assert "'undefined'" not in notes


def test_detection_matches_pypulseq_detect_rf_use(se14):
    """The same trajectory as pypulseq's read(detect_rf_use=True) + calculate_kspace; without detection pypulseq
    (and dtoc before) puts k off centre."""
    pytest.importorskip("pypulseq")
    k = load_sequence(se14).nominal_kspace_rad_per_m()
    ref = _pypulseq_kspace(se14, True)
    if np.allclose(ref, _pypulseq_kspace(se14, False)):
        pytest.skip("this pypulseq's detect_rf_use does not reach calculate_kspace")
    np.testing.assert_allclose(k, ref, atol=1e-3 * np.abs(ref).max())


def test_rf_use_override_and_errors(se14):
    ir = load_sequence(se14, rf_use={2: "excitation"})
    assert [r.use for r in ir.rf] == ["excitation", "excitation"]
    assert ir.nominal_kspace_rad_per_m()[0].min() > 300  # the old, off-centre reading, asked for
    assert {e["id"]: e["how"] for e in ir.meta["rf_use"]} == {1: "detected", 2: "--rf-use"}
    with pytest.raises(InputError, match="no RF event 9"):
        load_sequence(se14, rf_use={9: "refocusing"})


def test_cli_rf_use_option(se14, capsys):
    code, _, err = run_cli(capsys, "predict", se14, "--rf-use", "2=bogus")
    assert code == 2 and "unknown use 'bogus'" in err
    code, out, err = run_cli(capsys, "predict", se14, "--rf-use", "2=r")
    assert code == 0, err
    assert "refocusing (from --rf-use)" in out + err
