"""Validator: one deliberately broken file (or system) per rule; shipped files pass; CLI exit codes."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from dtoc.errors import InputError
from dtoc.seq.check import check_file, check_ir_limits
from dtoc.seq.read import from_pypulseq
from dtoc.seq.seqtext import sign_text
from dtoc.seq.system import SystemSpec

REPO = Path(__file__).resolve().parents[1]
SEQ = REPO / "sequences"
SMALL = SEQ / "epi_small.seq"


def _edit_field(text: str, section: str, first_token: str, col: int, value: str) -> str:
    """Replace field ``col`` of the line starting with ``first_token`` in ``section``."""
    lines = text.split("\n")
    cur = None
    for i, ln in enumerate(lines):
        s = ln.strip()
        if s.startswith("["):
            cur = s
            continue
        if cur == section and s.split()[:1] == [first_token]:
            t = s.split()
            t[col] = value
            lines[i] = " ".join(t)
            return "\n".join(lines)
    raise AssertionError(f"{section} {first_token} not found")


def _broken(tmp_path, fn, name="broken.seq", resign=True, src=SMALL):
    text = src.read_bytes().decode()
    body = text[: text.find("\n[SIGNATURE]")]
    new = fn(body)
    p = tmp_path / name
    p.write_bytes(sign_text(new) if resign else new.encode())
    return p


def test_shipped_files_pass_except_overlimit_epi():
    for p in sorted(SEQ.glob("*.seq")):
        if p.stem == "epi_esp073":
            continue
        if p.stem not in ("epi_small", "gre_small", "epi_esp081", "gre_paper_r100us"):
            continue  # the rest in the slow test
        r = check_file(p)
        assert r.ok, (p.name, [v.to_dict() for v in r.violations[:3]])


@pytest.mark.slow
def test_all_shipped_files_pass_except_overlimit_epi():
    for p in sorted(SEQ.glob("*.seq")):
        r = check_file(p)
        assert r.ok == (p.stem != "epi_esp073"), p.name


def test_overlimit_epi_rejected_with_slew_figure():
    r = check_file(SEQ / "epi_esp073.seq")
    assert r.rules() == {"slew_rate"} and r.limits_source == "file definitions"
    vals = [v.value for v in r.violations]
    assert len(vals) == 63  # every readout reversal
    # 2 x 9.3946 mT/m over 90 us = 208.77 T/m/s
    g_ro_mT_per_m = 1 / (0.25 * 10e-6) / 42.577478e6 * 1e3
    assert max(vals) == pytest.approx(2 * g_ro_mT_per_m / 90e-6 * 1e-3, rel=1e-5)
    assert all(v.axis == "x" and v.limit == 180 for v in r.violations)


def test_grad_amplitude(tmp_path):
    r = check_file(SMALL, SystemSpec(max_grad_mT_per_m=9.0))  # readout is 9.39 mT/m
    assert "grad_amplitude" in r.rules()
    assert max(v.value for v in r.violations if v.rule == "grad_amplitude") > 9.39


def test_grad_vector():
    r = check_file(SMALL, SystemSpec(max_grad_vector_mT_per_m=9.5))  # x 9.39 and y blips together
    assert "grad_vector" in r.rules() and "grad_amplitude" not in r.rules()


def test_slew_vector():
    r = check_file(SMALL, SystemSpec(max_slew_vector_T_per_m_per_s=160.0))
    assert "slew_vector" in r.rules() and "slew_rate" not in r.rules()


def test_half_raster_edge_segment_slew():
    """An arbitrary gradient starts at first=0 and its first raster-centre sample is 1 mT/m: the played
    slew on that half-raster segment is 1 mT/m / 5 us = 200 T/m/s (a raster-step estimate says 100)."""
    import pypulseq as pp

    from dtoc.constants import hz_per_m_from_mT_per_m

    sys_ = pp.Opts(max_grad=80, grad_unit="mT/m", max_slew=1000, slew_unit="T/m/s")
    seq = pp.Sequence(system=sys_)
    w = hz_per_m_from_mT_per_m(np.ones(20))
    seq.add_block(pp.make_arbitrary_grad("x", w, first=0.0, last=0.0, system=sys_))
    ir = from_pypulseq(seq)
    v = check_ir_limits(ir, SystemSpec(max_slew_T_per_m_per_s=180.0))
    assert [x.rule for x in v] == ["slew_rate"]
    assert v[0].value == pytest.approx(200.0, rel=1e-9)
    assert not check_ir_limits(ir, SystemSpec(max_slew_T_per_m_per_s=201.0))


def test_slew_on_overlimit_file():
    r = check_file(SMALL, SystemSpec(max_slew_T_per_m_per_s=100.0))
    assert "slew_rate" in r.rules()


def test_continuity(tmp_path):
    # flat readout of block 3 (gradient 5) played 0.5 % low: jumps against its neighbours
    p = _broken(tmp_path, lambda t: _edit_field(t, "[GRADIENTS]", "5", 1, "398000"))
    r = check_file(p)
    assert "continuity" in r.rules()
    v = [x for x in r.violations if x.rule == "continuity"][0]
    assert v.value == pytest.approx(2000.0, rel=1e-6) and v.axis == "x"


def test_gradient_ends_nonzero_inside_block(tmp_path):
    p = _broken(tmp_path, lambda t: _edit_field(t, "[BLOCKS]", "3", 1, "17"))  # block 3 longer than its gradient
    assert "grad_end_nonzero" in check_file(p).rules()


def test_sequence_ends_nonzero(tmp_path):
    def drop_last_block(t):
        lines = t.split("\n")
        i = max(
            j
            for j, ln in enumerate(lines)
            if re.match(r"^\s*\d+\s+\d+\s+\d+\s+\d+", ln) and j < t[: t.find("[RF]")].count("\n")
        )
        del lines[i]
        return "\n".join(lines)

    r = check_file(_broken(tmp_path, drop_last_block))
    assert "grad_end_nonzero" in r.rules()
    assert any("sequence ends" in v.message for v in r.violations)


def test_gradient_starts_nonzero_after_delay(tmp_path):
    p = _broken(tmp_path, lambda t: _edit_field(t, "[GRADIENTS]", "5", 6, "10"))
    assert "grad_start_nonzero" in check_file(p).rules()


def test_block_duration_too_short(tmp_path):
    p = _broken(tmp_path, lambda t: _edit_field(t, "[BLOCKS]", "3", 1, "15"))
    assert "block_duration" in check_file(p).rules()


def test_block_raster(tmp_path):
    def fine_block_raster(t):
        t = t.replace("BlockDurationRaster 1e-05", "BlockDurationRaster 1e-06")
        lines = t.split("\n")
        out, cur = [], None
        for ln in lines:
            s = ln.strip()
            if s.startswith("["):
                cur = s
            elif cur == "[BLOCKS]" and s and not s.startswith("#"):
                tok = s.split()
                tok[1] = str(int(tok[1]) * 10 + (5 if tok[0] == "2" else 0))  # block 2: +5 us
                ln = " ".join(tok)
            out.append(ln)
        return "\n".join(out)

    p = _broken(tmp_path, fine_block_raster)
    r = check_file(p)  # the file's own (1 us) block raster: block 2 is off the 10 us gradient raster
    assert r.rules() == {"block_raster"} and "block 2" in r.violations[0].message
    r = check_file(p, SystemSpec())  # Siemens: 10 us block raster
    assert r.rules() == {"block_raster", "raster"}


def test_grad_raster(tmp_path):
    p = _broken(tmp_path, lambda t: _edit_field(t, "[TRAP]", "1", 2, "95"))  # gz rise 95 us
    assert "grad_raster" in check_file(p).rules()


def test_rf_dead_time(tmp_path):
    """A vendor convention: checked when a system names it, never from the file's limits alone."""
    p = _broken(tmp_path, lambda t: _edit_field(t, "[RF]", "1", 6, "50"))
    r = check_file(p, SystemSpec(max_grad_mT_per_m=50, max_slew_T_per_m_per_s=500))
    assert "rf_dead_time" in r.rules()
    v = next(x for x in r.violations if x.rule == "rf_dead_time")
    assert v.kind == "convention" and v.source == "system siemens-7T-terra" and v.value == pytest.approx(50)
    r = check_file(p)
    assert "rf_dead_time" not in r.rules() and "not checked" in r.not_checked[0]


