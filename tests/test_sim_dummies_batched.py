"""Dummy trains and long sequences on the GPU's schedule (issue 33): the start-of-interval k by pointer
jumping when the path matrix is too large (``pdg_main._k_by_jumps``), and the final state of a dummy
train by the mirrored fused propagation in segments of bounded buffers (``pdg_fused.final_amplitudes``),
against the per-interval path the CPU keeps."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).parent))
from test_sim_fused import test_signal_and_gradient_equal_the_per_interval_propagation as _fused_equals_per_interval  # noqa: E402
from test_sim_physics import rich_phantom, small_gre  # noqa: E402

from dtoc.sim import pdg_main
from dtoc.sim.pdg import PDGConfig
from dtoc.sim.pdg_main import main_loop, prepare


@pytest.fixture
def no_path_matrix(monkeypatch):
    """Every graph above the k-path matrix's size: the k of all states by pointer jumping."""
    monkeypatch.setattr(pdg_main, "_K_PATH_MAX_ELEMS", 0)


def _final_state(ir, ph, fused: bool, cfg=None):
    with torch.no_grad():
        p = prepare(ir, ph, None, cfg or PDGConfig(), None, None, None, torch.float64, "cpu", final_z=True)
        _, A, K = main_loop(p, False, True, fused=fused)
    return A.numpy(), K.numpy()


def test_dummy_train_in_segments_by_pointer_jumping_equals_the_streaming_path(no_path_matrix):
    """Final amplitudes (1e-12 of their maximum) and k (1e-12 of its maximum) of a 12-repetition train, float64,
    diffusion, B0 and T2' in the phantom: the fused propagation with k by pointer jumping, in one buffer and
    in segments of a few steps, against the per-interval path; the segments are bit for bit the one buffer."""
    ir, ph = small_gre(n_rep=12), rich_phantom()
    A0, K0 = _final_state(ir, ph, False)
    A1, K1 = _final_state(ir, ph, True)
    A2, K2 = _final_state(ir, ph, True, PDGConfig(checkpoint_bytes=4e5))  # F fits, ~10 segments
    assert np.abs(A0).max() > 0 and np.abs(K0).max() > 0
    assert np.abs(A1 - A0).max() < 1e-12 * np.abs(A0).max()
    assert np.abs(K1 - K0).max() < 1e-12 * np.abs(K0).max()
    assert np.array_equal(A2, A1) and np.array_equal(K2, K1)


def test_segments_are_taken(no_path_matrix, monkeypatch):
    """The segmented run above really runs in several segments (a test of the test's byte budget)."""
    from dtoc.sim import pdg_fused

    calls = []
    orig = pdg_fused._forward
    monkeypatch.setattr(pdg_fused, "_forward", lambda *a, **k: calls.append(a[4]) or orig(*a, **k))
    _final_state(small_gre(n_rep=12), rich_phantom(), True, PDGConfig(checkpoint_bytes=4e5))
    assert len(calls) >= 4 and min(calls) >= 1, calls


def test_signal_and_gradient_with_k_by_pointer_jumping(no_path_matrix):
    """The main pass with the GPU's schedule, k by pointer jumping, against the per-interval path: signal 1e-12,
    gradient w.r.t. the gradient waveform (through the diffusion b-values) 1e-10, float64 (the check of
    tests/test_sim_fused.py with the path matrix switched off)."""
    _fused_equals_per_interval()


def test_dummy_train_operations_per_interval():
    """Operations of a dummy train's final state (``run_dummies``' main loop) with the GPU's schedule: three per
    added interval (one fused step; k by pointer jumping adds a round per doubling), measured 149 / 185 at
    5 / 17 intervals; the CPU's per-interval path 417 / 1,377 (80 per interval; 18,873 for 160 dummies of the
    32x32 paper GRE, 872 with this schedule)."""

    class Count(TorchDispatchMode):
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.n += 1
            return func(*args, **(kwargs or {}))

    ph = rich_phantom()
    counts = {}
    for n_rep in (4, 16):
        with torch.no_grad():
            p = prepare(
                small_gre(n_rep=n_rep), ph, None, PDGConfig(), None, None, None, torch.float64, "cpu", final_z=True
            )
            with Count() as c:
                main_loop(p, False, True, fused=True)
        counts[n_rep] = (c.n, len(p.graph.intervals))
    (f4, n4), (f16, n16) = counts[4], counts[16]
    assert n16 > n4 and f16 > f4, counts  # the count sees the train
    assert f16 - f4 <= 4 * (n16 - n4), counts
