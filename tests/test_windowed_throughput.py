"""The window loop's per-window cost: the unconstrained optima's k errors in batches of one structure, the dense
products on the run's BLAS thread count (docs/benchmarks.md, "Long sequences")."""

from __future__ import annotations

import numpy as np
import pytest

from dtoc.optimize import windowed as W


def test_blas_threads_sets_and_restores_the_count():
    from dtoc.util import blas

    libs = blas._openblas()
    if not libs:
        pytest.skip("no OpenBLAS loaded in this process (not Linux, or another BLAS)")
    old = [get() for get, _ in libs]
    want = 1 if max(old) > 1 else 2
    with blas.blas_threads(want):
        assert [get() for get, _ in libs] == [want] * len(libs)
    assert [get() for get, _ in libs] == old


class _Sc:
    """The two attributes of :class:`dtoc.optimize.windowed._Scales` the k errors use, with its method."""

    k_axes = np.array([0, 1, 2])
    k_unit = 0.5
    m_unit = 0.25
    k_errors_dk = W._Scales.k_errors_dk


def test_unconstrained_errors_in_batches_equal_one_product_per_window():
    """Windows of two structures, interleaved in runs, with more windows per run than a batch: every sample and
    moment gets the k error of its own window's unconstrained optimum ``-Hinv grad0``, as products per window
    give it."""
    rng = np.random.default_rng(1)
    n_adc, n_mom, n = 5, 2, 7
    rows = 3 * (n_adc + n_mom) + 4  # k rows, moment rows, then rows the errors do not read
    Js = {"a": rng.normal(size=(rows, n)), "b": rng.normal(size=(rows, n))}
    Hs = {}
    for k in Js:
        B = rng.normal(size=(n, n))
        Hs[k] = np.linalg.inv(B @ B.T + n * np.eye(n))
    order = ["a"] * 5 + ["b"] * 2 + ["a"] * 3
    st = W.WindowStats()
    st.unconstrained_adc_dk = np.full(n_adc * len(order), np.nan)
    st.unconstrained_moment_dk = np.full(n_mom * len(order), np.nan)
    acc = W._UnconstrainedErrors(_Sc(), st, batch=3)
    want_a, want_m = np.zeros(n_adc * len(order)), np.zeros(n_mom * len(order))
    for i, key in enumerate(order):
        r0d, grad0 = rng.normal(size=rows), rng.normal(size=n)
        sel = np.arange(i * n_adc, (i + 1) * n_adc)
        mom = list(range(i * n_mom, (i + 1) * n_mom))
        acc.add(key, {"J": Js[key], "Hinv": Hs[key]}, r0d, grad0, n_adc, n_mom, sel, slice(0, n_adc), mom, 0)
        ua, um = _Sc().k_errors_dk(r0d - Js[key] @ (Hs[key] @ grad0), n_adc, n_mom)
        want_a[sel], want_m[mom] = ua, um
    acc.flush()
    np.testing.assert_allclose(st.unconstrained_adc_dk, want_a, rtol=1e-12, atol=0)
    np.testing.assert_allclose(st.unconstrained_moment_dk, want_m, rtol=1e-12, atol=0)
