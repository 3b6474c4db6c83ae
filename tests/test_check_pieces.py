"""The check of a long written text in the read-back's pieces (issue 32: the export in bounded memory): the same
:class:`CheckResult` as the whole text's -- violations (rule, block, axis, figures, messages, in the same order),
checks, warnings, not-checked rules, sources and the inherited steps -- on texts cut into many small pieces."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import run_cli

from dtoc.seq import check as C
from dtoc.seq import write as W
from dtoc.seq.check import SafetyChecks, check_file, check_file_pieces, settle_inherited
from dtoc.seq.ir import edges_to_fine
from dtoc.seq.read import read_seq
from dtoc.seq.system import SystemSpec
from tests.foreign import writers
from tests.test_check_inherited_steps import GIRF, RUN, STEP, gre_with_z_step
from tests.test_pns import _example_model


def _written(tmp_path, data: bytes, spike=None, axes=(0, 1, 2)):
    """(output IR, path of its written text): the base ``data`` with every free edge of ``axes`` moved smoothly,
    and ``spike`` = (edge index, axis, mT/m) added."""
    p = tmp_path / "base.seq"
    p.write_bytes(data)
    ir = read_seq(p)
    e = ir.edge_grad_mT_per_m
    t = np.arange(e.shape[1]) * ir.raster_s
    on = np.isin(np.arange(3), axes)[:, None]
    e = e + (ir.free_mask[:, ::2] & on) * 0.02 * np.sin(2 * np.pi * t / (1e-3 * np.sqrt(2)))
    if spike is not None:
        e[spike[1], spike[0]] += spike[2]
    out = ir.with_grad(edges_to_fine(e))
    q = tmp_path / "out.seq"
    q.write_bytes(W.seq_bytes_of(out, version=W.writable_version(out), verify=False))
    return out, q


def _small_pieces(monkeypatch, out, n=6):
    monkeypatch.setattr(W, "VERIFY_PIECE_RASTER", max(round(out.duration_s / out.raster_s / n), 1))
    spans = W.verify_spans(out)
    assert len(spans) >= 4
    return spans


def _same(tmp_path, monkeypatch, out, q, system, safety=None):
    """The whole check and the piecewise one of ``q``: equal in every field; the pieces were used (no fallback)."""
    spans = _small_pieces(monkeypatch, out)
    whole = check_file(q, system, safety, conventions=None)
    calls = []
    monkeypatch.setattr(C, "check_file", lambda *a, **k: calls.append(a) or check_file(*a, **k))
    piecewise = check_file_pieces(q, spans, system, safety, conventions=None)
    assert calls == []  # checked in pieces, not whole
    assert piecewise.to_dict() == whole.to_dict()
    assert piecewise.warnings == whole.warnings and piecewise.definitions == whole.definitions
    return whole, piecewise, spans


@pytest.mark.parametrize(
    "make", [lambda: writers.gre3d(n=8, nz=4), lambda: writers.as_version(writers.gre3d(n=8, nz=4), "1.4.1")]
)
def test_a_clean_output_checked_in_pieces_is_the_whole_check(tmp_path, monkeypatch, make):
    out, q = _written(tmp_path, make())
    whole, _, _ = _same(tmp_path, monkeypatch, out, q, SystemSpec(max_grad_mT_per_m=80, max_slew_T_per_m_per_s=200))
    assert whole.ok


def test_tight_limits_fail_every_block_alike_whole_and_in_pieces(tmp_path, monkeypatch):
    """Limits at a third of the peak: amplitude, slew and vector rows in many blocks, pieces' boundaries among
    them, each once with the whole text's block, worst value and time."""
    out, q = _written(tmp_path, writers.gre3d(n=8, nz=4))
    g = float(np.abs(out.grad_mT_per_m).max())
    s = float(np.abs(np.diff(out.grad_mT_per_m, axis=1)).max() / out.dt_fine_s * 1e-3)
    whole, _, spans = _same(
        tmp_path, monkeypatch, out, q, SystemSpec(max_grad_mT_per_m=g / 3, max_slew_T_per_m_per_s=s / 3)
    )
    rules = {v.rule for v in whole.violations}
    assert {"grad_amplitude", "slew_rate", "grad_vector", "slew_vector"} <= rules
    blocks = {v.block for v in whole.violations}
    ids = out.meta["block_ids"]
    assert any(ids[b0] in blocks for _, b0, _, _ in spans[1:])  # a piece's first block fails too