def test_rf_ringdown():
    r = check_file(
        SEQ / "gre_small.seq", SystemSpec(max_grad_mT_per_m=50, max_slew_T_per_m_per_s=500, rf_ringdown_time_s=150e-6)
    )
    assert r.rules() == {"rf_ringdown"}


def test_rf_raster(tmp_path):
    """The RF delay off the file's own RF raster breaks the format; the file's 1 us raster on a scanner with a 3 us
    one breaks that scanner's convention."""
    r = check_file(SMALL, SystemSpec(rf_raster_s=3e-6))
    assert (
        r.rules() == {"raster"} and "RadiofrequencyRasterTime 1 us is not a whole multiple" in r.violations[0].message
    )
    p = _broken(tmp_path, lambda t: _edit_field(t, "[RF]", "1", 6, "100").replace(
        "RadiofrequencyRasterTime 1e-06", "RadiofrequencyRasterTime 3e-06"))  # fmt: skip
    r = check_file(p)
    assert "rf_raster" in r.rules() and next(v for v in r.violations if v.rule == "rf_raster").kind == "format"


def test_adc_dead_time():
    r = check_file(SMALL, SystemSpec(adc_dead_time_s=10e-6))  # ADC fills the flat block
    assert r.rules() == {"adc_dead_time"}


