"""Image-level hint: an x gradient delay recovered from the raw data of a simulated EPI scan (Nyquist ghost)."""

import numpy as np
import torch

from dtoc.hardware.model import HardwareModel, build_effect, girf_effect
from dtoc.identify.image_hint import fit_delays_to_raw
from dtoc.identify.synth import lowpass_girf
from dtoc.seq.load import load_sequence
from dtoc.sim.imager import Imager
from dtoc.sim.phantom import resolve_phantom


def test_delay_from_epi_raw_data(repo_root):
    ir = load_sequence(repo_root / "sequences" / "epi_small.yaml")
    ph = resolve_phantom(None, matrix=(int(ir.matrix[1]), int(ir.matrix[0])), fov_m=(ir.fov_m[0], ir.fov_m[1]))
    declared = HardwareModel([girf_effect(lowpass_girf(ir.dt_fine_s))])
    true = HardwareModel([*declared.effects, build_effect("delay", {"seconds": 3.5e-6}, axis="x")])
    with torch.no_grad():
        G, b0 = true(torch.as_tensor(ir.grad_mT_per_m), ir.dt_fine_s)
        s = Imager(ir, [ph]).signal(G, b0, 0)
    rng = np.random.default_rng(0)
    s_meas = s + torch.as_tensor(
        0.01 * float(s.abs().max()) * (rng.standard_normal(s.shape) + 1j * rng.standard_normal(s.shape))
    )
    r = fit_delays_to_raw(ir, ph, declared, s_meas, axes=("x",))
    assert abs(r.delays_s["x"] - 3.5e-6) < 0.1e-6
    assert r.loss_after < 0.3 * r.loss_before
    # The fitted twin predicts the measured ghost better than the declared model does.
    assert abs(r.ghost_twin_after - r.ghost_measured) < abs(r.ghost_twin_before - r.ghost_measured)
    assert [e.kind for e in r.model.effects] == ["girf", "delay"]
