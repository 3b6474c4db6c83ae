"""Where the remaining error's energy is: frequency band, time window, demanded amplitude / slew, axis.

The final residual of each measured channel is split into its white-noise part (``n sigma^2`` expected over
``n`` measured samples, ``sigma`` the noise floor) and the *excess* above it.  The excess is then
distributed (each share = energy in the part minus that part's expected noise energy, divided by the
total excess; the shares of a partition add up to 1, a share can be slightly negative by noise):

* **frequency**: the periodogram of every measured series over its full length (Parseval-normalised; the
  white noise contributes ``sigma^2`` per one-sided bin pair), cumulated from DC; reported as the share
  below the smallest of the edges 0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50 kHz that holds at least half of the
  excess ("65 % below 2 kHz"), and the frequency band that holds 90 % of it;
* **time window**: before the first demanded gradient, during demanded gradients (any axis non-zero),
  between them (zero demand), after the last demanded gradient;
* **demand**: the share at the top 10 % of the demanded |g| and of the demanded |dg/dt| on the residual's
  own axis (10 % of the samples: a share well above 10 % means the error grows with amplitude / slew);
* **axis**: the share per measured axis (G and k channels).

Used by :func:`dtoc.identify.search.identify` for one note per channel (``remaining``) and the report's
``residual_energy`` extra.  Shares are of the channel as measured (a k error integrates G: a G error during
a gradient leaves a constant k error after it).
"""

from __future__ import annotations

import numpy as np

from dtoc.constants import AXES
from dtoc.identify.data import IdentData

#: Band edges (Hz) the frequency share is reported against.
EDGES_HZ = (100.0, 200.0, 500.0, 1e3, 2e3, 5e3, 10e3, 20e3, 50e3, 100e3, 200e3)
#: The excess must exceed this many standard deviations of the noise energy (sqrt(2 n) sigma^2) and this
#: fraction of the total energy to be described.
MIN_EXCESS_Z = 5.0
MIN_EXCESS_FRACTION = 0.02


def _windows(g: np.ndarray) -> dict:
    """(M, N) boolean masks of the time windows of each waveform (demand on any axis)."""
    active = np.any(np.abs(g) > 1e-9 * max(float(np.max(np.abs(g))), 1e-300), axis=1)  # (M, N)
    M, N = active.shape
    idx = np.arange(N)[None, :]
    first = np.where(active.any(1), active.argmax(1), N)[:, None]
    last = np.where(active.any(1), N - 1 - active[:, ::-1].argmax(1), -1)[:, None]
    return {
        "before the first demanded gradient": idx < first,
        "during demanded gradients": active,
        "between demanded gradients (zero demand)": (~active) & (idx > first) & (idx < last),
        "after the last demanded gradient": idx > last,
    }


