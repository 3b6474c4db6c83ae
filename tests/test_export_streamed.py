"""The export's text is written, signed, checked and moved into place without being held whole in memory
(docs/optimize.md, "Memory of the export"): the streamed steps give the bytes and the verdicts of the whole-text
ones they replace."""

from __future__ import annotations

import hashlib

import numpy as np
import pypulseq
import pytest

from dtoc.seq import pieces
from dtoc.seq.ir import edges_to_fine
from dtoc.seq.pieces import TextIndex, mapped_text, signature_ok, text_facts
from dtoc.seq.pulseq import seq_file
from dtoc.seq.read import read_seq
from dtoc.seq.seqtext import sign_file, sign_text
from dtoc.seq.versions import set_revision, set_revision_file, strip_signature
from dtoc.seq.write import seq_bytes_of, write_seq_text
from tests.foreign import writers


def _changed(p):
    ir = read_seq(p)
    e = ir.edge_grad_mT_per_m.copy()
    e[ir.free_mask[:, ::2]] *= 1.02
    return ir.with_grad(edges_to_fine(e))


def test_streamed_signature_is_pypulseqs(tmp_path):
    """pypulseq's own signed text (its signing reads the whole text) and :func:`seq_file`'s (unsigned, then the
    md5 in chunks) are the same bytes."""
    seq = pypulseq.Sequence()
    seq.read(str(_write(tmp_path / "b.seq", writers.epi(n=16))))
    ref = tmp_path / "ref.seq"
    seq.write(str(ref), create_signature=True)
    ours = tmp_path / "ours.seq"
    seq_file(seq, ours)
    assert ours.read_bytes() == ref.read_bytes()
    unsigned = tmp_path / "u.seq"
    seq_file(seq, unsigned, signed=False)
    assert b"[SIGNATURE]" not in unsigned.read_bytes()
    sign_file(unsigned)
    assert unsigned.read_bytes() == sign_text(unsigned.read_bytes()) == ref.read_bytes()


@pytest.mark.parametrize("version", [None, "1.4.0", "1.4.1", "1.5.0", "1.5.1", "1.5.2"])
def test_written_file_is_the_texts_bytes(tmp_path, version):
    """:func:`write_seq_text` (the export's writer) gives :func:`seq_bytes_of`'s bytes in every format dtoc
    writes, read back to the changed waveform; the version's [VERSION] set on the first chunk is
    :func:`set_revision` of the whole text."""
    new = _changed(_write(tmp_path / "b.seq", writers.tse(n=16, etl=4)))
    p = tmp_path / "o.seq"
    v = write_seq_text(new, p, {"DtocX": 3}, None, version)
    data = p.read_bytes()
    assert data == seq_bytes_of(new, {"DtocX": 3}, None, version)
    assert signature_ok(data) and f"revision {v[2]}\n".encode() in data[:200]
    back = read_seq(p)
    assert np.abs(back.grad_mT_per_m - new.grad_mT_per_m).max() < 1e-5 * np.abs(new.grad_mT_per_m).max()
    whole = set_revision(strip_signature(data), (1, 4, 2))
    q = tmp_path / "q.seq"
    q.write_bytes(strip_signature(data)[:-1])
    set_revision_file(q, (1, 4, 2), newline=True)
    assert q.read_bytes() == whole


def _write(p, data: bytes):
    p.write_bytes(data)
    return p


