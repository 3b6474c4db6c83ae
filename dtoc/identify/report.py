"""The identify report: JSON (docs/contracts.md §3 plus extras), a rich table, a PNG of residuals.

JSON keys (minimum, exactly as the contract): ``before``, ``after``, ``heldout_before``, ``heldout_after``
(each {"G_rmse", "k_rmse", "b0_rmse"}, null for unmeasured channels), ``noise`` ({"G", "k", "b0"}),
``effects`` (kind, axis, input_axis, params, stderr, score; in the order added), ``explained``,
``remaining``.  Extras: ``relative_to_noise`` (every rmse divided by its noise floor), ``per_axis``
(rmse per axis), ``noise_method``, ``heldout`` (how folds were made), ``declared`` (description),
``screening`` (top candidates per round with their scores), ``n_samples``, ``dtoc_version``, ``adopted``
(true when the updated model holds at least one found effect and was therefore written), ``rejected`` (effects
the adoption gate removed: name, kind, axes, params, score, reasons; docs/identify.md), ``residual_energy``
(per channel: where the final residual's energy above the noise floor is, :mod:`dtoc.identify.energy`).
Units: G mT/m, k rad/m, b0 uT; scores in chi-square units (held-out BIC decrease).
"""

from __future__ import annotations

import json
import math

import numpy as np

from dtoc.constants import AXES
from dtoc.identify.candidates import lti_features, lti_physical_text
from dtoc.identify.kinds import effect_name
from dtoc.identify.search import IdentifyResult, rejected_line
from dtoc.util.figures import png_bytes
from dtoc.version import __version__

CH = ("G", "k", "b0")
UNITS = {"G": "mT/m", "k": "rad/m", "b0": "uT"}


