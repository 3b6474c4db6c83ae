"""Error figures and honest notes on what the residual still contains.

* :func:`rmse` — root-mean-square residual per channel (and per axis) over the measured samples.
* :func:`spectral_peaks` — narrow-band structure: the residual, whitened by the noise floor, is split
  into Hann-windowed segments of 256 samples; the averaged periodogram of each frequency bin is compared with
  the median over bins (the broadband level).  For white noise each bin is a chi-square with 2 * n_seg
  degrees of freedom (scaled); a bin is significant when its ratio exceeds the Bonferroni-corrected
  (p = 1e-3 over all bins) chi-square quantile and is at least 1.5 x the level.  Contiguous significant bins
  are merged and reported by their peak.
* :func:`dependence_note` — does the residual power grow with the demanded slew rate or amplitude?  The mean
  whitened power in the top decile of |dg/dt| (or |g|) against the bottom half; a ratio above 2 that is
  statistically significant is reported (a missing *linear* effect also concentrates at high slew, so the
  note says "grows with", and the search has already tried every linear candidate).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from dtoc.constants import AXES
from dtoc.identify.data import IdentData

SEG = 256


def rmse(data: IdentData, res: dict, weight: np.ndarray | None = None) -> dict:
    """{"G": float|None, "k": ..., "b0": ...} and per-axis {"G_x": ...} RMS of residuals over measured samples.

    Args:
        res: {channel: residual array} (unmeasured entries ignored via the data's masks).
        weight: optional (M, N) 0/1 sample selection.
    """
    out = {c: None for c in ("G", "k", "b0")}
    w = np.ones((data.M, data.N)) if weight is None else weight
    for c, r in res.items():
        m = data.mask(c) * (w[:, None, :] if c != "b0" else w)
        n = m.sum()
        out[c] = float(np.sqrt(np.sum((r * m) ** 2) / n)) if n > 0 else None
        if c != "b0":
            for a, ax in enumerate(AXES):
                na = m[:, a].sum()
                out[f"{c}_{ax}"] = float(np.sqrt(np.sum((r[:, a] * m[:, a]) ** 2) / na)) if na > 0 else None
    return out


def _series(data: IdentData, c: str, z: np.ndarray) -> list[np.ndarray]:
    if c == "b0":
        return [z[m] for m in range(data.M)]
    return [z[m, a] for m in range(data.M) for a in range(3) if data.axes_measured[m, a]]


def spectral_peaks(data: IdentData, c: str, z: np.ndarray, p_value: float = 1e-3, max_peaks: int = 3) -> list[dict]:
    """Significant narrow-band peaks of a whitened residual channel.

    Returns:
        [{"f_hz": peak frequency, "ratio": power / broadband level}], strongest first.
    """
    series = [s for s in _series(data, c, z) if s.size >= SEG]
    if not series:
        return []
    win = np.hanning(SEG)
    acc = np.zeros(SEG // 2 + 1)
    nseg = 0
    for s in series:
        nfull = (s.size - SEG) // (SEG // 2) + 1
        idx = np.arange(nfull)[:, None] * (SEG // 2) + np.arange(SEG)[None, :]
        segs = s[idx]
        segs = segs - segs.mean(axis=1, keepdims=True)
        acc += (np.abs(np.fft.rfft(segs * win, axis=1)) ** 2).sum(0)
        nseg += nfull
    psd = acc / nseg
    f = np.fft.rfftfreq(SEG, data.dt_s)
    use = np.arange(2, len(f) - 1)  # skip DC / lowest bin (window leakage of the mean) and Nyquist
    level = np.median(psd[use])
    if level <= 0:
        return []
    ratio = psd / level
    # Overlapping Hann segments: about 0.9 * nseg independent ones.
    dof = 2 * max(1.0, 0.9 * nseg)
    thr = stats.chi2.isf(p_value / len(use), dof) / dof
    sig = np.zeros(len(f), dtype=bool)
    sig[use] = (ratio[use] > thr) & (ratio[use] > 1.5)
    peaks = []
    i = 0
    while i < len(f):
        if sig[i]:
            j = i
            while j + 1 < len(f) and sig[j + 1]:
                j += 1
            k = i + int(np.argmax(ratio[i : j + 1]))
            peaks.append({"f_hz": float(f[k]), "ratio": float(ratio[k])})
            i = j + 1
        else:
            i += 1
    peaks.sort(key=lambda p: -p["ratio"])
    return peaks[:max_peaks]


def dependence_note(data: IdentData, zG: np.ndarray, what: str = "slew") -> str | None:
    """A note when whitened residual power grows with the demanded slew rate (``what='slew'``) or amplitude."""
    g = data.g
    x = np.abs(np.gradient(g, data.dt_s, axis=-1)) if what == "slew" else np.abs(g)
    m = np.broadcast_to(data.axes_measured[:, :, None], g.shape)
    xv, pv = x[m], (zG ** 2)[m]
    if xv.size < 100 or np.all(xv == xv.flat[0]):
        return None
    hi_thr = np.quantile(xv, 0.9)
    lo_thr = np.quantile(xv, 0.5)
    hi = pv[xv >= hi_thr]
    lo = pv[xv <= lo_thr]
    if hi.size < 10 or lo.size < 10 or hi_thr <= lo_thr:
        return None
    ratio = hi.mean() / max(lo.mean(), 1e-300)
    # Welch t-test on the powers (large samples).
    se = np.sqrt(hi.var() / hi.size + lo.var() / lo.size)
    zstat = (hi.mean() - lo.mean()) / max(se, 1e-300)
    if ratio > 2.0 and hi.mean() > 1.2 and zstat > 5:
        if what == "slew":
            return (f"residual grows with slew rate: mean power {ratio:.1f}x higher at the top 10 % of |dg/dt| "
                    f"(>= {hi_thr * 1e-3:.0f} T/m/s) than at the lower half: non-linear (e.g. slew-rate limit) or "
                    f"unmodelled fast dynamics")
        return (f"residual grows with gradient amplitude: mean power {ratio:.1f}x higher at the top 10 % of |g| "
                f"(>= {hi_thr:.1f} mT/m): amplitude-dependent (non-linear) gain or heating")
    return None
