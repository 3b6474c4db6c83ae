"""What the measured waveforms can separate: axis labels, degenerate pairs, and stability across folds.

Three tests of the found model, each a reason not to adopt an effect (docs/identify.md, step 5b):

1. **Axis labels** (:func:`label_problems`, a profile-likelihood test): an eddy-current effect names the axis
   whose slew drives it (``cross_eddy[y]<-x``; ``exp_eddy[y]`` is driven by y itself; ``b0_eddy<-z``).  The
   effect is swapped for each alternative with another driving axis (``cross_eddy[y]<-z``, ``exp_eddy[y]``;
   ``b0_eddy<-x``) and all parameters are refitted.  When an alternative fits within ``threshold``
   chi-square units of the found one, the data cannot tell the axes apart and the label would be a
   tie-break: the effect is not adopted, and the report names the alternatives and why (e.g. the axes
   played identical waveforms).
2. **Degenerate pairs** (:func:`redundancy_problems`): an effect whose parameters are strongly correlated
   (|r| >= :data:`DEGENERATE_CORR` in the joint fit's covariance) with another effect's is removed and the
   rest refitted; if the chi-square then rises by no more than ``threshold + p ln n`` (the search's own
   criterion for adding it), the effect is not needed beside its partner and is not adopted, and the report
   names the degeneracy (e.g. a measurement clock error and gains on k-space data).
3. **Stability** (:func:`stability_problems`): every scalar parameter is estimated on each held-out fold's
   *test* samples alone (disjoint data: waveforms, or time windows of a single waveform), with its standard
   error; when the fold estimates disagree beyond their errors (chi-square homogeneity test,
   p < :data:`STABILITY_P`) and by more than :data:`STABILITY_REL` of the parameter's size, the parameter
   describes different things in different parts of the data and is not adopted.  Effects on an axis that
   also carries an ``lti`` filter are exempt (the taps are not re-solved per fold, so a parameter the filter
   can trade with, e.g. a delay, would be forced to absorb the difference); the filter and they passed the
   held-out score together.
"""

from __future__ import annotations

import copy
import math

import numpy as np
from scipy import stats

from dtoc.constants import AXES
from dtoc.hardware.model import build_effect
from dtoc.identify.kinds import effect_name
from dtoc.identify.twin import Found, Twin

#: |correlation| of two effects' parameters above which they are tested for redundancy.
DEGENERATE_CORR = 0.8
#: Homogeneity p-value below which fold estimates disagree.
STABILITY_P = 1e-3
#: ... and the smallest disagreement (max |fold - mean| over |value - neutral|) that matters.
STABILITY_REL = 0.1


def alternatives(e) -> list[tuple[str, str | None, str | None]]:
    """(kind, axis, input_axis) of the effects that differ from ``e`` only in the axis driving them."""
    if e.kind == "cross_eddy":
        out = [("exp_eddy", e.axis, None)]
        return out + [("cross_eddy", e.axis, a) for a in AXES if a not in (e.axis, e.input_axis)]
    if e.kind == "exp_eddy" and e.axis is not None:
        return [("cross_eddy", e.axis, a) for a in AXES if a != e.axis]
    if e.kind == "b0_eddy":
        return [("b0_eddy", None, a) for a in AXES if a != e.input_axis]
    return []


def driving_axis(kind: str, axis, input_axis) -> str | None:
    return axis if kind == "exp_eddy" else input_axis


def _alt_name(kind, axis, input_axis) -> str:
    s = kind + (f"[{axis}]" if axis else "") + (f"<-{input_axis}" if input_axis else "")
    return s


def slew_similarity(g: np.ndarray, axes_: list[str]) -> str:
    """Why the driving axes ``axes_`` are hard to tell apart, from the demanded slews of all waveforms."""
    idx = [AXES.index(a) for a in axes_]
    d = np.diff(g, axis=-1)
    pairs = []
    for i in range(len(idx)):
        for j in range(i + 1, len(idx)):
            a, b = d[:, idx[i]].reshape(-1), d[:, idx[j]].reshape(-1)
            na, nb = float(np.sqrt(a @ a)), float(np.sqrt(b @ b))
            if na == 0 or nb == 0:
                pairs.append((idx[i], idx[j], None))
                continue
            pairs.append((idx[i], idx[j], float(a @ b) / (na * nb)))
    same = all(r is not None and abs(r) > 0.999 for _, _, r in pairs)
    names = sorted(axes_, key=AXES.index)
    who = "the three axes" if len(names) == 3 else " and ".join(f"{a}" for a in names) + " axes"
    if same:
        return f"{who} played identical waveforms (up to scale); play test waveforms on one axis at a time"
    if any(r is None for _, _, r in pairs):
        idle = [AXES[i] for i in idx if not np.any(d[:, i])]
        return f"the {'/'.join(idle)} axis played no gradient; play test waveforms on every axis, one at a time"
    rs = ", ".join(f"{AXES[i]}/{AXES[j]} {r:+.2f}" for i, j, r in pairs)
    return f"the demanded slews of these axes are too alike here (correlation {rs}); play test waveforms on one axis at a time"


