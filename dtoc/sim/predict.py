"""`dtoc predict`: realized versus demanded gradients, k-space and B0 phase of a sequence under a hardware model.

Figures (all realized minus demanded/nominal, per physical axis x, y, z):

- gradient error on the IR's fine grid (dt = raster/2): max |G - g| and RMS over the whole sequence, mT/m;
- k-space error at every ADC sample (k counted from the last excitation, refocusing negates it,
  :mod:`dtoc.seq.kspace`): max and RMS in rad/m and in units of dk = 2 pi / FOV;
- with a reference (``--reference BASE``, :mod:`dtoc.sim.reference`) every "demanded/nominal" above is the
  base's: the realized trajectory of a pre-compensated output against what its base intended;
- accrued B0 phase at ADC samples: ``phi = -gamma * integral b0 dt`` from the last excitation (rad), max |phi|;
- EPI (``kind`` 'epi', or readout polarity alternating between consecutive ADC events): per ADC line the mean readout-axis k error
  ``dk_line`` (rad/m); odd and even lines' means, their difference (the Nyquist-ghost-driving offset,
  rad/m and in dk) and the spread within each parity; the same for the phase-encode axis.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from dtoc.constants import AXES
from dtoc.hardware.model import HardwareModel
from dtoc.seq.ir import SequenceIR
from dtoc.util.figures import png_bytes


def realize(
    ir: SequenceIR, model: HardwareModel, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float64
) -> tuple[np.ndarray, np.ndarray]:
    """Realized gradient (3, M) mT/m and B0 (M,) uT of the IR's demanded gradient on its fine grid."""
    from dtoc.sim.twin import Twin

    with torch.no_grad():
        G, b0 = Twin(ir, model.to(device), dtype=dtype, device=device).realize(
            torch.as_tensor(ir.grad_mT_per_m, dtype=dtype, device=device)
        )
    b0 = torch.zeros(G.shape[-1], dtype=G.dtype, device=G.device) if b0 is None else b0
    return G.double().cpu().numpy(), b0.double().cpu().numpy()


#: fine samples of one piece of :func:`realized_pieces` (6 MB a float64 (3, n) waveform; the overlap-add block of
#: :mod:`dtoc.hardware.convolution`, so a GIRF spectrum of its size), besides the chain's memory on either side
QUALITY_CHUNK = 1 << 18
#: :func:`predict` plays a sequence of more fine samples than this piece by piece (its figures; the whole waveforms
#: only when a plot asks for them)
PREDICT_STREAM_MIN = 1 << 21


def streamable(twin) -> bool:
    """True when the twin's chain can be played piece by piece with a bounded memory either side (ideal, or affine
    with a finite :func:`dtoc.hardware.memory.memory_s`), on a grid of at least 3 samples."""
    from dtoc.hardware.memory import is_affine, memory_s

    hw = None if twin.is_ideal else twin.hardware
    return is_affine(hw) and all(np.isfinite(memory_s(hw))) and twin.ir.n_fine >= 3


@dataclass
class Piece:
    """One piece of :func:`realized_pieces`: fine samples ``s .. e`` (``e`` is the next piece's ``s``) of the
    demanded ``g`` and realized ``G`` (3, e - s + 1) and the B0 term ``b0`` (e - s + 1,) or None; samples
    ``s .. own - 1`` are this piece's own (the last piece owns its last sample too)."""

    s: int
    e: int
    own: int
    g: torch.Tensor
    G: torch.Tensor
    b0: torch.Tensor | None

    def channels(self) -> torch.Tensor:
        """(3 or 4, L): G, with the B0 term as a fourth channel (integrated like a gradient, the phase's sign and
        unit as :func:`b0_phase_at_adc_rad`)."""
        return self.G if self.b0 is None else torch.cat([self.G, self.b0[None]])


