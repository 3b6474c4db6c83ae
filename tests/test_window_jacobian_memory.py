"""The windows' Jacobian (dtoc.optimize.window_jacobian) holds what its rows x columns need, not rows x the span
between a window's first and last free edge: a 4.9 min MPRAGE's longest window (an inversion's spoiler and a readout
~1.1 s apart, 4,806 free variables) held 1.8 GB of gap there (issue 32)."""

from __future__ import annotations

import tracemalloc

import numpy as np

from dtoc.optimize import window_jacobian as WJ
from dtoc.optimize.limits import fine_free_mask

DT = 5e-6
N_EDGES = 40_001
W = 2 * N_EDGES - 1
RF_SAMPLES = 600


def _jacobian(fr: np.ndarray, R: np.ndarray) -> np.ndarray:
    rfm = np.zeros(W, dtype=bool)
    rfm[1000 : 1000 + RF_SAMPLES] = True  # an RF pulse's G-during-RF rows
    t_adc = np.linspace(0.5e-3, (W - 1) * DT, 64)  # k rows along the whole window
    ones = np.ones(3)
    return WJ.lti_jacobian(
        R, DT, fr, fine_free_mask(fr), t_adc, np.zeros(0), [0.1e-3], ["excitation"], rfm, np.array([0, 1]), ones, ones,
        1.0,
    )  # fmt: skip


def test_free_edges_far_apart_cost_their_columns_not_the_gap():
    rng = np.random.default_rng(5)
    lag = np.abs(np.arange(2 * W) - W)
    R = rng.standard_normal((3, 3, 2 * W)) * np.exp(-lag / 50.0)  # a short impulse response, centred at W
    fr = np.zeros((3, N_EDGES), dtype=bool)
    fr[0, 100:200] = True
    fr[0, 39_000:39_100] = True  # a second run 38,800 edges (0.39 s) after the first
    fr[1, 150:250] = True
    tracemalloc.start()
    J = _jacobian(fr, R)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert J.shape == (2 * 64 + 3 * RF_SAMPLES, 300)
    # its own arrays: the responses' integrals and hats, 4 x (3, 3, 2W) float64 = 46 MB, and J (1.6 MB); the gap
    # between the runs, RF rows x 38,900 edges x 8 bytes, would be 187 MB more for each of the three output axes
    assert peak < 46e6 + 30e6, peak / 1e6
    # each run's columns are what the Jacobian of that run alone (one contiguous run) gives, bit for bit
    for cols, run in ((slice(0, 100), (0, 100, 200)), (slice(100, 200), (0, 39_000, 39_100))):
        one = np.zeros_like(fr)
        one[run[0], run[1] : run[2]] = True
        np.testing.assert_array_equal(J[:, cols], _jacobian(one, R))
    assert np.abs(J).max() > 0
