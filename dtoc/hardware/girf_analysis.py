"""Figures of a GIRF per term: DC gain, -3 dB bandwidth, group delay; frequency response on a grid.

Definitions (``H`` with the convention of :mod:`dtoc.hardware.girf_io`):

- DC gain: ``H(0) = sum(h)`` (dimensionless; uT per mT/m for B0 terms).
- -3 dB bandwidth: the lowest f > 0 where ``|H(f)| < |H(0)| / sqrt(2)`` (linear interpolation between
  grid points); None if never below (within the kernel's Nyquist frequency) or if ``|H(0)|`` is ~0.
- group delay (``group_delay_s``): ``-slope / (2 pi)`` of a least-squares line through the unwrapped
  phase over 0 <= f <= 4 kHz (well inside the ~10 kHz bandwidth of whole-body gradient systems), the
  bulk delay a sequence sees.  Positive = the output lags.  Also given: the centroid
  ``sum(t h) / sum(h)`` (``centroid_s``), which equals the group delay exactly at f = 0 for clean kernels
  but is dominated by noise in long measured kernel tails.  Both None for terms with ~0 DC gain
  (|H(0)| < 10 % of max |H| below 1 kHz, e.g. noisy cross terms).
"""

from __future__ import annotations

import numpy as np

from dtoc.constants import AXES
from dtoc.hardware.girf_io import GirfData

#: Upper end of the phase-fit band for the group delay, Hz.
GROUP_DELAY_BAND_HZ = 4000.0


def response_grid(gd: GirfData, min_points: int = 16384) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(f (F,) Hz >= 0, H (3, 3, F), H0 (3, F) or None)`` up to the kernel's Nyquist frequency.

    Frequency-domain GIRFs are returned on their own grid (f >= 0): interpolating measured spectra
    through the time domain would leak their (often large, noisy) out-of-band values into the band.
    """
    if not gd.is_time_domain:
        sel = gd.f_hz >= 0
        return gd.f_hz[sel], gd.H[..., sel], (None if gd.H0 is None else gd.H0[..., sel])
    td = gd.to_time_domain()
    L = td.h.shape[-1]
    nfft = max(8 * L, 2 * min_points)
    f = np.fft.rfftfreq(nfft, td.dt_s)
    ph = np.exp(-2j * np.pi * f * td.t0_s)
    H = np.fft.rfft(td.h, n=nfft, axis=-1) * ph
    H0 = None if td.h0 is None else np.fft.rfft(td.h0, n=nfft, axis=-1) * ph
    return f, H, H0


def _bandwidth(f: np.ndarray, mag: np.ndarray) -> float | None:
    ref = mag[0]
    if ref < 1e-6:
        return None
    below = np.flatnonzero(mag < ref / np.sqrt(2))
    if below.size == 0 or below[0] == 0:
        return None
    j = below[0]
    y0, y1 = mag[j - 1], mag[j]
    thr = ref / np.sqrt(2)
    return float(f[j - 1] + (y0 - thr) / (y0 - y1) * (f[j] - f[j - 1]))


def term_figures(taps: np.ndarray, t_s: np.ndarray, f: np.ndarray, H: np.ndarray) -> dict:
    """Figures of one term from its taps (L,) at times t_s and its response H on f (>= 0)."""
    dc = float(np.sum(taps))
    mag = np.abs(H)
    out = {
        "dc_gain": dc,
        "bandwidth_3db_hz": _bandwidth(f, mag),
        "group_delay_s": None,
        "centroid_s": None,
        "peak_gain": float(mag.max()),
        "peak_hz": float(f[int(np.argmax(mag))]),
    }
    if abs(dc) > 0.1 * max(mag[f <= 1000.0].max() if np.any(f <= 1000.0) else mag[0], 1e-30):
        out["centroid_s"] = float(np.sum(t_s * taps) / dc)
        sel = f <= GROUP_DELAY_BAND_HZ
        if sel.sum() >= 3:
            phi = np.unwrap(np.angle(H[sel] * np.sign(dc)))
            slope = np.polyfit(f[sel], phi, 1)[0]
            out["group_delay_s"] = float(-slope / (2 * np.pi))
    return out


def girf_summary(gd: GirfData) -> list[dict]:
    """One row per term: ``{"term": "x->y", "input": "x", "output": "y"|"b0", ...figures}``.

    Self terms first (x->x, y->y, z->z), then cross terms, then B0 terms.
    """
    td = gd.to_time_domain()
    f, H, H0 = response_grid(td)
    t = td.t0_s + np.arange(td.h.shape[-1]) * td.dt_s
    order = [(a, a) for a in range(3)] + [(o, i) for i in range(3) for o in range(3) if o != i]
    rows = []
    for o, i in order:
        row = {"term": f"{AXES[i]}->{AXES[o]}", "input": AXES[i], "output": AXES[o]}
        row.update(term_figures(td.h[o, i], t, f, H[o, i]))
        rows.append(row)
    if td.h0 is not None:
        for i in range(3):
            row = {"term": f"{AXES[i]}->b0", "input": AXES[i], "output": "b0"}
            row.update(term_figures(td.h0[i], t, f, H0[i]))
            rows.append(row)
    return rows


def magnitude_at(gd: GirfData, f_hz, o: int, i: int) -> np.ndarray:
    """|H[o, i](f)| at the given frequencies (Hz): DTFT of taps, or linear interpolation of a
    frequency-domain GIRF on its own grid."""
    f = np.atleast_1d(np.asarray(f_hz, dtype=np.float64))
    if not gd.is_time_domain:
        return np.interp(f, gd.f_hz, np.abs(gd.H[o, i]))
    H, _ = gd.response(f)
    return np.abs(H[o, i])
