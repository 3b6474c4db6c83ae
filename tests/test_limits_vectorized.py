"""The projection onto the limits as whole-array operations (issues 32/33): the repair's greedy passes and
Dykstra's pair projections give the numbers of the plain per-sample / per-expression algorithm bit for bit, and
a tensor is projected where it lies with the same numbers as the numpy path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dtoc.optimize import limits as L
from dtoc.optimize.limits import EdgeProjector, Limits

RASTER = 10e-6


def _scalar_greedy(y, lo, hi, dlo, dhi):
    """The reference: the repair's greedy pass one sample after the other (Python floats)."""
    out, prev = [], None
    for n, v in enumerate(y.tolist()):
        a, b = float(lo[n]), float(hi[n])
        if prev is not None:
            a = max(a, prev + float(dlo[n - 1]))
            b = min(b, prev + float(dhi[n - 1]))
        if a > b:
            b = a
        prev = a if v < a else (b if v > b else v)
        out.append(prev)
    return np.asarray(out)


def _plain_dykstra(P: EdgeProjector, x: np.ndarray, n_iter: int) -> np.ndarray:
    """The reference: Dykstra's projection written as plain expressions, one new array each."""

    def pairs(v, start):
        y = v.copy()
        a, b = y[:, start:-1:2], y[:, start + 1 :: 2]
        m = min(a.shape[1], b.shape[1])
        a, b = a[:, :m], b[:, :m]
        mask = P.pair_free[:, start::2][:, :m]
        d = b - a
        if P.uniform:
            excess = np.where(mask, np.clip(np.abs(d) - P.step, 0.0, None), 0.0) * np.sign(d)
        else:
            excess = np.where(mask, d - np.clip(d, P.dlo[:, start::2][:, :m], P.dhi[:, start::2][:, :m]), 0.0)
        y[:, start : start + 2 * m : 2] = a + 0.5 * excess
        y[:, start + 1 : start + 1 + 2 * m : 2] = b - 0.5 * excess
        return y

    sets = (lambda v: np.clip(v, P.lo, P.hi), lambda v: pairs(v, 0), lambda v: pairs(v, 1))
    incr = [np.zeros_like(x) for _ in sets]
    for _ in range(n_iter):
        for i, proj in enumerate(sets):
            z = x + incr[i]
            x_new = proj(z)
            incr[i] = z - x_new
            x = x_new
    return np.clip(x, P.lo, P.hi)


def _bits(a) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64)).view(np.uint64)


def _problem(seed: int, n: int = 600, oblique: bool = False):
    rng = np.random.default_rng(seed)
    base = np.zeros((3, n + 1))
    base[0, :21] = np.minimum(np.arange(21), 20) * 1.0  # a fixed ramp (1 mT/m per raster = 100 T/m/s)
    free = np.ones((3, n + 1), bool)
    free[:, :21] = False
    free[:, -1] = False
    free[2, 300:320] = False  # a fixed stretch in the middle of z
    R = None
    if oblique:
        c, s = np.cos(0.4), np.sin(0.4)
        R = ((1, 0, 0), (0, c, -s), (0, s, c))
    lim = Limits(25.0, 150.0).rotated(R)
    return EdgeProjector(base, free, RASTER, lim), rng


@pytest.mark.parametrize("oblique", [False, True])
@pytest.mark.parametrize("scale", [0.3, 3.0, 60.0])  # near the set (short chains) .. far (the scalar fallback)
def test_greedy_sweeps_equal_the_scalar_loop_bit_for_bit(oblique, scale):
    P, rng = _problem(1, oblique=oblique)
    for trial in range(3):
        y = np.where(P.free, rng.normal(0, scale, P.base.shape) + np.sin(np.arange(P.n_edges) / 7.0) * 20, P.base)
        fw = L._sequential_clip(L._NP, y, P.lo, P.hi, P.dlo, P.dhi)
        bw = L._sequential_clip(L._NP, y[:, ::-1], P.lo[:, ::-1], P.hi[:, ::-1], -P.dhi[:, ::-1], -P.dlo[:, ::-1])
        for a in range(3):
            ref_f = _scalar_greedy(y[a], P.lo[a], P.hi[a], P.dlo[a], P.dhi[a])
            ref_b = _scalar_greedy(y[a, ::-1], P.lo[a, ::-1], P.hi[a, ::-1], -P.dhi[a, ::-1], -P.dlo[a, ::-1])
            assert np.array_equal(_bits(fw[a]), _bits(ref_f)), (trial, a)
            assert np.array_equal(_bits(bw[a]), _bits(ref_b)), (trial, a)
        x = P.repair(y)
        assert P.is_feasible(x, tol=1e-9)
        assert np.array_equal(x[~P.free], P.base[~P.free])


