"""The front of the sequence layer: a base sequence from whatever the user gives (``.seq`` file, spec file, spec).

Every command that takes a base sequence (simulate, predict, optimize) calls :func:`load_sequence`.
"""

from __future__ import annotations

from pathlib import Path

from dtoc.errors import InputError
from dtoc.seq.build import build_ir
from dtoc.seq.ir import SequenceIR
from dtoc.seq.read import read_seq
from dtoc.seq.spec import BaseSpec, load_spec


def load_sequence(path_or_spec, **kwargs) -> SequenceIR:
    """A base sequence from a ``.seq`` file, a spec ``.yaml``/``.yml`` file or a spec object.

    This is what every command that takes a base sequence (simulate, predict, optimize) calls.
    Keyword arguments go to :func:`read_seq` / :func:`from_pypulseq`.
    """
    if isinstance(path_or_spec, BaseSpec):
        return build_ir(path_or_spec, **kwargs)
    p = Path(path_or_spec)
    if p.suffix.lower() in (".yaml", ".yml"):
        ir = build_ir(load_spec(p), **kwargs)
        ir.meta["spec_path"] = str(p)
        return ir
    if p.suffix.lower() != ".seq" and p.exists():
        raise InputError(f"{p}: expected a .seq file or a spec .yaml")
    return read_seq(p, **kwargs)
