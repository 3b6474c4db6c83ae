"""Work the optimizer no longer does (docs/optimize.md): the first CG stops once every sample is within the
tolerance, the discarding tries no threshold below it, and the final waveform is simulated once."""

import math

import numpy as np
import pytest
import torch
import yaml

from dtoc.hardware.model import resolve_model
from dtoc.optimize import loss as L
from dtoc.optimize import optimizer as O
from dtoc.optimize import solver as SV
from dtoc.optimize.config import load_config
from dtoc.optimize.limits import EdgeProjector, Limits
from dtoc.optimize.run import free_edges
from dtoc.optimize.twin import EdgeTwin
from dtoc.seq.build import build_ir
from dtoc.seq.spec import parse_spec


@pytest.fixture(scope="module")
def epi():
    """EPI 32 at 1.2 ms echo spacing, example 7 T GIRF, limits that do not bind."""
    with open("sequences/epi_small.yaml") as fh:
        d = yaml.safe_load(fh)
    d.update(matrix=32, echo_spacing_ms=1.2)
    ir = build_ir(parse_spec(d))
    lim = Limits(400.0, 2000.0)
    P = EdgeProjector(ir.edge_grad_mT_per_m, free_edges(ir), ir.raster_s, lim)
    tw = EdgeTwin(ir, resolve_model(girf="girf/example_7T.npz").frozen(), P)
    return tw, L.build_context(ir, lim), load_config("epi").weights


def _kerr(tw, ctx, x):
    with torch.no_grad():
        return O.kspace_error_dk(tw.forward_edges(x, moments=False).kspace_rad_per_m, ctx)


def _solve(tw, ctx, w, tol, every):
    f = O.linear_objective(tw, ctx, w)
    return SV.solve_to_tolerance(
        f, tw.base_edges(), tw.projector, tw.free_t, lambda x: _kerr(tw, ctx, x), k_tol_dk=tol, budget=600,
        check_every=every,
    )  # fmt: skip


def test_first_cg_stops_once_every_sample_is_within_the_tolerance(epi):
    """At a loose tolerance (0.05 dk, the base at ~0.7 dk) the checked CG stops with every sample within it after
    fewer iterations than the CG left to converge, and says so ('tolerance'); the figure is the projected
    waveform's."""
    tw, ctx, w = epi
    tol = 0.05
    assert _kerr(tw, ctx, tw.base_edges()).max() > 5 * tol
    x_full, rep_full = _solve(tw, ctx, w, tol, 0)
    x, rep = _solve(tw, ctx, w, tol, 5)
    err = _kerr(tw, ctx, x)
    assert rep.stop_reason == "tolerance" and err.max() <= tol
    assert rep.achieved_max_dk == pytest.approx(float(err.max()), rel=1e-9)
    assert rep.cg_iterations < rep_full.cg_iterations and rep.evaluations < rep_full.evaluations
    assert tw.projector.is_feasible(x.numpy())
    assert not rep.unconstrained_converged  # stopped early: no claim that the unconstrained optimum was reached


class _CountingImager:
    """A stand-in imager: counts its simulations; the image is the signal reshaped (any function would do)."""

    def __init__(self, n):
        self.calls = 0
        self.targets = [torch.ones(n, dtype=torch.float64)]

    def signal(self, G, b0, idx):
        self.calls += 1
        return G.sum(0)[: self.targets[0].numel()].clone()

    def image(self, sig, keep_mask=None):
        return sig if keep_mask is None else sig * torch.as_tensor(keep_mask, dtype=sig.dtype)


def test_discard_tries_no_threshold_below_the_tolerance(epi):
    """Every sample within the floor: all kept, no candidate image, not even the simulation; with no floor the
    candidates are tried (the simulation runs)."""
    tw, ctx, w = epi
    x = tw.base_edges()
    err = _kerr(tw, ctx, x)
    im = _CountingImager(err.size)
    keep, thr, nr = O.choose_discard(tw, im, ctx, x, floor_dk=float(err.max()) + 1e-9)
    assert keep.all() and thr == math.inf and math.isnan(nr) and im.calls == 0
    O.choose_discard(tw, im, ctx, x)
    assert im.calls == 1


def test_memo_signal_simulates_a_waveform_once():
    """The same waveform (bit for bit) is simulated once and the result returned equal (a copy); another waveform,
    or one that needs its gradient, is simulated."""
    im = O.memo_signal(_CountingImager(4))
    G = torch.arange(12, dtype=torch.float64).reshape(3, 4)
    a = im.signal(G, None, 0)
    b = im.signal(G.clone(), None, 0)
    assert im.calls == 1 and torch.equal(a, b) and a.data_ptr() != b.data_ptr()
    G2 = G.clone()
    G2[0, 0] = np.nextafter(0.0, 1.0)  # one bit
    im.signal(G2, None, 0)
    assert im.calls == 2
    im.signal(G, None, 1)  # another phantom
    assert im.calls == 3
    Gg = G.clone().requires_grad_(True)
    im.signal(Gg, None, 0)
    im.signal(Gg, None, 0)
    assert im.calls == 5
    assert O.memo_signal(None) is None