def realized_pieces(twin, played, chunk: int | None = None) -> Iterator[Piece]:
    """The demanded waveform ``played`` (3, M) through ``twin``'s chain piece by piece (``chunk`` fine samples,
    default :data:`QUALITY_CHUNK`), each realized with the chain's memory (:func:`dtoc.hardware.memory.memory_s`)
    on either side: memory bounded by a piece.  Equal to the whole realization up to the memory's truncation
    (1e-6 relative) and rounding; one piece is the whole realization.  Only where :func:`streamable`."""
    from dtoc.hardware.memory import memory_s

    ch = QUALITY_CHUNK if chunk is None else int(chunk)
    M, dt = twin.ir.n_fine, twin.ir.dt_fine_s
    causal, acausal = memory_s(None if twin.is_ideal else twin.hardware)
    hc, ha = int(math.ceil(causal / dt)) + 2, int(math.ceil(acausal / dt)) + 2
    for s in range(0, M - 1, ch):
        e = min(s + ch, M - 1)
        lo, hi = max(0, s - hc), min(M, e + 1 + ha)
        gp = twin.demanded(played[:, lo:hi])
        Gp, bp = twin.realize(gp)
        own = e + 1 if e == M - 1 else e
        yield Piece(
            s,
            e,
            own,
            gp[:, s - lo : e + 1 - lo],
            Gp[:, s - lo : e + 1 - lo],
            None if bp is None else bp[s - lo : e + 1 - lo],
        )


def stream_kspace(ir: SequenceIR, pieces) -> torch.Tensor:
    """(C, N_adc) k of ``(s, w)`` pieces (:func:`dtoc.seq.kspace.kspace_at_streamed`) at the IR's ADC samples."""
    from dtoc.seq.kspace import kspace_at_streamed

    rf = ir.rf
    return kspace_at_streamed(
        pieces, ir.n_fine, ir.dt_fine_s, ir.adc_times_s, [r.t_center_s for r in rf], [r.use for r in rf]
    )


def _stats(err: np.ndarray) -> tuple[float, float]:
    if err.size == 0:
        return 0.0, 0.0
    return float(np.max(np.abs(err))), float(np.sqrt(np.mean(err**2)))


def predict(
    ir: SequenceIR, model: HardwareModel, device: str = "cpu", reference: SequenceIR | None = None
) -> dict[str, Any]:
    """Compute the figures of the module docstring; returns a JSON-serialisable dict.

    ``reference``: the base ``ir`` was compiled from (same structure, :func:`dtoc.sim.reference.check_same_structure`):
    errors are then realized (of ``ir``) minus the *base's* demanded gradient and nominal k, in the base's dk,
    instead of minus ``ir``'s own (pre-compensated) demand.  ``k_error_max_dk``: the largest per-axis max in dk
    (the optimize manifest's ``kspace_max_error_dk`` when dk is the grid's).
    Also holds (under ``"_arrays"``, not for JSON) the realized waveforms and k for plotting.
    """
    from dtoc.sim.twin import Twin

    twin = Twin(ir, model.to(device), dtype=torch.float64, device=device)
    if ir.n_fine > PREDICT_STREAM_MIN and streamable(twin):
        return _predict_streamed(ir, twin, model, device, reference)
    G, b0 = realize(ir, model, device)
    ref = ir if reference is None else reference
    g = ref.grad_mT_per_m
    grad_error = {}
    for a, name in enumerate(AXES):
        mx, rms = _stats(G[a] - g[a])
        grad_error[name] = {"max_mT_per_m": mx, "rms_mT_per_m": rms}
    k0 = k = None
    phi_max = None
    if ir.n_adc_samples:
        k0 = ref.kspace_rad_per_m().numpy()
        k = ir.kspace_rad_per_m(G).numpy()
        phi_max = float(np.max(np.abs(b0_phase_at_adc_rad(ir, b0))))
    out = _record(ir, ref, grad_error, k, k0, phi_max, float(np.max(np.abs(b0))) if b0.size else 0.0)
    out["_arrays"] = {"G": G, "g": g, "b0": b0, "k": k, "k0": k0}
    return out


class _WholeArrays(dict):
    """``_arrays`` of a streamed :func:`predict`: k and k0 at once, the whole realized ``G`` and ``b0`` only when
    asked for (a plot); then realized whole, as the short-sequence path does."""

    def __init__(self, ir, model, device, g, k, k0):
        super().__init__(g=g, k=k, k0=k0)
        self._src = (ir, model, device)

    def __missing__(self, key):
        if key not in ("G", "b0"):
            raise KeyError(key)
        G, b0 = realize(*self._src)
        self.update(G=G, b0=b0)
        return self[key]


