"""The [SHAPES] section read at once (dtoc.seq.seqtext, docs/optimize.md "The export's time"): the same parse as
the line by line reading on every format version, and, on anything but plain shapes, the line by line reading
and its one-line error."""

from __future__ import annotations

import pytest

import dtoc.seq.seqtext as S
from dtoc.errors import InputError
from tests.foreign import writers as W
from tests.foreign.writers import as_version


def _both(tmp_path, data: bytes, monkeypatch):
    p = tmp_path / "x.seq"
    p.write_bytes(data)
    fast = S.parse_seq_text(p)
    with monkeypatch.context() as m:
        m.setattr(S, "_read_shapes", lambda body, first: None)
        slow = S.parse_seq_text(p)
    return fast, slow


def _same(fast, slow, at_once: bool = True) -> None:
    assert fast.version == slow.version and fast.section_order == slow.section_order
    assert fast.shapes == slow.shapes  # ids, num_samples, every sample (as Python floats), line numbers
    for name, lines in slow.sections.items():
        got = [(ln.lineno, ln.text) for ln in fast.sections[name]]
        want = [(ln.lineno, ln.text) for ln in lines]
        if name == "[SHAPES]" and at_once:  # the header lines only
            want = [w for w in want if w[1].split()[0] in ("shape_id", "num_samples")]
        assert got == want, name
    assert fast.signature_hash == slow.signature_hash


@pytest.mark.parametrize("version", ["1.5.0", "1.4.1", "1.3.1", "1.2.1"])
@pytest.mark.parametrize("writer", ["epi", "tse", "gre3d"])
def test_read_at_once_is_the_line_by_line_parse(tmp_path, monkeypatch, version, writer):
    data = getattr(W, writer)()
    if version != "1.5.0":
        try:
            data = as_version(data, version)
        except (ValueError, NotImplementedError):
            pytest.skip(f"{writer} is not written as {version}")
    fast, slow = _both(tmp_path, data, monkeypatch)
    assert len(fast.shapes) >= 2 and len(fast.sections["[SHAPES]"]) == 2 * len(fast.shapes)
    _same(fast, slow)


def test_read_at_once_is_used(tmp_path, monkeypatch):
    """(the fast reading is what runs on a plain text: not a test of the fallback twice)"""
    p = tmp_path / "x.seq"
    p.write_bytes(W.epi())
    calls = []
    real = S._read_shapes
    monkeypatch.setattr(S, "_read_shapes", lambda body, first: calls.append(1) or real(body, first))
    st = S.parse_seq_text(p)
    assert calls == [1] and all(ln.text.split()[0] in ("shape_id", "num_samples") for ln in st.sections["[SHAPES]"])


def _shape_lines(data: bytes) -> tuple[str, int]:
    text = data.decode()
    i = text.index("[SHAPES]")
    j = text.index("shape_id", i)
    j = text.index("\n", text.index("num_samples", j)) + 1  # the first sample line of the first shape
    return text, j


@pytest.mark.parametrize(
    "edit,message",
    [
        (lambda t, j: t[:j] + "# a comment\n" + t[j:], None),  # legal: the line by line reading keeps it
        (lambda t, j: t[:j] + "\n\n" + t[j:], "at once"),  # blank lines, legal, read at once
        (lambda t, j: t[:j] + "1 2\n" + t[j:], "not a number: '1 2'"),
        (lambda t, j: t[:j] + "nan\n" + t[j:], "is not finite"),
        (lambda t, j: t[:j] + "1_000\n" + t[j:], "not a number: '1_000'"),
        (lambda t, j: t[:j] + "0x10\n" + t[j:], "not a number: '0x10'"),
        (lambda t, j: t[:j] + "１\n" + t[j:], "3001 values for num_samples"),  # Unicode: a digit to both
        (lambda t, j: t[:j] + "1e400\n" + t[j:], "is not finite"),
        (lambda t, j: t.replace("num_samples", "num_samples ", 1).replace("num_samples  ", "num_samples  +"), None),
    ],
)
def test_anything_but_plain_shapes_is_read_line_by_line(tmp_path, monkeypatch, edit, message):
    text, j = _shape_lines(W.epi())
    data = edit(text, j).encode()
    p = tmp_path / "x.seq"
    p.write_bytes(data)
    if message in (None, "at once"):  # a legal text: the same parse as the reading with the fast path off
        fast, slow = _both(tmp_path, data, monkeypatch)
        _same(fast, slow, at_once=message is not None)
        assert (len(fast.sections["[SHAPES]"]) == 2 * len(fast.shapes)) is (message is not None)
        return
    with pytest.raises(InputError) as fast:
        S.parse_seq_text(p)
    with monkeypatch.context() as m:
        m.setattr(S, "_read_shapes", lambda body, first: None)
        with pytest.raises(InputError) as slow:
            S.parse_seq_text(p)
    assert str(fast.value) == str(slow.value) and message in str(fast.value)


def test_length_errors_name_the_same_shape(tmp_path, monkeypatch):
    """A shape with more values than its num_samples: the same one line, read at once or line by line."""
    text, j = _shape_lines(W.epi())
    data = (text[:j] + "0.5\n" * 400 + text[j:]).encode()
    p = tmp_path / "x.seq"
    p.write_bytes(data)
    with pytest.raises(InputError) as fast:
        S.parse_seq_text(p)
    monkeypatch.setattr(S, "_read_shapes", lambda body, first: None)
    with pytest.raises(InputError) as slow:
        S.parse_seq_text(p)
    assert str(fast.value) == str(slow.value) and "values for num_samples" in str(fast.value)
