"""Memory of a long (windowed) run outside the solve: the figures' realization streamed piece by piece, the running
integral of k by chunks, the reader's waveform held once (docs/optimize.md, "Long sequences")."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
from dtoc.hardware.effects import B0Eddy, Delay, Lti
from dtoc.hardware.model import HardwareModel
from dtoc.seq import kspace as K

REPO = Path(__file__).resolve().parents[1]


def _idle_gre_ir(reps: int, idle_edges: int):
    sys.path.insert(0, str(Path(__file__).parent))
    from test_windowed import _idle_gre_ir as make

    return make(reps, idle_edges)


def _events(n: int, dt: float, rng) -> tuple[np.ndarray, list[str]]:
    tc = np.sort(rng.uniform(0, (n - 1) * dt, 24))
    return tc, ["excitation", "refocusing", "undefined", "inversion"] * 6


def test_chunked_running_integral_is_the_whole_one_bit_for_bit(monkeypatch):
    """k of a long waveform without a graph, integrated by chunks, equals the whole running integral's bit for bit
    (excitations, refocusing and other pulses; query times on chunk borders and at both ends)."""
    rng = np.random.default_rng(3)
    n, dt = 200_001, 5e-6
    g = rng.normal(size=(3, n)) * 20
    t = np.r_[0.0, np.sort(rng.uniform(0, (n - 1) * dt, 3000)), 4096 * dt, 8192 * dt, (n - 1) * dt]
    tc, uses = _events(n, dt, rng)
    whole = K.kspace_at(g, dt, t, tc, uses)
    monkeypatch.setattr(K, "CUMULATIVE_CHUNK", 4096)
    assert K._chunked(torch.as_tensor(g))
    chunked = K.kspace_at(g, dt, t, tc, uses)
    assert torch.equal(whole, chunked)
    assert torch.equal(K.kspace_at(g, dt, t), K.pwl_integral_at(g, dt, t) * GAMMA_RAD_PER_S_PER_MT)  # no RF event
    m = np.r_[0, 1, 4095, 4096, 4097, rng.integers(0, n, 500), n - 1]
    assert torch.equal(K.pwl_cumulative(torch.as_tensor(g), dt)[:, m], K.cumulative_at(g, dt, m))
    # a waveform in a graph keeps the whole (differentiable) path
    gt = torch.as_tensor(g).requires_grad_(True)
    assert not K._chunked(gt)
    K.kspace_at(gt, dt, t[:10], tc, uses).sum().backward()
    assert gt.grad is not None


def test_streamed_kspace_equals_the_whole_waveforms():
    """k from a waveform given in pieces (each starting on the last sample of the one before): one piece is
    kspace_at bit for bit, many pieces agree to rounding."""
    rng = np.random.default_rng(4)
    n, dt = 50_001, 5e-6
    g = torch.as_tensor(rng.normal(size=(4, n)) * 20)
    t = np.r_[0.0, np.sort(rng.uniform(0, (n - 1) * dt, 2000)), (n - 1) * dt]
    tc, uses = _events(n, dt, rng)
    whole = K.kspace_at(g, dt, t, tc, uses)
    assert torch.equal(K.kspace_at_streamed([(0, g)], n, dt, t, tc, uses), whole)
    cuts = [0, 1, 777, 20_000, 20_001, 49_999, n - 1]
    pieces = [(s, g[:, s : e + 1]) for s, e in zip(cuts[:-1], cuts[1:])]
    got = K.kspace_at_streamed(pieces, n, dt, t, tc, uses)
    assert torch.allclose(got, whole, rtol=0, atol=1e-9 * float(whole.abs().max()))


def test_quality_of_a_long_sequence_is_streamed_with_the_same_figures(monkeypatch):
    """The figures of a windowed run (no image) from the chain played piece by piece with its memory on either side
    (an FFT-applied eddy kernel, a delay and a B0 eddy term): the k figures of the whole realization to 1e-9, the
    report's waveform span identical, the B0 term's phase at the ADC samples (the side-car's) as from the whole B0
    waveform, which is not kept."""
    import dtoc.optimize.run as R
    from dtoc.optimize import loss as L
    from dtoc.optimize.config import load_config
    from dtoc.optimize.limits import EdgeProjector
    from dtoc.optimize.twin import EdgeTwin
    from dtoc.sim import predict as P
    from dtoc.sim.predict import b0_phase_at_adc_rad

    ir = _idle_gre_ir(4, 3000)
    taps = -0.05 * np.exp(-np.arange(40) / 8.0)[None].repeat(3, 0)
    hw = HardwareModel([Lti(taps, 5e-5), Delay(4e-6), B0Eddy(0.5, 3e-3, "x")]).frozen()
    cfg = load_config(ir.kind, None).model_copy(update={"gmax_mT_per_m": 32, "smax_T_per_m_per_s": 130})
    lim, _ = R.limits_and_sources(ir, cfg)
    twin = EdgeTwin(ir, hw, EdgeProjector(ir.edge_grad_mT_per_m, R.free_edges(ir), ir.raster_s, lim))
    ctx = L.build_context(ir, lim)
    whole = R.quality(twin, None, ctx, ir.grad_mT_per_m)
    assert whole["_b0"] is not None and np.abs(whole["_b0"]).max() > 0
    monkeypatch.setattr(P, "QUALITY_CHUNK", 2000)  # 13 pieces, the chain's memory (~14 ms) across their borders
    n = 5000
    got = R.quality(twin, None, ctx, ir.grad_mT_per_m, waveform_samples=n)
    assert got["_b0"] is None
    for key in ("kspace_rmse_rad_per_m", "kspace_max_dk", "kspace_max_err_rad_per_m"):
        assert got[key] == pytest.approx(whole[key], rel=1e-9)
    assert np.allclose(got["_k"], whole["_k"], rtol=0, atol=1e-9 * np.abs(whole["_k"]).max())
    assert np.array_equal(got["_g"], whole["_g"][:, :n])
    assert np.allclose(got["_G"], whole["_G"][:, :n], rtol=0, atol=1e-12)
    phase = b0_phase_at_adc_rad(ir, whole["_b0"])
    assert np.abs(phase).max() > 1e-3
    assert np.allclose(got["_b0_phase_adc"], phase, rtol=0, atol=1e-9 * np.abs(phase).max())


def test_predict_of_a_long_sequence_is_streamed_with_the_same_figures(monkeypatch):
    """`dtoc predict` of a long sequence piece by piece: every figure of the whole path (gradient error max / RMS,
    k error, B0 peak and phase) to 1e-9; the whole waveforms only when a plot asks for them, then the same."""
    from dtoc.sim import predict as P

    ir = _idle_gre_ir(4, 3000)
    taps = -0.05 * np.exp(-np.arange(40) / 8.0)[None].repeat(3, 0)
    hw = HardwareModel([Lti(taps, 5e-5), Delay(4e-6), B0Eddy(0.5, 3e-3, "x")])
    whole = P.predict(ir, hw)
    monkeypatch.setattr(P, "PREDICT_STREAM_MIN", 1000)
    monkeypatch.setattr(P, "QUALITY_CHUNK", 2000)
    got = P.predict(ir, hw)
    assert isinstance(got["_arrays"], P._WholeArrays) and "G" not in got["_arrays"]
    assert whole["b0_phase_max_rad"] > 1e-3 and whole["k_error_max_dk"] > 1e-3

    def close(a, b):
        if isinstance(a, dict):
            assert a.keys() == b.keys()
            for key in a:
                if key != "_arrays":
                    close(a[key], b[key])
        elif isinstance(a, list):
            assert len(a) == len(b) and all(close(x, y) is None for x, y in zip(a, b))
        elif isinstance(a, float):
            assert b == pytest.approx(a, rel=1e-9, abs=1e-12)
        else:
            assert a == b

    close(whole, got)
    assert np.array_equal(got["_arrays"]["G"], whole["_arrays"]["G"])  # the plot's: realized whole on demand
    assert np.array_equal(got["_arrays"]["b0"], whole["_arrays"]["b0"])


def test_the_reader_holds_the_waveform_once(tmp_path):
    """A read file's IR and the writer's reference are one array (48 bytes per raster step, not twice); the writer
    still rewrites only what changed."""
    from dtoc.seq.load import load_sequence
    from dtoc.seq.write import changed_blocks

    ir = load_sequence(REPO / "sequences" / "epi_esp081.seq")
    assert ir.source_grad_mT_per_m is ir.grad_mT_per_m
    assert changed_blocks(ir) == {}
    g = ir.grad_mT_per_m.copy()
    m = int(np.flatnonzero(ir.free_mask[0])[len(np.flatnonzero(ir.free_mask[0])) // 2])
    g[0, m] += 0.5
    out = ir.with_grad(g)
    assert out.source_grad_mT_per_m is ir.grad_mT_per_m and not np.shares_memory(out.grad_mT_per_m, ir.grad_mT_per_m)
    assert list(changed_blocks(out)) == [int(out.block_of_fine_index(np.array([m]))[0])]


_CHILD = r"""
import json, os, sys
sys.path.insert(0, os.getcwd()); sys.path.insert(0, os.path.join(os.getcwd(), "tests"))
import numpy as np
from test_windowed import _idle_gre_ir
from dtoc.hardware.effects import Delay, Lti
from dtoc.hardware.model import HardwareModel
from dtoc.optimize.config import load_config
from dtoc.optimize.run import optimize_sequence
ir = _idle_gre_ir(int(sys.argv[1]), int(sys.argv[2]))
taps = -0.05 * np.exp(-np.arange(40) / 8.0)[None].repeat(3, 0)
hw = HardwareModel([Lti(taps, 5e-5), Delay(4e-6)]).frozen()
cfg = load_config(ir.kind, None).model_copy(update={"gmax_mT_per_m": 32, "smax_T_per_m_per_s": 130, "windowed": "on"})
res = optimize_sequence(ir, hardware=hw, config=cfg)
hwm = [int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith("VmHWM")][0]
print(json.dumps({"peak": hwm, "windows": res.manifest["windowed"]["windows"], "k": res.manifest["after"]["kspace_max_error_dk"],
                  "edges": int(ir.edge_grad_mT_per_m.shape[1])}))
"""


def _run_peak(reps: int, idle_edges: int) -> dict:
    env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": "65536", "OMP_NUM_THREADS": "1"}  # freed arrays leave the RSS
    r = subprocess.run(
        [sys.executable, "-c", _CHILD, str(reps), str(idle_edges)], cwd=REPO, env=env, capture_output=True,
        text=True, timeout=600,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status")
@pytest.mark.slow
def test_whole_windowed_run_memory_does_not_grow_with_the_duration():
    """The whole ``optimize_sequence`` of a 4x longer windowed sequence (12 identical 5 s periods against 3: 0.6 M
    against 0.15 M raster steps) peaks within 1.2x the resident memory (each in its own process, freed arrays
    returned to the system), and what it adds per raster step stays under 150 bytes: the waveform (48), the
    edges and the masks, not the limit envelopes (48) nor Dykstra's copies of them (~150) a projector that only
    checks feasibility does not need.  Measured 2026-11-27 (2-core Xeon, load ~10): 685 -> 745 MB (1.09x); the
    parent commit (the base's and the output's realization whole in the figures, two whole-length limit step
    arrays) 696 -> 883 MB (1.27x, ~410 bytes per raster step against ~130 then); with the envelopes in pieces
    (load ~12): 707 -> 814 MB (1.15x, 238 bytes per step) before, 676 -> 716 MB (1.06x, 88 bytes per step) after."""
    a, b = _run_peak(3, 50_000), _run_peak(12, 50_000)
    assert (a["windows"], b["windows"]) == (3, 12)
    assert b["peak"] <= 1.2 * a["peak"], (a, b)
    assert b["edges"] > 3.9 * a["edges"]
    per_step = (b["peak"] - a["peak"]) / (b["edges"] - a["edges"])
    assert per_step < 150, (per_step, a, b)