def _predict_streamed(ir: SequenceIR, twin, model, device, reference: SequenceIR | None) -> dict[str, Any]:
    """:func:`predict` of a long sequence, piece by piece (:func:`realized_pieces`): the figures as the whole path
    computes them (sums of squares and maxima accumulated per piece; k and the B0 phase at the ADC samples
    integrated across the pieces), never a whole realized waveform."""
    ref = ir if reference is None else reference
    g = ref.grad_mT_per_m
    mx, ss, b0max = np.zeros(3), np.zeros(3), 0.0
    with torch.no_grad():

        def pieces():
            nonlocal b0max
            for p in realized_pieces(twin, ir.grad_mT_per_m):
                n = p.own - p.s
                err = p.G[:, :n].double().cpu().numpy() - g[:, p.s : p.own]
                mx[:] = np.maximum(mx, np.abs(err).max(axis=1))
                ss[:] += (err**2).sum(axis=1)
                if p.b0 is not None:
                    b0max = max(b0max, float(p.b0[:n].abs().max()))
                yield p.s, p.channels()

        kb = stream_kspace(ir, pieces()).double().cpu().numpy() if ir.n_adc_samples else None
        if kb is None:  # no ADC: the waveform figures alone
            for _ in pieces():
                pass
    M = ir.n_fine
    grad_error = {
        name: {"max_mT_per_m": float(mx[a]), "rms_mT_per_m": float(np.sqrt(ss[a] / M))} for a, name in enumerate(AXES)
    }
    k = None if kb is None else kb[:3]
    k0 = None if kb is None else ref.kspace_rad_per_m().numpy()
    phi_max = None if kb is None else (float(np.max(np.abs(-kb[3] * 1e-3))) if kb.shape[0] == 4 else 0.0)
    out = _record(ir, ref, grad_error, k, k0, phi_max, b0max)
    out["_arrays"] = _WholeArrays(ir, model, device, g, k, k0)
    return out


def _record(ir: SequenceIR, ref: SequenceIR, grad_error: dict, k, k0, phi_max, b0_max: float) -> dict[str, Any]:
    """The figures of :func:`predict` (the module doc) from the gradient errors, k and k0 at the ADC samples (None
    without ADC), the largest B0 phase and field."""
    out: dict[str, Any] = {
        "dt_s": ir.dt_fine_s,
        "duration_s": ir.duration_s,
        "n_adc_samples": ir.n_adc_samples,
        "fov_m": list(ir.fov_m) if ir.fov_m else None,
        "grad_error": grad_error,
        "k_error": {},
    }
    if k is not None:
        _k_figures(out, k, k0, ref.dk_rad_per_m)
        out["b0_phase_max_rad"] = phi_max
        out["epi"] = _epi_offsets(ref, k, k0)
    else:
        out["k_error_max_dk"] = None
        out["b0_phase_max_rad"] = None
        out["epi"] = None
    out["b0_max_uT"] = b0_max
    return out


def _k_figures(out: dict, k: np.ndarray, k0: np.ndarray, dk) -> None:
    """``out['k_error']`` per axis and ``out['k_error_max_dk']`` of k against k0 (rad/m; in dk where known)."""
    for a, name in enumerate(AXES):
        mx, rms = _stats(k[a] - k0[a])
        row = {"max_rad_per_m": mx, "rms_rad_per_m": rms, "max_dk": None, "rms_dk": None}
        if dk is not None and np.isfinite(dk[a]):
            row.update(max_dk=mx / dk[a], rms_dk=rms / dk[a])
        out["k_error"][name] = row
    kd = [r["max_dk"] for r in out["k_error"].values() if r["max_dk"] is not None]
    out["k_error_max_dk"] = max(kd) if kd else None


def is_epi(ir: SequenceIR) -> bool:
    """An echo train: the IR says ``kind == 'epi'``, or (kind unknown) the readout gradient at the centres
    of consecutive ADC events alternates in sign (a GRE's repeated readouts do not)."""
    if ir.kind is not None:
        return ir.kind == "epi"
    tc = np.array([a.t_start_s + 0.5 * a.num_samples * a.dwell_s for a in ir.adc])
    gc = np.interp(tc, ir.t_fine_s, ir.grad_mT_per_m[ir.readout_axis])
    return bool(np.all(gc != 0) and np.all(gc[1:] * gc[:-1] < 0))


