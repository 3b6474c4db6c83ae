"""Off-centre slices and FOV shifts after pre-compensation (docs/optimize.md, "Off-centre").

A scanner's Pulseq interpreter places an off-centre slice or FOV (position r0, m) by demodulating each ADC
sample with the phase its *demanded* gradients give: ``phi_int(t) = r0 . k_demanded(t)``.  The spins at r0
accrue ``r0 . k_realized(t)``.  On the base file the difference is ``r0 . (k_realized - k0)`` (the hardware's
k error); after pre-compensation k_realized ~ k0 but k_demanded is deliberately not k0, so the difference
``r0 . (k_realized - k_demanded)`` becomes the pre-compensation itself times the offset.  What the format
allows to correct it: per ADC event, a phase offset and a frequency offset -- the least-squares line through
the residual phase over the event's samples.  What stays is reported (rad, max and RMS over ADC samples).
RF events: the slice-select axis is held (docs/optimize.md), so the interpreter's RF frequency (from the demanded
slice gradient) stays right; a sequence whose slice axis is freed is refused with ``--offset``.

Sign: Pulseq's receiver multiplies the signal by ``exp(-i (phase_offset + 2 pi freq_offset t))``, so the
correction *adds* the fitted line to the ADC's phase and frequency offsets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dtoc.errors import InputError


@dataclass
class OffcentreResult:
    """Residual FOV-shift phase at the ADC samples, rad, and the per-ADC corrections."""

    residual_base_rad: np.ndarray  # (N,) base file played on the hardware
    residual_uncorrected_rad: np.ndarray  # (N,) output, interpreter phase from its demanded gradient
    residual_corrected_rad: np.ndarray  # (N,) after the per-ADC phase/frequency corrections
    adc_phase_rad: np.ndarray  # (n_adc,) added to each ADC's phase offset
    adc_freq_hz: np.ndarray  # (n_adc,) added to each ADC's frequency offset

    def summary(self) -> dict:
        def mr(x):
            return {
                "max_rad": float(np.max(np.abs(x))) if x.size else 0.0,
                "rms_rad": float(np.sqrt(np.mean(x**2))) if x.size else 0.0,
            }

        return {
            "base": mr(self.residual_base_rad),
            "output_uncorrected": mr(self.residual_uncorrected_rad),
            "output_corrected": mr(self.residual_corrected_rad),
            "max_adc_phase_correction_rad": float(np.max(np.abs(self.adc_phase_rad)))
            if self.adc_phase_rad.size
            else 0.0,
            "max_adc_freq_correction_hz": float(np.max(np.abs(self.adc_freq_hz))) if self.adc_freq_hz.size else 0.0,
        }


def parse_offset(text: str | None) -> np.ndarray | None:
    """``x,y,z`` in m (physical) -> (3,), refusing values that look like mm (|r| > 0.5 m) or are not finite."""
    if text is None:
        return None
    try:
        v = np.array([float(x) for x in text.replace(",", " ").split()])
    except ValueError:
        raise InputError(f"--offset {text!r}: expected three numbers x,y,z in m") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InputError(f"--offset {text!r}: expected three finite numbers x,y,z in m")
    if np.max(np.abs(v)) > 0.5:
        raise InputError(f"--offset {text!r}: beyond 0.5 m from isocentre (mm given where m is expected?)")
    return v


def offcentre_correction(
    ir_base, ir_out, k_base_realized, k_out_realized, offset_phys_m, rotation=None
) -> OffcentreResult:
    """Residual FOV-shift phases and the per-ADC line fit that removes what the format allows.

    Args:
        ir_base / ir_out: the base and the pre-compensated sequence (same ADC layout).
        k_base_realized / k_out_realized: (3, N) realized k of the base / output on the hardware model, rad/m.
        offset_phys_m: (3,) physical offset r0, m.  rotation: logical -> physical R (None: identity).
    """
    r0 = np.asarray(offset_phys_m, dtype=np.float64)
    if rotation is not None:
        r0 = np.asarray(rotation, dtype=np.float64).T @ r0  # into the file's logical frame, where k lives
    k0 = ir_base.nominal_kspace_rad_per_m()
    kd = ir_out.nominal_kspace_rad_per_m()  # what the interpreter demodulates with
    base = r0 @ (np.asarray(k_base_realized) - k0)
    unc = r0 @ (np.asarray(k_out_realized) - kd)
    t = ir_out.adc_times_s
    corr = unc.copy()
    ph = np.zeros(len(ir_out.adc))
    fr = np.zeros(len(ir_out.adc))
    i0 = 0
    for i, a in enumerate(ir_out.adc):
        sl = slice(i0, i0 + a.num_samples)
        i0 += a.num_samples
        tt = t[sl] - a.t_start_s
        A = np.stack([np.ones_like(tt), tt], axis=1)
        coef = (
            np.linalg.lstsq(A, unc[sl], rcond=None)[0]
            if tt.size >= 2
            else np.array([unc[sl].mean() if tt.size else 0.0, 0.0])
        )
        ph[i], fr[i] = coef[0], coef[1] / (2 * np.pi)
        corr[sl] = unc[sl] - A @ coef
    return OffcentreResult(base, unc, corr, ph, fr)