@pytest.mark.parametrize("chunk_marker_at", [0, 1, 7, 11])
def test_text_facts_match_the_whole_texts(tmp_path, monkeypatch, chunk_marker_at):
    """:func:`text_facts` read in chunks states what the whole-text checks state: the signature's match (also
    with [SIGNATURE] and a marker cut by a chunk boundary), its types, a carriage return, the markers."""
    data = sign_text(writers.epi(n=8))
    i = data.find(b"\n[SIGNATURE]")
    chunk = max(i + 6 - chunk_marker_at, 1)  # the boundary falls inside "\n[SIGNATURE]"
    real_open = open

    class Small:
        def __init__(self, f):
            self.f = f

        def read(self, n=-1):
            return self.f.read(chunk)

        def __enter__(self):
            return self

        def __exit__(self, *a):
            self.f.close()

    monkeypatch.setattr(pieces, "open", lambda *a, **k: Small(real_open(*a, **k)), raising=False)
    marker = b"\n[BLOCKS]"
    for text, ok in (
        (data, True),
        (data.replace(b"Hash ", b"Hash 0"), False),  # a wrong hash
        (data[:i] + b"\n", True),  # unsigned
        (data[:50] + b"\r" + data[51:], False),  # content changed: the signature no longer matches
    ):
        p = _write(tmp_path / "t.seq", text)
        f = text_facts(p, (marker, b"\nextension ROTATIONS "))
        assert f.signature_ok is signature_ok(text) is ok
        assert f.signed is (b"\n[SIGNATURE]" in text)
        assert f.has_cr is (b"\r" in text)
        assert f.markers == frozenset({marker})
        assert f.signature_types == ((b"md5",) if f.signed else ())


def test_mapped_index_cuts_the_same_pieces(tmp_path, monkeypatch):
    """A :class:`TextIndex` over the mapped text, its pages released every scan window (here every 4 kB), cuts
    the pieces of one over the bytes, byte for byte."""
    monkeypatch.setattr(pieces, "SCAN_WINDOW", 4096)
    p = tmp_path / "o.seq"
    write_seq_text(_changed(_write(tmp_path / "b.seq", writers.gre3d(n=8, nz=4))), p)
    data = p.read_bytes()
    ref = TextIndex(data)
    drops = []
    with mapped_text(p) as (mm, drop):
        idx = TextIndex(mm, lambda: (drops.append(1), drop()))
        n = ref.n_blocks
        assert idx.n_blocks == n > 8 and len(drops) > len(data) // 4096
        extras = pieces.share(ref.unused(), 3)
        cuts = [0, n // 3, 2 * n // 3, n]
        for k in range(3):
            a = idx.piece(cuts[k], cuts[k + 1], extras[k])
            drop()
            assert a == ref.piece(cuts[k], cuts[k + 1], extras[k])
    assert hashlib.md5(data).hexdigest() == hashlib.md5(p.read_bytes()).hexdigest()  # (read only)


def test_lean_shape_dedup_is_pypulseqs():
    """The shape library de-duplicated without its copies (:func:`dtoc.seq.pulseq.lean_shape_dedup`): the same
    library (data bits, types, ids) and id mapping as pypulseq's own ``remove_duplicates(9)``; the old shapes
    released."""
    import copy

    from pypulseq.event_lib import EventLibrary

    from dtoc.seq.pulseq import lean_shape_dedup

    rng = np.random.default_rng(3)
    lib = EventLibrary(numpy_data=True)
    base = [rng.normal(size=n) * s for n, s in ((5, 1.0), (7, 1e-3), (5, 123.0), (9, 0.0))]
    shapes = []
    for i in range(40):
        a = base[i % 4] * (1 + (1e-12 if i % 3 else 1e-6) * (i // 4))  # equal after rounding to 9 digits, or not
        shapes.append(a)
        lib.find_or_insert(a, "g" if i % 5 else "")
    lib.find_or_insert(np.array([9.99999999996, -0.0, 0.0]), "t")  # a power-of-ten crossing and a signed zero
    ref_lib, ref_map = copy.deepcopy(lib).remove_duplicates(9)
    lean_shape_dedup(lib)
    new, mapping = lib.remove_duplicates(9)
    assert mapping == ref_map and len(set(mapping.values())) < len(mapping) - 1  # some were duplicates
    assert list(new.data) == list(ref_lib.data) and new.type == ref_lib.type
    assert new.next_free_ID == ref_lib.next_free_ID
    assert all(new.data[k].tobytes() == ref_lib.data[k].tobytes() for k in new.data)
    assert not lib.data and not lib.keymap
