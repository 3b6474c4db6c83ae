"""The written text read back in pieces (issue 32: the export of a long output in bounded memory): every line of
the text in some piece, a difference anywhere still refused by name in one line, and the read-back's memory that of
a piece, not of the sequence."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pypulseq
import pytest

from dtoc.errors import DtocError
from dtoc.seq import write as W
from dtoc.seq.ir import edges_to_fine
from dtoc.seq.pieces import TextIndex, share
from dtoc.seq.read import read_seq
from dtoc.seq.seqtext import sign_text
from tests.foreign import writers


def _moved(path):
    """The base at ``path`` with every free raster edge moved smoothly (every block with a free edge rewritten)."""
    ir = read_seq(path)
    e = ir.edge_grad_mT_per_m
    t = np.arange(e.shape[1]) * ir.raster_s
    return ir.with_grad(edges_to_fine(e + ir.free_mask[:, ::2] * 0.02 * np.sin(2 * np.pi * t / (1e-3 * np.sqrt(2)))))


def _written(tmp_path, data: bytes, name="base.seq"):
    p = tmp_path / name
    p.write_bytes(data)
    out = _moved(p)
    v = W.writable_version(out)
    return out, W.seq_bytes_of(out, version=v, verify=False), v


def _lines(text: bytes) -> list[bytes]:
    """The data lines of a text (no comments, blank lines, section headers nor signature)."""
    body = text[: text.find(b"\n[SIGNATURE]")] if b"\n[SIGNATURE]" in text else text
    return [ln.strip() for ln in body.split(b"\n") if ln.strip() and not ln.strip().startswith((b"#", b"["))]


@pytest.mark.parametrize(
    "make",
    [
        lambda: writers.gre_multislice_labels(),  # labels: the extension list and its sections
        lambda: writers.as_version(writers.gre3d(n=8, nz=4), "1.4.1"),  # edges a 1.4 reader infers
        lambda: writers.rotated_trapezoids_151(),  # the ROTATIONS extension
    ],
)
def test_every_line_of_the_text_is_in_a_piece_and_the_pieces_read_back(tmp_path, monkeypatch, make):
    """Pieces of a few blocks: each data line of the text (library entries no block uses too) is in some piece,
    and the pieces' read-back passes as the whole text's does."""
    out, data, v = _written(tmp_path, make())
    monkeypatch.setattr(W, "VERIFY_PIECE_RASTER", max(round(out.duration_s / out.raster_s / 6), 1))
    spans = W.verify_spans(out)
    assert len(spans) >= 4 or len(spans) == len(out.block_edges_s) - 1
    idx = TextIndex(data)
    extras = share(idx.unused(), len(spans))
    seen: set[bytes] = set()
    for (c0, _, _, c1), extra in zip(spans, extras, strict=True):
        seen.update(_lines(idx.piece(c0, c1, extra)))
    missing = [ln for ln in _lines(data) if ln not in seen]
    assert not missing, missing[:3]
    W.verify_written(out, data, v)  # pieces
    monkeypatch.setattr(W, "VERIFY_PIECE_RASTER", 1 << 30)
    W.verify_written(out, data, v)  # whole


def test_a_difference_in_a_late_piece_is_named_as_the_whole_text_names_it(tmp_path, monkeypatch):
    """One shape sample of the last rewritten gradient changed (text re-signed): the pieces refuse it with the
    whole read-back's message."""
    out, data, v = _written(tmp_path, writers.gre3d(n=8, nz=4))
    i = data.rfind(b"shape_id")
    j = data.find(b"\n", data.find(b"num_samples", i)) + 1
    bad = sign_text(data[:j] + b"0.5" + data[data.find(b"\n", j) :])
    with pytest.raises(DtocError) as whole:
        W.verify_written(out, bad, v)
    monkeypatch.setattr(W, "VERIFY_PIECE_RASTER", 64)
    assert len(W.verify_spans(out)) >= 8
    with pytest.raises(DtocError) as pieces:
        W.verify_written(out, bad, v)
    assert str(pieces.value) == str(whole.value) and "plays another gradient" in str(whole.value)
    with pytest.raises(DtocError, match="signature does not match"):  # the whole text's signature, checked once
        W.verify_written(out, data[: data.rfind(b"Hash ") + 5] + b"0" * 32 + b"\n", v)