def test_adc_raster(tmp_path):
    p = _broken(tmp_path, lambda t: _edit_field(t, "[ADC]", "1", 2, "9950"))  # dwell 9.95 us
    assert "adc_raster" in check_file(p).rules()


def test_adc_sample_count(tmp_path):
    p = _broken(tmp_path, lambda t: _edit_field(t, "[ADC]", "1", 1, "14"))
    assert "adc_samples" not in check_file(p).rules()  # a vendor convention: not from the file's limits alone
    r = check_file(p, SystemSpec(max_grad_mT_per_m=50, max_slew_T_per_m_per_s=500))
    assert "adc_samples" in r.rules()
    assert check_file(SMALL, SystemSpec(adc_max_samples=8)).rules() == {"adc_samples"}


def test_signature_mismatch_and_missing(tmp_path):
    p = _broken(tmp_path, lambda t: t.replace("Created by PyPulseq", "Created by someone"), resign=False)
    p.write_bytes(p.read_bytes() + SMALL.read_bytes()[SMALL.read_bytes().find(b"\n[SIGNATURE]") :])
    r = check_file(p)
    assert r.rules() == {"signature"} and "!=" in r.violations[0].message
    q = _broken(tmp_path, lambda t: t, name="unsigned.seq", resign=False)
    r = check_file(q)  # the signature is optional in the specification: a warning, not a violation
    assert r.ok and any("unsigned" in w for w in r.warnings)


def test_line_endings(tmp_path):
    p = _broken(tmp_path, lambda t: t.replace("\n", "\r\n"))
    assert check_file(p).rules() == {"line_endings"}


def test_integer_fields_without_scientific_notation(tmp_path):
    # pypulseq 1.5.0.post1 writes an RF delay >= 1 s as 1e+06; the same form for 100 us:
    p = _broken(tmp_path, lambda t: _edit_field(t, "[RF]", "1", 6, "1e+02"))
    r = check_file(p)
    assert r.rules() == {"integer_format"}
    assert "'1e+02'" in r.violations[0].message


def test_required_definitions(tmp_path):
    p = _broken(tmp_path, lambda t: t.replace("AdcRasterTime 1e-07 \n", ""))
    r = check_file(p)
    assert r.rules() == {"definitions"} and "AdcRasterTime" in r.violations[0].message


def test_raster_differs_from_system():
    r = check_file(SEQ / "gre_paper_r100us.seq", SystemSpec(max_grad_mT_per_m=50, max_slew_T_per_m_per_s=500))
    assert "raster" in r.rules()


def test_unreadable_file_is_an_input_error(tmp_path):
    p = tmp_path / "t.seq"
    p.write_bytes(SMALL.read_bytes()[:1500])
    with pytest.raises(InputError, match="truncated"):
        check_file(p)


def test_cli_check_exit_codes_and_json(tmp_path, capsys):
    from dtoc.cli.main import run

    with pytest.raises(SystemExit) as e:
        run(["check", str(SMALL)])
    assert e.value.code == 0
    assert "OK: no violations" in capsys.readouterr().out  # the table is on stdout
    with pytest.raises(SystemExit) as e:
        run(["check", str(SEQ / "epi_esp073.seq"), "--json", "-"])
    assert e.value.code == 1
    d = json.loads(capsys.readouterr().out)
    assert d["ok"] is False and d["n_violations"] == 63 and d["violations"][0]["rule"] == "slew_rate"
    with pytest.raises(SystemExit) as e:
        run(["check", str(SMALL), "--gmax", "5"])
    assert e.value.code == 1
    capsys.readouterr()
    sysf = tmp_path / "sys.yaml"
    sysf.write_text("max_slew_T_per_m_per_s: 100\n")
    with pytest.raises(SystemExit) as e:
        run(["check", str(SMALL), "--system", str(sysf), "--json", "-"])
    assert e.value.code == 1
    assert json.loads(capsys.readouterr().out)["limits_source"].startswith("--system")
    with pytest.raises(SystemExit) as e:  # a sequence spec as --system: its design system
        run(["check", str(SEQ / "epi_esp073.seq"), "--system", str(SEQ / "epi_esp073.yaml")])
    assert e.value.code == 1 and "208.8" in capsys.readouterr().out
    sysf.write_text("max_slew: 100\n")
    with pytest.raises(SystemExit) as e:
        run(["check", str(SMALL), "--system", str(sysf)])
    assert e.value.code == 2
    assert "max_slew: unknown key" in capsys.readouterr().err


