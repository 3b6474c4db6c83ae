"""The realized-trajectory side-car of a pre-compensated ``.seq`` (docs/contracts.md §5).

Beside ``OUT.seq``, ``OUT.traj.npz`` holds what the digital twin predicts the scanner will sample when it plays
the file: the realized k of every ADC sample, the accrued B0 phase and which samples the optimizer chose to
skip -- for reconstruction with the true trajectory rather than the nominal one.
"""

from __future__ import annotations

import numpy as np

#: Layout version of the side-car (bumped on any change of keys or meaning).
SIDECAR_VERSION = 1


def sidecar_arrays(
    ir, k_realized_rad_per_m, b0_phase_rad, keep_mask, dk_rad_per_m, model_sha256: str | None
) -> dict[str, np.ndarray]:
    """The side-car's arrays (keys and units in docs/contracts.md §5).

    Args:
        ir: the base sequence (:class:`dtoc.seq.ir.SequenceIR`): nominal k, sample times, ADC layout.
        k_realized_rad_per_m: (3, N_adc) predicted realized k of the output at every ADC sample, rad/m.
        b0_phase_rad: (N_adc,) accrued B0 phase at every ADC sample, rad (zeros without a B0 term).
        keep_mask: (N_adc,) bool, False = skipped (discarded) by the optimizer.
        dk_rad_per_m: (3,) the k-space unit the figures use (inf on axes not encoded).
        model_sha256: sha256 of the hardware model file the prediction used (None: in-memory or ideal).
    """
    n = ir.n_adc_samples
    empty = np.zeros(0, dtype=np.int32)
    event = np.concatenate([empty] + [np.full(a.num_samples, i, dtype=np.int32) for i, a in enumerate(ir.adc)])
    sample = np.concatenate([empty] + [np.arange(a.num_samples, dtype=np.int32) for a in ir.adc])
    keep = np.ones(n, dtype=bool) if keep_mask is None else np.asarray(keep_mask, dtype=bool)
    return {
        "version": np.array(SIDECAR_VERSION, dtype=np.int32),
        "t_s": np.asarray(ir.adc_times_s, dtype=np.float64),
        "adc_event": event.astype(np.int32),
        "sample_in_adc": sample.astype(np.int32),
        "k_nominal_rad_per_m": np.asarray(ir.nominal_kspace_rad_per_m(), dtype=np.float64),
        "k_realized_rad_per_m": np.asarray(k_realized_rad_per_m, dtype=np.float64),
        "b0_phase_rad": np.asarray(b0_phase_rad, dtype=np.float64),
        "discarded": ~keep,
        "dk_rad_per_m": np.asarray(dk_rad_per_m, dtype=np.float64),
        "model_sha256": np.array(model_sha256 or ""),
    }
