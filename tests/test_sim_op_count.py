"""Operation count of the twin: the number of dispatched aten operations (each a kernel launch plus
Python on a GPU) must grow sublinearly with the number of repetitions.

Counted with a ``TorchDispatchMode`` on the CPU.  The paper's spoiled GRE spec (sequences/gre_paper.yaml)
at matrix = repetitions = n, with the 3.2 ms readout of the paper kept (dwell 3.2 ms / n) and TE 3.5 ms
(the 64-line prewinder does not fit 3.15 ms).  The simulator counts use the GPU's signal batching
(``PDGConfig(schedule="batched")``, the default off the CPU); the CPU default splits the signal into
cache-sized batches (faster there) and is bounded separately.  Issue 33 asks, at 64 TRs, for at most 3x
the count at 16 TRs and at most 50 per TR; what is reached (and asserted, as a regression guard) is in
each test's docstring.  Before the fused main pass (main 989a85e) ``dtoc.simulate`` dispatched 2,769 /
5,469 / 17,021 operations at 16 / 32 / 64 TRs.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).parent))
from opt_synth import eddy_model  # noqa: E402

SEQ = Path(__file__).resolve().parents[1] / "sequences"


class _Count(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.n = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.n += 1
        return func(*args, **(kwargs or {}))


def _spec(name: str, n: int):
    from dtoc.seq.spec import load_spec

    return load_spec(SEQ / name).model_copy(update=dict(matrix=n, repetitions=n, dwell_us=3200.0 / n, te_ms=3.5))


def _simulate_ops(n: int, cfg) -> int:
    """Operations of one PDG simulation of a realized gradient (2 % off the nominal; graph and index
    tensors built by a first call outside the count), as the optimizer loop runs it."""
    import dtoc
    from dtoc.sim import pdg
    from dtoc.sim.phantom import phantom_for

    ir = dtoc.load_sequence(_spec("gre_paper.yaml", n))
    ph = phantom_for(ir, None)
    graph = pdg.build_graph(ir, cfg, ph)
    with torch.no_grad():
        s0 = pdg.simulate(ir, ph, graph=graph, config=cfg)
    g = torch.as_tensor(ir.grad_mT_per_m) * 1.02
    with _Count() as c, torch.no_grad():
        s1 = pdg.simulate(ir, ph, g, graph=graph, config=cfg)
    assert s0.shape == s1.shape == (1, n * n) and bool((s0 != s1).any())
    return c.n


def _dtoc_simulate_ops(n: int) -> int:
    import dtoc

    ir = dtoc.load_sequence(_spec("gre_paper.yaml", n))
    with _Count() as c:
        res = dtoc.simulate(ir)
    assert res.metrics  # the whole public call ran (ideal and realized simulation, reconstruction, metrics)
    return c.n


def _iteration_ops(n: int) -> int:
    """Operations of one full-loss iteration (twin forward, simulation, image, loss, backward) of the
    Figure-5 GRE at n lines with the loop's simulator preset (fast, float32) and the paper's eddy model."""
    import dtoc
    from dtoc.optimize import loss as L
    from dtoc.optimize import optimizer as O
    from dtoc.optimize.config import OptimizeConfig
    from dtoc.optimize.limits import EdgeProjector, Limits
    from dtoc.optimize.run import free_edges, make_phantoms
    from dtoc.optimize.twin import EdgeTwin
    from dtoc.sim.imager import Imager
    from dtoc.sim.pdg import PDGConfig

    ir = dtoc.load_sequence(_spec("gre_paper_fig5.yaml", n))
    cfg = OptimizeConfig(n_dummies=0)
    lim = Limits(50.0, 500.0)
    P = EdgeProjector(ir.edge_grad_mT_per_m, free_edges(ir), ir.raster_s, lim)
    tw, ctx = EdgeTwin(ir, eddy_model(), P), L.build_context(ir, lim)
    # the loop's preset (fast, float32) with the GPU's signal batching
    im = Imager(ir, make_phantoms(ir, cfg), n_dummies=0, config=PDGConfig.fast(schedule="batched"), dtype=torch.float32)
    x = torch.as_tensor(ir.edge_grad_mT_per_m, dtype=torch.float64).clone().requires_grad_(True)
    weights = O.full_weights(cfg)
    O.evaluate(tw, im, ctx, weights, x, 0)  # warm caches (graph index tensors) outside the count
    with _Count() as c:
        total, _, _ = O.evaluate(tw, im, ctx, weights, x, 0)
        total.backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().max() > 0
    return c.n


@pytest.mark.slow
def test_simulate_operation_count_grows_sublinearly():
    """One simulation with the GPU's batching: measured 862 / 1,451 / 2,709 at 16 / 32 / 64 TRs (42 per TR
    at 64: within the issue's 50; 3.14x the count at 16, just above its 3x: the nine operations per RF
    interval of the fused recursion stay linear).  The CPU default through the public ``dtoc.simulate``
    (cache-sized signal batches): 1,101 / 1,679 / 6,308, ~100 per TR instead of ~270 before."""
    from dtoc.sim.pdg import PDGConfig

    torch.set_num_threads(1)
    counts = {n: _simulate_ops(n, PDGConfig(schedule="batched")) for n in (16, 32, 64)}
    assert counts[64] <= 50 * 64, counts
    assert counts[64] <= 3.3 * counts[16], counts
    assert _dtoc_simulate_ops(64) <= 110 * 64


@pytest.mark.slow
def test_optimizer_iteration_operation_count_grows_sublinearly():
    torch.set_num_threads(1)
    # sublinear (~2.2x for 4x the TRs), but still ~17 operations per RF
    # interval in the propagation's forward + adjoint, so 90 per TR at 64 TRs, not yet the 50
    # (docs/benchmarks.md, "Operation count"); this guards what is reached
    counts = {n: _iteration_ops(n) for n in (16, 32, 64)}  # measured 2,763 / 3,236 / 5,697
    assert counts[64] <= 3 * counts[16], counts
    assert counts[64] <= 100 * 64, counts
