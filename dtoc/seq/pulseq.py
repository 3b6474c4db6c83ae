"""The pypulseq adapter at the bottom of the sequence layer: how pypulseq is called, silenced and written.

Everything here depends on pypulseq (imported lazily, so commands that never touch it start fast) and on
nothing else of dtoc's sequence layer; the reader, writer, builder and validator all sit on top of it.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import sys
import tempfile
import types
import warnings
from pathlib import Path

import numpy as np

#: pypulseq modules its ``Sequence`` imports at load time for plotting, PNS and gradient spectra -- which pull in
#: matplotlib and scipy.signal (~0.45 s of the ~0.75 s that ``import pypulseq`` costs) -- and for ``PPoly``
#: (``Sequence.get_gradients`` only: scipy.interpolate, with scipy.special/optimize/linalg/sparse, ~0.2 s), and the
#: names it takes from them.  dtoc uses none of them; :func:`import_pypulseq` defers each until one of its names is
#: called.
_DEFERRED = {
    "scipy.interpolate": ("PPoly",),
    "pypulseq.Sequence.calc_grad_spectrum": ("calculate_gradient_spectrum",),
    "pypulseq.Sequence.calc_pns": ("calc_pns",),
    "pypulseq.utils.paper_plot": ("paper_plot",),
    "pypulseq.utils.seq_plot": ("SeqPlot",),
}


def _deferred_module(name: str, names: tuple[str, ...]) -> types.ModuleType:
    """A stand-in for module ``name``: each of ``names`` is a function that imports the real module on its first
    call and calls the real one; any other attribute (a name a later pypulseq takes from it) imports the real
    module at once, so nothing breaks, it only is not deferred."""
    stub = types.ModuleType(name)

    def real() -> types.ModuleType:
        if sys.modules.get(name) is stub:
            del sys.modules[name]
        return importlib.import_module(name)

    for n in names:

        def call(*args, _n=n, **kwargs):
            return getattr(real(), _n)(*args, **kwargs)

        call.__name__ = n
        setattr(stub, n, call)

    def other(attr: str):
        if attr.startswith("__"):  # the import system's probes (__path__, ...): a plain module has none
            raise AttributeError(attr)
        return getattr(real(), attr)

    stub.__getattr__ = other  # type: ignore[method-assign]
    return stub


def import_pypulseq() -> types.ModuleType:
    """``import pypulseq``, with its plotting / PNS / spectrum modules and scipy.interpolate deferred
    (:data:`_DEFERRED`) when pypulseq is not loaded yet: every dtoc command that reads or writes a ``.seq``
    starts ~0.65 s faster (docs/benchmarks.md, "CLI start-up")."""
    if "pypulseq" not in sys.modules:
        for name, names in _DEFERRED.items():
            if name not in sys.modules:
                sys.modules[name] = _deferred_module(name, names)
    return importlib.import_module("pypulseq")


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


def seq_bytes(seq, v141: bool = False, in_place: bool = False, check_timing: bool = True) -> bytes:
    """The signed Pulseq 1.5.0 text of a Sequence (pypulseq ``write``), as bytes; ``v141``: pypulseq's 1.4.1
    writer instead.  ``in_place``: ``seq`` is the caller's to change, and its duplicate events are removed in
    place (pypulseq's write otherwise removes them on a deep copy of every library: the same text, without that
    copy).  ``check_timing`` False: without pypulseq's timing check, which only warns (silenced here) and decodes
    every block (the same text; for a caller that checks the text it reads back)."""
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "out.seq"
        with quiet():
            if in_place:
                seq.remove_duplicates(in_place=True)
            seq.write(
                str(p),
                create_signature=True,
                v141_compat=v141,
                remove_duplicates=not in_place,
                check_timing=check_timing,
            )
        return p.read_bytes()
