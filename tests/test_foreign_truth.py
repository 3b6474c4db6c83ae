"""What dtoc says about a file it did not write is true (tests/foreign/writers_truth.py): the RF use of a pre-1.5
file detected from its pulses as the reference tools do, overridable, stated per pulse; dtoc check tells the
format's rules, the user's limits and vendor conventions apart and assumes none of the latter."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli
from foreign.writers_truth import gre_variant, se_epi_v14

from dtoc.errors import InputError
from dtoc.seq.check import check_file
from dtoc.seq.load import load_sequence
from dtoc.seq.system import SystemSpec


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


# ------------------------------------------------------------------------------------------------ dtoc check
PROFILE = """name: site-terra
b0_T: 7
gmax_mT_per_m: 32
smax_T_per_m_per_s: 130
rasters: {grad_s: 1.0e-5, rf_s: 1.0e-6, adc_s: 1.0e-7, block_s: 1.0e-5}
dead_times: {rf_dead_time_s: 1.0e-4, rf_ringdown_time_s: 3.0e-5, adc_dead_time_s: 1.0e-5}
"""


@pytest.fixture(scope="module")
def variants(tmp_path_factory):
    d = tmp_path_factory.mktemp("variants")
    files = {
        "ring20": gre_variant(rf_ringdown_s=20e-6),  # Pulseq MATLAB's default ring-down
        "rf10": gre_variant(rf_raster_s=10e-6),  # a legal, coarser RF raster
        "seg": gre_variant(adc_samples=12000, adc_dwell_s=1e-6, max_adc_segment=6000),
        "noseg": gre_variant(adc_samples=12000, adc_dwell_s=1e-6),
    }
    for k, b in files.items():
        (d / f"{k}.seq").write_bytes(b)
    (d / "profile.yaml").write_text(PROFILE)
    (d / "profile_adc.yaml").write_text(PROFILE + "adc_samples_divisor: 4\nadc_max_samples: 8192\n")
    return d


def test_limits_alone_assume_no_vendor_convention(variants, capsys):
    """--gmax/--smax check the format and the limits; dead times, ring-down, ADC samples and rasters are not
    assumed (the 20 us ring-down, the 10 us RF raster and the 12,000-sample ADCs pass), and that is said."""
    for name in ("ring20", "rf10", "seg", "noseg"):
        code, out, err = run_cli(capsys, "check", variants / f"{name}.seq", "--gmax", "32", "--smax", "130")
        assert code == 0, (name, out)
        flat = " ".join(out.split())  # the console wraps long lines
        assert "limits from --gmax 32 --smax 130" in flat and "vendor conventions not checked" in flat
        assert "not checked, no scanner profile or --system names them" in err
        assert all("  " not in ln.strip() for ln in out.splitlines())


def test_profile_conventions_are_checked_with_their_source(variants, capsys):
    prof = variants / "profile.yaml"
    code, out, _ = run_cli(capsys, "check", variants / "ring20.seq", "--scanner", prof, "--json", "-")
    d = json.loads(out)
    assert code == 1 and {v["rule"] for v in d["violations"]} == {"rf_ringdown"}
    v = d["violations"][0]
    assert v["kind"] == "convention" and v["source"] == "--scanner site-terra"
    assert v["value"] == pytest.approx(20) and v["limit"] == pytest.approx(30)
    # a declared 10 us RF raster is a whole multiple of the scanner's 1 us: legal
    assert run_cli(capsys, "check", variants / "rf10.seq", "--scanner", prof)[0] == 0
    # ADC sample rules only where the profile names them; a declared MaxAdcSegmentLength splits the ADC
    code, _, err = run_cli(capsys, "check", variants / "noseg.seq", "--scanner", prof)
    assert code == 0 and "ADC sample count and segmenting: not checked" in err
    prof_adc = variants / "profile_adc.yaml"
    assert run_cli(capsys, "check", variants / "seg.seq", "--scanner", prof_adc)[0] == 0
    code, out, _ = run_cli(capsys, "check", variants / "noseg.seq", "--scanner", prof_adc)
    flat = " ".join(out.split())
    assert code == 1 and "12000 samples exceeds 8192 per ADC" in flat
    assert "FAILED: convention (--scanner site-terra): 16 x adc_samples (worst 12000 vs 8192)" in flat


def test_segment_rules(variants):
    sysspec = SystemSpec(max_grad_mT_per_m=32, max_slew_T_per_m_per_s=130)
    assert check_file(variants / "seg.seq", sysspec).ok  # 2 segments of 6000 <= 8192, multiple of 4
    r = check_file(variants / "seg.seq", SystemSpec(max_grad_mT_per_m=32, max_slew_T_per_m_per_s=130,
                                                    adc_max_samples=4096))  # fmt: skip
    assert r.rules() == {"adc_samples"} and "segment of 6000 samples exceeds 4096" in r.violations[0].message


def test_each_kind_names_its_source(variants):
    r = check_file(variants / "ring20.seq", SystemSpec(max_grad_mT_per_m=5, max_slew_T_per_m_per_s=130),
                   limits_source="--gmax 5")  # fmt: skip
    kinds = {v.rule: (v.kind, v.source) for v in r.violations}
    assert kinds["grad_amplitude"] == ("limits", "--gmax 5")
    assert kinds["rf_ringdown"] == ("convention", "system siemens-7T-terra")
    s = r.summary()
    assert s.startswith("limits (--gmax 5): ") and "| convention (system siemens-7T-terra): " in s
    assert "grad_amplitude (worst " in s and "  " not in s


def test_optimize_never_reports_zero_violations_for_a_failing_output(variants, capsys, monkeypatch, tmp_path):
    """A written output that fails a rule the user asked for (here: a format rule, injected into the check of the
    output) is reported as failing, exit 1 -- never 'limits verified, 0 violations'."""
    import dtoc.optimize.run as run_mod
    from dtoc.seq.check import Violation

    real = run_mod.check_file_pieces  # what write_checked calls (a text of one piece: check_file)

    def failing(*a, **k):
        res = real(*a, **k)
        res.violations.append(
            Violation(
                "rf_raster",
                1,
                None,
                105.0,
                10.0,
                "us",
                "RF delay not on the file's RF raster",
                "format",
                "Pulseq format 1.5.0",
            )  # fmt: skip
        )
        return res

    monkeypatch.setattr(run_mod, "check_file_pieces", failing)
    out = tmp_path / "o.seq"
    code, so, err = run_cli(
        capsys, "optimize", variants / "rf10.seq", "-o", out, "--ideal", "--gmax", "32", "--smax", "130",
        "--iters", "2", "--warm-iters", "0", "-q", "--no-trajectory", "--json", tmp_path / "m.json",
    )  # fmt: skip
    assert code == 1, err
    flat = " ".join((so + err).split())
    assert "0 violations" not in flat
    assert (
        "dtoc check of the written file FAILED: format (Pulseq format 1.5.0): rf_raster (worst 105 us vs 10 us)" in flat
    )
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["output"]["check_ok"] is False and m["output"]["check_failed"].startswith("format")


# ------------------------------------------------------------------------------------- figures that mean something
REPO = Path(__file__).resolve().parents[1]
GIRF = REPO / "girf" / "example_7T.npz"


def test_no_signal_gives_a_reason_not_a_zero(variants, capsys, tmp_path):
    """A protocol whose RF flips ~1e-100 deg (field-camera exports) excites nothing: the image figures are a reason,
    never NRMSE 0 %; the k figures stay."""
    p = tmp_path / "zero.seq"
    p.write_bytes(gre_variant(flip_deg=1e-98))
    code, out, err = run_cli(capsys, "simulate", p, "--girf", GIRF, "--dummies", "0", "--json", "-", "-q")
    assert code == 0, err
    d = json.loads(out)
    assert d["nrmse_percent"] is None and d["image_reason"].startswith("no signal: the largest RF flip angle is")
    assert d["kspace_max_error_dk"] > 0.01  # the k error is real: the trajectory is played
    code, out, _ = run_cli(capsys, "simulate", p, "--girf", GIRF, "--dummies", "0", "-q")
    assert "no signal" in " ".join(out.split()) and "0 %" not in out


def test_simulate_and_optimize_share_one_before(variants, capsys, tmp_path):
    """The same file and GIRF: the same 'before' NRMSE in simulate and optimize (a GRE in its steady state in both:
    optimize's 300 dummy repetitions are simulate's default too)."""
    f = variants / "rf10.seq"
    code, out, err = run_cli(capsys, "simulate", f, "--girf", GIRF, "--json", "-", "-q")
    assert code == 0, err
    sim = json.loads(out)
    assert sim["simulation"]["dummies"] == 300 and "300 dummy repetitions" in err
    m = tmp_path / "m.json"
    code, _, err = run_cli(
        capsys, "optimize", f, "-o", tmp_path / "o.seq", "--girf", GIRF, "--gmax", "32", "--smax", "130",
        "--iters", "0", "--warm-iters", "0", "-q", "--no-trajectory", "--json", m,
    )  # fmt: skip
    assert code == 0, err
    before = json.loads(m.read_text())["before"]
    assert before["nrmse_percent"] > 0.1
    assert before["nrmse_percent"] == pytest.approx(sim["nrmse_percent"], rel=1e-6)
    assert before["kspace_max_error_dk"] == pytest.approx(sim["kspace_max_error_dk"], rel=1e-6)


def test_mirrored_phase_layout_is_not_two_lines_wider():
    """Phase lines -N/2+1 .. N/2 (phase encoded from the top, as JEMRIS writes its EPI): 64 lines are a 64 grid
    (the +N/2 line is the -N/2 line of the periodic grid), not 66; the reconstruction puts it there."""
    from dtoc.seq.geometry import infer_cartesian_grid

    n, dk = 64, 2 * math.pi / 0.25
    ro = (np.arange(n) - n / 2) * dk
    lines = [np.stack([ro, np.full(n, (n / 2 - i) * dk), np.zeros(n)]) for i in range(n)]  # +32 .. -31
    g = infer_cartesian_grid(np.concatenate(lines, axis=1), [n] * n)
    assert g is not None and g.matrix_readout_phase == (64, 64)
    assert g.fov_m[1] == pytest.approx(0.25, rel=1e-9)


def test_ramp_sampled_fov_comes_from_the_file_definition(tmp_path):
    """A ramp-sampled EPI with a FOV definition: the readout FOV is the file's, and the note says what the mean
    sampling step would have given (and where the phase step disagrees with the definition)."""
    from foreign.writers import se_epi

    from dtoc.seq.seqtext import sign_text

    b = se_epi(ramp_sampling=True).decode()
    body = b[: b.find("\n[SIGNATURE]")]
    p = tmp_path / "ramp_fov.seq"
    p.write_bytes(sign_text(body.replace("[DEFINITIONS]\n", "[DEFINITIONS]\nFOV 0.22 0.22 0.004 \n")))
    q = tmp_path / "ramp.seq"
    q.write_bytes(b.encode())
    ir0 = load_sequence(q)
    ir = load_sequence(p)
    assert (
        ir.meta["recon"] == "ndft" and ir.fov_m[0] == pytest.approx(0.22) and ir.fov_m[1] == pytest.approx(0.22, 1e-4)
    )
    assert ir0.fov_m[0] != pytest.approx(0.22, rel=1e-3)  # the mean step alone: another FOV
    note = next(n for n in ir.meta["notes"] if n.startswith("ramp-sampled"))
    assert "the file's FOV definition along x" in note and f"{1e3 * ir0.fov_m[0]:.4g} mm" in note
    assert "not the defined" not in note  # the phase step agrees with the definition


def test_pre15_file_optimizes_with_its_detected_rf_use_recorded_and_written(se14, capsys, tmp_path):
    """The 1.4.1 spin-echo EPI end to end: the manifest records each [RF] event's use and how it was decided, the
    written file states them (excitation, refocusing), so its re-read k is centred too."""
    out, m = tmp_path / "o.seq", tmp_path / "m.json"
    code, _, err = run_cli(
        capsys, "optimize", se14, "-o", out, "--ideal", "--gmax", "32", "--smax", "130", "--iters", "0",
        "--warm-iters", "0", "-q", "--no-trajectory", "--json", m,
    )  # fmt: skip
    if code != 0 and "KeyError" in err:
        pytest.skip("this writer cannot write a file read from format 1.4 (issue 36)")
    assert code == 0, err
    assert "worse than the base" not in err  # ideal hardware: 1e-13 % is float noise, not a worse image
    table = json.loads(m.read_text())["sequence"]["rf_use"]
    assert [(e["id"], e["use"], e["how"]) for e in table] == [
        (1, "excitation", "detected"),
        (2, "refocusing", "detected"),
    ]
    ir = load_sequence(out)
    assert [r.use for r in ir.rf] == ["excitation", "refocusing"]
    np.testing.assert_allclose(ir.nominal_kspace_rad_per_m(), load_sequence(se14).nominal_kspace_rad_per_m(), atol=1e-6)


def test_a_file_with_definitions_is_told_the_real_cause(tmp_path):
    """FOV and Matrix defined: never 'no FOV/matrix definitions'; when the samples are on no grid, the note names
    why (kz accumulated by unrewound z blocks), and where they are, it compares the grid with the definitions."""
    defs = {"FOV": [0.22, 0.22, 0.005], "Matrix": [16, 16, 1]}
    p = tmp_path / "kz.seq"
    p.write_bytes(gre_variant(sync_kz_per_m=5.0, definitions=defs))
    notes = " ".join(load_sequence(p).meta["notes"])
    assert (
        "no FOV/matrix definitions" not in notes
        and "the file defines FOV 220 x 220 x 5 mm and matrix 16 x 16 x 1" in notes
    )
    assert "k steps along z too" in notes and "accumulate kz" in notes
    q = tmp_path / "defs.seq"
    q.write_bytes(gre_variant(definitions=defs))
    ir = load_sequence(q)
    notes = " ".join(ir.meta["notes"])
    assert "no FOV/matrix definitions" not in notes and "they agree with the definitions" in notes
    assert ir.geometry.matrix_readout_phase == (16, 16)
    r = tmp_path / "defs2.seq"
    r.write_bytes(gre_variant(definitions={"FOV": [0.11, 0.22, 0.005]}))
    notes = " ".join(load_sequence(r).meta["notes"])
    assert (
        "the ADC positions step by 2 pi / 220 mm along x (readout), not 2 pi / the defined 110 mm (oversampled 2x)"
        in notes
    )


def test_detected_use_of_a_tse_and_an_inversion_prepared_file(tmp_path):
    """1.4.1 versions of the CPMG TSE and the MPRAGE-like file: 90s excite and 180s refocus (the reference rule);
    a 180 followed by an excitation before any ADC sample is an inversion (k at every sample unchanged)."""
    from foreign.writers import mprage, tse
    from foreign.writers_truth import to_v141

    p = tmp_path / "tse.seq"
    p.write_bytes(to_v141(tse()))
    ir = load_sequence(p)
    assert [(e["use"], e["count"]) for e in ir.meta["rf_use"]] == [("excitation", 4), ("refocusing", 32)]
    q = tmp_path / "mprage.seq"
    q.write_bytes(to_v141(mprage(n=16, nz=2, tr_shot=0.6, ti=0.2)))
    ir = load_sequence(q)
    assert [(e["use"], e["flip_deg"]) for e in ir.meta["rf_use"]] == [("inversion", 180.0), ("excitation", 8.0)]
    k_as_refocusing = load_sequence(q, rf_use={1: "refocusing"}).nominal_kspace_rad_per_m()
    np.testing.assert_array_equal(ir.nominal_kspace_rad_per_m(), k_as_refocusing)


def test_a_file_without_encoding_gradients_has_no_image(tmp_path, capsys):
    """An FID (RF + ADC, no gradient) sits at k = 0 at every sample: no image grid is made up from a FOV
    definition (it was given an 8 x 8 grid and a 300-dummy simulation before), simulate refuses in one line."""
    from dtoc.seq.pulseq import import_pypulseq, quiet

    pp = import_pypulseq()
    sys_ = pp.Opts(rf_ringdown_time=20e-6, rf_dead_time=100e-6, adc_dead_time=10e-6)
    seq = pp.Sequence(sys_)
    rf = pp.make_block_pulse(flip_angle=math.radians(30), duration=0.5e-3, system=sys_, use="excitation")
    adc = pp.make_adc(256, dwell=20e-6, delay=100e-6, system=sys_)
    for _ in range(4):
        seq.add_block(rf)
        seq.add_block(adc, pp.make_delay(50e-3))
    seq.set_definition("FOV", [0.25, 0.25, 0.005])
    p = tmp_path / "fid.seq"
    with quiet():
        seq.write(str(p))
    ir = load_sequence(p)
    assert any("every ADC sample sits at k = 0" in n for n in ir.meta.get("notes", []))
    assert ir.matrix is None
    code, _, err = run_cli(capsys, "simulate", p, "-q")
    assert code == 2 and err.strip().splitlines()[-1].startswith("dtoc: error:")
    assert "no image grid" in err