def _epi_offsets(ir: SequenceIR, k: np.ndarray, k0: np.ndarray) -> dict[str, Any] | None:
    if len(ir.adc) < 2 or ir.readout_axis is None or not is_epi(ir):
        return None
    dk = ir.dk_rad_per_m
    ro, pe = ir.readout_axis, ir.phase_axis
    bounds = np.cumsum([0] + [a.num_samples for a in ir.adc])
    res: dict[str, Any] = {
        "n_lines": len(ir.adc),
        "readout_axis": AXES[ro],
        "phase_axis": AXES[pe] if pe is not None else None,
    }
    for key, ax in (("readout", ro), ("phase", pe)):
        if ax is None:
            continue
        line = np.array(
            [np.mean(k[ax, bounds[i] : bounds[i + 1]] - k0[ax, bounds[i] : bounds[i + 1]]) for i in range(len(ir.adc))]
        )
        even, odd = line[0::2], line[1::2]
        d = float(np.mean(odd) - np.mean(even))
        scale = dk[ax] if dk is not None and np.isfinite(dk[ax]) else None
        res[key] = {
            "even_mean_rad_per_m": float(np.mean(even)),
            "odd_mean_rad_per_m": float(np.mean(odd)),
            "odd_minus_even_rad_per_m": d,
            "odd_minus_even_dk": None if scale is None else d / scale,
            "even_spread_rad_per_m": float(np.ptp(even)),
            "odd_spread_rad_per_m": float(np.ptp(odd)),
            "line_offsets_rad_per_m": line.tolist(),
        }
    return res


def zoom_window_ms(ir: SequenceIR) -> tuple[float, float]:
    """A window showing the waveform detail: three ADC events around the middle one (EPI: the k = 0
    line and its neighbours), else the first 2 ms after the first ADC start."""
    if ir.adc:
        j = len(ir.adc) // 2
        a0 = ir.adc[max(j - 1, 0)]
        a1 = ir.adc[min(j + 1, len(ir.adc) - 1)]
        lo = a0.t_start_s - 0.2e-3
        hi = a1.t_start_s + a1.num_samples * a1.dwell_s + 0.2e-3
        if len(ir.adc) < 3 or hi - lo > 6e-3:  # GRE-like: one TR's readout neighbourhood
            a = ir.adc[j]
            lo = a.t_start_s - 1.0e-3
            hi = a.t_start_s + a.num_samples * a.dwell_s + 1.0e-3
        return max(lo, 0.0) * 1e3, min(hi, ir.duration_s) * 1e3
    return 0.0, min(ir.duration_s, 2e-3) * 1e3


def b0_phase_at_adc_rad(ir: SequenceIR, b0_uT) -> np.ndarray:
    """(N_adc,) phase accrued by a spatially uniform field offset ``b0_uT`` ((M,) on the fine grid) at every
    ADC sample, rad, integrated like a gradient channel (the same excitation/refocusing bookkeeping as k)."""
    b0 = np.asarray(b0_uT, dtype=np.float64)
    b3 = np.zeros((3, b0.size))
    b3[0] = b0
    kb = ir.kspace_rad_per_m(b3).numpy()[0]  # gamma_mT * integral(b0 [uT]) -> scale to rad
    return -kb * 1e-3  # uT = 1e-3 mT


