"""The output pre-flight in seconds on long files (issue 36, point 5): the base is written in the target version
and read back as the sub-sequence of its distinct blocks (each with the neighbours it is written against),
not the whole protocol; that sub-sequence plays exactly what the base plays in those blocks, and a defect
the writer would hit is still refused before any work (then decided on the whole base, its message the
base's).  Files from our own writers (tests/foreign/writers.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from foreign.writers import as_version, gre

from dtoc.errors import DtocError, InputError
from dtoc.seq import write as W
from dtoc.seq.read import read_seq


def _read(tmp_path: Path, name: str, data: bytes):
    p = tmp_path / name
    p.write_bytes(data)
    return read_seq(p)


def _same_blocks(ir, sub, blocks):
    """The sub-sequence's block b' plays the base's block blocks[b'] sample for sample (all axes)."""
    e = np.round(np.asarray(ir.block_edges_s) / ir.dt_fine_s).astype(int)
    es = np.round(np.asarray(sub.block_edges_s) / sub.dt_fine_s).astype(int)
    for i, b in enumerate(blocks):
        a, s = ir.grad_mT_per_m[:, e[b] + 1 : e[b + 1]], sub.grad_mT_per_m[:, es[i] + 1 : es[i + 1]]
        assert a.shape == s.shape and np.array_equal(a, s), f"block {b}"
        for m, ms in ((e[b], es[i]), (e[b + 1], es[i + 1])):  # the shared edges too, where the run does not end
            if (
                0 < ms < es[-1]
                and (i == 0 or blocks[i - 1] == b - 1)
                and (i + 1 == len(blocks) or blocks[i + 1] == b + 1)
            ):
                assert np.array_equal(ir.grad_mT_per_m[:, m], sub.grad_mT_per_m[:, ms])


@pytest.mark.parametrize("version", ["1.5.0", "1.4.1", "1.4.0"])
def test_long_gre_preflight_writes_its_distinct_blocks(tmp_path, version, monkeypatch):
    """A 64-line GRE: the pre-flight writes a few blocks, not 64 TRs; they play what the base plays there, and
    the pre-flight passes on them alone (no fallback to the whole base)."""
    data = gre(n=64)
    ir = _read(tmp_path, "g.seq", data if version == "1.5.0" else as_version(data, version))
    rep = W._representative_free_edges(ir)
    blocks = W.preflight_blocks(ir, rep)
    nb = len(ir.block_edges_s) - 1
    assert blocks is not None and len(blocks) <= nb // 8, (len(blocks), nb)
    sub, sub_rep = W._sub_ir(ir, blocks, rep)
    _same_blocks(ir, sub, blocks)
    assert sub_rep.sum() == rep.sum()  # every representative free edge is moved in the sub-sequence
    written = []
    real = W._write_moved
    monkeypatch.setattr(W, "_write_moved", lambda ir0, target, r, v: (written.append(target), real(ir0, target, r, v)))
    assert W.preflight_write(ir) == tuple(int(x) for x in version.split("."))
    assert len(written) == 1 and written[0] is not ir and len(written[0].block_edges_s) - 1 == len(blocks)


def test_a_writer_defect_is_refused_with_the_whole_base(tmp_path, monkeypatch):
    """A failure on the sub-sequence is decided on the whole base: one InputError line, the base's wording."""
    ir = _read(tmp_path, "g.seq", gre(n=64))
    calls = []

    def broken(ir0, data, version, adc_offsets=None):
        calls.append(len(ir0.block_edges_s) - 1)
        raise DtocError("format 1.5.0 text plays another gradient: block 7 axis x")

    monkeypatch.setattr(W, "verify_written", broken)
    with pytest.raises(InputError, match=r"^the base cannot be written as Pulseq format 1\.5\.0: .*block 7 axis x$"):
        W.preflight_write(ir)
    assert len(calls) == 2 and calls[0] < calls[1] == len(ir.block_edges_s) - 1  # the sub-sequence, then the base


def test_zero_duration_last_block(tmp_path):
    """A file ending with a zero-duration block (Pulseq MATLAB's epi_rs ends with a label-only block): the
    pre-flight's block selection handles it (an IndexError was an internal error at 'dtoc optimize')."""
    from test_seq_versions import _with_empty_block

    data = gre(n=64)
    ir0 = _read(tmp_path, "g.seq", data)
    nb = len(ir0.block_edges_s) - 1
    ir = _read(tmp_path, "z.seq", _with_empty_block(data, nb))
    assert len(ir.block_edges_s) - 1 == nb + 1 and ir.block_edges_s[-1] == ir.block_edges_s[-2]
    rep = W._representative_free_edges(ir)
    blocks = W.preflight_blocks(ir, rep)
    assert blocks is not None and len(blocks) < nb // 4
    assert W.preflight_write(ir) == (1, 5, 0)
