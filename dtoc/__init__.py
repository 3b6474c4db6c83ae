"""dtoc: a command-line MRI sequence compiler, and the library behind it.

    import dtoc
    ir = dtoc.load_sequence("base.seq")
    res = dtoc.simulate(ir, dtoc.load_model(girf="h.npz"))
    run = dtoc.optimize_sequence("base.seq", girf="h.npz", out="out.seq")

Data flow (one sub-package per stage, docs/architecture.md):
    dtoc.seq       sequence I/O: the sequence IR, .seq read/write, specs, validator, diff
    dtoc.hardware  the hardware twin: demanded -> realized gradients and B0 (GIRF, eddy currents, ...)
    dtoc.identify  identification beside the twin: GIRF fitting, residual tracing (`dtoc identify`)
    dtoc.sim       the forward model (Twin), phantoms, PDG Bloch simulation, reconstruction, image metrics
    dtoc.optimize  digital-twin optimization and the classic pre-emphasis baseline
    dtoc.cli       the thin typer layer over all of the above

The public names (``__all__``) are loaded on first use, so ``import dtoc`` imports neither torch nor
pypulseq.  Units and conventions: docs/conventions.md; the API: docs/api.md.
"""

from __future__ import annotations

import importlib
from typing import Any

from dtoc.version import __version__

#: public name -> module that defines it
_EXPORTS = {
    "load_sequence": "dtoc.api",
    "build_sequence": "dtoc.api",
    "load_model": "dtoc.api",
    "simulate": "dtoc.api",
    "predict": "dtoc.api",
    "optimize_sequence": "dtoc.api",
    "identify_effects": "dtoc.api",
    "check": "dtoc.api",
    "diff": "dtoc.api",
    "run_batch": "dtoc.api",
    "SequenceIR": "dtoc.seq.ir",
    "EncodingGeometry": "dtoc.seq.geometry",
    "HardwareModel": "dtoc.hardware.model",
    "HardwareChain": "dtoc.sim.twin",
    "Twin": "dtoc.sim.twin",
    "Realization": "dtoc.sim.twin",
    "Imager": "dtoc.sim.imager",
    "Phantom": "dtoc.sim.phantom",
    "OptimizeConfig": "dtoc.optimize.config",
    "DtocError": "dtoc.errors",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'dtoc' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
