"""PNG of a GIRF: magnitude and phase of every term (self, cross, B0) and the impulse responses."""

from __future__ import annotations

import io

import numpy as np

from dtoc.constants import AXES
from dtoc.hardware.girf_analysis import response_grid
from dtoc.hardware.girf_io import GirfData
from dtoc.util.atomic import atomic_write_bytes


def plot_girf(gd: GirfData, path, title: str = "", force: bool = False, fmax_hz: float = 50e3):
    """Write a 3-row figure: |H| (self and cross), phase of self terms, impulse responses (taps / dt)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    td = gd.to_time_domain()
    f, H, H0 = response_grid(gd)
    sel = f <= fmax_hz
    t_ms = (td.t0_s + np.arange(td.h.shape[-1]) * td.dt_s) * 1e3
    fig, axs = plt.subplots(3, 1, figsize=(9, 9))
    for o in range(3):
        for i in range(3):
            lab = f"{AXES[i]}->{AXES[o]}"
            if o == i:
                axs[0].plot(f[sel] * 1e-3, np.abs(H[o, i, sel]), lw=1.0, label=lab)
                axs[1].plot(f[sel] * 1e-3, np.unwrap(np.angle(H[o, i, sel])), lw=1.0, label=lab)
                axs[2].plot(t_ms, td.h[o, i] / (td.dt_s * 1e3), lw=0.8, label=lab)
            else:
                axs[0].plot(f[sel] * 1e-3, np.abs(H[o, i, sel]), lw=0.5, alpha=0.7, label=lab)
    if H0 is not None:
        for i in range(3):
            axs[0].plot(f[sel] * 1e-3, np.abs(H0[i, sel]), lw=0.5, ls=":", label=f"{AXES[i]}->b0 (uT per mT/m)")
    axs[0].set_yscale("log")
    axs[0].set_ylabel("|H|")
    axs[0].legend(ncol=4, fontsize=6)
    axs[1].set_ylabel("phase (rad)")
    axs[1].set_xlabel("f (kHz)")
    axs[1].legend(fontsize=6)
    width = np.sum(np.abs(td.h[[0, 1, 2], [0, 1, 2]]) > 1e-3 * np.abs(td.h).max(), axis=-1).max() if td.h.size else 1
    axs[2].set_xlim(-0.2, max(0.2, 1.5 * width * td.dt_s * 1e3 / 2))
    axs[2].set_xlabel("t (ms)")
    axs[2].set_ylabel("impulse response (1/ms)")
    axs[2].legend(fontsize=6)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, metadata={"Software": None})
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue(), force=force)
