"""A base that fails a timing rule its output would inherit (issue 36, point 5: fail in seconds, every message true):
``dtoc optimize`` refuses it in the pre-flight, naming the base's own violation, before any optimization work; a
violation dtoc itself introduces still fails the written file's check."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_helpers import run_cli
from foreign.writers_truth import gre_variant

import dtoc.optimize.run as run_mod
from dtoc.seq.check import base_timing_violations, check_file
from dtoc.seq.load import load_sequence
from dtoc.seq.seqtext import sign_text
from dtoc.seq.system import SystemSpec

OPT = ("--ideal", "--gmax", "32", "--smax", "130", "--iters", "2", "--warm-iters", "0", "-q", "--no-trajectory")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("inherited")
    (d / "off.seq").write_bytes(gre_variant(adc_dwell_s=10.05e-6))  # 10050 ns: not a multiple of the 100 ns raster
    (d / "ok.seq").write_bytes(gre_variant())  # 10 us dwell
    return d


def _no_work(monkeypatch):
    """The optimization's first steps raise: a refusal must come before any of them."""

    def boom(*a, **k):
        raise AssertionError("optimization work started")

    for name in ("EdgeTwin", "warm_start_stage", "full_loss_stage", "quality"):
        monkeypatch.setattr(run_mod, name, boom)


def test_base_timing_violations_counts_every_block(files):
    ir = load_sequence(files / "off.seq")
    found = base_timing_violations(ir.source)
    assert [(v.rule, n) for v, n in found] == [("adc_raster", 16)]  # one readout kind, 16 readouts
    v = found[0][0]
    assert v.value == pytest.approx(10050) and v.limit == pytest.approx(100) and v.unit == "ns"
    # the same rule dtoc check applies to the file: the same figure
    res = check_file(files / "off.seq", SystemSpec(max_grad_mT_per_m=32, max_slew_T_per_m_per_s=130))
    assert {w.rule for w in res.violations} == {"adc_raster"} and len(res.violations) == 16
    assert res.violations[0].value == pytest.approx(v.value)
    assert base_timing_violations(load_sequence(files / "ok.seq").source) == []


def test_inherited_violation_refused_before_any_work(files, tmp_path, capsys, monkeypatch):
    _no_work(monkeypatch)
    out = tmp_path / "o.seq"
    code, so, err = run_cli(capsys, "optimize", files / "off.seq", "-o", out, *OPT, "--json", tmp_path / "m.json")
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.startswith("dtoc: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    line = lines[0]
    assert "the base itself fails dtoc check's rule adc_raster" in line
    assert "AdcRasterTime 100 ns declared by the file" in line
    # the first readout is block 3 (RF, prephaser, readout)
    assert "16 block(s), first block 3: ADC dwell not on the file's ADC raster (10050 ns)" in line
    assert not out.exists() and not (tmp_path / "m.json").exists()


def test_violation_dtoc_introduces_still_fails(files, tmp_path, capsys, monkeypatch):
    """A clean base passes the pre-flight; an output whose writer moved the ADC dwell off the raster fails the written
    file's check (exit 1, never "0 violations"), as before."""
    real = run_mod.write_seq_text

    def bad_writer(ir, path, *a, **k):
        v = real(ir, path, *a, **k)
        text = Path(path).read_text()
        Path(path).write_bytes(sign_text(text.replace(" 16 10000 ", " 16 10050 ").encode()))  # [ADC]: num dwell(ns)
        return v

    monkeypatch.setattr(run_mod, "write_seq_text", bad_writer)
    out = tmp_path / "o.seq"
    code, so, err = run_cli(capsys, "optimize", files / "ok.seq", "-o", out, *OPT, "--json", tmp_path / "m.json")
    assert code == 1, err
    flat = " ".join((so + err).split())
    assert "0 violations" not in flat and "the base itself" not in flat
    assert "dtoc check of the written file FAILED: format (Pulseq format 1.5.0): 16 x adc_raster" in flat
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["output"]["check_ok"] is False and "adc_raster" in m["output"]["check_failed"]
