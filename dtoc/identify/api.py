"""One call for the CLI and for scripts: files in, report and updated model out.

:func:`run_identify` loads the measurement (:func:`dtoc.hardware.measurement.load_measurement`, one-line
errors naming the key), resolves the declared model (``--girf`` / ``--model``; neither = ideal hardware),
runs :func:`dtoc.identify.search.identify`, and writes every requested output atomically (the report JSON,
the updated model JSON accepted by ``load_model`` / ``--model``, the residual PNG).  All outputs are
checked for writability *before* the (possibly long) identification starts.
"""

from __future__ import annotations

import os
from pathlib import Path

from dtoc.identify.data import from_measurement
from dtoc.identify.search import IdentifyResult, identify
from dtoc.util.atomic import atomic_write_bytes, atomic_write_text, check_output_path


def run_identify(measured: str | os.PathLike, girf: str | os.PathLike | None = None,
                 model: str | os.PathLike | None = None, out_model: str | os.PathLike | None = None,
                 json_out: str | os.PathLike | None = None, png_out: str | os.PathLike | None = None,
                 force: bool = False, max_effects: int = 6, threshold: float = 10.0, kinds=None,
                 progress=None) -> IdentifyResult:
    """Identify missing effects in ``measured`` against the declared model and write the outputs.

    Returns:
        The :class:`dtoc.identify.search.IdentifyResult`.
    """
    from dtoc.hardware.measurement import load_measurement
    from dtoc.hardware.model import resolve_model, save_model
    from dtoc.identify.report import report_json, residual_png

    for p in (out_model, json_out, png_out):
        if p is not None:
            check_output_path(p, force)
    meas = load_measurement(measured)
    declared = resolve_model(girf=girf, model=model)
    data = from_measurement(meas)
    res = identify(data, declared, max_effects=max_effects, threshold=threshold, kinds=kinds, progress=progress)
    if json_out is not None:
        atomic_write_text(json_out, report_json(res), force=force)
    if out_model is not None:
        save_model(res.updated_model(), out_model, force=force)
    if png_out is not None:
        atomic_write_bytes(png_out, residual_png(res), force=force)
    return res
