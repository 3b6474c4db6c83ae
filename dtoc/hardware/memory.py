"""How far back (and ahead) a hardware chain remembers: the horizon of windowed optimization.

A realized gradient at time t depends on the demanded gradient in ``[t - causal_s, t + acausal_s]`` up to a
relative error ``tol``: a GIRF or ``lti`` kernel through its tap extent (``t0_s`` < 0: acausal taps), an
exponential eddy current ``tau ln(|alpha| / tol)``, a resonance ``(2 q / w0) ln(|amplitude| / tol)``, a delay
its value.  The memory of a chain is the sum over its effects.  Used by :mod:`dtoc.optimize.windowed`
(docs/optimize.md, "Long sequences").
"""

from __future__ import annotations

import math

import numpy as np

#: effect kinds whose output is an affine function of the demanded waveform (windowed optimization
#: precomputes their response; a chain with any other kind, e.g. slew_limit, is solved in one piece)
AFFINE_KINDS = frozenset(
    {
        "girf",
        "lti",
        "delay",
        "delay_bandlimited",
        "gain",
        "offset",
        "exp_eddy",
        "cross_eddy",
        "b0_eddy",
        "exp_eddy_chain",
        "cross_eddy_chain",
        "b0_eddy_chain",
        "resonance",
    }
)


def _effects(chain):
    """(effects list, True) of a HardwareModel (possibly wrapped in a RotatedChain); (None, False) otherwise."""
    inner = getattr(chain, "hardware", None)
    if inner is not None and hasattr(chain, "R"):
        chain = inner
    eff = getattr(chain, "effects", None)
    return (list(eff), True) if eff is not None else (None, False)


def is_affine(chain) -> bool:
    """True for ideal hardware (None) and models made only of :data:`AFFINE_KINDS`."""
    if chain is None:
        return True
    eff, ok = _effects(chain)
    return ok and all(e.kind in AFFINE_KINDS for e in eff)


def _decay_s(rate_per_s: np.ndarray, amp: np.ndarray, tol: float) -> float:
    rate = np.abs(np.asarray(rate_per_s, dtype=np.float64)).ravel()
    a = np.abs(np.asarray(amp, dtype=np.float64)).ravel()
    a = np.broadcast_to(a, rate.shape) if a.size == 1 else a
    out = 0.0
    for r, x in zip(rate, a):
        if x > tol and r > 0:
            out = max(out, math.log(x / tol) / r)
    return out


def memory_s(chain, tol: float = 1e-6) -> tuple[float, float]:
    """(causal_s, acausal_s): how long before / after t the demanded waveform still moves G(t) by more than
    ``tol`` (relative).  Ideal hardware: (0, 0); an unknown chain (not a HardwareModel): (inf, inf)."""
    if chain is None:
        return 0.0, 0.0
    eff, ok = _effects(chain)
    if not ok:
        return math.inf, math.inf
    causal = acausal = 0.0
    for e in eff:
        k = e.kind
        if k in ("girf", "lti"):
            n = (e.h if k == "girf" else e.taps).shape[-1]
            start, end = e.t0_s, e.t0_s + (n - 1) * e.dt_s
            causal += max(0.0, end)
            acausal += max(0.0, -start)
        elif k in ("delay", "delay_bandlimited"):
            d = float(e.seconds.detach())
            causal += max(0.0, d)
            acausal += max(0.0, -d)
        elif k.startswith(("exp_eddy", "cross_eddy", "b0_eddy")):
            tau = e.tau_s.detach().cpu().double().numpy()
            alpha = getattr(e, e.alpha_name).detach().cpu().double().numpy()
            causal += _decay_s(1.0 / np.maximum(tau, 1e-300), alpha, tol)
        elif k == "resonance":
            w0 = 2 * math.pi * float(e.f0_hz.detach())
            causal += _decay_s(np.array([w0 / (2 * float(e.q.detach()))]), np.array([float(e.amplitude.detach())]), tol)
    return causal, acausal