def test_greedy_long_active_chain_falls_back_to_the_scalar_loop(monkeypatch):
    """A zig-zag far beyond the slew limit keeps the limiter active over the whole row: the sweep budget runs out
    and the rest of the row is the scalar loop, with the same numbers."""
    n = 3000
    lo, hi = np.full((1, n), -100.0), np.full((1, n), 100.0)
    dl, dh = np.full((1, n - 1), -0.5), np.full((1, n - 1), 0.5)
    y = np.where(np.arange(n) % 2 == 0, 90.0, -90.0)[None]
    calls = []
    orig = L._clip_loop
    monkeypatch.setattr(L, "_clip_loop", lambda *a: (calls.append(a[-1]), orig(*a))[1])
    x = L._sequential_clip(L._NP, y, lo, hi, dl, dh)
    assert calls, "the budget should have run out on a chain as long as the row"
    assert np.array_equal(_bits(x[0]), _bits(_scalar_greedy(y[0], lo[0], hi[0], dl[0], dh[0])))


@pytest.mark.parametrize("oblique", [False, True])
@pytest.mark.parametrize("n_iter", [1, 8, 60])
def test_dykstra_equals_the_plain_expressions_bit_for_bit(oblique, n_iter):
    P, rng = _problem(2, n=601, oblique=oblique)  # an odd and an even edge count over the two cases
    for scale in (0.5, 10.0, 80.0):
        x = np.where(P.free, rng.normal(0, scale, P.base.shape), P.base)
        x[0, 50:60] = -0.0  # signed zeros go through the same operations
        assert np.array_equal(_bits(P._dykstra(x, n_iter)), _bits(_plain_dykstra(P, x, n_iter)))


@pytest.mark.parametrize("n_iter", [0, 1, 8])
def test_dykstra_of_a_row_without_free_samples_is_its_values_plus_zero(n_iter):
    """Only the rows with free samples are computed; a fixed row ends as the plain expressions' last box makes it:
    its values, bit for bit (a clip returns the bound it equals, so a -0.0 stays)."""
    n = 200
    base = np.zeros((3, n + 1))
    k = np.arange(n + 1)
    base[2] = 0.5 * np.maximum(0, np.minimum(k - 20, n - k))  # a triangle within the limits (50 T/m/s)
    base[2, 5:15] = -0.0
    free = np.ones((3, n + 1), bool)
    free[:, [0, -1]] = False
    free[2] = False
    P = EdgeProjector(base, free, RASTER, Limits(100.0, 100.0))
    x = np.where(free, np.random.default_rng(5).normal(0, 30, base.shape), base)
    got, ref = P._dykstra(x, n_iter), _plain_dykstra(P, x, n_iter)
    assert np.array_equal(_bits(got), _bits(ref))
    assert np.array_equal(_bits(got[2]), _bits(base[2]))


@pytest.mark.parametrize("oblique", [False, True])
@pytest.mark.parametrize("exact", [False, True])
def test_tensor_path_gives_the_numpy_numbers(oblique, exact):
    """The path a tensor on an accelerator takes (here run on CPU tensors): the same numbers as the numpy path,
    in the input's dtype; a point already in the set comes back unchanged."""
    P, rng = _problem(3, oblique=oblique)
    for scale in (0.5, 40.0):
        y = rng.normal(0, scale, P.base.shape)
        ref = P.project(y, n_iter=8, exact=exact)
        got = P._project_device(torch.as_tensor(y), 8, exact)
        assert got.dtype == torch.float64
        assert np.array_equal(_bits(got.numpy()), _bits(ref))
        got32 = P._project_device(torch.as_tensor(y, dtype=torch.float32), 8, exact)
        assert got32.dtype == torch.float32
        ref32 = P.project(torch.as_tensor(y, dtype=torch.float32), n_iter=8, exact=exact)
        assert torch.equal(got32, ref32)
    free = np.ones((3, 201), bool)
    free[:, [0, -1]] = False
    P = EdgeProjector(np.zeros((3, 201)), free, RASTER, Limits(25.0, 150.0))
    inside = np.where(free, np.sin(np.arange(201) / 30.0) * np.array([[1.0], [-0.5], [0.25]]), 0.0)
    assert P.is_feasible(inside, tol=0.0)
    for exact in (False, True):
        assert np.array_equal(_bits(P._project_device(torch.as_tensor(inside), 8, exact).numpy()), _bits(inside))


def test_tensor_repair_meets_the_limits():
    P, rng = _problem(4)
    y = torch.as_tensor(rng.normal(0, 60, P.base.shape))
    x = P._project_device(y, 2, True).numpy()
    assert P.is_feasible(x, tol=1e-9)
    assert np.array_equal(x[~P.free], P.base[~P.free])
