"""Error figures and honest notes on what the residual still contains.

* :func:`rmse` — root-mean-square residual per channel (and per axis) over the measured samples.
* :func:`spectral_peaks` — narrow-band structure: the residual, whitened by the noise floor, is split
  into Hann-windowed segments of 256 samples; the averaged periodogram of each frequency bin is compared with
  the median over bins (the broadband level).  For white noise each bin is a chi-square with 2 * n_seg
  degrees of freedom (scaled); a bin is significant when its ratio exceeds the Bonferroni-corrected
  (p = 1e-3 over all bins) chi-square quantile and is at least 1.5 x the level.  Contiguous significant bins
  are merged and reported by their peak; a region whose maximum is the lowest usable bin, or that is wider
  than ``NARROW_MAX_BINS`` bins without a distinct peak, is flagged as broadband (low-frequency structure
  shaped like the waveforms' spectrum, e.g. a non-linear gain), not narrow-band.
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
#: A significant region wider than this many periodogram bins (or touching the lowest usable bin) is
#: reported as broadband structure, not as a narrow-band peak.
NARROW_MAX_BINS = 6


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
        [{"f_hz": peak frequency, "ratio": power / broadband level, "narrow": bool, "f_lo_hz", "f_hi_hz":
        extent of the significant region}], strongest first.  ``narrow`` is False for a region whose maximum
        is at the lowest usable bin, or that spans more than :data:`NARROW_MAX_BINS` bins without a peak 3x
        above its low-frequency end: broadband structure that follows the waveforms' own spectrum, which must
        not be reported as a resonance.
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
            # A region peaking at the lowest usable bin, or a wide one without a distinct peak, is broadband
            # structure (the spectrum of the waveforms themselves: a missing or non-linear effect), not a
            # resonance.
            if k == use[0]:  # rises towards DC: the low-frequency spectrum of the waveforms themselves
                narrow = False
            else:  # a distinct peak above the region's low-frequency end, or a short isolated region
                narrow = bool(ratio[k] >= 3.0 * ratio[i] or (j - i + 1) <= NARROW_MAX_BINS)
            peaks.append(
                {
                    "f_hz": float(f[k]),
                    "ratio": float(ratio[k]),
                    "narrow": bool(narrow),
                    "f_lo_hz": float(f[i]),
                    "f_hi_hz": float(f[j]),
                }
            )
            i = j + 1
        else:
            i += 1
    peaks.sort(key=lambda p: -p["ratio"])
    return peaks[:max_peaks]


def power_growth(x: np.ndarray, zG: np.ndarray, m: np.ndarray):
    """(ratio, z statistic, threshold) of the whitened residual power at the top decile of ``x`` against its
    lower half (Welch t-test on the powers), or None when undefined."""
    xv, pv = x[m], (zG**2)[m]
    if xv.size < 100 or np.all(xv == xv.flat[0]):
        return None
    hi_thr = np.quantile(xv, 0.9)
    lo_thr = np.quantile(xv, 0.5)
    hi = pv[xv >= hi_thr]
    lo = pv[xv <= lo_thr]
    if hi.size < 10 or lo.size < 10 or hi_thr <= lo_thr:
        return None
    ratio = hi.mean() / max(lo.mean(), 1e-300)
    se = np.sqrt(hi.var() / hi.size + lo.var() / lo.size)
    zstat = (hi.mean() - lo.mean()) / max(se, 1e-300)
    return ratio, zstat, hi_thr, hi.mean()


def gradient_residual(data: IdentData, res: dict, sigma: dict):
    """(residual in mT/m (M, 3, N), its white-noise level, a suffix for notes) of the gradient: the G residual
    when G is measured; else, for k-only data, the k residual differenced sample to sample and divided by
    gamma dt (the G error it implies; noise sqrt(2) sigma_k / (gamma dt), neighbours anti-correlated, which
    makes the dependence and last-ramp tests conservative); None without G or k."""
    from dtoc.constants import GAMMA_RAD_PER_S_PER_MT

    if data.G is not None:
        return res["G"], sigma["G"], ""
    if data.k is None:
        return None
    gdt = GAMMA_RAD_PER_S_PER_MT * data.dt_s
    r = np.diff(res["k"], axis=-1, prepend=0.0) / gdt
    r[..., 0] = 0.0
    return r, np.sqrt(2.0) * sigma["k"] / gdt, " (from the k residual differenced in time)"


def dependence_note(data: IdentData, zG: np.ndarray, what: str = "slew") -> str | None:
    """A note when whitened residual power grows with the demanded slew rate (``what='slew'``) or amplitude.

    Amplitude is tested both per axis (|g| of the residual's own axis: saturation, non-linear gain) and as the
    magnitude of the whole gradient vector (a field quadratic in the gradients, e.g. a concomitant field, shows
    on one axis when *other* axes are driven); the stronger significant one is reported."""
    g = data.g
    m = np.broadcast_to(data.axes_measured[:, :, None], g.shape)
    if what == "slew":
        tests = [("own", np.abs(np.gradient(g, data.dt_s, axis=-1)))]
    else:
        vec = np.sqrt((g**2).sum(axis=1, keepdims=True))
        tests = [("own", np.abs(g)), ("vector", np.broadcast_to(vec, g.shape))]
    best = None
    for name, x in tests:
        r = power_growth(x, zG, m)
        if r is None:
            continue
        ratio, zstat, hi_thr, hi_mean = r
        if ratio > 2.0 and hi_mean > 1.2 and zstat > 5 and (best is None or zstat > best[2]):
            best = (name, ratio, zstat, hi_thr)
    on_axes = []
    if what == "slew":  # which axes: the residual of each axis against its own demanded slew
        for a, ax in enumerate(AXES):
            ma = np.zeros(g.shape, dtype=bool)
            ma[:, a] = m[:, a]
            r = power_growth(tests[0][1], zG, ma)
            if r is not None and r[0] > 2.0 and r[3] > 1.2 and r[1] > 5:
                on_axes.append((ax, r))
        if best is None and on_axes:
            ax, (ratio, zstat, hi_thr, _) = max(on_axes, key=lambda t: t[1][1])
            best = ("own", ratio, zstat, hi_thr)
    if best is None:
        return None
    name, ratio, _, hi_thr = best
    if what == "slew":
        where = " on " + ", ".join(ax for ax, _ in on_axes) if on_axes and len(on_axes) < 3 else ""
        return (
            f"residual grows with slew rate{where}: mean power {ratio:.1f}x higher at the top 10 % of |dg/dt| "
            f"(>= {hi_thr * 1e-3:.0f} T/m/s) than at the lower half: non-linear (e.g. slew-rate limit) or "
            f"unmodelled fast dynamics"
        )
    if name == "vector":
        return (
            f"residual grows with gradient amplitude: mean power {ratio:.1f}x higher at the top 10 % of the "
            f"gradient vector magnitude |g| (>= {hi_thr:.1f} mT/m) than at the lower half, also where the own "
            "axis is not driven: a field quadratic in the gradients (concomitant field) or a non-linear cross term"
        )
    return (
        f"residual grows with gradient amplitude: mean power {ratio:.1f}x higher at the top 10 % of |g| "
        f"(>= {hi_thr:.1f} mT/m): amplitude-dependent (non-linear) gain, amplifier saturation or heating"
    )


#: Samples closer than this to a corner of the demand are left out of the hysteresis test: a linear
#: transient (resonance, fast eddy current) left in the residual decays within it, a hysteresis offset does not.
REST_GUARD_S = 0.5e-3
#: Smallest up/down difference of the rest residual, in noise floors, worth a note.
DIRECTION_MIN_SIGMA = 0.5


def _far_from_corners(g: np.ndarray, guard: float) -> np.ndarray:
    from dtoc.identify.noise import quiet_samples

    return quiet_samples(g, guard=int(np.ceil(guard)))


def last_ramp_direction(g: np.ndarray) -> np.ndarray:
    """(..., N) sign (+1 / -1, 0 before the first ramp) of the most recent non-zero slope of ``g``."""
    d = np.sign(np.diff(np.asarray(g, dtype=np.float64), axis=-1, prepend=0.0))
    d[..., 0] = np.sign(np.asarray(g)[..., 0])
    idx = np.where(d != 0, np.arange(d.shape[-1]), 0)
    np.maximum.accumulate(idx, axis=-1, out=idx)
    out = np.take_along_axis(d, idx, axis=-1)
    return out


def direction_note(data: IdentData, res_G: np.ndarray, sigma_G: float, quiet: np.ndarray) -> str | None:
    """A note when the residual at zero demand depends on the direction of the last ramp (a hysteresis-like
    memory of the amplifier / iron, which no effect of the library describes).

    Compares the mean G residual (mT/m) on samples where the demand is zero and that are away from corners
    (``quiet`` (M, 3, N)) after up-ramps with that after down-ramps (at zero demand an amplitude-dependent
    gain leaves nothing, so the two are told apart); reported when the difference exceeds 0.5 x the noise floor and
    is significant (z > 5 against white noise of ``sigma_G``).
    """
    s = last_ramp_direction(data.g)
    quiet = quiet & _far_from_corners(data.g, REST_GUARD_S / data.dt_s)
    rest = np.abs(data.g) <= 1e-9 * max(float(np.max(np.abs(data.g))), 1e-300)
    use = quiet & rest & np.broadcast_to(data.axes_measured[:, :, None], data.g.shape)
    up, dn = use & (s > 0), use & (s < 0)
    n1, n2 = int(up.sum()), int(dn.sum())
    if n1 < 100 or n2 < 100:
        return None
    m1, m2 = float(res_G[up].mean()), float(res_G[dn].mean())
    diff = m1 - m2
    z = abs(diff) / (sigma_G * np.sqrt(1.0 / n1 + 1.0 / n2))
    if abs(diff) > DIRECTION_MIN_SIGMA * sigma_G and z > 5:
        return (
            f"residual at zero demand depends on the direction of the last ramp ({m1:+.3g} mT/m after "
            f"up-ramps, {m2:+.3g} mT/m after down-ramps, z = {z:.0f}): a memory the model lacks, "
            f"hysteresis-like (not in the library) or a slow linear transient (time constant > "
            f"{REST_GUARD_S * 1e3:g} ms) that no added effect captured"
        )
    return None
