"""Outputs are continuous exactly where their bases are (issue 36, writer defect): a block boundary that two
blocks do not play as one edge -- next to a zero-duration block (JEMRIS writes them between readouts), or
between blocks of different 1.5.1 rotations -- keeps the base's value, so an optimized output written in any
version (1.4.0, 1.4.1, 1.5.x) has no gradient jump there.  Files from our own writers (tests/foreign/writers.py).

Each test moves every free sample of the base (what an optimizer may do at most), writes it, and asks
``dtoc check`` (the rule the corpus outputs failed: 7-37 Hz/m jumps); it also shows that the same move of the
held boundaries is such a jump, so the tests see the class they guard against."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli
from foreign.writers import as_version, epi, radial
from test_seq_versions import _with_empty_block

from dtoc.seq.check import check_file
from dtoc.seq.ir import edges_to_fine
from dtoc.seq.read import held_boundaries, read_seq
from dtoc.seq.system import SystemSpec
from dtoc.seq.write import seq_bytes_of

REPO = Path(__file__).resolve().parents[1]
GIRF = REPO / "girf" / "example_7T.npz"
LIMITS = SystemSpec(max_grad_mT_per_m=80, max_slew_T_per_m_per_s=400)  # only the format's rules matter here
JUMPS = {"continuity", "grad_start_nonzero", "grad_end_nonzero"}


def _moved(ir, held_too: bool = False):
    """Every free edge sample moved by 0.05 mT/m (about 2 kHz/m); ``held_too``: the held boundaries as well."""
    e = ir.edge_grad_mT_per_m.copy()
    free = ir.free_mask[:, ::2].copy()
    if held_too:
        for m in held_boundaries(ir):
            free[:, m // 2] = np.any(ir.free_mask[:, ::2], axis=1)
    e[free] += 0.05
    return ir.with_grad(edges_to_fine(e))


def _jumps(tmp_path: Path, name: str, data: bytes) -> list:
    p = tmp_path / name
    p.write_bytes(data)
    return [v for v in check_file(p, LIMITS).violations if v.rule in JUMPS]


@pytest.mark.parametrize("version", ["1.4.0", "1.4.1", "1.5.0"])
def test_zero_duration_block_boundary_is_held(tmp_path, version):
    """An EPI with an empty zero-duration block between two readouts (as JEMRIS writes): the boundary it
    sits on is held; every other free sample moved, the output in the base's version has no jump."""
    ir0 = read_seq(_write(tmp_path / "a.seq", epi(n=16)))
    ro = next(a.block for a in ir0.adc)
    base = _with_empty_block(epi(n=16), ro + 1)
    base = base if version == "1.5.0" else as_version(base, version)
    ir = read_seq(_write(tmp_path / "b.seq", base))
    m = int(round(ir.block_edges_s[ro + 2] / ir.dt_fine_s))  # the empty block's start and end
    assert held_boundaries(ir) == [m]
    assert not ir.free_mask[:, m].any() and ir.free_mask[0, m - 2] and ir.free_mask[0, m + 2]
    assert not _jumps(tmp_path, "base.seq", base)
    out = seq_bytes_of(_moved(ir), version=version)
    assert not _jumps(tmp_path, "out.seq", out)
    # the held boundary keeps the base's value in the written file; moved, it would not (so the hold is what keeps it)
    g0 = ir.grad_mT_per_m[:, m]
    assert np.allclose(read_seq(_write(tmp_path / "o.seq", out)).grad_mT_per_m[:, m], g0, atol=1e-6)
    moved = seq_bytes_of(_moved(ir, held_too=True), version=version)
    assert not np.allclose(read_seq(_write(tmp_path / "m.seq", moved)).grad_mT_per_m[:, m], g0, atol=1e-3)


