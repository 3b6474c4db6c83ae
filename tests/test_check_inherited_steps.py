"""A base's own gradient steps, kept by its output, are inherited; steps dtoc introduces fail before anything is
written (issue 36, the trufi files: the final check tells the two apart).

The base (a small GRE written here) steps its slice-select axis (z, never changed by the optimizer) between the RF
block and the next one by ``STEP`` Hz/m: within the slew limit (Pulseq's own continuity tolerance is smax x one
gradient raster) but above ``dtoc check``'s 1 Hz/m.  dtoc's writer rewrites only the blocks and axes it changes, so
the output keeps that step at the same block and axis, no larger: reported as inherited (stderr, manifest), exit 0.
The same step in an output whose base has none is introduced: one line, exit 1, nothing written."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from cli_helpers import run_cli

import dtoc.optimize.run as run_mod
from dtoc.seq.check import check_file, split_inherited, step_limit_hz_per_m
from dtoc.seq.system import SystemSpec

REPO = Path(__file__).resolve().parents[1]
GIRF = REPO / "girf" / "example_7T.npz"
STEP = 2000.0  # Hz/m (0.047 mT/m): well within 130 T/m/s x 10 us (55 kHz/m)
LIMITS = SystemSpec(max_grad_mT_per_m=32, max_slew_T_per_m_per_s=130)
RUN = ("--gmax", "32", "--smax", "130", "--warm-iters", "30", "--iters", "0", "--threads", "1", "-q")
RUN += ("--no-trajectory",)


def gre_with_z_step(step_hz_per_m: float, n: int = 8) -> bytes:
    """A 2D GRE (n x n) whose z rephaser starts at ``step_hz_per_m`` after the slice-select trapezoid ended at 0."""
    import pypulseq as pp

    from dtoc.seq.pulseq import quiet

    sys = pp.Opts(max_grad=32, grad_unit="mT/m", max_slew=130, slew_unit="T/m/s", rf_ringdown_time=30e-6,
                  rf_dead_time=100e-6, adc_dead_time=10e-6)  # fmt: skip
    # the writer's neighbour check (pypulseq: |step| <= its max_slew x raster) lifted, as other writers do not make it
    loose = pp.Opts(max_grad=32, grad_unit="mT/m", max_slew=5000, slew_unit="T/m/s", rf_ringdown_time=30e-6,
                    rf_dead_time=100e-6, adc_dead_time=10e-6)  # fmt: skip
    seq = pp.Sequence(loose)
    rf, gz, _ = pp.make_sinc_pulse(flip_angle=math.radians(10), duration=1e-3, slice_thickness=5e-3, system=sys,
                                   return_gz=True, delay=sys.rf_dead_time)  # fmt: skip
    gzr = pp.make_extended_trapezoid("z", times=[0, 2e-4, 6e-4, 8e-4], amplitudes=[step_hz_per_m, -gz.amplitude / 2,
                                     -gz.amplitude / 2, 0], system=loose)  # fmt: skip
    dk = 1 / 0.22
    gx = pp.make_trapezoid("x", flat_area=n * dk, flat_time=1.6e-3, system=sys)
    adc = pp.make_adc(n, duration=gx.flat_time, delay=gx.rise_time, system=sys)
    gxpre = pp.make_trapezoid("x", area=-gx.area / 2, duration=8e-4, system=sys)
    for i in range(n):
        seq.add_block(rf, gz)
        seq.add_block(gxpre, pp.make_trapezoid("y", area=(i - n / 2) * dk, duration=8e-4, system=sys), gzr)
        seq.add_block(gx, adc)
        seq.add_block(pp.make_trapezoid("x", area=2 * n * dk, system=sys))
    with quiet():
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / "g.seq"
            seq.write(str(p))
            return p.read_bytes()


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("steps")
    (d / "step.seq").write_bytes(gre_with_z_step(STEP))
    (d / "clean.seq").write_bytes(gre_with_z_step(0.0))
    return d


def _steps(path: Path) -> list:
    return [v for v in check_file(path, LIMITS).violations if v.rule == "continuity"]


def test_the_base_steps_where_it_is_written(files):
    """The test's base: one continuity step per RF period, block 2, 6, ... on z, of STEP; the clean twin has none."""
    s = _steps(files / "step.seq")
    assert [(v.block, v.axis) for v in s] == [(2 + 4 * i, "z") for i in range(8)]
    assert all(v.value == pytest.approx(STEP, rel=1e-5) for v in s)
    assert not _steps(files / "clean.seq")


def test_split_inherited_rules():
    """Same rule, block and axis, not worse (up to the rule's 1 Hz/m), within smax x raster: inherited; worse, new, or
    beyond the slew limit's step: introduced."""
    from dtoc.seq.check import Violation

    def v(block, value):
        return Violation("continuity", block, "z", value, 1.0, "Hz/m", "jump")

    base = [v(2, 2000.0), v(6, 1e5)]
    step = step_limit_hz_per_m(LIMITS)
    assert step == pytest.approx(130 * 10e-6 * 42.577478e6)  # 55.35 kHz/m
    intro, inh = split_inherited([v(2, 2000.5), v(2, 2002.0), v(3, 10.0), v(6, 1e5)], base, LIMITS)
    assert [(w.block, w.value) for w, _ in inh] == [(2, 2000.5)]
    assert [(w.block, w.value) for w in intro] == [(2, 2002.0), (3, 10.0), (6, 1e5)]  # worse; new; beyond the slew


