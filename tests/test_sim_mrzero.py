"""Agreement with MRzeroCore 1.2.0 on the paper's scenarios (fixtures from bench/sim/make_reference.py).

Each fixture holds the .seq file, the dtoc phantom and MRzeroCore's signal for them (only numbers; MRzero
is not needed to run these tests).  dtoc simulates the same file on the same phantom; both signals are
reconstructed by the same plain iFFT and compared with the paper's NRMSE (magnitude images), MRzero's
image as the reference.  Alignments: docs/metrics.md ("Agreement with MRzeroCore").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from dtoc.seq.load import load_sequence
from dtoc.sim import metrics, pdg, recon
from dtoc.sim.phantom import load_phantom

FIX = Path(__file__).resolve().parent / "fixtures"


def _compare(name: str):
    ir = load_sequence(FIX / f"mrzero_{name}.seq")
    ph = load_phantom(FIX / f"mrzero_{name}_phantom.npz")
    with np.load(FIX / f"mrzero_{name}_signal.npz") as z:
        ref = z["signal"]
        assert str(z["mrzero_version"]) == "1.2.0"
    assert ref.shape == (1, ir.n_adc_samples)
    with torch.no_grad():
        sig = pdg.simulate(ir, ph)
    img = recon.reconstruct(sig, ir).abs()
    img_ref = recon.reconstruct(torch.as_tensor(ref), ir).abs()
    # MRzero's receiver phase differs by a constant factor; magnitudes and the signal up to that factor agree
    s, r = sig.numpy()[0], ref[0]
    c = np.vdot(r, s) / np.vdot(r, r)
    return float(metrics.nrmse(img, img_ref)), abs(c), float(np.linalg.norm(s - c * r) / np.linalg.norm(s)), img_ref


def test_epi_64_agrees_with_mrzero():
    nrmse, scale, sig_err, img_ref = _compare("epi")
    assert nrmse <= 0.005  # required: 0.5 %; measured 1.8e-6 (MRzero runs in float32)
    assert nrmse < 1e-4
    assert scale == pytest.approx(1.0, abs=1e-4) and sig_err < 1e-4
    assert float(img_ref.max()) > 0.1  # a real image, not two empty ones


def test_gre_paper_agrees_with_mrzero():
    nrmse, scale, sig_err, img_ref = _compare("gre")
    assert nrmse <= 0.005  # required: 0.5 %; measured 0.23 % (MRzero's own box-voxel error ~1 %, docs/metrics.md)
    assert scale == pytest.approx(1.0, abs=2e-3) and sig_err < 0.01
    assert float(img_ref.max()) > 0.01