def _snapshot(twin: Twin):
    return list(twin.found), [copy.deepcopy(f.effect.state_dict()) for f in twin.found]


def _restore(twin: Twin, snap) -> None:
    order, state = snap
    twin.found[:] = order
    for f, st in zip(twin.found, state):
        f.effect.load_state_dict(st)


#: An alternative whose best-scaled contribution misses the found effect's by more than this many times the
#: threshold (chi-square units) is not refitted: a refit of the other parameters cannot close such a gap.
PRESCREEN_FACTOR = 25.0


def _whitened(twin: Twin, pred) -> np.ndarray:
    """The prediction as one whitened vector over the measured channels (what the refit's chi-square sees)."""
    from dtoc.identify.data import integrate_k

    d = twin.data
    parts = []
    for c in d.channels():
        if c == "G":
            x = pred.G
        elif c == "k":
            x = integrate_k(pred.G, d.dt_s)
        else:
            x = pred.b0
        parts.append((x * d.mask(c) / twin.sigma[c]).reshape(-1))
    return np.concatenate(parts)


def _gap(twin: Twin, i: int, alt: Found) -> float:
    """min over a of || c_found - a c_alt ||^2 (whitened): how far the alternative's contribution, at the found
    effect's parameters and best scale, is from the found effect's own."""
    others = [f for j, f in enumerate(twin.found) if j != i]
    base = _whitened(twin, twin.predict(include=others))
    cf = _whitened(twin, twin.predict()) - base
    ca = _whitened(twin, twin.predict(include=[*others[:i], alt, *others[i:]])) - base
    den = float(ca @ ca)
    a = float(cf @ ca) / den if den > 0 else 0.0
    r = cf - a * ca
    return float(r @ r)


def label_problems(twin: Twin, chi2: float, threshold: float) -> list[tuple[int, str, list[str]]]:
    """[(index, reason, names to exclude from further search)] for effects whose driving axis the data cannot
    tell (module docstring, test 1).  Alternatives whose contribution at the found parameters is far from the
    found effect's (:data:`PRESCREEN_FACTOR`) are not refitted.  The twin is left as it was."""
    out = []
    snap = _snapshot(twin)
    for i, f in enumerate(list(twin.found)):
        alts = alternatives(f.effect)
        if not alts:
            continue
        params = {k: v for k, v in f.effect.params_dict().items()}
        ties = []
        for kind, axis, inp in alts:
            try:
                eff = build_effect(kind, params, axis=axis, input_axis=inp)
            except Exception:  # noqa: BLE001 - an alternative that cannot be built is no alternative
                continue
            alt = Found(eff, f.score, f.position)
            if _gap(twin, i, alt) > PRESCREEN_FACTOR * threshold:
                continue
            twin.found[i] = alt
            try:
                chi_alt = twin.refit(max_iter=10)["chi2"]
            finally:
                _restore(twin, snap)
            if chi_alt <= chi2 + threshold:
                ties.append((_alt_name(kind, axis, inp), chi_alt - chi2, driving_axis(kind, axis, inp)))
        if ties:
            drivers = [driving_axis(f.effect.kind, f.effect.axis, f.effect.input_axis)] + [t[2] for t in ties]
            drivers = [a for a in dict.fromkeys(drivers) if a is not None]
            alt_txt = ", ".join(f"{n} (chi-square {d:+.1f})" for n, d, _ in ties)
            reason = (
                f"{effect_name(f.effect)}: not identifiable from these waveforms: {alt_txt} fit as well "
                f"(within {threshold:g}), so the axis driving it cannot be named; {slew_similarity(twin.data.g, drivers)}"
            )
            out.append((i, reason, [n for n, _, _ in ties]))
    return out


