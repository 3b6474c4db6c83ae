"""PNG report of one `dtoc optimize` run: waveforms, k-space, images, loss curves."""

from __future__ import annotations

import numpy as np

from dtoc.util.atomic import atomic_write_bytes
from dtoc.util.figures import png_bytes


def plotted_span(ir) -> tuple[int, float]:
    """The report's waveform panel: (number of fine samples from t = 0, end time s) -- the first ~3 ADC windows
    (the first ~5 readouts of an EPI), or the whole sequence when it has no more than 3."""
    t_end = ir.duration_s
    if len(ir.adc) > 3:
        t_end = ir.adc[3].t_start_s + 0.2e-3 if ir.kind != "epi" else ir.adc[min(5, len(ir.adc) - 1)].t_start_s
    x, dtf = t_end + 1e-12, ir.dt_fine_s
    c = int(np.floor(x / dtf))  # the last i with i * dtf <= x, as a comparison on the times themselves
    while (c + 1) * dtf <= x:
        c += 1
    while c >= 0 and c * dtf > x:
        c -= 1
    return min(c + 1, ir.n_fine), t_end


def write_report_png(path, figures: dict, manifest: dict, force: bool = False):
    """Write a 2 x 3 panel report (deterministic: no timestamps in the PNG metadata)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ir = figures["ir"]
    before, after, keep = figures["before"], figures["after"], figures["keep"]
    ro = ir.readout_axis if ir.readout_axis is not None else 0
    pa = ir.phase_axis if ir.phase_axis is not None else 1 - ro if ro in (0, 1) else 1
    fig, ax = plt.subplots(2, 3, figsize=(15, 8.5))
    n, t_end = plotted_span(ir)
    t_ms = np.arange(n) * ir.dt_fine_s * 1e3
    a = ax[0, 0]
    a.plot(t_ms, ir.grad_mT_per_m[ro, :n], "k--", lw=1, label="target g0")
    a.plot(t_ms, before["_G"][ro, :n], color="tab:red", lw=1, label="realized (base)")
    a.plot(t_ms, after["_g"][ro, :n], color="tab:green", lw=1, label="demanded (optimized)")
    a.plot(t_ms, after["_G"][ro, :n], color="tab:blue", lw=1, label="realized (optimized)")
    for adc in ir.adc:
        if adc.t_start_s <= t_end:
            a.axvspan(adc.t_start_s * 1e3, (adc.t_start_s + adc.num_samples * adc.dwell_s) * 1e3, color="0.9", zorder=0)
    a.set_xlabel("t (ms)")
    a.set_ylabel(f"g{'xyz'[ro]} (mT/m)")
    a.set_title("readout-axis waveforms")
    a.legend(fontsize=7)
    # k-space
    a = ax[0, 1]
    k0 = ir.nominal_kspace_rad_per_m()
    dk = ir.dk_rad_per_m if ir.dk_rad_per_m is not None else np.ones(3)
    a.plot(k0[ro] / dk[ro], k0[pa] / dk[pa], "k.", ms=2, label="target")
    a.plot(before["_k"][ro] / dk[ro], before["_k"][pa] / dk[pa], ".", color="tab:red", ms=2, label="base")
    ka = after["_k"]
    a.plot(ka[ro, keep] / dk[ro], ka[pa, keep] / dk[pa], ".", color="tab:blue", ms=2, label="optimized (kept)")
    if (~keep).any():
        a.plot(ka[ro, ~keep] / dk[ro], ka[pa, ~keep] / dk[pa], "x", color="tab:orange", ms=3, label="skipped")
    a.set_xlabel("k readout (dk)")
    a.set_ylabel("k phase (dk)")
    a.set_title("k-space at ADC samples")
    a.legend(fontsize=7)
    # loss curves
    a = ax[0, 2]
    hist = figures["history"]
    if hist:
        its = np.arange(len(hist))
        keys = sorted({k for h in hist for k in h if k not in ("stage", "it", "loss", "phantom")})
        a.semilogy(its, [max(h["loss"], 1e-16) for h in hist], "k", lw=1.2, label="total")
        for k in keys:
            a.semilogy(its, [max(h.get(k, np.nan), 1e-16) for h in hist], lw=0.8, label=k)
        a.legend(fontsize=7)
    a.set_xlabel("record")
    a.set_title("loss (weighted terms)")
    # images
    imgr = figures.get("imager")
    if imgr is not None:
        target = imgr.targets[0].abs().cpu().numpy()
        vmax = target.max()
        for j, (img, title) in enumerate(
            (
                (target, "target I0"),
                (before.get("_image"), f"base: NRMSE {_pct(before.get('nrmse'))}"),
                (after.get("_image"), f"optimized: NRMSE {_pct(after.get('nrmse'))}"),
            )
        ):
            a = ax[1, j]
            if img is not None:
                img = np.asarray(img)
                if img.ndim == 3:  # a 3D image: its central z slice
                    title += f" (z {img.shape[0] // 2}/{img.shape[0]})"
                    img = img[img.shape[0] // 2]
                a.imshow(img, cmap="gray", vmin=0, vmax=vmax, origin="lower")
            a.set_title(title)
            a.axis("off")
    else:
        for j in range(3):
            ax[1, j].axis("off")
    m = manifest
    fig.suptitle(
        f"dtoc optimize ({m['options']['method']}): gmax {m['limits']['gmax_mT_per_m']:g} mT/m, "
        f"smax {m['limits']['smax_T_per_m_per_s']:g} T/m/s, skipped {m['n_samples_discarded']} samples"
    )
    return atomic_write_bytes(path, png_bytes(fig, dpi=90), force=force)


def _pct(v):
    return "n/a" if v is None else f"{100 * v:.2f} %"