@pytest.mark.parametrize("axis", [0, 1])
@pytest.mark.parametrize("kind", ["amplitude", "slew"])
def test_a_violation_at_a_piece_boundary_is_found_once_in_its_block(tmp_path, monkeypatch, kind, axis):
    """A spike on the free edge nearest the second piece's first block start: the amplitude (at that edge) or slew
    (the segments either side, one in each piece) violation is reported as the whole check reports it."""
    base = writers.gre3d(n=8, nz=4)
    out0, _ = _written(tmp_path, base)
    spans = _small_pieces(monkeypatch, out0)
    k = int(round(out0.block_edges_s[spans[1][1]] / out0.raster_s))
    free = np.flatnonzero(out0.free_mask[axis, ::2])
    j = int(free[np.argmin(np.abs(free - k))])
    assert abs(j - k) <= 2
    g = float(np.abs(out0.grad_mT_per_m).max())
    s = float(np.abs(np.diff(out0.grad_mT_per_m, axis=1)).max() / out0.dt_fine_s * 1e-3)
    e = float(out0.edge_grad_mT_per_m[axis, j])
    if kind == "amplitude":  # the edge at 1.5 x the peak: beyond 1.2 x, its segments within 4 x the slew
        spike, system = 1.5 * g - e, SystemSpec(max_grad_mT_per_m=1.2 * g, max_slew_T_per_m_per_s=4 * s + 3 * g / 1e-2)
    else:  # three times the peak slew in the raster steps either side of the edge
        spike, system = (
            3 * s * out0.raster_s * 1e3,
            SystemSpec(max_grad_mT_per_m=2 * g, max_slew_T_per_m_per_s=1.05 * s),
        )
    out, q = _written(tmp_path, base, spike=(j, axis, spike))
    whole, _, _ = _same(tmp_path, monkeypatch, out, q, system)
    rule = "grad_amplitude" if kind == "amplitude" else "slew_rate"
    bad = [v for v in whole.violations if v.rule == rule and v.axis == "xyz"[axis]]
    assert bad and len({v.block for v in bad}) == len(bad)  # one row per block
    assert {v.rule for v in whole.violations} <= {rule, "grad_vector" if kind == "amplitude" else "slew_vector"}


def test_pns_and_acoustics_on_the_stitched_waveform_are_the_whole_checks(tmp_path, monkeypatch):
    out, q = _written(tmp_path, writers.gre3d(n=8, nz=4))
    safety = SafetyChecks(pns=_example_model(), acoustic_bands_hz=((500.0, 700.0), (1000.0, 1200.0)))
    whole, _, _ = _same(
        tmp_path, monkeypatch, out, q, SystemSpec(max_grad_mT_per_m=80, max_slew_T_per_m_per_s=200), safety
    )
    assert any("PNS" in c for c in whole.checks) and any("acoustic" in c for c in whole.checks)


@pytest.mark.skipif(not GIRF.exists(), reason="girf/example_7T.npz absent")
def test_an_inherited_step_settles_alike_whole_and_in_pieces(tmp_path, monkeypatch, capsys):
    """``dtoc optimize`` of the base with its own z step (tests/test_check_inherited_steps.py), its written text
    checked in pieces of 64 raster steps by write_checked: the inherited records are those of the whole check of
    the file written, settled against the base."""
    base, out, man = tmp_path / "step.seq", tmp_path / "o.seq", tmp_path / "o.json"
    base.write_bytes(gre_with_z_step(STEP))
    monkeypatch.setattr(W, "VERIFY_PIECE_RASTER", 64)
    calls = []
    monkeypatch.setattr(C, "check_file", lambda *a, **k: calls.append(a) or check_file(*a, **k))
    code, _, err = run_cli(capsys, "optimize", base, "--girf", GIRF, "-o", out, "--json", man, *RUN)
    assert code == 0, err
    assert calls == []  # write_checked checked the text in pieces
    m = json.loads(man.read_text())
    system = SystemSpec(max_grad_mT_per_m=32, max_slew_T_per_m_per_s=130, grad_raster_s=1e-5, block_raster_s=1e-5)
    whole = check_file(out, system, conventions=None)
    records = settle_inherited(whole, read_seq(base).source, system)
    assert len(records) == 8 and json.loads(json.dumps(records)) == m["output"]["check_inherited"]
    assert m["output"]["check_ok"] is whole.ok is True and m["output"]["checks"] == whole.checks


def test_a_text_the_pieces_would_misname_is_checked_whole(tmp_path, monkeypatch):
    """A CR in the text (a rule that names the text, not a piece): the whole check runs, and its result comes back."""
    out, q = _written(tmp_path, writers.gre3d(n=8, nz=4))
    spans = _small_pieces(monkeypatch, out)
    q.write_bytes(q.read_bytes().replace(b"\n[BLOCKS]", b"\r\n[BLOCKS]", 1))
    system = SystemSpec(max_grad_mT_per_m=80, max_slew_T_per_m_per_s=200)
    res = check_file_pieces(q, spans, system, conventions=None)
    assert res.to_dict() == check_file(q, system, conventions=None).to_dict()
    assert "line_endings" in res.rules() and "signature" in res.rules()
