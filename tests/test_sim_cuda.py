"""The simulator on CUDA equals the CPU run (signal and gradient); skipped where no CUDA device exists.

Everything in dtoc runs and is tested on CPU; this file is the check of the ``device`` argument for
machines with a GPU (float64: rounding only, 1e-9 of the maximum; float32: 1e-4).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_sim_physics import rich_phantom, small_gre

from dtoc.sim.pdg import PDGConfig, build_graph, simulate

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 1e-4)])
@pytest.mark.parametrize("calibrate", [False, True])
def test_cuda_equals_cpu(dtype, tol, calibrate):
    ir = small_gre(n_rep=4)
    ph = rich_phantom()
    ph.coil_sens = np.stack([np.ones((4, 4)), np.exp(1j * np.arange(16).reshape(4, 4) / 3.0)])
    cfg = PDGConfig(calibrate_emission=calibrate)
    graph = build_graph(ir, cfg, ph)
    out = {}
    for dev in ("cpu", "cuda"):
        g = torch.as_tensor(ir.grad_mT_per_m, dtype=dtype, device=dev).clone().requires_grad_(True)
        s = simulate(ir, ph, g, graph=graph, config=cfg, dtype=dtype, device=dev)
        assert s.device.type == dev
        (s.real**2 + s.imag**2).sum().backward()
        out[dev] = (s.detach().cpu().numpy(), g.grad.cpu().numpy())
    (s0, g0), (s1, g1) = out["cpu"], out["cuda"]
    assert np.abs(s1 - s0).max() <= tol * np.abs(s0).max()
    assert np.abs(g1 - g0).max() <= tol * np.abs(g0).max()


def test_replayed_warm_start_equals_the_eager_one_on_cuda(tmp_path, monkeypatch):
    """The warm start's steps captured as CUDA graphs (dtoc.util.replay) and replayed give the eager steps'
    result: the bundled small EPI with the example GIRF (affine solve) and the small GRE with the paper's eddy
    model and a fixed-count warm start (FISTA), each run with graphs and with ``DTOC_CUDA_GRAPHS=0``."""
    from pathlib import Path

    import dtoc
    from dtoc.optimize.config import load_config
    from dtoc.util import replay

    repo = Path(__file__).resolve().parents[1]
    jobs = [
        ("epi_small.seq", "epi", {"iters": 0}, dict(girf=repo / "girf" / "example_7T.npz")),
        (
            "gre_small.seq",
            "gre",
            {"iters": 0, "warm_iters": 40, "n_dummies": 0, "gmax_mT_per_m": 10.0},
            dict(model=repo / "girf" / "paper_eddy_both.json"),
        ),
    ]
    for seq, kind, ov, hw in jobs:
        ir = dtoc.load_sequence(repo / "sequences" / seq)
        out = {}
        for graphs in ("1", "0"):
            monkeypatch.setenv(replay.ENV, graphs)
            before = replay.totals()
            res = dtoc.optimize_sequence(
                ir, out=tmp_path / f"{graphs}.seq", config=load_config(kind, None, ov), force=True, device="cuda", **hw
            )
            after = replay.totals()
            out[graphs] = (res.manifest["after"]["kspace_max_error_dk"], after["replays"] - before["replays"])
            assert after["failed"] == before["failed"], after["failed"]
        (k1, n1), (k0, n0) = out["1"], out["0"]
        assert n1 > 10 and n0 == 0, (seq, n1, n0)
        assert abs(k1 - k0) <= 1e-6 * max(abs(k0), 1e-3), (seq, k1, k0)
