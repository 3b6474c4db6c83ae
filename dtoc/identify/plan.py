"""`dtoc identify-plan`: a short set of test waveforms that identifies a candidate set, checked before playing it.

:func:`propose` designs, for each axis in turn (never two axes at once, so that every cross term has its own
driving axis): a train of triangles at the full slew rate with times to peak from 50 to 160 us (the
broadband probe of a GIRF measurement: delays, filters, resonances), a long trapezoid at the full amplitude
followed by a long rest (gain, offset, exponential eddy currents up to the record length, B0 terms), and the
same trapezoid at minus half the amplitude and half the slew rate (amplitude and slew dependence:
non-linear gain, a slew-rate limit).  All start and end at zero.

:func:`check` is the identifiability test that ``identify`` applies to measured data, here on the linearised
design before any measurement: each candidate effect at a nominal size (:data:`NOMINAL`) is appended to ideal
hardware, the Jacobian of the predicted realized gradient (G channel, white noise ``sigma_G``) with respect to
every scalar parameter is taken by central differences, and from (J^T J)^-1 each parameter gets a standard
error and its largest correlation with a parameter of *another* effect.  An effect is identifiable when every
parameter's standard error is below a third of its nominal size (the adoption rule of docs/identify.md) and
no correlation with another effect reaches :data:`DEGENERATE_CORR` (then the two are named as degenerate).
The same check on waveforms that play one waveform on all axes at once names the cross terms as degenerate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from dtoc.constants import AXES
from dtoc.hardware.model import HardwareModel, build_effect

#: (kind, axis, input_axis, params) of each candidate at a nominal (small, typical) size.
NOMINAL: dict[str, list] = {
    "delay": [("delay", a, None, {"seconds": 1e-6}) for a in AXES],
    "gain": [("gain", a, None, {"factor": 0.99}) for a in AXES],
    "offset": [("offset", a, None, {"mT_per_m": 0.02}) for a in AXES],
    "exp_eddy": [("exp_eddy", a, None, {"alpha": 0.01, "tau_s": 1e-3}) for a in AXES],
    "cross_eddy": [("cross_eddy", o, i, {"alpha": 0.005, "tau_s": 1e-3}) for o in AXES for i in AXES if i != o],
    "resonance": [
        ("resonance", a, None, {"f0_hz": 1200.0, "q": 20.0, "amplitude": 0.002, "phase_rad": 0.5}) for a in AXES
    ],
    "slew_limit": [("slew_limit", a, None, {"max_slew_T_per_m_per_s": None}) for a in AXES],
    "time_base": [("time_base", None, None, {"ppm": 20.0})],
}
#: Neutral values (the parameter at which the effect does nothing); 0 when not listed.
NEUTRAL = {("gain", "factor"): 1.0}
#: Parameters without a size (an angle): no standard-error rule.
UNSIZED = {("resonance", "phase_rad")}
#: |correlation| with another effect's parameter at which two effects are called degenerate.
DEGENERATE_CORR = 0.99


def _trapezoid(n_ramp: int, n_flat: int, amp: float) -> np.ndarray:
    r = np.arange(1, n_ramp + 1) / n_ramp
    return np.concatenate([amp * r, np.full(n_flat, amp), amp * r[::-1][1:], [0.0]])


def propose(
    dt_s: float = 10e-6,
    gmax_mT_per_m: float = 30.0,
    smax_T_per_m_per_s: float = 150.0,
    record_s: float = 50e-3,
    axes=AXES,
) -> tuple[np.ndarray, list[str]]:
    """(g (M, 3, N) mT/m, labels) of the proposed test waveforms (module docstring): 3 per axis."""
    N = int(round(record_s / dt_s))
    smax = smax_T_per_m_per_s * 1e3  # mT/m/s
    out, labels = [], []
    for ax in axes:
        a = AXES.index(ax)
        tri = np.zeros(N)
        n = int(round(0.5e-3 / dt_s))
        for tp in np.linspace(50e-6, 160e-6, 12):
            k = max(1, int(round(tp / dt_s)))
            peak = min(gmax_mT_per_m, smax * k * dt_s)
            w = _trapezoid(k, 0, peak)
            if n + w.size >= N:
                break
            tri[n : n + w.size] = w
            n += w.size + int(round(1e-3 / dt_s))
        g = np.zeros((3, N))
        g[a] = tri
        out.append(g)
        labels.append(f"{ax}: 12 triangles at {smax_T_per_m_per_s:g} T/m/s, 50-160 us to peak")
        for amp, slew, name in ((gmax_mT_per_m, smax, "full"), (-0.5 * gmax_mT_per_m, 0.5 * smax, "-half")):
            nr = max(1, int(math.ceil(abs(amp) / slew / dt_s)))
            w = _trapezoid(nr, int(round(0.3 * record_s / dt_s)), amp)
            g = np.zeros((3, N))
            s0 = int(round(0.5e-3 / dt_s))
            g[a, s0 : s0 + w.size] = w[: N - s0]
            out.append(g)
            labels.append(
                f"{ax}: trapezoid {amp:+g} mT/m ({name} amplitude, {slew * 1e-3:g} T/m/s), "
                f"{0.3 * record_s * 1e3:g} ms plateau, then rest"
            )
    return np.stack(out), labels


@dataclass
class Verdict:
    """The identifiability of one candidate effect on the checked waveforms."""

    name: str
    identifiable: bool
    rel_se: float  # largest standard error / nominal size over its parameters
    partner: str | None  # the other effect it is most correlated with
    corr: float
    reason: str


def _name(kind, axis, inp) -> str:
    return kind + (f"[{axis}]" if axis else "") + (f"<-{inp}" if inp else "")


def check(
    g: np.ndarray,
    dt_s: float,
    kinds=None,
    sigma_G: float = 0.01,
) -> list[Verdict]:
    """Identifiability of every candidate of ``kinds`` (default: all of :data:`NOMINAL`) on waveforms ``g``
    (M, 3, N) measured in G with white noise ``sigma_G`` (module docstring)."""
    gt = torch.as_tensor(np.asarray(g, dtype=np.float64))
    smax = float(np.max(np.abs(np.diff(g, axis=-1)))) / dt_s * 1e-3
    cands = []
    for kind in kinds or list(NOMINAL):
        for k, ax, inp, p in NOMINAL.get(kind, []):
            p = dict(p)
            if kind == "slew_limit":
                p["max_slew_T_per_m_per_s"] = 0.9 * smax
            cands.append((k, ax, inp, p))
    cols, owner, sizes = [], [], []
    for ci, (k, ax, inp, p) in enumerate(cands):
        for n, v in p.items():
            h = 1e-4 * abs(v) if v else 1e-6
            preds = []
            for sgn in (1.0, -1.0):
                q = dict(p)
                q[n] = v + sgn * h
                model = HardwareModel([build_effect(k, q, axis=ax, input_axis=inp)])
                with torch.no_grad():
                    G, _ = model(gt, dt_s)
                preds.append(G.numpy().reshape(-1))
            cols.append((preds[0] - preds[1]) / (2 * h) / sigma_G)
            owner.append((ci, n))
            sizes.append(abs(v - NEUTRAL.get((k, n), 0.0)))
    J = np.stack(cols, axis=1)
    JTJ = np.einsum("np,nq->pq", J, J)
    d = np.sqrt(np.maximum(np.diag(JTJ), 1e-300))
    C = JTJ / d[:, None] / d[None, :]
    # Degeneracy first: a parameter (nearly) a combination of another effect's columns has an inflated error.
    cov = np.linalg.pinv(JTJ, rcond=1e-13, hermitian=True)
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    # A column in the null space of J^T J (exactly degenerate): infinite error.
    w, V = np.linalg.eigh(C)
    null = V[:, w < 1e-10 * max(w.max(), 1e-300)]
    if null.size:
        se = np.where(np.abs(null).max(axis=1) > 1e-3, np.inf, se)
    out = []
    for ci, (k, ax, inp, _p) in enumerate(cands):
        idx = [j for j, (c, _) in enumerate(owner) if c == ci]
        rel = 0.0
        for j in idx:
            if (k, owner[j][1]) in UNSIZED:
                continue
            rel = max(rel, se[j] / max(sizes[j], 1e-300))
        best, partner = 0.0, None
        for j in idx:
            for m, (c2, _) in enumerate(owner):
                if c2 != ci and abs(C[j, m]) > abs(best):
                    best, partner = float(C[j, m]), _name(*cands[c2][:3])
        ok = rel < 1.0 / 3.0 and abs(best) < DEGENERATE_CORR
        if ok:
            reason = f"identifiable: relative standard error {rel:.2g}"
        elif abs(best) >= DEGENERATE_CORR:
            reason = f"not identifiable: degenerate with {partner} (correlation {best:+.3f})"
        else:
            reason = f"not identifiable: relative standard error {rel:.2g} (must be < 1/3)"
        out.append(Verdict(_name(k, ax, inp), ok, rel, partner, best, reason))
    return out
