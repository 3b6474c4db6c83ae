"""The pypulseq adapter at the bottom of the sequence layer: how pypulseq is called, silenced and written.

Everything here depends on pypulseq (imported lazily, so commands that never touch it start fast) and on
nothing else of dtoc's sequence layer; the reader, writer, builder and validator all sit on top of it.
"""

from __future__ import annotations

import contextlib
import io
import tempfile
import warnings
from pathlib import Path

import numpy as np


@contextlib.contextmanager
def quiet():
    """Silence pypulseq's prints and warnings (it prints to stdout on read/write)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with contextlib.redirect_stdout(io.StringIO()):
            yield


def representable_amplitudes(amps_hz_per_m) -> np.ndarray:
    """Round the largest-magnitude vertex to 6 significant digits (what pypulseq writes for the
    amplitude), so that the file plays ``amplitude x shape`` with only the 1e-7 shape quantisation:
    played error <= 5e-8 x |amplitude| (0.15 Hz/m at 72 mT/m) instead of 5e-6 x |amplitude|."""
    a = np.array(amps_hz_per_m, dtype=np.float64)
    if a.size and np.any(a != 0):
        peak = float(np.max(np.abs(a)))
        a6 = float(f"{peak:.6g}")
        near = np.abs(a) >= min(a6, peak) * (1 - 1e-12)  # the peak vertices, and any above the rounded peak
        a[near] = np.sign(a[near]) * a6
    return a


def seq_bytes(seq) -> bytes:
    """The signed Pulseq 1.5 text of a Sequence (pypulseq ``write``), as bytes."""
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "out.seq"
        with quiet():
            seq.write(str(p), create_signature=True)
        return p.read_bytes()
