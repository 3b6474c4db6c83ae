"""Small synthetic sequences and hardware models for the optimizer tests (no seq I/O needed).

``gre_ir``: the paper's GRE structure (TR 10 ms, RF 0-2 ms without gradients, prewinder, readout
of ``n`` samples at 0.1 ms dwell from 2.5 ms, spoiler, phase rewinder) on a 0.1 ms raster, FOV 32 mm.
``eddy_model``: the paper's Eq. 1 with exact exponential convolution.
"""

from __future__ import annotations

import numpy as np
import torch

from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
from dtoc.seq.ir import ADCEvent, RFEvent, SequenceIR, edges_to_fine

R = 1e-4  # raster, s


def gre_ir(n: int = 16, reps: int | None = None, fov_m: float = 0.032) -> SequenceIR:
    reps = n if reps is None else reps
    per = 100  # edges per TR
    dk = 2 * np.pi / fov_m
    gr = dk / (GAMMA_RAD_PER_S_PER_MT * R)  # readout amplitude, mT/m (7.34 for 32 mm)
    e = np.zeros((3, per * reps + 1))
    rf, adc, edges_s = [], [], []
    half = n // 2
    for r in range(reps):
        o = r * per
        p = -(half + 1) * gr / 4.0
        e[0, o + 21 : o + 25] = p
        e[0, o + 25 : o + 25 + n + 1] = gr
        e[0, o + 26 + n : o + 36 + n] = 17.6
        j = r % n
        pe = (j - half) * gr / 4.0
        e[1, o + 21 : o + 25] = pe
        e[1, o + 26 + n : o + 30 + n] = -pe
        rf.append(
            RFEvent(
                block=2 * r,
                t_start_s=o * R,
                t_center_s=o * R + 1e-3,
                duration_s=2e-3,
                flip_angle_rad=np.deg2rad(15),
                phase_rad=float(np.deg2rad(117) * r * (r + 1) / 2 % (2 * np.pi)),
                freq_offset_hz=0.0,
                use="excitation",
            )
        )
        adc.append(
            ADCEvent(block=2 * r + 1, t_start_s=o * R + 2.5e-3, num_samples=n, dwell_s=R, phase_rad=rf[-1].phase_rad)
        )
        edges_s += [o * R, o * R + 2e-3]
    edges_s.append(per * reps * R)
    free = np.zeros((3, 2 * e.shape[1] - 1), bool)
    idx = np.arange(e.shape[1])
    fe = (idx % per) >= 20
    fe[-1] = False
    free[:2, ::2] = fe
    return SequenceIR(
        raster_s=R,
        grad_mT_per_m=edges_to_fine(e),
        block_edges_s=np.array(edges_s),
        rf=rf,
        adc=adc,
        free_mask=free,
        fov_m=(fov_m, fov_m, fov_m),
        matrix=(n, n),
        kind="gre",
        readout_axis=0,
        phase_axis=1,
        meta={"synthetic": True},
    )


def eddy_model(alphas=(0.1, 0.1), taus_s=(1e-3, 100e-3)):
    """Hardware callable (g (B,3,T), dt) -> (G, None) with G = g - sum alpha * (g' conv exp(-t/tau))."""
    from dtoc.hardware.recursion import exp_response

    def model(g: torch.Tensor, dt_s: float):
        G = g
        for a, tau in zip(alphas, taus_s):
            G = G - a * exp_response(g, dt_s, torch.tensor(tau, dtype=g.dtype))
        return G, None

    return model