def _num(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _rm(d: dict) -> dict:
    return {f"{c}_rmse": _num(d.get(c)) for c in CH}


def _effect_entry(f) -> dict:
    e = f.effect
    params = e.params_dict()
    entry = {
        "kind": e.kind,
        "axis": e.axis,
        "input_axis": e.input_axis,
        "params": params,
        "stderr": {k: (v if isinstance(v, list) else _num(v)) for k, v in f.stderr.items()},
        "score": _num(f.score),
    }
    if e.kind == "lti":
        feats = (f.notes or {}).get("features")
        if feats is None:
            taps = np.asarray(params["taps"], dtype=np.float64).reshape(-1)
            feats = lti_features(taps, int(round(params["t0_s"] / params["dt_s"])), params["dt_s"])
        entry["features"] = feats
    return entry


def _energy_entry(d: dict) -> dict:
    """JSON form of :func:`dtoc.identify.energy.describe` (shares of the energy above the noise floor)."""
    below = d.get("below_hz")
    return {
        "rms": _num(d["rms"]),
        "excess_fraction": _num(d["excess_fraction"]),
        "below_hz": None if below is None else {"edge_hz": _num(below[0]), "share": _num(below[1])},
        "band_90_hz": [_num(x) for x in d["band_90_hz"]],
        "windows": {k: _num(v) for k, v in d["windows"].items()},
        "top_amplitude": _num(d.get("top_amplitude")),
        "top_slew": _num(d.get("top_slew")),
        "axes": {k: _num(v) for k, v in (d.get("axes") or {}).items()},
    }


def report_dict(r: IdentifyResult) -> dict:
    """The JSON report as a dict (deterministic for deterministic inputs)."""
    noise = {c: (_num(r.noise[c].sigma) if c in r.noise else None) for c in CH}
    rel = {}
    for name, d in (
        ("before", r.before),
        ("after", r.after),
        ("heldout_before", r.heldout_before),
        ("heldout_after", r.heldout_after),
    ):
        rel[name] = {c: (_num(d[c] / noise[c]) if d.get(c) is not None and noise[c] else None) for c in CH}
    per_axis = {}
    for name, d in (("before", r.before), ("after", r.after), ("heldout_after", r.heldout_after)):
        per_axis[name] = {
            f"{c}_{ax}": _num(d.get(f"{c}_{ax}")) for c in ("G", "k") for ax in AXES if d.get(f"{c}_{ax}") is not None
        }
    return {
        "before": _rm(r.before),
        "after": _rm(r.after),
        "heldout_before": _rm(r.heldout_before),
        "heldout_after": _rm(r.heldout_after),
        "noise": noise,
        "effects": [_effect_entry(f) for f in r.twin.found],
        "explained": bool(r.explained),
        "remaining": list(r.remaining),
        "relative_to_noise": rel,
        "per_axis": per_axis,
        "noise_method": {c: r.noise[c].method for c in r.noise},
        "heldout": r.folds.describe(),
        "declared": r.twin.declared.description
        or ("ideal hardware" if not r.twin.declared.effects else "declared model"),
        "screening": [[{"candidate": n, "score": s} for n, s in rnd] for rnd in r.history],
        "n_samples": int(sum(np.sum(r.data.mask(c) > 0) for c in r.data.channels())),
        "adopted": bool(r.adopted),
        "residual_energy": {c: _energy_entry(v) for c, v in r.energy.items()},
        "rejected": [{**x, "params": {k: v for k, v in x["params"].items() if k != "taps"}} for x in r.rejected],
        "dtoc_version": __version__,
    }


def report_json(r: IdentifyResult) -> str:
    return json.dumps(report_dict(r), indent=2, sort_keys=False) + "\n"


def _fmt_params(entry: dict) -> str:
    parts = []
    for k, v in entry["params"].items():
        if isinstance(v, list):
            continue
        if entry["kind"] == "lti" and k in ("dt_s", "t0_s"):
            continue
        se = entry["stderr"].get(k)
        parts.append(f"{k}={v:.6g}" + (f" ± {se:.2g}" if isinstance(se, float) else ""))
    if entry["kind"] == "lti":
        ft = entry["features"]
        n = len(np.asarray(entry["params"]["taps"]).reshape(-1))
        parts.append(
            f"{n} taps; {lti_physical_text(ft)}; peak |dH|={ft['peak_abs']:.3g} at {ft['peak_hz'] / 1e3:.2f} kHz"
        )
    return ", ".join(parts)


def print_table(r: IdentifyResult, console=None) -> None:
    """Rich tables on stdout: errors before/after (absolute and x noise), effects found, verdict."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    con = console or Console(highlight=False)
    d = report_dict(r)
    t = Table(title=f"dtoc identify — residual vs {d['declared']} ({d['heldout']})")
    for col in ("channel", "noise", "before", "after", "held-out before", "held-out after"):
        t.add_column(col, justify="right" if col != "channel" else "left")
    for c in r.data.channels():
        n = d["noise"][c]

        def cell(key, c=c, n=n):
            v = d[key][f"{c}_rmse"]
            return "—" if v is None else f"{v:.4g} ({v / n:.2f}x)"

        t.add_row(
            f"{c} ({UNITS[c]})",
            f"{n:.3g}",
            cell("before"),
            cell("after"),
            cell("heldout_before"),
            cell("heldout_after"),
        )
    con.print(t)
    for c in r.data.channels():
        con.print(
            f"noise floor {c}: {d['noise_method'][c]}; values in brackets are multiples of it",
            markup=False,
            soft_wrap=True,
        )
    e = Table(title="effects added (in order)")
    for col in ("#", "kind", "axis", "input", "parameters ± stderr", "score"):
        e.add_column(col)
    for i, entry in enumerate(d["effects"]):
        axis = "b0" if entry["kind"].startswith("b0_eddy") else (entry["axis"] or "all")
        e.add_row(
            str(i + 1),
            entry["kind"],
            axis,
            str(entry["input_axis"] or "—"),
            escape(_fmt_params(entry)),
            f"{entry['score']:.4g}",
        )
    if not d["effects"]:
        e.add_row("—", "none", "", "", "no candidate is both significant and adopted", "")
    con.print(e)
    adopted_names = {effect_name(f.effect) for f in r.twin.found}
    for x in r.rejected:
        con.print(rejected_line(x, adopted_names), markup=False, soft_wrap=True)
    if not d["adopted"]:
        con.print(
            "no updated model: nothing beyond the declared model is supported by the data (no model file written)"
        )
    con.print(f"explained: {'yes' if d['explained'] else 'NO'}")
    for note in d["remaining"]:
        con.print(f"  - {note}", markup=False, soft_wrap=True)  # one line per note (grep-able)


def _psd(x: np.ndarray, dt_s: float, seg: int = 512):
    """Welch PSD (Hann, 50 % overlap) averaged over the leading axes of x (..., N); units^2/Hz."""
    x2 = x.reshape(-1, x.shape[-1])
    seg = min(seg, x2.shape[-1])
    win = np.hanning(seg)
    acc = np.zeros(seg // 2 + 1)
    n = 0
    for row in x2:
        if not np.any(row):
            continue
        for s in range(0, row.size - seg + 1, seg // 2):
            acc += np.abs(np.fft.rfft(row[s : s + seg] * win)) ** 2
            n += 1
    f = np.fft.rfftfreq(seg, dt_s)
    scale = 2.0 * dt_s / np.sum(win**2)
    return f, acc * scale / max(n, 1)


def _rows(r: IdentifyResult) -> list:
    """Plot rows: (channel, axis index or None, label) for every measured channel and axis."""
    rows = []
    for c in r.data.channels():
        if c == "b0":
            rows.append((c, None, "b0"))
        else:
            rows += [(c, a, f"{c} {AXES[a]}") for a in range(3) if r.data.axes_measured[:, a].any()]
    return rows


def residual_png(r: IdentifyResult) -> bytes:
    """PNG bytes of the residuals before (declared model) and after (updated model), one row per measured
    channel and axis: (1) time course of the waveform with the largest residual on that axis, before and
    after; (2) the same after only, zoomed, with the +-noise floor band; (3) Welch PSD of the residual over
    all measured waveforms, before and after, with the white-noise level of the noise floor."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = _rows(r)
    fig, axs = plt.subplots(len(rows), 3, figsize=(15, 2.6 * len(rows) + 0.8), squeeze=False)
    t_ms = np.arange(r.data.N) * r.data.dt_s * 1e3
    for i, (c, a, lab) in enumerate(rows):
        rb, ra = r.residual_before[c], r.residual_after[c]
        if a is not None:
            rb, ra = rb[:, a], ra[:, a]
            ok = r.data.axes_measured[:, a]
        else:
            ok = np.ones(r.data.M, dtype=bool)
        s = r.noise[c].sigma
        u = UNITS[c]
        energy = np.where(ok, (rb**2).sum(-1), -1.0)
        m = int(np.argmax(energy))
        ax = axs[i, 0]
        ax.plot(t_ms, rb[m], lw=0.7, color="tab:red", label="before (declared)")
        ax.plot(t_ms, ra[m], lw=0.7, color="tab:blue", label="after (updated)")
        ax.set_xlabel("t [ms]")
        ax.set_ylabel(f"{lab} residual [{u}]")
        same = bool(np.array_equal(rb[ok], ra[ok]))
        ax.set_title(
            f"{lab}: measured - predicted, waveform {r.data.labels[m]}" + (" (after = before)" if same else ""),
            fontsize=9,
        )
        ax.legend(fontsize=7, loc="upper right")
        ax = axs[i, 1]
        ax.plot(t_ms, ra[m], lw=0.6, color="tab:blue", label="after")
        ax.axhspan(-s, s, color="0.75", alpha=0.6, label=f"±noise floor ({s:.3g} {u})")
        ax.set_xlabel("t [ms]")
        ax.set_ylabel(f"{lab} residual [{u}]")
        ax.set_title(f"{lab}: after, zoomed (rms {np.sqrt(np.mean(ra[ok] ** 2)):.3g} {u})", fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
        ax = axs[i, 2]
        fb, pb = _psd(rb[ok], r.data.dt_s)
        fa, pa = _psd(ra[ok], r.data.dt_s)
        ax.semilogy(fb / 1e3, np.maximum(pb, 1e-300), lw=0.8, color="tab:red", label="before")
        ax.semilogy(fa / 1e3, np.maximum(pa, 1e-300), lw=0.8, color="tab:blue", label="after")
        ax.axhline(2.0 * s * s * r.data.dt_s, color="k", ls="--", lw=0.8, label="white noise at the floor")
        ax.set_xlabel("f [kHz]")
        ax.set_ylabel(f"PSD [({u})²/Hz]")
        ax.set_title(f"{lab}: residual spectrum (all waveforms)", fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    verdict = (
        "explained (held-out residual consistent with noise)"
        if r.explained
        else "NOT explained: " + "; ".join(n[:90] for n in r.remaining[:2])
    )
    found = ", ".join(effect_name(f.effect) for f in r.twin.found) or "none"
    fig.suptitle(f"dtoc identify residuals: effects added: {found}\n{verdict}", fontsize=10)
    return png_bytes(fig, dpi=80)