def plot_prediction(ir: SequenceIR, res: dict[str, Any], path, title: str = "", force: bool = False):
    """PNG, 4 panels: demanded (dashed) vs realized (solid) gradients over the whole sequence and in a
    zoom around the middle ADC events (ADC windows shaded); realized minus demanded gradient; k error at
    the ADC samples in units of dk = 2 pi / FOV (rad/m when the FOV is unknown), EPI line means marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dtoc.util.atomic import atomic_write_bytes, check_output_path

    check_output_path(path, force)
    arr = res["_arrays"]
    t_ms = ir.t_fine_s * 1e3
    g, G = arr["g"], arr["G"]
    cols = ("C0", "C1", "C2")
    used = [a for a in range(3) if np.any(g[a]) or np.any(G[a])] or [0, 1, 2]
    fig, axs = plt.subplots(2, 2, figsize=(13, 8))
    ax_full, ax_zoom, ax_err, ax_k = axs[0, 0], axs[0, 1], axs[1, 0], axs[1, 1]
    lo, hi = zoom_window_ms(ir)
    zsel = (t_ms >= lo) & (t_ms <= hi)
    for a in used:
        for ax, sel in ((ax_full, slice(None)), (ax_zoom, zsel)):
            ax.plot(t_ms[sel], g[a, sel], color=cols[a], lw=0.9, ls="--", label=f"g{AXES[a]} demanded")
            ax.plot(t_ms[sel], G[a, sel], color=cols[a], lw=0.9, alpha=0.8, label=f"G{AXES[a]} realized")
        ax_err.plot(
            t_ms,
            G[a] - g[a],
            color=cols[a],
            lw=0.7,
            label=f"G{AXES[a]} - g{AXES[a]} (max {res['grad_error'][AXES[a]]['max_mT_per_m']:.3g})",
        )
    ax_full.axvspan(lo, hi, color="0.85", zorder=0)
    for ev in ir.adc:
        t0 = ev.t_start_s * 1e3
        t1 = t0 + ev.num_samples * ev.dwell_s * 1e3
        if t1 >= lo and t0 <= hi:
            ax_zoom.axvspan(max(t0, lo), min(t1, hi), color="0.9", zorder=0)
    ax_full.set_title("whole sequence (grey: zoomed window)", fontsize=9)
    ax_zoom.set_title("zoom around the middle ADC events (shaded: ADC)", fontsize=9)
    for ax in (ax_full, ax_zoom):
        ax.set_xlabel("t (ms)")
        ax.set_ylabel("gradient (mT/m)")
        ax.grid(alpha=0.3)
    ax_zoom.set_xlim(lo, hi)
    ax_full.legend(ncol=3, fontsize=7, loc="lower right")
    ax_err.set_xlabel("t (ms)")
    ax_err.set_ylabel("realized - demanded (mT/m)")
    ax_err.set_title("gradient error", fontsize=9)
    ax_err.legend(fontsize=7)
    ax_err.grid(alpha=0.3)
    if arr["k"] is not None:
        dk = ir.dk_rad_per_m
        ta = ir.adc_times_s * 1e3
        for a in used:
            scale = dk[a] if dk is not None and np.isfinite(dk[a]) and dk[a] > 0 else 1.0
            unit = "dk" if scale != 1.0 else "rad/m"
            e = (arr["k"][a] - arr["k0"][a]) / scale
            ax_k.plot(ta, e, ".", ms=1.5, color=cols[a], label=f"k{AXES[a]} error ({unit})")
        epi = res.get("epi") or {}
        ro = epi.get("readout")
        if ro and dk is not None and ir.readout_axis is not None:
            bounds = np.cumsum([0] + [ev.num_samples for ev in ir.adc])
            tm = np.array([ta[bounds[i] : bounds[i + 1]].mean() for i in range(len(ir.adc))])
            lm = np.asarray(ro["line_offsets_rad_per_m"]) / dk[ir.readout_axis]
            ax_k.plot(tm[0::2], lm[0::2], "v", ms=4, color="k", label="readout line mean, even lines")
            ax_k.plot(
                tm[1::2],
                lm[1::2],
                "^",
                ms=4,
                color="0.5",
                label=f"odd lines (odd - even {ro['odd_minus_even_dk']:.3g} dk)",
            )
        ax_k.set_xlabel("ADC sample time (ms)")
        ax_k.set_ylabel("k - k nominal (dk = 2 pi / FOV)")
        ax_k.set_title("k-space error at the ADC samples", fontsize=9)
        ax_k.legend(fontsize=7)
        ax_k.grid(alpha=0.3)
    else:
        ax_k.text(0.5, 0.5, "no ADC samples", ha="center", va="center", transform=ax_k.transAxes)
        ax_k.set_axis_off()
    fig.suptitle(title, fontsize=10)
    return atomic_write_bytes(path, png_bytes(fig, dpi=100), force=force)
