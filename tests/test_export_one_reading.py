"""The export's read-back and check on one reading of the written text (issue 32): each piece parsed once by dtoc
and read once by dtoc's reader (and once by pypulseq as written), that reading serving the read-back's comparison
and the check's rules; the record is the check of the written file, and a difference is refused with the one line
:func:`dtoc.seq.write.verify_written` gives."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pypulseq
import pytest

from dtoc.errors import DtocError
from dtoc.optimize import run as run_mod
from dtoc.optimize.limits import Limits
from dtoc.optimize.run import write_checked
from dtoc.seq import seqtext
from dtoc.seq import write as W
from dtoc.seq.check import check_file
from dtoc.seq.ir import edges_to_fine
from dtoc.seq.read import read_seq
from dtoc.seq.system import SystemSpec
from tests.foreign import writers

LIMITS = Limits(80.0, 200.0)


def _moved(tmp_path, data: bytes):
    """The base ``data`` with every free raster edge moved smoothly (every block with a free edge rewritten)."""
    p = tmp_path / "base.seq"
    p.write_bytes(data)
    ir = read_seq(p)
    e = ir.edge_grad_mT_per_m
    t = np.arange(e.shape[1]) * ir.raster_s
    return ir.with_grad(edges_to_fine(e + ir.free_mask[:, ::2] * 0.02 * np.sin(2 * np.pi * t / (1e-3 * np.sqrt(2)))))


@pytest.fixture
def counts(monkeypatch):
    """{'parse': texts dtoc parsed, 'pypulseq': texts pypulseq read}."""
    n = {"parse": 0, "pypulseq": 0}
    parse, read = seqtext._parse, pypulseq.Sequence.read

    def counted_parse(p, raw):
        n["parse"] += 1
        return parse(p, raw)

    def counted_read(self, *a, **k):
        n["pypulseq"] += 1
        return read(self, *a, **k)

    monkeypatch.setattr(seqtext, "_parse", counted_parse)
    monkeypatch.setattr(pypulseq.Sequence, "read", counted_read)
    return n


@pytest.mark.parametrize("version", [None, "1.4.1"])
@pytest.mark.parametrize("pieces", [True, False])
def test_each_piece_is_parsed_and_read_once(tmp_path, monkeypatch, counts, version, pieces):
    """A 3D GRE output written in pieces (or whole): one dtoc parse and one dtoc reading per piece (was two each),
    plus pypulseq's own reading of the bytes as written (was three pypulseq readings per piece); the record is the
    whole check of the file written."""
    base = writers.gre3d(n=8, nz=4)
    out_ir = _moved(tmp_path, base if version is None else writers.as_version(base, version))
    if pieces:
        monkeypatch.setattr(W, "VERIFY_PIECE_RASTER", max(round(out_ir.duration_s / out_ir.raster_s / 6), 1))
    n = len(W.verify_spans(out_ir))
    assert (n >= 4) if pieces else (n == 1)
    counts.update(parse=0, pypulseq=0)
    out = tmp_path / "o.seq"
    rec = write_checked(out_ir, out, False, LIMITS)
    assert counts == {"parse": n, "pypulseq": 2 * n}
    whole = check_file(out, SystemSpec(max_grad_mT_per_m=80.0, max_slew_T_per_m_per_s=200.0), conventions=None)
    assert rec["check_ok"] is whole.ok is True and rec["checks"] == whole.checks
    assert rec["format_version"] == (version or "1.5.0")


def _adc_moved(data: bytes) -> bytes:
    """The written text with its first ADC event's delay 10 us later (re-signed): within every rule and limit."""
    j = data.find(b"\n", data.find(b"\n[ADC]") + 1)  # the end of the header line
    while data[j + 1 : j + 2] == b"#":  # (a comment naming the columns)
        j = data.find(b"\n", j + 1)
    k = data.find(b"\n", j + 1)
    t = data[j + 1 : k].split()
    t[3] = str(int(t[3]) + 10).encode()  # id num dwell delay ...
    return seqtext.sign_text(data[: j + 1] + b" ".join(t) + data[k:])


@pytest.mark.parametrize("pieces", [True, False])
def test_a_difference_is_refused_as_the_read_back_alone_refuses_it(tmp_path, monkeypatch, pieces):
    """The written text with an ADC moved (what the shared reading's comparison finds, no rule does): refused in
    the one line verify_written gives on that text, nothing written."""
    out_ir = _moved(tmp_path, writers.gre3d(n=8, nz=4))
    if pieces:
        monkeypatch.setattr(W, "VERIFY_PIECE_RASTER", max(round(out_ir.duration_s / out_ir.raster_s / 6), 1))
    bad = _adc_moved(W.seq_bytes_of(out_ir, verify=False))
    with pytest.raises(DtocError) as alone:
        W.verify_written(out_ir, bad, (1, 5, 0))
    assert "moves the ADC of block" in str(alone.value)
    monkeypatch.setattr(
        run_mod, "write_seq_text", lambda ir, path, *a, **k: (Path(path).write_bytes(bad), (1, 5, 0))[1]
    )
    out = tmp_path / "o.seq"
    with pytest.raises(DtocError) as export:
        write_checked(out_ir, out, False, LIMITS)
    assert str(export.value) == str(alone.value) and "\n" not in str(export.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["base.seq"]


REPO = Path(__file__).resolve().parents[1]
GIRF = REPO / "girf" / "example_7T.npz"
#: ``dtoc optimize`` with the written text read back and checked in pieces of 256 raster steps (a long-ish export)
IN_PIECES = (
    "import sys, dtoc.seq.write as W; W.VERIFY_PIECE_RASTER = 256; from dtoc.cli.main import run; run(sys.argv[1:])"
)


@pytest.mark.skipif(not GIRF.exists(), reason="girf/example_7T.npz absent")
def test_a_sigterm_during_the_read_back_stops_the_export_with_nothing_written(tmp_path):
    """SIGTERM at the export's read-back of the written text (its first piece, ``DTOC_FAULT_SIGNAL=verify``): exit
    143 at once, one line, no output and no temporary left (the signal used to wait for the write, the read-back
    and the check, then for the outputs to be complete)."""
    base, outs = tmp_path / "base.seq", tmp_path / "out"
    base.write_bytes(writers.gre3d(n=8, nz=4))
    outs.mkdir()
    r = subprocess.run(
        [sys.executable, "-c", IN_PIECES, "optimize", base, "--girf", GIRF, "-o", outs / "o.seq", "--json",
         outs / "o.json", "-q", "--gmax", "80", "--smax", "200", "--warm-iters", "20", "--iters", "2", "--threads", "1"],
        cwd=REPO, capture_output=True, text=True, timeout=600,
        env={**os.environ, "DTOC_FAULT_SIGNAL": "verify:SIGTERM"},
    )  # fmt: skip
    assert r.returncode == 143, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last == "dtoc: interrupted by SIGTERM: no output written" and "Traceback" not in r.stderr, r.stderr
    assert list(outs.iterdir()) == []  # no .seq, manifest, side-car, nor a temporary of any
