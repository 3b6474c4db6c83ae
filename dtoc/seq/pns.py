"""Peripheral nerve stimulation by the SAFE model (Hebrank & Gebhardt, ISMRM 2000, abstract 2007).

Per physical axis, the slew rate s(t) = dG/dt (T/m/s) passes three first-order (RC) low-pass filters:

    stim(t) = (a1 |LP_tau1(s)| + a2 LP_tau2(|s|) + a3 |LP_tau3(s)|) / stim_limit * g_scale * 100   [% of limit]

and the total is the root sum of squares over the axes; above 100 % the scanner's stimulation monitor stops
the sequence.  The parameters come from the vendor's hardware file, entered in a scanner profile
(docs/scanner.md).  This is the same model pypulseq ships (``pypulseq.utils.safe_pns_prediction``), written
as IIR filters (``scipy.signal.lfilter``) so that a whole sequence on the fine grid costs O(n); the tests check
the two agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class SafeAxis(BaseModel):
    """SAFE parameters of one gradient axis (the vendor file's names, units in ours)."""

    model_config = ConfigDict(extra="forbid")
    tau1_ms: float = Field(gt=0)
    tau2_ms: float = Field(gt=0)
    tau3_ms: float = Field(gt=0)
    a1: float = Field(ge=0)
    a2: float = Field(ge=0)
    a3: float = Field(ge=0)
    stim_limit_T_per_m_per_s: float = Field(gt=0)
    stim_thresh_T_per_m_per_s: float = Field(gt=0)
    g_scale: float = Field(gt=0)


class SafeModel(BaseModel):
    """SAFE parameters of the three physical axes; ``limit_percent``: what the check allows (100 = the monitor's)."""

    model_config = ConfigDict(extra="forbid")
    x: SafeAxis
    y: SafeAxis
    z: SafeAxis
    limit_percent: float = Field(100.0, gt=0, le=100.0)


def _rc_lowpass(x: np.ndarray, tau_s: float, dt_s: float) -> np.ndarray:
    """y[n] = (1 - alpha) y[n-1] + alpha x[n], alpha = dt / (tau + dt) (zero initial state)."""
    from scipy.signal import lfilter

    alpha = dt_s / (tau_s + dt_s)
    return lfilter([alpha], [1.0, -(1.0 - alpha)], x)


def safe_axis_percent(slew_T_per_m_per_s: np.ndarray, dt_s: float, p: SafeAxis) -> np.ndarray:
    """(n,) stimulation of one axis, % of its stimulation limit."""
    s = np.asarray(slew_T_per_m_per_s, dtype=np.float64)
    s1 = p.a1 * np.abs(_rc_lowpass(s, p.tau1_ms * 1e-3, dt_s))
    s2 = p.a2 * _rc_lowpass(np.abs(s), p.tau2_ms * 1e-3, dt_s)
    s3 = p.a3 * np.abs(_rc_lowpass(s, p.tau3_ms * 1e-3, dt_s))
    return (s1 + s2 + s3) / p.stim_limit_T_per_m_per_s * p.g_scale * 100.0


@dataclass
class PnsResult:
    """Per-axis and total stimulation, % of the limit, on the waveform's sample grid (n - 1 slew samples)."""

    per_axis_percent: np.ndarray  # (3, n - 1)
    total_percent: np.ndarray  # (n - 1,)
    dt_s: float

    @property
    def max_percent(self) -> float:
        return float(self.total_percent.max()) if self.total_percent.size else 0.0

    @property
    def t_max_s(self) -> float:
        return float((np.argmax(self.total_percent) + 0.5) * self.dt_s) if self.total_percent.size else 0.0


def safe_pns(grad_mT_per_m: np.ndarray, dt_s: float, model: SafeModel, rotation=None) -> PnsResult:
    """SAFE stimulation of a (3, n) gradient waveform (mT/m, sampled every ``dt_s``), on the physical axes
    (``rotation``: the file's logical -> physical R; None = the file's axes are physical)."""
    g = np.asarray(grad_mT_per_m, dtype=np.float64) * 1e-3  # T/m
    if rotation is not None:
        g = np.asarray(rotation, dtype=np.float64) @ g
    slew = np.diff(g, axis=1) / dt_s  # T/m/s
    per = np.stack([safe_axis_percent(slew[a], dt_s, p) for a, p in enumerate((model.x, model.y, model.z))])
    return PnsResult(per, np.sqrt(np.sum(per**2, axis=0)), dt_s)
