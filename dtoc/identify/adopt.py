"""The adoption gate: an updated model is adopted only where the data support every part of it.

:func:`gate_problems` lists what is wrong with the current set of found effects (empty list: adopt):

1. **Physical bounds** (:data:`PHYSICAL_BOUNDS`): e.g. a time constant shorter than one sample, an eddy
   amplitude |alpha| >= 1, a delay of 100 us or more, a gain outside 0.5-1.5.  A value outside them is
   not a property of a gradient chain but a fit that found a numerical shortcut.
2. **Identified**: every adopted scalar parameter has a finite standard error below |value| / 3 (for a
   gain: |factor - 1| / 3; a parameter whose error is comparable to its size is not determined by the
   data), and none ended at a
   bound of the refit.  ``lti`` taps are exempt one by one (a FIR filter's taps are correlated by design);
   the filter as a whole passed the held-out score.
3. **Never worse held out**: on every measured channel (G, k, b0) the held-out RMS residual of the updated
   model is no larger than the declared model's on the same samples.
4. **Loads back**: the model file text, read by dtoc's own loader (:func:`dtoc.hardware.model.load_model`,
   with its plausibility ranges), predicts the same realized gradient and B0 as the fitted model to 1e-9
   (relative to the signal), checked in a temporary folder *before* any output is written.

:func:`dtoc.identify.search.identify` removes the offending effect with the lowest score (or, for a
held-out or round-trip failure, the one added last), refits the rest and checks again, until the gate
passes or nothing is left; every removal is reported with its reason.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dtoc.identify.kinds import effect_name

#: (kind, parameter) -> (low, high, unit, absolute?) physical range of an adopted parameter; ``absolute``:
#: the bound applies to |value|.  ``dt`` in a bound means the measurement's sample interval.
PHYSICAL_BOUNDS: dict[tuple[str, str], tuple[float | str, float, str, bool]] = {
    ("delay", "seconds"): (0.0, 100e-6, "s", True),
    ("delay_bandlimited", "seconds"): (0.0, 100e-6, "s", True),
    ("gain", "factor"): (0.5, 1.5, "", False),
    ("offset", "mT_per_m"): (0.0, 2.0, "mT/m", True),
    ("exp_eddy", "alpha"): (0.0, 1.0, "", True),
    ("exp_eddy", "tau_s"): ("dt", 10.0, "s", False),
    ("cross_eddy", "alpha"): (0.0, 1.0, "", True),
    ("cross_eddy", "tau_s"): ("dt", 10.0, "s", False),
    ("b0_eddy", "alpha_uT_per_mT_per_m"): (0.0, 10.0, "uT per mT/m", True),
    ("b0_eddy", "tau_s"): ("dt", 10.0, "s", False),
    ("slew_limit", "max_slew_T_per_m_per_s"): (1.0, 1e4, "T/m/s", False),
    ("time_base", "ppm"): (0.0, 1000.0, "ppm", True),
    ("resonance", "f0_hz"): (1.0, 1e5, "Hz", False),
    ("resonance", "q"): (0.5, 1e4, "", False),
    ("resonance", "amplitude"): (0.0, 1.0, "", True),
}

#: Parameters without a size to compare their error with (an angle): exempt from the identification rule.
UNSIZED = {("resonance", "phase_rad")}

#: A parameter is identified when its standard error is below |value - neutral| / IDENTIFIED_RATIO, where
#: ``neutral`` is the value at which the effect does nothing (:data:`NEUTRAL`; 0 for all others).
IDENTIFIED_RATIO = 3.0
NEUTRAL = {("gain", "factor"): 1.0}


@dataclass
class Problem:
    """Why the current model may not be adopted; ``index`` is the found effect at fault (None: the model)."""

    index: int | None
    reason: str


def _scalar(p: torch.Tensor) -> float | None:
    return float(p.detach().reshape(())) if p.numel() == 1 else None


def bound_problems(found: list, dt_s: float) -> list[Problem]:
    """Parameters outside :data:`PHYSICAL_BOUNDS`."""
    out = []
    for i, f in enumerate(found):
        e = f.effect
        for n in e.param_names:
            rng = PHYSICAL_BOUNDS.get((e.kind.removesuffix("_chain"), n))
            v = _scalar(getattr(e, n))
            if rng is None or v is None:
                continue
            lo_raw, hi, unit, absolute = rng
            lo = dt_s if lo_raw == "dt" else float(lo_raw)
            x = abs(v) if absolute else v
            inside = (x < hi) if absolute else (lo <= x <= hi)
            if not math.isfinite(v) or not inside:
                span = f"|{n}| < {hi:g}" if absolute else f"{lo:g} <= {n} <= {hi:g}"
                out.append(Problem(i, f"{effect_name(e)}: {n} = {v:.4g}{(' ' + unit) if unit else ''} outside {span}"))
    return out


def identification_problems(found: list, at_bound: list) -> list[Problem]:
    """Scalar parameters whose standard error is not below |value| / 3, or that ended at a refit bound."""
    out = []
    bound = {(i, n) for i, n in at_bound}
    for i, f in enumerate(found):
        e = f.effect
        if e.kind == "lti":
            continue
        for n in e.param_names:
            v = _scalar(getattr(e, n))
            if v is None or (e.kind, n) in UNSIZED:
                continue
            if (i, n) in bound:
                out.append(Problem(i, f"{effect_name(e)}: {n} ended at the bound of its fit"))
                continue
            se = f.stderr.get(n)
            size = abs(v - NEUTRAL.get((e.kind, n), 0.0))
            if se is None or not math.isfinite(se) or not se < size / IDENTIFIED_RATIO:
                out.append(
                    Problem(
                        i,
                        f"{effect_name(e)}: {n} = {v:.4g} ± {se if se is not None else float('nan'):.2g} is not "
                        f"identified (standard error must be < |value{' - 1' if (e.kind, n) in NEUTRAL else ''}|/{IDENTIFIED_RATIO:g})",
                    )
                )
    return out


def heldout_problems(heldout_before: dict, heldout_after: dict, channels) -> list[Problem]:
    """Channels whose held-out RMS got worse than the declared model's."""
    out = []
    for c in channels:
        b, a = heldout_before.get(c), heldout_after.get(c)
        if b is None or a is None:
            continue
        if not (math.isfinite(a) and a <= b):
            out.append(Problem(None, f"held-out {c} residual {a:.4g} is worse than the declared model's {b:.4g}"))
    return out


