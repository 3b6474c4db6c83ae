"""Forbidden acoustic bands: how much of a gradient waveform's switching power falls inside a band.

Gradient coils have mechanical resonances; vendors forbid sustained switching at frequencies inside given bands
(for an EPI: the readout's fundamental 1 / (2 echo spacing)).  Per physical axis, dtoc computes the power
spectrum of the whole demanded waveform (mean removed; below 20 Hz ignored: the slow envelope) and the fraction
of that AC power inside each forbidden band; a fraction above ``max_power_fraction`` (default 0.1, a profile
setting) fails the check.  This is dtoc's criterion, stated as such: vendors do not publish theirs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

F_MIN_HZ = 20.0


@dataclass
class BandResult:
    band_hz: tuple[float, float]
    axis: int
    power_fraction: float
    peak_hz: float  # the strongest frequency of that axis inside the band


def band_power_fractions(grad_mT_per_m: np.ndarray, dt_s: float, bands_hz, rotation=None) -> list[BandResult]:
    """For every physical axis that switches and every band: the fraction of the AC power inside the band."""
    g = np.asarray(grad_mT_per_m, dtype=np.float64)
    if rotation is not None:
        g = np.asarray(rotation, dtype=np.float64) @ g
    n = g.shape[1]
    f = np.fft.rfftfreq(n, dt_s)
    ac = f >= F_MIN_HZ
    out = []
    for a in range(3):
        x = g[a] - g[a].mean()
        if not np.any(np.abs(x) > 1e-9):
            continue
        p = np.abs(np.fft.rfft(x)) ** 2
        total = float(p[ac].sum())
        if total <= 0:
            continue
        for lo, hi in bands_hz:
            m = ac & (f >= lo) & (f <= hi)
            frac = float(p[m].sum() / total) if m.any() else 0.0
            peak = float(f[m][np.argmax(p[m])]) if m.any() else float("nan")
            out.append(BandResult((float(lo), float(hi)), a, frac, peak))
    return out