def _corr(cov: np.ndarray) -> np.ndarray:
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    with np.errstate(invalid="ignore"):
        return cov / d[:, None] / d[None, :]


def redundancy_problems(twin: Twin, fit: dict, threshold: float, n_samples: int) -> list[tuple[int, str]]:
    """[(index, reason)] for effects not needed beside a strongly correlated partner (module docstring, test 2);
    at most one (the least needed).  The twin is left as it was."""
    free = fit.get("free") or []
    cov = fit.get("cov_u")
    if cov is None or len(free) < 2 or not np.all(np.isfinite(np.diag(cov))):
        return []
    C = _corr(cov)
    partner: dict[int, tuple[float, int]] = {}
    for a, (i, _, _) in enumerate(free):
        for b, (j, _, _) in enumerate(free):
            if i == j or not np.isfinite(C[a, b]):
                continue
            if abs(C[a, b]) >= DEGENERATE_CORR and abs(C[a, b]) > abs(partner.get(i, (0.0, -1))[0]):
                partner[i] = (float(C[a, b]), j)
    if not partner:
        return []
    snap = _snapshot(twin)
    best = None
    for i, (r, j) in partner.items():
        p = sum(1 for (k, _, _) in free if k == i)
        twin.found.pop(i)
        try:
            chi_wo = twin.refit(max_iter=10)["chi2"]
        finally:
            _restore(twin, snap)
        margin = chi_wo - fit["chi2"] - p * math.log(max(n_samples, 2))
        if margin <= threshold and (best is None or margin < best[0]):
            best = (margin, i, j, r, chi_wo - fit["chi2"], p)
    if best is None:
        return []
    _, i, j, r, d, p = best
    if d < 0:  # the reduced model fits better: the joint fit with it had stalled (the gate refits without it)
        change = (
            f"without it the refitted model fits better (chi-square lower by {-d:.1f}): the joint fit with it had "
            "stalled; the rest is refitted from the reduced model"
        )
    else:
        change = f"without it the chi-square rises by only {d:.1f} (<= {threshold:g} + {p} ln n)"
    return [
        (
            i,
            f"{effect_name(twin.found[i].effect)}: not needed beside {effect_name(twin.found[j].effect)}: the two "
            f"are nearly degenerate on these waveforms (parameter correlation {r:+.2f}); {change}",
        )
    ]


def stability_problems(twin: Twin, fit: dict, est: np.ndarray, se: np.ndarray) -> list[tuple[int, str]]:
    """[(index, reason)] for scalar parameters whose per-fold estimates ``est`` (K, p) (in the refit's
    transformed units, standard errors ``se`` (K, p)) disagree (module docstring, test 3)."""
    from dtoc.identify.adopt import NEUTRAL, UNSIZED

    out = []
    free = fit.get("free") or []
    u = fit.get("u")
    lti_axes = {f.effect.axis for f in twin.found if f.effect.kind == "lti"}
    for k, (i, n, t) in enumerate(free):
        e = twin.found[i].effect
        if (e.kind, n) in UNSIZED or e.kind == "lti" or (lti_axes and (e.axis in lti_axes or e.axis is None)):
            continue
        ok = np.isfinite(est[:, k]) & np.isfinite(se[:, k]) & (se[:, k] > 0)
        if ok.sum() < 2:
            continue
        x, s = est[ok, k], se[ok, k]
        w = 1.0 / s**2
        mean = float(np.sum(w * x) / np.sum(w))
        Q = float(np.sum(w * (x - mean) ** 2))
        p = float(stats.chi2.sf(Q, ok.sum() - 1))
        val = lambda uu, t=t: math.exp(uu) if t == "log" else (uu * twin.data.dt_s if t == "dt" else uu)  # noqa: E731
        v = val(float(u[k]))
        size = abs(v - NEUTRAL.get((e.kind, n), 0.0))
        vals = np.array([val(float(xx)) for xx in x])
        ses = np.array([abs(val(float(xx) + ss) - val(float(xx))) for xx, ss in zip(x, s)])
        spread = float(np.max(np.abs(vals - v)))
        if p < STABILITY_P and spread > STABILITY_REL * size:
            fo = ", ".join(f"{a:.4g} ± {b:.2g}" for a, b in zip(vals, ses))
            out.append(
                (
                    i,
                    f"{effect_name(e)}: {n} is not stable across the held-out folds ({fo} on the {len(vals)} folds' own "
                    f"samples; homogeneity p = {p:.1g}): it describes different things in different parts of the data",
                )
            )
    return out
