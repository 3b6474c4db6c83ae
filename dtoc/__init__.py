"""dtoc: a command-line MRI sequence compiler.

Data flow (one sub-package per stage):
    dtoc.seq       sequence I/O: the sequence IR, .seq read/write, specs, validator, diff
    dtoc.hardware  the hardware twin: demanded -> realized gradients and B0 (GIRF, eddy currents, ...)
    dtoc.identify  identification beside the twin: GIRF fitting, residual tracing (`dtoc identify`)
    dtoc.sim       phantoms, phase-distribution-graph Bloch simulation, reconstruction, image metrics
    dtoc.optimize  digital-twin optimization and the classic pre-emphasis baseline
    dtoc.cli       the thin typer layer over all of the above

Units and conventions: docs/conventions.md.
"""

__version__ = "0.1.0"
