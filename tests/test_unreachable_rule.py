"""The one rule that names the samples above the k tolerance (docs/optimize.md, "Solver"): shared by the whole
and the windowed solve (dtoc.optimize.solver.explain_unreachable)."""

from __future__ import annotations

import numpy as np

from dtoc.optimize.solver import FIXED_SHARE, active_limits_nearest, explain_unreachable


class _Limits:
    """The part of an EdgeProjector the rule reads: masks of edges (3, N+1) and segments (3, N) at their bound."""

    def __init__(self, amp: np.ndarray, slew: np.ndarray, raster_s: float = 1e-5):
        self.amp, self.slew, self.raster_s = amp, slew, raster_s
        self.free = np.ones_like(amp)

    def at_limits(self, x):
        return self.amp, self.slew


def _limits(n=100, amp_at=(), slew_at=()):
    amp = np.zeros((3, n + 1), dtype=bool)
    slew = np.zeros((3, n), dtype=bool)
    for a, i in amp_at:
        amp[a, i] = True
    for a, i in slew_at:
        slew[a, i] = True
    return _Limits(amp, slew)


def test_the_nearest_limit_before_a_sample_is_named_else_the_nearest_after():
    P = _limits(amp_at=[(0, 10)], slew_at=[(1, 40), (2, 80)])
    names, t = active_limits_nearest(P, np.zeros((3, 101)), np.array([5e-5, 2e-4, 5e-4, 9e-4]))
    # 50 us: nothing before, the amplitude limit at 100 us after it (an acausal GIRF lets a later limit act)
    assert names == ["amplitude x", "amplitude x", "slew y", "slew z"]
    assert np.allclose(t, [1e-4, 1e-4, 4e-4, 8e-4])
    none, tn = active_limits_nearest(_limits(), np.zeros((3, 101)), np.array([1e-4]))
    assert none == [""] and np.isnan(tn[0])


def test_fixed_only_when_the_unconstrained_optimum_misses_by_most_of_the_error():
    P = _limits(slew_at=[(0, 5)])
    err = np.array([0.005, 0.30, 0.30, 0.30, 0.30])
    unc = np.array([0.0, 0.02, 0.29, 0.001, np.nan])
    u = explain_unreachable(np.zeros((3, 101)), err, unc, 0.01, P, np.arange(5) * 1e-4)
    assert list(u.indices) == [1, 2, 3, 4]
    # 0.02 dk without limits is above the tolerance, but the limits cost the other 0.28 dk: 'limits', not 'fixed'
    assert 0.02 < FIXED_SHARE * 0.30
    assert u.reason == ["limits", "fixed", "limits", "fixed"]
    assert u.limit[0] == "slew x" and u.limit[1] == ""
    assert "without limits 0.02 dk" in u.summary()


def test_limits_named_when_no_limit_is_at_its_bound_is_no_claim():
    u = explain_unreachable(np.zeros((3, 101)), np.array([0.3]), np.array([0.001]), 0.01, _limits(), np.array([1e-4]))
    assert u.reason == ["unresolved"]
    u2 = explain_unreachable(
        np.zeros((3, 101)), np.array([0.3]), np.array([0.2]), 0.01, _limits(), np.array([1e-4]), unc_converged=False
    )
    assert u2.reason == ["unresolved"]