def _limits_reference(ir, system):
    """The checker's rules written the plain way (per-sample block tables, whole-array norms): the
    memory-lean check_ir_limits must give exactly these violations."""
    g = ir.grad_mT_per_m
    dtf = ir.dt_fine_s
    m_edges = np.round(np.asarray(ir.block_edges_s) / dtf).astype(np.int64)
    nb = len(m_edges) - 1
    seg_block = np.searchsorted(m_edges, np.arange(g.shape[1] - 1), side="right") - 1
    smp_block = np.clip(np.searchsorted(m_edges, np.arange(g.shape[1]), side="right") - 1, 0, nb - 1)
    slew = np.diff(g, axis=1) / dtf * 1e-3
    out = []

    def worst(rule, vals, blocks, limit, axis):
        bad = np.flatnonzero(np.abs(vals) > limit * (1 + 1e-6))
        for b in np.unique(blocks[bad]):
            sel = bad[blocks[bad] == b]
            i = sel[np.argmax(np.abs(vals[sel]))]
            out.append((rule, int(b) + 1, axis, float(abs(vals[i])), round(i * dtf * 1e3, 3)))

    for a in range(3):
        worst("grad_amplitude", g[a], smp_block, system.max_grad_mT_per_m, "xyz"[a])
        worst("slew_rate", slew[a], seg_block, system.max_slew_T_per_m_per_s, "xyz"[a])
    worst("grad_vector", np.linalg.norm(g, axis=0), smp_block, system.vector_grad_limit_mT_per_m, None)
    worst("slew_vector", np.linalg.norm(slew, axis=0), seg_block, system.vector_slew_limit_T_per_m_per_s, None)
    return out


def test_check_ir_limits_equals_plain_reference():
    """Random waveforms over blocks of uneven length, violations at block boundaries, the last sample and
    in several blocks at once: the same (rule, block, axis, worst value, time) as the plain computation."""
    from dtoc.seq.ir import SequenceIR

    rng = np.random.default_rng(7)
    raster = 10e-6
    n_r = rng.integers(3, 40, size=25)
    edges = np.concatenate([[0], np.cumsum(n_r)]) * raster
    n_fine = 2 * int(n_r.sum()) + 1
    g = rng.normal(0, 12, size=(3, n_fine))
    g[0, 0] = 45.0  # first sample
    g[1, -1] = -50.0  # last sample (belongs to the last block)
    m_edges = np.round(edges / (raster / 2)).astype(int)
    g[2, m_edges[5]] = 60.0  # a block boundary sample: the block it starts
    ir = SequenceIR(raster_s=raster, grad_mT_per_m=g, block_edges_s=edges)
    system = SystemSpec(max_grad_mT_per_m=32.0, max_slew_T_per_m_per_s=130.0)
    got = [
        (v.rule, v.block, v.axis, v.value, float(re.search(r"t = ([\d.]+) ms", v.message).group(1)))
        for v in check_ir_limits(ir, system)
    ]
    want = _limits_reference(ir, system)
    assert len(want) > 50 and {w[0] for w in want} == {"grad_amplitude", "slew_rate", "grad_vector", "slew_vector"}
    assert got == want


_HALF_RASTER_SEQ = """# Pulseq sequence file
# a shaped gradient sampled at raster centres through an explicit time shape (as Pulseq MATLAB writes some)

[VERSION]
major 1
minor 4
revision 1

[DEFINITIONS]
AdcRasterTime 1e-07
BlockDurationRaster 1e-05
GradientRasterTime 1e-05
RadiofrequencyRasterTime 1e-06

[BLOCKS]
1 100   0   1   0   0   0   0

[GRADIENTS]
1 100000 1 2 0

[SHAPES]

shape_id 1
num_samples 4
0
1
1
0

shape_id 2
num_samples 4
TIMES

"""


@pytest.mark.parametrize("times, ok", [("0.5 1.5 2.5 3.5", True), ("0 1 2 3", True), ("0.25 1.5 2.5 3.5", False)])
def test_shaped_gradient_times_on_the_half_raster_are_the_formats(tmp_path, times, ok):
    """Shaped-gradient times at raster centres (x.5 rasters: arbitrary gradients, 1.5.1 oversampling) are legal
    (a field-camera calibration file got a false grad_raster violation); a quarter raster is not."""
    p = tmp_path / "half.seq"
    p.write_text(_HALF_RASTER_SEQ.replace("TIMES", "\n".join(times.split())))
    res = check_file(p, SystemSpec(max_grad_mT_per_m=40, max_slew_T_per_m_per_s=1000))
    assert res.ok is ok
    assert ok or {v.rule for v in res.violations} == {"grad_raster"}
