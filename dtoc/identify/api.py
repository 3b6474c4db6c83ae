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

import numpy as np

from dtoc.identify.data import from_measurement
from dtoc.identify.search import IdentifyResult, identify
from dtoc.util.atomic import atomic_write_bytes, atomic_write_text, check_outputs, outputs_together

#: Plausible peak slew rate of the demanded test waveforms, T/m/s.  Outside it ``dt`` is almost surely in the
#: wrong unit (ms or us instead of s: a factor 1e3 either way), which the sample count alone cannot reveal.
SLEW_RANGE_T_PER_M_PER_S = (2.0, 1e4)


def load_identify_measurement(path: str | os.PathLike):
    """:func:`dtoc.hardware.measurement.load_measurement` plus the checks ``identify`` needs on top:

    * a file that is not an ``.npz`` archive (e.g. a single ``.npy`` array saved under that name) is a
      one-line error, not a crash;
    * the demanded peak slew rate, max |dg/dt| with ``dt`` as given, must lie in
      :data:`SLEW_RANGE_T_PER_M_PER_S`: a ``dt`` written in ms (1e3 too large) makes every ramp 1e3 times
      too slow, one written in us too fast.
    Raises:
        InputError naming the file and key.
    """
    import zipfile

    from dtoc.errors import InputError
    from dtoc.hardware.measurement import load_measurement

    p = Path(path)
    if p.is_file() and not zipfile.is_zipfile(p):
        raise InputError(
            f"{p}: not an .npz archive (expected the measurement keys dt, g, G and/or k saved with numpy.savez)"
        )
    meas = load_measurement(p)
    slew = float(np.max(np.abs(np.diff(meas.g, axis=-1)))) / meas.dt_s * 1e-3  # T/m/s
    lo, hi = SLEW_RANGE_T_PER_M_PER_S
    if slew > 0 and not lo <= slew <= hi:
        raise InputError(
            f"{p}: key 'dt' = {meas.dt_s:g} s gives a peak demanded slew of {slew:.3g} T/m/s "
            f"(plausible {lo:g} to {hi:g}): is 'dt' in s (not ms or us) and 'g' in mT/m?"
        )
    return meas


def run_identify(
    measured: str | os.PathLike,
    girf: str | os.PathLike | None = None,
    model: str | os.PathLike | None = None,
    out_model: str | os.PathLike | None = None,
    json_out: str | os.PathLike | None = None,
    png_out: str | os.PathLike | None = None,
    force: bool = False,
    max_effects: int = 6,
    threshold: float = 10.0,
    kinds=None,
    progress=None,
    declared_model=None,
) -> IdentifyResult:
    """Identify missing effects in ``measured`` against the declared model and write the outputs.

    The updated model (``out_model``) is written only when the adoption gate kept at least one effect
    (``res.adopted``); otherwise no model file is written and an existing one is left untouched.

    Returns:
        The :class:`dtoc.identify.search.IdentifyResult`.
    """
    from dtoc.hardware.model import resolve_model, save_model
    from dtoc.identify.report import report_json, residual_png

    check_outputs(
        {"-o": out_model, "--json": json_out, "--png": png_out},
        {"measurement": measured, "--girf": girf, "--model": model},
        force,
    )
    meas = load_identify_measurement(measured)
    declared = declared_model if declared_model is not None else resolve_model(girf=girf, model=model)
    data = from_measurement(meas)
    res = identify(data, declared, max_effects=max_effects, threshold=threshold, kinds=kinds, progress=progress)
    # Render everything first, so that a failure while rendering leaves no output half-done.
    text = report_json(res) if json_out is not None else None
    png = residual_png(res) if png_out is not None else None
    updated = res.updated_model()
    with outputs_together():
        if out_model is not None and res.adopted:  # docs/identify.md: no model file unless an effect is adopted
            save_model(updated, out_model, force=force)
        if json_out is not None and str(json_out) != "-":
            atomic_write_text(json_out, text, force=force)
        if png_out is not None:
            atomic_write_bytes(png_out, png, force=force)
    return res
