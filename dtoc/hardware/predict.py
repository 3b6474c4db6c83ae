"""`dtoc predict`: realized versus demanded gradients, k-space and B0 phase of a sequence under a hardware model.

Figures (all realized minus demanded/nominal, per physical axis x, y, z):

- gradient error on the IR's fine grid (dt = raster/2): max |G - g| and RMS over the whole sequence, mT/m;
- k-space error at every ADC sample (k counted from the last excitation, refocusing negates it,
  :mod:`dtoc.seq.kspace`): max and RMS in rad/m and in units of dk = 2 pi / FOV;
- accrued B0 phase at ADC samples: ``phi = -gamma * integral b0 dt`` from the last excitation (rad), max |phi|;
- EPI (more than one ADC event, readout axis known): per ADC line the mean readout-axis k error
  ``dk_line`` (rad/m); odd and even lines' means, their difference (the Nyquist-ghost-driving offset,
  rad/m and in dk) and the spread within each parity; the same for the phase-encode axis.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from dtoc.constants import AXES
from dtoc.hardware.model import HardwareModel
from dtoc.seq.ir import SequenceIR


def realize(ir: SequenceIR, model: HardwareModel, device: str | torch.device = "cpu",
            dtype: torch.dtype = torch.float64) -> tuple[np.ndarray, np.ndarray]:
    """Realized gradient (3, M) mT/m and B0 (M,) uT of the IR's demanded gradient on its fine grid."""
    g = torch.as_tensor(ir.grad_mT_per_m, dtype=dtype, device=device)
    model = model.to(device)
    with torch.no_grad():
        G, b0 = model(g, ir.dt_fine_s)
    return G.double().cpu().numpy(), b0.double().cpu().numpy()


def _stats(err: np.ndarray) -> tuple[float, float]:
    if err.size == 0:
        return 0.0, 0.0
    return float(np.max(np.abs(err))), float(np.sqrt(np.mean(err**2)))


def predict(ir: SequenceIR, model: HardwareModel, device: str = "cpu") -> dict[str, Any]:
    """Compute the figures of the module docstring; returns a JSON-serialisable dict.

    Also holds (under ``"_arrays"``, not for JSON) the realized waveforms and k for plotting.
    """
    G, b0 = realize(ir, model, device)
    g = ir.grad_mT_per_m
    out: dict[str, Any] = {"dt_s": ir.dt_fine_s, "duration_s": ir.duration_s, "n_adc_samples": ir.n_adc_samples,
                           "fov_m": list(ir.fov_m) if ir.fov_m else None, "grad_error": {}, "k_error": {}}
    for a, name in enumerate(AXES):
        mx, rms = _stats(G[a] - g[a])
        out["grad_error"][name] = {"max_mT_per_m": mx, "rms_mT_per_m": rms}
    k0 = k = None
    if ir.n_adc_samples:
        k0 = ir.kspace_rad_per_m().numpy()
        k = ir.kspace_rad_per_m(G).numpy()
        dk = ir.dk_rad_per_m
        for a, name in enumerate(AXES):
            mx, rms = _stats(k[a] - k0[a])
            row = {"max_rad_per_m": mx, "rms_rad_per_m": rms, "max_dk": None, "rms_dk": None}
            if dk is not None and np.isfinite(dk[a]):
                row.update(max_dk=mx / dk[a], rms_dk=rms / dk[a])
            out["k_error"][name] = row
        # B0 phase: integrate b0 like a gradient channel (same excitation/refocusing bookkeeping)
        b3 = np.zeros_like(G)
        b3[0] = b0
        kb = ir.kspace_rad_per_m(b3).numpy()[0]  # gamma_mT * integral(b0 [uT]) -> scale to rad
        phi = -kb * 1e-3  # uT = 1e-3 mT
        out["b0_phase_max_rad"] = float(np.max(np.abs(phi)))
        out["epi"] = _epi_offsets(ir, k, k0)
    else:
        out["b0_phase_max_rad"] = None
        out["epi"] = None
    out["b0_max_uT"] = float(np.max(np.abs(b0))) if b0.size else 0.0
    out["_arrays"] = {"G": G, "b0": b0, "k": k, "k0": k0}
    return out


def _epi_offsets(ir: SequenceIR, k: np.ndarray, k0: np.ndarray) -> dict[str, Any] | None:
    if len(ir.adc) < 2 or ir.readout_axis is None:
        return None
    dk = ir.dk_rad_per_m
    ro, pe = ir.readout_axis, ir.phase_axis
    bounds = np.cumsum([0] + [a.num_samples for a in ir.adc])
    res: dict[str, Any] = {"n_lines": len(ir.adc), "readout_axis": AXES[ro], "phase_axis": AXES[pe] if pe is not None else None}
    for key, ax in (("readout", ro), ("phase", pe)):
        if ax is None:
            continue
        line = np.array([np.mean(k[ax, bounds[i]:bounds[i + 1]] - k0[ax, bounds[i]:bounds[i + 1]]) for i in range(len(ir.adc))])
        even, odd = line[0::2], line[1::2]
        d = float(np.mean(odd) - np.mean(even))
        scale = dk[ax] if dk is not None and np.isfinite(dk[ax]) else None
        res[key] = {
            "even_mean_rad_per_m": float(np.mean(even)), "odd_mean_rad_per_m": float(np.mean(odd)),
            "odd_minus_even_rad_per_m": d, "odd_minus_even_dk": None if scale is None else d / scale,
            "even_spread_rad_per_m": float(np.ptp(even)), "odd_spread_rad_per_m": float(np.ptp(odd)),
            "line_offsets_rad_per_m": line.tolist(),
        }
    return res


def plot_prediction(ir: SequenceIR, res: dict[str, Any], path, title: str = "", force: bool = False):
    """PNG: demanded vs realized gradients (top), k error at ADC samples (bottom)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dtoc.util.atomic import atomic_write_bytes

    arr = res["_arrays"]
    t_ms = ir.t_fine_s * 1e3
    fig, axs = plt.subplots(2, 1, figsize=(10, 6.5))
    for a, c in zip(range(3), ("C0", "C1", "C2")):
        axs[0].plot(t_ms, ir.grad_mT_per_m[a], color=c, lw=0.8, ls="--", label=f"g{AXES[a]} demanded")
        axs[0].plot(t_ms, arr["G"][a], color=c, lw=0.8, label=f"G{AXES[a]} realized")
    axs[0].set_xlabel("t (ms)")
    axs[0].set_ylabel("gradient (mT/m)")
    axs[0].legend(ncol=3, fontsize=7)
    if arr["k"] is not None:
        ta = ir.adc_times_s * 1e3
        for a, c in zip(range(3), ("C0", "C1", "C2")):
            axs[1].plot(ta, arr["k"][a] - arr["k0"][a], ".", ms=2, color=c, label=f"k{AXES[a]} error")
        axs[1].set_xlabel("ADC sample time (ms)")
        axs[1].set_ylabel("k - k0 (rad/m)")
        axs[1].legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue(), force=force)
