"""The non-uniform DFT reconstruction (dtoc.sim.ndft) used for non-Cartesian 2D sequences."""

from __future__ import annotations

import copy

import numpy as np
import torch
from cli_helpers import run_cli
from foreign.writers import gre, radial

from dtoc.seq.load import load_sequence
from dtoc.sim.imager import Imager
from dtoc.sim.phantom import phantom_for


def test_on_cartesian_samples_it_is_the_inverse_fft(tmp_path):
    """Same samples, same grid: the NDFT image equals the plain iFFT image up to a global scale (its density
    weights are uniform on a Cartesian grid) -- signs, centring and orientation agree."""
    p = tmp_path / "gre.seq"
    p.write_bytes(gre(n=16))
    ir = load_sequence(p)
    imager = Imager(ir, [phantom_for(ir, "brain")])
    sig = imager.target_signals[0]
    cart = imager.image(sig)
    ir2 = copy.copy(ir)
    ir2.meta = {**ir.meta, "recon": "ndft"}
    from dtoc.sim.recon import reconstruct

    nd = reconstruct(sig, ir2)
    a, b = cart.abs().numpy().ravel(), nd.abs().numpy().ravel()
    scale = float(a @ b / (b @ b))
    # 3e-6: the file's k positions sit 1e-7 dk off the grid the iFFT snaps to; a sign or centring error is O(1)
    assert np.linalg.norm(a - scale * b) / np.linalg.norm(a) < 1e-4 and abs(scale - 1) < 1e-3


def test_radial_simulate_and_gradient(tmp_path, capsys):
    p = tmp_path / "rad.seq"
    p.write_bytes(radial(n=32, spokes=24))
    ir = load_sequence(p)
    assert ir.meta.get("recon") == "ndft" and ir.geometry.matrix_xy == (32, 32)
    assert any("non-uniform DFT" in n for n in ir.meta["notes"])
    code, out, err = run_cli(capsys, "simulate", p, "--json", "-", "-q")
    import json

    assert code == 0 and json.loads(out)["nrmse_percent"] == 0.0  # ideal hardware: the same image
    # differentiable in the signal (the optimizer's image term)
    imager = Imager(ir, [phantom_for(ir, "brain")])
    s = imager.target_signals[0].clone().requires_grad_(True)
    imager.image(s).abs().sum().backward()
    assert s.grad is not None and torch.isfinite(s.grad).all() and s.grad.abs().max() > 0
