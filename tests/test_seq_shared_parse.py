"""One parse of a written text (issue 33): the export's writer read-back, its ``dtoc check`` rules and the reader
share the parse of the same bytes (:func:`dtoc.seq.seqtext.shared_parse`); the checks, messages and bytes are
those of separate parses."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from dtoc.errors import InputError
from dtoc.optimize.limits import Limits
from dtoc.optimize.run import write_checked
from dtoc.seq import seqtext
from dtoc.seq.check import check_file
from dtoc.seq.load import load_sequence
from dtoc.seq.seqtext import parse_seq_text, shared_parse

REPO = Path(__file__).resolve().parents[1]
SMALL = REPO / "sequences" / "epi_small.seq"


@pytest.fixture
def parses(monkeypatch):
    """The number of texts actually parsed."""
    n = []
    orig = seqtext._parse
    monkeypatch.setattr(seqtext, "_parse", lambda p, raw: (n.append(str(p)), orig(p, raw))[1])
    return n


def _fields(st) -> dict:
    return {f.name: getattr(st, f.name) for f in dataclasses.fields(st) if f.name not in ("path", "layout")}


def test_same_bytes_parse_once_in_scope_each_with_its_path(tmp_path, parses):
    a, b, c = tmp_path / "a.seq", tmp_path / "b.seq", tmp_path / "c.seq"
    a.write_bytes(SMALL.read_bytes())
    b.write_bytes(SMALL.read_bytes())
    c.write_bytes(SMALL.read_bytes().replace(b"Name ", b"Nome ", 1))  # other bytes
    with shared_parse():
        sa, sb = parse_seq_text(a), parse_seq_text(b)
        assert len(parses) == 1
        assert (sa.path, sb.path) == (str(a), str(b))
        assert _fields(sb) == _fields(sa)
        parse_seq_text(c)
        assert len(parses) == 2  # another text: parsed
    parse_seq_text(a)
    parse_seq_text(a)
    assert len(parses) == 4  # outside the scope: every call parses
    assert _fields(parse_seq_text(b)) == _fields(sa)


def test_a_bad_text_is_refused_each_time_with_its_own_path(tmp_path):
    a, b = tmp_path / "a.seq", tmp_path / "b.seq"
    for p in (a, b):
        p.write_bytes(b"[VERSION]\nmajor 1\n")
    with shared_parse():
        for p in (a, b):
            with pytest.raises(InputError, match=str(p)):
                parse_seq_text(p)


def test_check_file_parses_its_text_once_with_the_same_result(tmp_path, parses):
    res = check_file(SMALL)
    assert len(parses) == 1  # its rules and the reader (was 2)
    with shared_parse():
        shared = check_file(SMALL)
    assert shared.violations == res.violations and shared.warnings == res.warnings
    assert (shared.checks, shared.not_checked, shared.definitions) == (res.checks, res.not_checked, res.definitions)


def test_export_parses_the_written_text_once(tmp_path, parses):
    """The export's write: the writer's read-back and the check share one parse (were 3), and the result is the
    check of the written file on its own."""
    ir = load_sequence(SMALL)
    parses.clear()
    out = tmp_path / "out.seq"
    rec = write_checked(ir, out, False, Limits(72.0, 180.0))
    assert len(parses) == 1
    alone = check_file(out)  # with the limits the file records (the same 72 / 180)
    assert rec["check_ok"] == alone.ok
    assert rec["checks"] == list(alone.checks)
    assert rec["check_not_checked"] == list(alone.not_checked)
