"""Dummy cycles before the sequence: the steady-state longitudinal magnetisation (:func:`dtoc.sim.pdg.steady_state_mz`).

The dummy train is the base sequence's repetitions played back to back without ADC, with quadratic RF
spoiling continued; it runs through the same PDG model (graph with the final Mz observed).
"""

from __future__ import annotations

import numpy as np
import torch

from dtoc.errors import InputError
from dtoc.seq.ir import SequenceIR
from dtoc.sim.pdg_main import main_loop, prepare


def detect_rf_spoiling(ir: SequenceIR) -> float:
    """Quadratic RF-spoiling increment (rad) of the excitations of ``ir``; 0 when the phases are not quadratic.

    RF spoiling sets phi_j = phi_0 + c j (j + 1) / 2: the second difference of consecutive excitation
    phases is the constant c (e.g. 117 deg).
    """
    p = np.array([r.phase_rad for r in sorted(ir.rf, key=lambda r: r.t_center_s) if r.excites])
    if p.size < 3:
        return 0.0
    d2 = np.angle(np.exp(1j * (p[2:] - 2 * p[1:-1] + p[:-2])))
    if np.all(np.abs(np.angle(np.exp(1j * (d2 - d2[0])))) < 1e-3) and abs(d2[0]) > 1e-6:  # file phases are rounded
        return float(d2[0])
    return 0.0


def dummy_train(ir: SequenceIR, n: int, block_range, rf_spoil_rad: float = 0.0) -> SequenceIR:
    """IR of ``n`` repetitions (block ranges) played back to back, without ADC.

    With ``rf_spoil_rad`` = c, the RF phases of repetition d are shifted by q(d) - q(d mod n_template)
    (cycled base repetitions) or q(d) (a single block range), q(j) = c j (j+1)/2, so that quadratic RF
    spoiling continues through the whole train instead of restarting.
    """
    from dataclasses import replace as _replace

    from dtoc.seq.ir import SequenceIR as _IR

    edges = ir.block_edges_s
    nb = len(edges) - 1
    if block_range is not None:
        b0, b1 = int(block_range[0]), int(block_range[1])
        if not (0 <= b0 < b1 <= nb):
            raise InputError(f"steady_state_mz: block_range {block_range} outside 0..{nb}")
        reps = [(b0, b1)]
    else:
        exc = sorted({r.block for r in ir.rf if r.excites} or {r.block for r in ir.rf})
        if not exc:
            raise InputError("steady_state_mz: the sequence has no RF pulse")
        reps = [(exc[i], exc[i + 1] if i + 1 < len(exc) else nb) for i in range(len(exc))]
    dtf = ir.dt_fine_s
    segs, rfs, bedges = [], [], [0.0]
    t_off = 0.0
    for d in range(n):
        b0, b1 = reps[d % len(reps)]
        m0 = int(round(edges[b0] / dtf))
        m1 = int(round(edges[b1] / dtf))
        segs.append(ir.grad_mT_per_m[:, m0:m1])
        shift = t_off - m0 * dtf
        q = lambda j: rf_spoil_rad * j * (j + 1) / 2.0  # noqa: E731
        dphi = q(d) - (q(d % len(reps)) if block_range is None else 0.0)
        for r in ir.rf:
            if b0 <= r.block < b1:
                rfs.append(
                    _replace(
                        r,
                        block=len(bedges) - 1 + (r.block - b0),
                        t_start_s=r.t_start_s + shift,
                        t_center_s=r.t_center_s + shift,
                        phase_rad=float(np.angle(np.exp(1j * (r.phase_rad + dphi)))),
                    )
                )
        for b in range(b0 + 1, b1 + 1):
            bedges.append(edges[b] + shift)
        t_off += (m1 - m0) * dtf
    last = reps[(n - 1) % len(reps)][1]
    g = np.concatenate(
        segs + [ir.grad_mT_per_m[:, int(round(edges[last] / dtf)) : int(round(edges[last] / dtf)) + 1]], axis=1
    )
    return _IR(
        raster_s=ir.raster_s,
        grad_mT_per_m=g,
        block_edges_s=np.array(bedges),
        rf=rfs,
        adc=[],
        fov_m=ir.fov_m,
        matrix=ir.matrix,
        kind=ir.kind,
        readout_axis=ir.readout_axis,
        phase_axis=ir.phase_axis,
    )


def run_dummies(ir, phantom, n_dummies, block_range, cfg, dtype, device, rf_spoil_rad=None):
    """Voxel-mean Mz (ny, nx) after ``n_dummies`` repetitions (see :func:`dtoc.sim.pdg.steady_state_mz`)."""
    if n_dummies <= 0:
        return torch.as_tensor(phantom.pd, dtype=dtype, device=device)
    if rf_spoil_rad is None:
        rf_spoil_rad = detect_rf_spoiling(ir)
    train = dummy_train(ir, n_dummies, block_range, rf_spoil_rad)
    with torch.no_grad():
        p = prepare(train, phantom, None, cfg, None, None, None, dtype, device, final_z=True)
        graph, vox = p.graph, p.vox
        _, A, K = main_loop(p, False, True)
        last = graph.intervals[-1]
        zi = np.where(last.is_z)[0]
        mz = vox.observe_mz(A[zi], K[zi], last.tau_s[zi])
    out = torch.zeros(phantom.shape, dtype=dtype, device=device).reshape(-1)
    out[vox.index] = mz.real.to(dtype)
    return out.reshape(phantom.shape)