def describe(data: IdentData, c: str, res: np.ndarray, sigma: float) -> dict | None:
    """The excess energy of channel ``c``'s residual ``res`` by frequency, time window, demand and axis.

    Returns:
        None when the excess is not significant, else {"rms", "excess_fraction" (of the total energy),
        "below_hz": (edge, share), "band_90_hz": (lo, hi), "windows": {name: share}, "top_amplitude",
        "top_slew" (shares at the top 10 % of |g| / |dg/dt|), "axes": {axis: share}}.
    """
    mk = data.mask(c)
    g = data.g
    if c == "b0":
        series = [(res[m] * mk[m], mk[m], None, m) for m in range(data.M) if mk[m].any()]
    else:
        series = [(res[m, a] * mk[m, a], mk[m, a], a, m) for m in range(data.M) for a in range(3) if mk[m, a].any()]
    if not series:
        return None
    s2 = sigma**2
    n = float(sum(w.sum() for _, w, _, _ in series))
    E = float(sum(np.sum(r**2) for r, _, _, _ in series))
    En = n * s2
    Ex = E - En
    if not (Ex > MIN_EXCESS_Z * np.sqrt(2.0 * n) * s2 and Ex > MIN_EXCESS_FRACTION * E):
        return None
    N = data.N
    f = np.fft.rfftfreq(N, data.dt_s)
    wgt = np.full(f.size, 2.0)
    wgt[0] = 1.0
    if N % 2 == 0:
        wgt[-1] = 1.0
    spec = np.zeros(f.size)
    noise_spec = np.zeros(f.size)
    for r, w, _, _ in series:
        spec += wgt * np.abs(np.fft.rfft(r)) ** 2 / N
        noise_spec += wgt * s2 * w.sum() / N
    cum = np.cumsum(spec - noise_spec) / Ex
    below = None
    for e in EDGES_HZ:
        if e >= f[-1]:
            break
        share = float(cum[np.searchsorted(f, e, side="right") - 1])
        if share >= 0.5:
            below = (e, share)
            break
    lo_i = int(np.searchsorted(cum, 0.05))
    hi_i = int(min(np.searchsorted(cum, 0.95), f.size - 1))
    win = _windows(g)
    windows = {}
    for name, wm in win.items():
        e_w = 0.0
        n_w = 0.0
        for r, w, _, m in series:
            e_w += float(np.sum((r**2)[wm[m]]))
            n_w += float(w[wm[m]].sum())
        windows[name] = (e_w - n_w * s2) / Ex
    out = {
        "rms": float(np.sqrt(E / n)),
        "excess_fraction": Ex / E,
        "below_hz": below,
        "band_90_hz": (float(f[lo_i]), float(f[hi_i])),
        "windows": windows,
    }
    if c != "b0":
        slew = np.abs(np.gradient(g, data.dt_s, axis=-1))
        for key, x in (("top_amplitude", np.abs(g)), ("top_slew", slew)):
            vals = np.concatenate([x[m, a][w > 0] for _, w, a, m in series])
            thr = np.quantile(vals, 0.9)
            if thr <= 0:
                out[key] = None
                continue
            e_t = n_t = 0.0
            for r, w, a, m in series:
                sel = x[m, a] >= thr
                e_t += float(np.sum((r**2)[sel]))
                n_t += float(w[sel].sum())
            out[key] = (e_t - n_t * s2) / Ex
        axes = {}
        for a, ax in enumerate(AXES):
            e_a = sum(float(np.sum(r**2)) for r, _, aa, _ in series if aa == a)
            n_a = sum(float(w.sum()) for _, w, aa, _ in series if aa == a)
            if n_a > 0:
                axes[ax] = (e_a - n_a * s2) / Ex
        out["axes"] = axes
    return out


def _pct(x: float) -> str:
    return f"{100.0 * x:.0f} %"


def note(c: str, d: dict, unit: str) -> str:
    """One line describing :func:`describe`'s result for channel ``c``."""
    parts = [
        f"remaining {c} error {d['rms']:.3g} {unit} RMS, {_pct(d['excess_fraction'])} of its energy above the noise floor; of that excess:"
    ]
    if d["below_hz"] is not None:
        e, share = d["below_hz"]
        parts.append(f"{_pct(share)} below {e / 1e3:g} kHz,")
    lo, hi = d["band_90_hz"]
    parts.append(f"90 % within {lo / 1e3:.2g}-{hi / 1e3:.3g} kHz;")
    wins = sorted(((v, k) for k, v in d["windows"].items() if v >= 0.1), reverse=True)
    parts.append(", ".join(f"{_pct(v)} {k}" for v, k in wins) + ";" if wins else "no time window dominates;")
    # the windows partition the samples, so their shares of the excess sum to 100 %: a window with less
    # energy than the noise floor predicts has a negative share, named so that the shown ones add up
    below = sorted((v, k) for k, v in d["windows"].items() if v <= -0.1)
    if below:
        names = ", ".join(f"{_pct(v)} {k}" for v, k in below)
        parts.append(f"{names} (less energy than the noise floor predicts there; the shares sum to 100 %);")
    dem = []
    for key, what in (("top_amplitude", "|g|"), ("top_slew", "|dg/dt|")):
        v = d.get(key)
        if v is not None and v >= 0.2:
            dem.append(f"{_pct(v)} at the top 10 % of the demanded {what}")
    if dem:
        parts.append(", ".join(dem) + ";")
    if d.get("axes") and len(d["axes"]) > 1:
        parts.append("by axis " + " / ".join(f"{ax} {_pct(v)}" for ax, v in d["axes"].items()))
    return " ".join(parts).rstrip(";")
