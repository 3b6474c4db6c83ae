"""The pypulseq adapter at the bottom of the sequence layer: how pypulseq is called, silenced and written.

Everything here depends on pypulseq (imported lazily, so commands that never touch it start fast) and on
nothing else of dtoc's sequence layer; the reader, writer, builder and validator all sit on top of it.
"""

from __future__ import annotations

import contextlib
import hashlib
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
    every block (the same text; for a caller that checks the text it reads back).  The text of :func:`seq_file`."""
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "out.seq"
        seq_file(seq, p, v141=v141, in_place=in_place, check_timing=check_timing)
        return p.read_bytes()


def seq_file(
    seq, path: str | Path, v141: bool = False, in_place: bool = False, check_timing: bool = True, signed: bool = True
) -> None:
    """:func:`seq_bytes`' text written to ``path``; ``signed`` False: without its [SIGNATURE], for the caller to
    edit and sign in chunks (:func:`dtoc.seq.seqtext.sign_file`: pypulseq's own signing reads the whole text as
    a string and encodes it, twice the text's size, the peak of a long sequence's export).  With ``in_place``,
    the libraries' look-up tables (a copy of every event and shape, used only to add events) are released after
    the de-duplication: ``seq`` is the caller's to discard."""
    with quiet():
        if in_place:
            lean_shape_dedup(seq.shape_library)
            seq.remove_duplicates(in_place=True)
            for lib in vars(seq).values():
                if hasattr(lib, "keymap") and hasattr(lib, "find_or_insert"):
                    lib.keymap = {}
        seq.write(
            str(path),
            create_signature=signed,
            v141_compat=v141,
            remove_duplicates=not in_place,
            check_timing=check_timing,
        )


def _round_significant(data: np.ndarray, digits: int) -> np.ndarray:
    """``data`` rounded to ``digits`` significant digits, as pypulseq rounds a shape before writing it (the same
    float operations, so the same bits), read-only."""
    mags = 10 ** (digits - np.ceil(np.log10(np.abs(data) + 1e-12)))
    out = np.round(data * mags) / mags
    out.flags.writeable = False
    return out


def lean_shape_dedup(lib) -> None:
    """Make the shape library ``lib``'s ``remove_duplicates`` (pypulseq's write calls it: every shape rounded to 9
    significant digits, each distinct rounded shape kept once, ids in the old ids' order) give the same library
    and mapping without holding the old and new libraries and both look-up tables at once (four copies of every
    shape: ~0.5 GB on a 1-minute 3D FLASH): the look-up tables are dropped (only adding an event uses them), each
    old shape is released as it is rounded, and a distinct shape is found by a 16-byte digest of its bytes (the
    bytes compared on a hit).  A library of other data is left as it is.  ``lib`` is the caller's to discard."""
    if not getattr(lib, "numpy_data", False):
        return

    def remove_duplicates(digits):
        new = type(lib)(numpy_data=True)
        mapping = {0: 0}
        seen: dict[bytes, list[int]] = {}
        lib.keymap = {}
        for k in sorted(lib.data):
            r = _round_significant(np.asarray(lib.data.pop(k)), digits)
            key = r.tobytes()
            h = hashlib.blake2b(key, digest_size=16).digest()
            hit = next((i for i in seen.get(h, ()) if new.data[i].tobytes() == key), None)
            if hit is None:
                hit = new.next_free_ID
                new.data[hit] = r
                if lib.type.get(k, ""):
                    new.type[hit] = lib.type[k]
                new.next_free_ID = hit + 1
                seen.setdefault(h, []).append(hit)
            mapping[k] = hit
        return new, mapping

    lib.remove_duplicates = remove_duplicates