@pytest.mark.skipif(not GIRF.exists(), reason="girf/example_7T.npz absent")
def test_inherited_step_passes_and_is_reported(files, tmp_path, capsys):
    out, man = tmp_path / "o.seq", tmp_path / "o.json"
    code, so, err = run_cli(capsys, "optimize", files / "step.seq", "--girf", GIRF, "-o", out, "--json", man, *RUN)
    assert code == 0, err
    m = json.loads(man.read_text())
    assert m["after"]["kspace_max_error_dk"] < m["before"]["kspace_max_error_dk"]  # it did optimize (x, y changed)
    inh = m["output"]["check_inherited"]
    assert [(r["rule"], r["block"], r["axis"]) for r in inh] == [("continuity", 2 + 4 * i, "z") for i in range(8)]
    assert all(r["value"] == pytest.approx(STEP, rel=1e-5) and r["base_value"] == pytest.approx(STEP, rel=1e-5)
               for r in inh)  # fmt: skip
    assert m["output"]["check_ok"] is True
    flat = " ".join(err.split())
    assert "dtoc: warning: the output keeps the base's own gradient steps" in flat
    assert "8 x continuity (worst 2000 Hz/m at block" in flat and "the base's 2000 Hz/m" in flat
    assert "0 violations introduced, 8 inherited from the base" in flat and "Traceback" not in err
    # the written file does have them (what is reported is true of the file)
    assert [(v.block, v.axis) for v in _steps(out)] == [(2 + 4 * i, "z") for i in range(8)]


@pytest.mark.skipif(not GIRF.exists(), reason="girf/example_7T.npz absent")
def test_introduced_step_fails_before_writing(files, tmp_path, capsys, monkeypatch):
    """The clean base, its output written as the stepped file (a writer that introduced the steps): one line, exit 1,
    nothing written."""
    stepped = (files / "step.seq").read_bytes()
    monkeypatch.setattr(
        run_mod, "write_seq_text", lambda ir, path, *a, **k: (Path(path).write_bytes(stepped), (1, 5, 0))[1]
    )
    out, man = tmp_path / "o.seq", tmp_path / "o.json"
    code, so, err = run_cli(capsys, "optimize", files / "clean.seq", "--girf", GIRF, "-o", out, "--json", man, *RUN)
    assert code == 1, err
    lines = [ln for ln in err.splitlines() if ln.startswith("dtoc: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert "written file fails dtoc check: continuity at block 2, axis z" in lines[0]
    assert "the base has none there: introduced by the optimization; nothing written" in lines[0]
    assert not out.exists() and not man.exists()


def test_a_base_step_beyond_the_slew_limit_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """80 kHz/m (1.88 mT/m) in one step where dtoc may not change the waveform (the slice axis): beyond 130 T/m/s x
    10 us (55 kHz/m), a limit question (never inherited): one line naming it, before any optimization work."""
    base = tmp_path / "big.seq"
    base.write_bytes(gre_with_z_step(80000.0))

    def boom(*a, **k):
        raise AssertionError("optimization work started")

    monkeypatch.setattr(run_mod, "EdgeTwin", boom)
    out = tmp_path / "o.seq"
    code, so, err = run_cli(capsys, "optimize", base, "--ideal", "-o", out, *RUN)
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.startswith("dtoc: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert "the base itself needs" in lines[0] and "above smax 130 on z" in lines[0]
    assert "dtoc never writes beyond the limits" in lines[0] and not out.exists()


@pytest.mark.parametrize(
    ("base_value", "out_value", "says"),
    [
        (None, 2000.0, "the base has none there: introduced by the optimization"),
        (2000.0, 2500.0, "worse than the base's 2000 Hz/m there: introduced by the optimization"),
        (6e4, 6e4, "the base itself steps 60000 Hz/m there, more than the 55351 Hz/m the slew limit allows"),
        (2000.0, 2000.0, None),  # inherited: no error, the record returned
    ],
)
def test_settle_inherited_says_why(monkeypatch, base_value, out_value, says):
    import dtoc.seq.check as C
    from dtoc.errors import ValidationFailed

    def v(value):
        return C.Violation("continuity", 2, "z", value, 1.0, "Hz/m", "jump from block 1: 0 -> x Hz/m")

    res = C.CheckResult(path="o.seq", system=LIMITS, limits_source="test", violations=[v(out_value)])
    monkeypatch.setattr(
        C, "gradient_rule_violations", lambda seq, system: [] if base_value is None else [v(base_value)]
    )
    if says is None:
        recs = C.settle_inherited(res, object(), LIMITS)
        assert res.violations == [] and [(r["block"], r["value"], r["base_value"]) for r in recs] == [
            (2, 2000.0, 2000.0)
        ]
        return
    with pytest.raises(ValidationFailed) as e:
        C.settle_inherited(res, object(), LIMITS)
    assert "written file fails dtoc check: continuity at block 2, axis z" in str(e.value) and says in str(e.value)
    assert str(e.value).endswith("nothing written")
