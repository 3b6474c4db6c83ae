"""The line-aware 'separable' signal evaluation (readouts along lines of constant phase-encoding moment, the
phase-encoded axis contracted once per line, the realized in-line perturbation by a Taylor series) equals the
exact per-state evaluation, in value and gradient, along x and along y (docs/simulator.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import dtoc.sim.pdg_signal as S
from dtoc.seq.load import load_sequence
from dtoc.sim.pdg import PDGConfig, build_graph, simulate
from dtoc.sim.phantom import brain_phantom

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def epi():
    ir = load_sequence(REPO / "sequences" / "epi_esp081.seq")
    ph = brain_phantom(32, fov_m=ir.fov_m[:2], b0=True)
    return ir, ph, build_graph(ir, PDGConfig(), ph)


def _counted(monkeypatch):
    calls = []
    orig = S._apply_kernel_lines

    def spy(*a, **k):
        calls.append(a[7])  # the phase-encoded axis
        return orig(*a, **k)

    monkeypatch.setattr(S, "_apply_kernel_lines", spy)
    return calls


@pytest.mark.parametrize("swap", [False, True], ids=["pe_y", "pe_x"])
@pytest.mark.parametrize("offset_mT_per_m", [0.0, 0.004], ids=["nominal", "drifting"])
def test_line_aware_equals_direct(epi, monkeypatch, swap, offset_mT_per_m):
    """Nominal lines (delta series of one term) and lines whose phase moment drifts (a constant 4 uT/m offset
    on the phase axis: ~0.05 rad across the object per line, a 3-5 term series): value to 1e-9 of the
    maximum against 'direct', gradient w.r.t. the whole waveform to 1e-9 against the per-sample windows."""
    ir, ph, g = epi
    G0 = torch.as_tensor(ir.grad_mT_per_m).clone()
    pe_axis = 0 if swap else 1
    if swap:
        G0 = G0[[1, 0, 2]]
    G0[pe_axis] += offset_mT_per_m
    ref = simulate(ir, ph, graph=g, grad_mT_per_m=G0, config=PDGConfig(signal_method="direct"))
    calls = _counted(monkeypatch)
    grads, sigs = [], []
    for line_aware in (True, False):
        G = G0.clone().requires_grad_(True)
        s = simulate(
            ir, ph, graph=g, grad_mT_per_m=G, config=PDGConfig(signal_method="separable", line_aware=line_aware)
        )
        (s.abs() ** 2).sum().backward()
        sigs.append(s.detach())
        grads.append(G.grad)
    assert calls and set(calls) == {pe_axis}  # the line path ran, on the right axis
    scale = float(ref.abs().max())
    assert float((sigs[0] - ref).abs().max()) < 1e-9 * scale
    assert float((sigs[1] - ref).abs().max()) < 1e-9 * scale
    assert float((grads[0] - grads[1]).abs().max()) < 1e-9 * float(grads[1].abs().max())


def test_line_windows_follow_the_blips():
    """Windows cut at every phase blip and at most W samples long; a radial-like readout has no lines."""
    m_ro = np.tile(np.arange(8.0), 4)
    m_pe = np.repeat(np.arange(4.0), 8) * 3.0
    w = S._line_windows(m_pe, m_ro, 5)
    assert w.tolist() == [[0, 5], [5, 8], [8, 13], [13, 16], [16, 21], [21, 24], [24, 29], [29, 32]]
    spoke = np.linspace(-1, 1, 16)
    assert S._line_windows(np.concatenate([spoke, spoke]), np.concatenate([spoke, -spoke]), 8) is None
