"""Loss normalisation (Eq. 4 terms) and the config precedence of dtoc.optimize."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from opt_synth import gre_ir  # noqa: E402

from dtoc.errors import InputError
from dtoc.optimize import loss as L
from dtoc.optimize.config import LossWeights, load_config
from dtoc.optimize.limits import Limits


@pytest.fixture(scope="module")
def ir():
    return gre_ir(8, reps=4)


def test_kspace_term_is_in_dk_squared_per_sample(ir):
    ctx = L.build_context(ir, Limits(50, 500))
    dk = 2 * np.pi / 0.032
    k = ctx.k0_rad_per_m.clone()
    k[0] += 0.5 * dk  # every sample off by half a grid step in x
    assert float(L.kspace_term(k, ctx)) == pytest.approx(0.25, rel=1e-12)
    k[1] += 1.0 * dk
    assert float(L.kspace_term(k, ctx)) == pytest.approx(1.25, rel=1e-12)
    # independent of FOV: a 4x larger FOV (4x smaller dk) with a proportionally smaller error gives the same
    ir2 = gre_ir(8, reps=4, fov_m=0.128)
    ctx2 = L.build_context(ir2, Limits(50, 500))
    k2 = ctx2.k0_rad_per_m.clone()
    k2[0] += 0.5 * 2 * np.pi / 0.128
    assert float(L.kspace_term(k2, ctx2)) == pytest.approx(0.25, rel=1e-12)


def test_image_term_is_scale_free_nrmse():
    rng = np.random.default_rng(0)
    i0 = torch.tensor(rng.random((8, 8)))
    i1 = i0 * 1.1
    v = float(L.image_term([i1], [i0]))
    assert v == pytest.approx(0.1, rel=1e-12)
    assert float(L.image_term([1e6 * i1], [1e6 * i0])) == pytest.approx(v, rel=1e-12)


def test_rf_term_penalises_deviation_during_rf_only(ir):
    ctx = L.build_context(ir, Limits(50, 500))
    G = ctx.g0_fine_mT_per_m.clone()
    assert float(L.rf_term(G, ctx)) == 0.0
    G2 = G.clone()
    G2[:, ~ctx.rf_mask] += 3.0  # outside RF: no effect
    assert float(L.rf_term(G2, ctx)) == 0.0
    G3 = G.clone()
    G3[0, ctx.rf_mask] += 0.1 * ctx.g_ref_mT_per_m
    assert float(L.rf_term(G3, ctx)) == pytest.approx(0.01, rel=1e-9)


def test_soft_limit_terms_zero_inside_positive_outside(ir):
    ctx = L.build_context(ir, Limits(50, 500))
    g = ctx.g0_fine_mT_per_m.clone()
    assert float(L.amplitude_term(g, ctx)) == 0.0 and float(L.slew_term(g, ctx)) == 0.0
    g[0, 10] = 60.0
    assert float(L.amplitude_term(g, ctx)) > 0 and float(L.slew_term(g, ctx)) > 0


def test_total_loss_weights_multiply_terms(ir):
    ctx = L.build_context(ir, Limits(50, 500))
    k = ctx.k0_rad_per_m.clone()
    k[0] += 2 * np.pi / 0.032
    g = ctx.g0_fine_mT_per_m
    tot, terms = L.total_loss(LossWeights(kspace=3.0), ctx, g=g, G=g, k=k)
    assert terms["kspace"] == pytest.approx(3.0)
    assert float(tot) == pytest.approx(3.0)


def test_config_precedence_kind_file_cli(tmp_path):
    c = load_config("epi")
    assert c.weights.kspace == 4.0 and c.lr == 0.01
    f = tmp_path / "c.yaml"
    f.write_text("iters: 7\nweights:\n  kspace: 2.5\n")
    c = load_config("epi", f)
    assert c.iters == 7 and c.weights.kspace == 2.5 and c.weights.image == 1.0
    c = load_config("epi", f, {"iters": 3, "lr": None})
    assert c.iters == 3 and c.lr == 0.01


def test_config_errors_are_one_line(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("iters: -1\n")
    with pytest.raises(InputError, match="iters") as e:
        load_config("gre", f)
    assert "\n" not in str(e.value)
    f.write_text("nonsense_key: 1\n")
    with pytest.raises(InputError, match="nonsense_key"):
        load_config(None, f)
    f.write_text("[unclosed\n")
    with pytest.raises(InputError, match="YAML"):
        load_config(None, f)


def test_moment_term_sees_a_cancelled_spoiler(ir):
    """The k term at the ADC samples is blind to the spoiler; the moment term (k just before each RF
    pulse, in dk^2 per pulse) is not: cancelling the spoiler area costs (area/dk)^2 per repetition."""
    from dtoc.optimize.limits import EdgeProjector
    from dtoc.optimize.twin import EdgeTwin

    ctx = L.build_context(ir, Limits(50, 500))
    P = EdgeProjector(ir.edge_grad_mT_per_m, ir.free_mask[:, ::2], ir.raster_s, Limits(50, 500))
    tw = EdgeTwin(ir, None, P)
    g0 = torch.as_tensor(ir.grad_mT_per_m)
    assert float(L.moment_term(tw.moments(g0), ctx)) == pytest.approx(0.0, abs=1e-20)
    g = g0.clone()
    # remove the x spoiler plateau (17.6 mT/m) of every TR, after the ADC: k at the samples is unchanged
    spoil = g[0] > 17.0
    g[0, spoil] = 0.0
    k_same = tw.kspace(g)
    assert torch.allclose(k_same, ctx.k0_rad_per_m)
    m = float(L.moment_term(tw.moments(g), ctx))
    assert m > 1.0  # many dk of dephasing per repetition lost
