"""Noise-floor estimators and the small exact pieces the search is built on."""

import numpy as np
import pytest
import torch

from dtoc.hardware.effects import Delay
from dtoc.hardware.model import HardwareModel, girf_effect
from dtoc.hardware.recursion import exp_response
from dtoc.identify.candidates import exp_columns, lti_features, pwl_shift
from dtoc.identify.data import IdentData, integrate_k
from dtoc.identify.folds import make_folds
from dtoc.identify.noise import difference_sigma, estimate_sigma, repeated_sigma
from dtoc.identify.synth import lowpass_girf, probe_waveforms, simulate_measurement
from dtoc.identify.workspace import cross_validate

DT = 10e-6


def test_difference_estimator_on_pure_noise():
    rng = np.random.default_rng(0)
    x = 0.37 * rng.standard_normal((5, 3, 4000))
    est = difference_sigma(x, np.ones_like(x))
    assert est.method == "difference"
    assert est.sigma == pytest.approx(0.37, rel=0.03)


def test_difference_estimator_sees_through_a_girf_sized_residual():
    """Ideal hardware declared, GIRF scanner: residual 10-100x the noise at corners; estimate within 10 %."""
    g = probe_waveforms(4, 4000, DT, seed=2)
    true = HardwareModel([girf_effect(lowpass_girf(DT))])
    for sigma in (0.01, 0.003):
        d = simulate_measurement(true, g, DT, sigma_G=sigma, seed=4)
        resid = d.G - g
        assert np.sqrt(np.mean(resid**2)) > 10 * sigma  # the residual is far above the noise ...
        est = estimate_sigma(None, g, d.G, resid, d.mask("G"))
        assert est.sigma == pytest.approx(sigma, rel=0.10)  # ... yet the noise floor is recovered


def test_difference_estimator_on_k_channel():
    g = probe_waveforms(3, 4000, DT, seed=5)
    true = HardwareModel([girf_effect(lowpass_girf(DT))])
    d = simulate_measurement(true, g, DT, sigma_G=None, sigma_k=0.05, seed=6)
    resid = d.k - integrate_k(g, DT)  # ideal-model residual in k: smooth, large
    est = estimate_sigma(None, g, d.k, resid, d.mask("k"))
    assert est.sigma == pytest.approx(0.05, rel=0.05)


def test_repeated_waveforms_are_preferred_and_exact():
    g1 = probe_waveforms(2, 3000, DT, seed=7)
    g = np.concatenate([g1, g1, g1])  # each waveform played three times
    true = HardwareModel([girf_effect(lowpass_girf(DT))])
    d = simulate_measurement(true, g, DT, sigma_G=0.02, seed=8)
    est = estimate_sigma(None, g, d.G, d.G - g, d.mask("G"))
    assert est.method == "repeated"
    assert est.sigma == pytest.approx(0.02, rel=0.03)
    assert repeated_sigma(g1, d.G[:2], d.mask("G")[:2]) is None  # nothing repeated -> not applicable


def test_given_sigma_wins():
    x = np.zeros((1, 3, 100))
    est = estimate_sigma(0.5, x, x, x, np.ones_like(x))
    assert (est.sigma, est.method) == (0.5, "given")


