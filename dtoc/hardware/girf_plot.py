"""PNG of a GIRF (``dtoc girf show --png``).

Four panels:

1. |H(f)| of the self terms (linear), with the -3 dB level and each term's bandwidth;
2. |H(f)| of the cross terms (dimensionless) and of the B0 terms (uT per mT/m), log scale, so that
   1 % cross terms and their noise floor are visible; all-zero terms are listed as "not in file";
3. phase of the self terms (rad, unwrapped) where |H| > 10 % of its DC value (beyond that the phase
   of measured data is noise), with the group delay of each term in the legend;
4. the self-term impulse responses ``h / dt`` (1/ms) around their peak (t in us).

The frequency axis runs to the kernel's Nyquist frequency or to the end of the file's own band.
"""

from __future__ import annotations

import numpy as np

from dtoc.constants import AXES
from dtoc.hardware.girf_analysis import girf_summary, response_grid
from dtoc.hardware.girf_io import GirfData
from dtoc.util.atomic import atomic_write_bytes, check_output_path
from dtoc.util.figures import png_bytes

_COLORS = ("C0", "C1", "C2")


def _band_end(f: np.ndarray, mags: list[np.ndarray]) -> float:
    """Highest frequency where any of the given responses is non-zero (the file's own band)."""
    nz = np.zeros(f.size, dtype=bool)
    for m in mags:
        nz |= m > 1e-12
    return float(f[np.flatnonzero(nz)[-1]]) if nz.any() else float(f[-1])


def plot_girf(gd: GirfData, path, title: str = "", force: bool = False, fmax_hz: float | None = None):
    """Write the 4-panel PNG described in the module docstring (atomic; refuses to overwrite unless ``force``).

    Args:
        gd: the GIRF.
        path: output .png.
        title: figure title (e.g. the file name).
        force: overwrite an existing file.
        fmax_hz: upper end of the frequency axes (default: Nyquist or the end of the file's band).
    """
    check_output_path(path, force)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    td = gd.to_time_domain()
    f, H, H0 = response_grid(gd)
    rows = {r["term"]: r for r in girf_summary(gd)}
    selfmag = [np.abs(H[a, a]) for a in range(3)]
    fend = fmax_hz or _band_end(f, selfmag)
    sel = f <= fend
    fk = f[sel] * 1e-3
    fig, axs = plt.subplots(2, 2, figsize=(12, 8))
    ax_m, ax_c, ax_p, ax_t = axs[0, 0], axs[0, 1], axs[1, 0], axs[1, 1]

    # 1. self-term magnitude
    for a in range(3):
        r = rows[f"{AXES[a]}->{AXES[a]}"]
        bw = r["bandwidth_3db_hz"]
        lab = f"{AXES[a]}->{AXES[a]}: DC {r['dc_gain']:.4f}" + (f", -3 dB {bw * 1e-3:.2f} kHz" if bw else "")
        ax_m.plot(fk, selfmag[a][sel], color=_COLORS[a], lw=1.0, label=lab)
    ax_m.axhline(1 / np.sqrt(2), color="0.5", lw=0.6, ls="--", label="-3 dB (0.707)")
    ax_m.set_xlim(0, fend * 1e-3)
    top = max(1.2, min(3.0, float(max(m[sel].max() for m in selfmag)) * 1.05))
    ax_m.set_ylim(0, top)
    ax_m.set_xlabel("f (kHz)")
    ax_m.set_ylabel("|H| self terms")
    ax_m.set_title("self terms: magnitude", fontsize=9)
    ax_m.legend(fontsize=7, loc="lower left")
    ax_m.grid(alpha=0.3)

    # 2. cross and B0 terms (log)
    absent = []
    ls = {0: "-", 1: "--", 2: ":"}
    for i in range(3):
        for o in range(3):
            if o == i:
                continue
            m = np.abs(H[o, i, sel])
            name = f"{AXES[i]}->{AXES[o]}"
            if not np.any(m > 0):
                absent.append(name)
                continue
            ax_c.plot(fk, m, lw=0.6, color=_COLORS[o], ls=ls[i], alpha=0.8, label=name)
    if H0 is not None:
        for i in range(3):
            m = np.abs(H0[i, sel])
            name = f"{AXES[i]}->b0"
            if not np.any(m > 0):
                absent.append(name)
                continue
            ax_c.plot(fk, m, lw=0.6, color=f"C{3 + i}", alpha=0.8, label=f"{name} (uT per mT/m)")
    if ax_c.lines:
        ax_c.set_yscale("log")
        ax_c.legend(fontsize=6, ncol=2, loc="upper left")
    ax_c.set_xlim(0, fend * 1e-3)
    ax_c.set_xlabel("f (kHz)")
    ax_c.set_ylabel("|H| cross terms; |H0| B0 terms")
    ax_c.set_title("cross and B0 terms" + (f" (not in file: {', '.join(absent)})" if absent else ""), fontsize=8)
    ax_c.grid(alpha=0.3, which="both")

    # 3. phase of self terms where the magnitude is meaningful
    for a in range(3):
        dc = abs(H[a, a, 0]) if f[0] == 0 else selfmag[a][0]
        good = sel & (selfmag[a] > 0.1 * max(dc, 1e-30))
        if not good.any():
            continue
        stop = np.flatnonzero(~good[: np.flatnonzero(good)[-1] + 1])
        last = stop[0] if stop.size else np.flatnonzero(good)[-1] + 1  # contiguous band from f = 0
        ph = np.unwrap(np.angle(H[a, a, :last]))
        gdel = rows[f"{AXES[a]}->{AXES[a]}"]["group_delay_s"]
        lab = f"{AXES[a]}->{AXES[a]}" + (f": group delay {gdel * 1e6:.2f} us" if gdel is not None else "")
        ax_p.plot(f[:last] * 1e-3, ph, color=_COLORS[a], lw=1.0, label=lab)
    ax_p.set_xlim(0, fend * 1e-3)
    ax_p.set_xlabel("f (kHz)")
    ax_p.set_ylabel("phase (rad)")
    ax_p.set_title("self terms: phase where |H| > 10 % of DC (positive delay = negative slope)", fontsize=8)
    ax_p.legend(fontsize=7)
    ax_p.grid(alpha=0.3)

    # 4. impulse responses around the peak
    t_us = (td.t0_s + np.arange(td.h.shape[-1]) * td.dt_s) * 1e6
    peaks = [t_us[int(np.argmax(np.abs(td.h[a, a])))] for a in range(3)]
    centre = float(np.median(peaks))
    lo, hi = centre - 100.0, centre + 200.0
    win = (t_us >= lo) & (t_us <= hi)
    for a in range(3):
        ax_t.plot(
            t_us[win],
            td.h[a, a, win] / (td.dt_s * 1e3),
            color=_COLORS[a],
            lw=0.9,
            marker="." if win.sum() < 120 else None,
            ms=3,
            label=f"{AXES[a]}->{AXES[a]}",
        )
    ax_t.axvline(0, color="0.5", lw=0.6)
    ax_t.set_xlim(lo, hi)
    ax_t.set_xlabel(f"t after the impulse (us); taps every {td.dt_s * 1e6:.4g} us")
    ax_t.set_ylabel("impulse response h/dt (1/ms)")
    ax_t.set_title("self terms: impulse response", fontsize=9)
    ax_t.legend(fontsize=7)
    ax_t.grid(alpha=0.3)

    fig.suptitle(title, fontsize=10)
    return atomic_write_bytes(path, png_bytes(fig, dpi=100), force=force)