def test_a_piece_pypulseq_cannot_read_is_refused_in_one_line(tmp_path, monkeypatch):
    """pypulseq's own reading of one piece fails (the third piece's second read): refused in one line naming the
    piece's blocks, as the whole text's failure is."""
    out, data, v = _written(tmp_path, writers.gre3d(n=8, nz=4))
    monkeypatch.setattr(W, "VERIFY_PIECE_RASTER", 64)
    real, calls = pypulseq.Sequence.read, []

    def read(self, path, *a, **k):
        calls.append(path)
        if len(calls) == 6:  # dtoc's and pypulseq's reading of each piece: the third piece's pypulseq reading
            raise ValueError("corrupt line")
        return real(self, path, *a, **k)

    monkeypatch.setattr(pypulseq.Sequence, "read", read)
    with pytest.raises(DtocError) as e:
        W.verify_written(out, data, v)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(
        "pypulseq cannot read the written format 1.5.0 text (the piece of blocks "
    )
    assert "ValueError: corrupt line" in msg


def _verify_peak(out, data, v) -> int:
    tracemalloc.start()
    try:
        W.verify_written(out, data, v)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_the_pieces_of_a_4x_longer_text_are_the_short_ones_size(tmp_path, monkeypatch):
    """What the read-back holds at a time besides a piece's reading: the piece's text (the same bytes at both lengths,
    1.2x at most) and the index, a few tens of bytes per block and library entry (not per line of the text)."""
    sizes = {}
    for nz in (2, 8):
        out, data, _ = _written(tmp_path, writers.gre3d(n=16, nz=nz), f"b{nz}.seq")
        monkeypatch.setattr(W, "VERIFY_PIECE_RASTER", 2048)
        spans = W.verify_spans(out)
        idx = TextIndex(data)
        extras = share(idx.unused(), len(spans))
        held = sum(a.nbytes for r in (*idx.rows.values(), *idx.ext_rows.values(), idx.shapes) for a in vars(r).values())
        entries = sum(len(r.ids) for r in (*idx.rows.values(), idx.shapes))
        sizes[nz] = (max(len(idx.piece(c0, c1, x)) for (c0, _, _, c1), x in zip(spans, extras, strict=True)), held)
        assert held < 100 * entries, (held, entries)  # (~50: ids, byte range, sort order and the referred ids)
    assert sizes[8][0] < 1.2 * sizes[2][0], sizes


@pytest.mark.slow
def test_the_read_back_of_a_4x_longer_text_holds_a_piece(tmp_path, monkeypatch):
    """The read-back's peak (Python allocations above the text it checks) of a 4x longer 3D GRE is within 1.2x the
    short one's: it holds one piece's reading and a few integers per block, not the sequence's reading (which the
    whole read-back holds: > 3x the pieces' here)."""
    short = _written(tmp_path, writers.gre3d(n=16, nz=1), "short.seq")
    long = _written(tmp_path, writers.gre3d(n=16, nz=4), "long.seq")
    assert len(long[1]) > 3.5 * len(short[1])
    monkeypatch.setattr(W, "VERIFY_PIECE_RASTER", 2048)
    assert len(W.verify_spans(short[0])) >= 4
    p_short, p_long = _verify_peak(*short), _verify_peak(*long)
    assert p_long < 1.2 * p_short, (p_short, p_long)
    monkeypatch.setattr(W, "VERIFY_PIECE_RASTER", 1 << 30)  # the whole read-back (before): the sequence's reading
    assert _verify_peak(*long) > 3 * p_long
