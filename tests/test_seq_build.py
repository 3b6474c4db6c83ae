"""Specs and the builder: golden files, determinism, paper numbers, over-limit warning, bad specs."""

import warnings
from pathlib import Path

import numpy as np
import pytest

from dtoc.constants import mT_per_m_from_hz_per_m
from dtoc.errors import InputError
from dtoc.seq.build import SpecLimitWarning, build, build_ir, build_to_file, seq_bytes
from dtoc.seq.spec import EpiSpec, load_spec, parse_spec

REPO = Path(__file__).resolve().parents[1]
SEQ = REPO / "sequences"
SPECS = sorted(p.stem for p in SEQ.glob("*.yaml"))
FAST = ["gre_small", "epi_small", "epi_esp081", "gre_paper_r100us"]
#: the pypulseq that wrote the golden files; another 1.5.x may format numbers differently, so with it
#: the golden files are compared semantically (dtoc diff) instead of byte for byte
GOLDEN_PYPULSEQ = "1.5.0.post1"


def _assert_matches_golden(name, data, tmp_path):
    import pypulseq

    golden = SEQ / f"{name}.seq"
    if pypulseq.__version__ == GOLDEN_PYPULSEQ:
        assert data == golden.read_bytes()
    else:
        from dtoc.seq.diff import diff_files

        p = tmp_path / f"{name}.seq"
        p.write_bytes(data)
        r = diff_files(golden, p, rtol=1e-5, atol=1e-9)
        assert r.same, r.differences[:3]


def test_shipped_specs_have_golden_files():
    assert {"gre_paper", "epi_esp073", "epi_esp081", "epi_esp261"} <= set(SPECS)
    assert len([s for s in SPECS if s.startswith("epi_esp")]) == 7
    for s in SPECS:
        assert (SEQ / f"{s}.seq").is_file(), s


def _build_matches_golden(name, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SpecLimitWarning)
        data = seq_bytes(build(load_spec(SEQ / f"{name}.yaml")))
    _assert_matches_golden(name, data, tmp_path)


@pytest.mark.parametrize("name", FAST)
def test_build_reproduces_golden_bytes(name, tmp_path):
    _build_matches_golden(name, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("name", SPECS)
def test_build_reproduces_golden_bytes_all(name, tmp_path):
    _build_matches_golden(name, tmp_path)


def test_build_is_deterministic_and_atomic(tmp_path):
    spec = load_spec(SEQ / "epi_small.yaml")
    a, b = tmp_path / "a.seq", tmp_path / "b.seq"
    build_to_file(spec, a)
    build_to_file(spec, b)
    assert a.read_bytes() == b.read_bytes()
    with pytest.raises(InputError, match="exists"):
        build_to_file(spec, a)
    build_to_file(spec, a, force=True)
    assert not list(tmp_path.glob(".*tmp"))


def test_gre_paper_timing_and_amplitudes():
    ir = build_ir(load_spec(SEQ / "gre_paper.yaml"))
    assert len(ir.rf) == 32 and len(ir.adc) == 32
    tr = 10e-3
    for j, (rf, adc) in enumerate(zip(ir.rf, ir.adc)):
        assert rf.t_center_s == pytest.approx(j * tr + 1.0e-3, abs=1e-9)
        assert rf.flip_angle_rad == pytest.approx(np.deg2rad(15), rel=1e-5)
        assert adc.t_start_s == pytest.approx(j * tr + 2.5e-3, abs=1e-9)  # 0.5 ms after the 2 ms RF period
        assert adc.num_samples == 32 and adc.dwell_s == pytest.approx(100e-6)
        # RF spoiling: quadratic phase, increment 117 deg, receiver follows
        want = np.deg2rad((117.0 * j * (j + 1) / 2) % 360)
        assert np.angle(np.exp(1j * (rf.phase_rad - want))) == pytest.approx(0, abs=1e-5)  # {:g}: 6 digits
        assert adc.phase_rad == pytest.approx(rf.phase_rad, abs=1e-9)
    g = ir.grad_mT_per_m
    # no gradient during the RF period
    rf_m = int(round(2e-3 / ir.dt_fine_s))
    assert np.abs(g[:, : rf_m + 1]).max() == 0
    # readout 1/(FOV*dwell) = 312.5 kHz/m = 7.34 mT/m; spoiler 17.6 mT/m; prewinder ~ -28 mT/m
    assert np.interp(ir.adc[0].sample_times_s, ir.t_fine_s, g[0]) == pytest.approx(
        np.full(32, mT_per_m_from_hz_per_m(312500.0)), rel=1e-6
    )
    assert mT_per_m_from_hz_per_m(312500.0) == pytest.approx(7.34, abs=0.005)
    assert g[0].max() == pytest.approx(17.6, rel=1e-5)
    assert -32 < g[0].min() < -25
    # TE: RF centre to the k = 0 sample
    assert ir.definitions["TE"] == pytest.approx(3.15e-3)
    k = ir.nominal_kspace_rad_per_m() / ir.dk_rad_per_m[:, None]
    kx = k[0].reshape(32, 32)
    ky = k[1].reshape(32, 32)
    assert np.abs(kx - (np.arange(32) - 16)[None, :]).max() < 1e-4
    assert np.abs(ky - (np.arange(32) - 16)[:, None]).max() < 1e-4


def test_epi_echo_spacings_and_overlimit_warning():
    with pytest.warns(SpecLimitWarning, match=r"slew_rate x 208\.8 > 180"):
        build(EpiSpec(name="e073", echo_spacing_ms=0.73))
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpecLimitWarning)
        build(EpiSpec(name="e075", echo_spacing_ms=0.75))  # shortest legal: ramps of 60 us each... within 180 T/m/s