def test_exp_columns_match_the_twin_recursion():
    rng = np.random.default_rng(1)
    P = np.cumsum(rng.standard_normal((2, 500)), axis=-1)
    taus = np.array([5e-6, 1e-3, 0.1])
    mine = exp_columns(P, DT, taus)
    ref = exp_response(torch.as_tensor(P).unsqueeze(-2), DT, torch.as_tensor(taus).reshape(-1, 1)).numpy()
    np.testing.assert_allclose(mine, np.moveaxis(ref, -2, 0), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("tau", [3.3e-6, -7.5e-6, 20e-6])
def test_pwl_shift_matches_delay_effect(tau):
    rng = np.random.default_rng(2)
    x = rng.standard_normal((2, 3, 300))
    ref, _ = Delay(tau)(torch.as_tensor(x), torch.zeros(2, 300, dtype=torch.float64), DT)
    np.testing.assert_allclose(pwl_shift(x, tau, DT), ref.detach().numpy(), atol=1e-12)


def test_cross_validation_arithmetic():
    """Per-unit statistics: CV of a single free column equals explicit leave-fold-out least squares."""
    rng = np.random.default_rng(3)
    folds = make_folds(6, 50)
    s = rng.standard_normal((6, 50))
    z = 0.7 * s + rng.standard_normal((6, 50))
    A = (s * s).sum(1)[:, None]
    b = (s * z).sum(1)[:, None]
    c = (z * z).sum(1)
    res = cross_validate(A, b, c, folds, [[0]], free=True)
    cv = 0.0
    fou = np.asarray(folds.fold_of_unit)
    for f in range(folds.K):
        tr, te = fou != f, fou == f
        th = (s[tr] * z[tr]).sum() / (s[tr] ** 2).sum()
        cv += ((z[te] - th * s[te]) ** 2).sum()
    assert res.cv_chi2 == pytest.approx(cv, rel=1e-12)
    assert res.theta[0] == pytest.approx((s * z).sum() / (s * s).sum(), rel=1e-12)
    # The full-Gram path gives the same numbers.
    res2 = cross_validate(A[:, :, None], b, c, folds, [[0]], free=True)
    assert res2.cv_chi2 == pytest.approx(cv, rel=1e-9)


def test_folds():
    f = make_folds(7, 100)
    assert f.mode == "waveforms" and f.K == 5
    f1 = make_folds(1, 1000)
    assert f1.mode == "time blocks" and f1.K == 4
    tot = sum(f1.sample_mask(k, train=False) for k in range(f1.K))
    np.testing.assert_array_equal(tot, np.ones((1, 1000)))  # test blocks tile the waveform exactly once


def test_lti_features_find_a_resonance():
    n = np.arange(200)
    taps = 0.02 * np.exp(-n * DT / 400e-6) * np.sin(2 * np.pi * 3.6e3 * n * DT)
    ft = lti_features(taps, 0, DT)
    assert ft["peak_hz"] == pytest.approx(3.6e3, abs=150)


def test_identdata_validation_messages():
    g = np.zeros((2, 3, 10))
    with pytest.raises(Exception, match="'G'"):
        IdentData(dt_s=1e-5, g=g, G=np.zeros((2, 3, 9)))
    with pytest.raises(Exception, match="neither 'G'"):
        IdentData(dt_s=1e-5, g=g)


@pytest.mark.parametrize("M", [3, 1])
def test_lti_toeplitz_statistics_equal_the_generic_ones(M):
    from dtoc.identify.candidates import lti_stats_toeplitz
    from dtoc.identify.workspace import Prediction, Workspace

    rng = np.random.default_rng(9)
    N = 400
    g = rng.standard_normal((M, 3, N))
    d = IdentData(dt_s=DT, g=g, G=g + 0.1 * rng.standard_normal((M, 3, N)))
    ws = Workspace(d, {"G": 0.1}, make_folds(M, N), Prediction(g))
    lags = list(range(-4, 12))

    def make(ms):
        cols = np.stack(
            [
                np.stack(
                    [
                        np.concatenate(
                            [np.zeros(max(lag, 0)), g[m, 1, max(-lag, 0) : N - max(lag, 0)], np.zeros(max(-lag, 0))]
                        )
                        for m in ms
                    ]
                )
                for lag in lags
            ]
        )
        return {1: cols}, None

    A1, b1 = ws.unit_stats(make, len(lags), full=True)
    A2, b2 = lti_stats_toeplitz(ws, g[:, 1], 1, lags)
    np.testing.assert_allclose(A2, A1, rtol=1e-10, atol=1e-8)
    np.testing.assert_allclose(b2, b1, rtol=1e-10, atol=1e-8)
