"""Warm start, full-loss stage and pre-emphasis of dtoc.optimize on a synthetic GRE with the paper's
exponential eddy currents (Eq. 1); no sequence files or simulator needed."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from opt_synth import eddy_model, gre_ir  # noqa: E402

from dtoc.optimize import loss as L
from dtoc.optimize import optimizer as O
from dtoc.optimize.config import LossWeights
from dtoc.optimize.limits import EdgeProjector, Limits, limit_violations
from dtoc.optimize.preemphasis import apply_preemphasis, fit_preemphasis
from dtoc.optimize.twin import EdgeTwin


def _setup(gmax, smax, n=8, reps=8, model=None):
    ir = gre_ir(n, reps=reps)
    lim = Limits(gmax, smax)
    P = EdgeProjector(ir.edge_grad_mT_per_m, ir.free_mask[:, ::2], ir.raster_s, lim)
    tw = EdgeTwin(ir, model or eddy_model(), P)
    return ir, lim, tw, L.build_context(ir, lim)


def _kerr(tw, ctx, x):
    with torch.no_grad():
        G, _ = tw.realize(tw.played(x))
        return O.kspace_error_dk(tw.kspace(G), ctx)


def test_warm_start_unconstrained_removes_eddy_current_kspace_error():
    torch.set_num_threads(1)
    ir, lim, tw, ctx = _setup(50, 500)
    e0 = _kerr(tw, ctx, tw.base_edges())
    assert e0.max() > 1.0  # both eddy currents displace k by more than a grid step
    x = O.warm_start(tw, ctx, LossWeights(), 300)
    e1 = _kerr(tw, ctx, x)
    assert e1.max() < 1e-3 * e0.max()
    fine = tw.export_fine(x)
    assert limit_violations(fine, ir.dt_fine_s, lim) == []
    assert np.array_equal(fine[~tw.fine_mask], ir.grad_mT_per_m[~tw.fine_mask])  # RF periods untouched


def test_warm_start_constrained_stays_feasible_and_beats_projected_base():
    ir, lim, tw, ctx = _setup(13, 130)
    base = tw.projector.project(tw.base_edges())
    x = O.warm_start(tw, ctx, LossWeights(), 300)
    assert tw.projector.is_feasible(x.numpy())
    f = O.linear_objective(tw, ctx, LossWeights())
    assert float(f(x)[0]) < 0.5 * float(f(base)[0])
    fine = tw.export_fine(x)
    assert limit_violations(fine, ir.dt_fine_s, lim) == []


def test_full_loss_keeps_best_and_feasible_without_imager():
    from dtoc.optimize.config import OptimizeConfig

    ir, lim, tw, ctx = _setup(20, 500)
    cfg = OptimizeConfig(iters=15, lr=0.05, weights=LossWeights(image=0.0))
    state = O.StageState(best_edges=tw.base_edges())
    x0 = tw.projector.project(tw.base_edges())
    f = lambda e: float(O.evaluate(tw, None, ctx, cfg.weights, e)[0])  # noqa: E731
    x = O.full_loss(tw, None, ctx, cfg, x0, state)
    assert f(x) <= f(x0) + 1e-12
    assert tw.projector.is_feasible(x.numpy(), tol=1e-9)
    assert len([h for h in state.history if h["stage"] == "full"]) == 15


def test_preemphasis_fit_recovers_exact_single_exponential_inverse():
    alpha, tau = 0.1, 1e-3
    model = eddy_model((alpha,), (tau,))
    ir = gre_ir(8, reps=2)
    fit = fit_preemphasis(model, ir.edge_grad_mT_per_m, ir.raster_s, n_terms=1, init_taus_s=(2e-3,))
    assert fit["alpha"][0] == pytest.approx(alpha / (1 - alpha), rel=0.03)
    assert fit["tau_s"][0] == pytest.approx((1 - alpha) * tau, rel=0.03)
    assert fit["rms_after_mT_per_m"] < 0.05 * fit["rms_before_mT_per_m"]


def test_exact_inverse_coefficients_undo_the_eddy_current():
    alpha, tau = 0.1, 5e-3
    model = eddy_model((alpha,), (tau,))
    g = torch.as_tensor(gre_ir(8, reps=2).grad_mT_per_m)
    dt = 5e-5
    pre = apply_preemphasis(g, dt, [alpha / (1 - alpha)], [(1 - alpha) * tau])
    G, _ = model(pre[None], dt)
    err = (G[0] - g).abs().max()
    raw = (model(g[None], dt)[0][0] - g).abs().max()
    assert float(err) < 0.02 * float(raw)


def test_adam_paper_with_restarts_descends_and_stays_feasible():
    from dtoc.optimize.config import OptimizeConfig

    ir, lim, tw, ctx = _setup(13, 130)
    cfg = OptimizeConfig(method="adam-paper", iters=40, lr=0.05, weights=LossWeights(image=0.0))
    state = O.StageState(best_edges=tw.base_edges())
    x0 = tw.projector.project(tw.base_edges())
    f = lambda e: float(O.evaluate(tw, None, ctx, cfg.weights, e)[0])  # noqa: E731
    x = O.full_loss(tw, None, ctx, cfg, x0, state, paper=True)
    assert f(x) < 0.9 * f(x0)
    assert tw.projector.is_feasible(x.numpy(), tol=1e-9)
    assert limit_violations(tw.export_fine(x), ir.dt_fine_s, lim) == []
