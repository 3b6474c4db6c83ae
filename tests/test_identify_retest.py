"""Re-test of an adopted non-linear effect (issue 37, GIRFOS): the search is rerun without it and the model
with the lower held-out error is kept (docs/identify.md, step 5c)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from dtoc.hardware.model import HardwareModel, girf_effect
from dtoc.identify.search import identify
from dtoc.identify.synth import lowpass_girf, simulate_measurement

DT = 10e-6


def _triangles(n: int = 300, slew_T_per_m_per_s: float = 115.0) -> np.ndarray:
    """12 negative triangles on x at the full slew rate, 100-320 us long (the GIRFOS test waveforms)."""
    t = (np.arange(n) + 0.5) * DT
    g = np.zeros((12, 3, n))
    for i, dur in enumerate(np.linspace(100e-6, 320e-6, 12)):
        half = dur / 2
        g[i, 0] = -np.clip(slew_T_per_m_per_s * 1e3 * (half - np.abs(t - 100 * DT - half)), 0.0, None)
    return g


@pytest.mark.slow
def test_slew_limit_that_mimics_a_linear_lowpass_is_dropped_on_retest():
    """A linear second-order low-pass (-3 dB near 6 kHz) on x, played with full-slew triangles: with
    slew_limit, exp_eddy and delay in the library a slew limit is adopted (it mimics the rounded, lagging
    peaks); the search without it explains the held-out data better, so the final model is linear, has no
    slew limit, and the report says which effect was dropped and both held-out errors."""
    truth = HardwareModel([girf_effect(lowpass_girf(DT, bandwidth_hz=6e3, cross=0.0))])
    d = simulate_measurement(truth, _triangles(), DT, sigma_G=None, sigma_k=0.02)
    r = identify(d, None, kinds=["slew_limit", "exp_eddy", "delay"])
    kinds = [f.effect.kind for f in r.twin.found]
    assert "slew_limit" not in kinds and kinds, kinds
    lines = [n for n in r.remaining if "dropped on re-test" in n]
    assert len(lines) == 1, r.remaining
    m = re.search(r"k ([0-9.]+)x -> ([0-9.]+)x the noise floor", lines[0])
    assert m is not None, lines[0]
    with_slew, without = float(m.group(1)), float(m.group(2))
    assert without < with_slew
