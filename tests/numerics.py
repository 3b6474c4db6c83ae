"""Which numpy transcendental functions this machine has, for goldens whose bits depend on them.

numpy computes exp, sin, cos, log, ... with SIMD code chosen at run time by the CPU (AVX-512 on some Intel
processors, AVX2 on others and on AMD ones), and the variants differ in their last bits.  A graph the PDG
pre-pass builds prunes states by thresholds on values computed with them, so on two such machines the same code
builds graphs that differ where a value sits on a threshold (docs/benchmarks.md, "PDG pre-pass").  A golden is
therefore recorded per kind of machine: ``golden_for(path)`` is ``NAME.<signature>.json`` beside ``path`` when
one was recorded on a machine with this one's functions, else ``path`` (the first recording, an Intel Xeon with
AVX-512)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np


def signature() -> str:
    """16 hex digits of the bits numpy's exp, expm1, log, log1p, sin, cos, tan, arctan2, power and sinc give on a
    fixed set of arguments on this machine."""
    x = np.linspace(-50.0, 50.0, 200_001)
    a = np.abs(x)
    h = hashlib.sha256()
    for v in (
        np.exp(x / 10),
        np.expm1(x / 100),
        np.log(a + 1e-3),
        np.log1p(a),
        np.sin(x),
        np.cos(x),
        np.tan(x / 60),
        np.arctan2(x, 1.7),
        np.power(a + 1, 0.37),
        np.sinc(x / 7),
    ):
        h.update(np.ascontiguousarray(v).tobytes())
    return h.hexdigest()[:16]


def golden_for(path: Path) -> Path:
    """The golden recorded on a machine with this one's functions, or ``path``."""
    own = path.with_name(f"{path.stem}.{signature()}{path.suffix}")
    return own if own.exists() else path