def test_epi_te_option():
    shortest = build_ir(EpiSpec(name="e", matrix=16, echo_spacing_ms=0.30)).definitions["TE"]
    ir = build_ir(EpiSpec(name="e", matrix=16, echo_spacing_ms=0.30, te_ms=10.0))
    te = ir.definitions["TE"]
    assert te == pytest.approx(10e-3, abs=5e-6 + 1e-12) and shortest < 5e-3  # nearest TE on the raster
    # the k = 0 sample (line 8, sample 8) is at the RF centre + TE
    i0 = 8 * 16 + 8
    assert ir.adc_times_s[i0] - ir.rf[0].t_center_s == pytest.approx(te, abs=1e-9)
    k = ir.nominal_kspace_rad_per_m()[:, i0]
    assert np.abs(k).max() < 1e-3 * ir.dk_rad_per_m[0]


def test_spec_partial_system_keeps_kind_defaults():
    s = parse_spec({"kind": "gre", "name": "g", "system": {"max_grad_mT_per_m": 30}})
    assert s.system.max_grad_mT_per_m == 30 and s.system.max_slew_T_per_m_per_s == 500


@pytest.mark.parametrize(
    "data, msg",
    [
        ({"kind": "gre", "name": "g", "fov_mm": 0}, r"fov_mm: Input should be greater than 0"),
        ({"kind": "gre", "name": "g", "te_ms": 1.0}, r"te_ms 1 is shorter than the minimum 3\.020 ms"),
        ({"kind": "epi", "name": "e", "echo_spacing_ms": 0.81, "te_ms": 10}, r"te_ms 10 is shorter than the minimum"),
        ({"kind": "gre", "name": "g", "dwell_us": -10}, r"dwell_us: Input should be greater than 0"),
        ({"kind": "gre", "name": "g", "fov": 32}, r"fov: unknown key"),
        ({"kind": "gre", "name": "g", "system": {"gmax": 3}}, r"system.gmax: unknown key"),
        ({"kind": "spiral", "name": "s"}, r"kind 'spiral' is not known"),
        ({"name": "s"}, r"missing key 'kind'"),
        ({"kind": "gre", "name": "g", "matrix": 31}, r"matrix must be even"),
        ({"kind": "gre", "name": "g", "tr_ms": 5}, r"tr_ms 5 is too short"),
        ({"kind": "epi", "name": "e", "echo_spacing_ms": 0.64}, r"leaves no time to reverse"),
        ({"kind": "epi", "name": "e"}, r"echo_spacing_ms: Field required"),
    ],
)
def test_bad_specs_one_line_errors(data, msg):
    with pytest.raises(InputError, match=msg) as ei:
        s = parse_spec(data, "spec.yaml")
        build(s, warn=False)
    assert "\n" not in str(ei.value)


def test_bad_spec_files(tmp_path):
    p = tmp_path / "s.yaml"
    with pytest.raises(InputError, match="spec file not found"):
        load_spec(p)
    p.write_text("kind: gre\nname: [unclosed\n")
    with pytest.raises(InputError, match="not valid YAML at line"):
        load_spec(p)
    p.write_text("- 1\n- 2\n")
    with pytest.raises(InputError, match="must be a mapping"):
        load_spec(p)
    p.write_bytes(b"\xff\xfe\x00bin")
    with pytest.raises(InputError, match="not a text file"):
        load_spec(p)
