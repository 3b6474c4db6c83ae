"""Re-test of an adopted non-linear effect (issue 37, GIRFOS): the search is rerun without it and the model
with the lower held-out error is kept (docs/identify.md, step 5c)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

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


class _Eff(torch.nn.Module):
    def __init__(self, kind: str, axis: str | None):
        super().__init__()
        self.kind, self.axis, self.input_axis = kind, axis, None
        self.p = torch.nn.Parameter(torch.zeros(()))


class _Found:
    def __init__(self, kind: str, axis: str | None):
        self.effect = _Eff(kind, axis)


class _Twin:
    """Two found effects whose parameters are correlated -0.99; ``refit`` (without one of them) returns a
    given chi-square."""

    def __init__(self, chi2_without: float):
        self.found = [_Found("delay", "z"), _Found("gain", "z")]
        self.chi2_without = chi2_without

    def refit(self, max_iter: int = 10) -> dict:
        return {"chi2": self.chi2_without}


@pytest.mark.parametrize("chi2_without", [1000.0 + 3.0, 1000.0 - 2040973.9])
def test_degenerate_pair_note_never_prints_a_negative_rise(chi2_without):
    """Removing one of a degenerate pair: a small rise is printed as a rise; a fall (the joint fit had stalled,
    the Bruker run printed "rises by only -2040973.9") is said as such."""
    from dtoc.identify.separability import redundancy_problems

    fit = {"free": [(0, "seconds", None), (1, "factor", None)], "cov_u": np.array([[1.0, -0.99], [-0.99, 1.0]])}
    fit["chi2"] = 1000.0
    twin = _Twin(chi2_without)
    out = redundancy_problems(twin, fit, threshold=10.0, n_samples=1000)  # type: ignore[arg-type]
    assert len(out) == 1
    text = out[0][1]
    assert "rises by only -" not in text
    if chi2_without > fit["chi2"]:
        assert "rises by only 3.0" in text, text
    else:
        assert "fits better (chi-square lower by 2040973.9)" in text and "stalled" in text, text
    assert len(twin.found) == 2  # the twin is left as it was