def roundtrip_problem(model, g: np.ndarray, dt_s: float) -> Problem | None:
    """Write the model file in a temporary folder, read it with :func:`load_model`, and compare predictions."""
    from dtoc.errors import InputError
    from dtoc.hardware.model import load_model, save_model

    gt = torch.as_tensor(g, dtype=torch.float64)
    with torch.no_grad():
        G0, b00 = model(gt, dt_s)
    with tempfile.TemporaryDirectory(prefix="dtoc-identify-") as d:
        path = Path(d) / "updated_model.json"
        try:
            save_model(model, path)
            back = load_model(path)
        except InputError as e:
            return Problem(None, f"the updated model does not load back: {e}")
        with torch.no_grad():
            G1, b01 = back(gt, dt_s)
    scale = max(float(G0.abs().max()), 1e-12)
    errG = float((G1 - G0).abs().max()) / scale
    scale0 = max(float(b00.abs().max()), 1e-12)
    err0 = float((b01 - b00).abs().max()) / scale0 if float(b00.abs().max()) > 0 else 0.0
    if not (errG <= 1e-9 and err0 <= 1e-9):
        return Problem(None, f"the updated model file predicts differently after loading (rel. {max(errG, err0):.2g})")
    return None


def pick_offender(problems: list[Problem], found: list) -> int:
    """Index of the found effect to remove: the lowest-scored one at fault; for model-level problems the
    one added last."""
    at_fault = sorted({p.index for p in problems if p.index is not None})
    if at_fault:
        return min(at_fault, key=lambda i: (found[i].score, -i))
    return len(found) - 1