def _label_block_file(p: Path, first_after: float) -> Path:
    """Three blocks as Pulseq MATLAB's trufi demo plays them: x runs up to 8 mT/m at a block end, a label-only block of
    zero duration, then x starts at ``first_after`` Hz/m (the writer's neighbour check lifted: pypulseq compares with
    the label block, Pulseq MATLAB with the previous block of non-zero duration)."""
    import pypulseq as pp

    from dtoc.seq.pulseq import quiet

    sys = pp.Opts(max_grad=40, grad_unit="mT/m", max_slew=100000, slew_unit="T/m/s")
    seq = pp.Sequence(sys)
    v = 340909.0  # Hz/m, 8 mT/m
    seq.add_block(pp.make_extended_trapezoid("x", times=[0, 1e-4, 3e-4], amplitudes=[0, v, v], system=sys))
    seq.add_block(pp.make_label(label="ONCE", type="SET", value=1))
    seq.add_block(pp.make_extended_trapezoid("x", times=[0, 2e-4, 3e-4], amplitudes=[first_after, v, 0], system=sys))
    with quiet():
        seq.write(str(p))
    return p


def test_zero_duration_block_is_transparent_to_continuity(tmp_path):
    """A zero-duration block (labels only) plays no time: Pulseq MATLAB's setBlock and checkTiming compare a block
    with the previous block of non-zero duration, so a gradient that runs on through a label block (its trufi demo:
    8 mT/m on x) passes; a real jump across one is still reported, named from the block before the label block."""
    assert not [v for v in check_file(_label_block_file(tmp_path / "t.seq", 340909.0), LIMITS).violations]
    bad = [v for v in check_file(_label_block_file(tmp_path / "j.seq", 0.0), LIMITS).violations if v.rule in JUMPS]
    assert [(v.rule, v.block, v.axis) for v in bad] == [("continuity", 3, "x")], bad
    assert "jump from block 1: 340909 -> 0 Hz/m" in bad[0].message and bad[0].value == pytest.approx(340909.0)


def test_boundaries_between_different_rotations_are_held(tmp_path):
    """A radial file turned by the 1.5.1 rotation extension: every boundary between two spokes of different
    rotations is held; the optimized-like output (1.5.1, rotations kept) has no jump."""
    base = radial(n=16, spokes=8, rotation_extension=True)
    ir = read_seq(_write(tmp_path / "r.seq", base))
    rot = ir.meta["rotations"]
    m_edges = np.round(np.asarray(ir.block_edges_s) / ir.dt_fine_s).astype(int)
    want = [
        int(m_edges[b])
        for b in range(1, len(m_edges) - 1)
        if rot.get(b - 1, [1, 0, 0, 0]) != rot.get(b, [1, 0, 0, 0]) and m_edges[b + 1] > m_edges[b]
    ]
    assert want and held_boundaries(ir) == want
    assert not _jumps(tmp_path, "base.seq", base)
    out = seq_bytes_of(_moved(ir))
    assert not _jumps(tmp_path, "out.seq", out)
    assert read_seq(_write(tmp_path / "o.seq", out)).meta["rotations"] == rot
    bad = _jumps(tmp_path, "bad.seq", seq_bytes_of(_moved(ir, held_too=True)))
    assert bad


@pytest.mark.skipif(not GIRF.exists(), reason="girf/example_7T.npz absent")
def test_optimized_14_epi_with_empty_block_passes_check(tmp_path, capsys):
    """End to end: `dtoc optimize` of a 1.4.0 EPI with an empty block between readouts writes a 1.4.0 file
    that its own output check passes (exit 0; the corpus's JEMRIS EPI exited 1 with 36.6 Hz/m jumps)."""
    ir0 = read_seq(_write(tmp_path / "a.seq", epi(n=16)))
    ro = next(a.block for a in ir0.adc)
    base = _write(tmp_path / "b.seq", as_version(_with_empty_block(epi(n=16), ro + 1), "1.4.0"))
    out, man = tmp_path / "o.seq", tmp_path / "o.json"
    fast = ["--warm-iters", "30", "--iters", "1", "--threads", "1", "--b0", "7", "--gmax", "32", "--smax", "130"]
    code, _, err = run_cli(capsys, "optimize", base, "--girf", GIRF, "-o", out, "--json", man, "-q", *fast)
    assert code == 0, err
    m = json.loads(man.read_text())
    assert m["output"]["format_version"] == "1.4.0"
    assert m["after"]["kspace_max_error_dk"] < 0.5 * m["before"]["kspace_max_error_dk"]
    assert not _jumps(tmp_path, "recheck.seq", out.read_bytes())


def _write(p: Path, data: bytes) -> Path:
    p.write_bytes(data)
    return p
