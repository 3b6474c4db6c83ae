"""`identify`: residual of the declared model -> trace to missing effects -> updated model and report.

Algorithm (forward stepwise selection with a held-out information criterion):

1. Predict the measurement with the declared model (none: ideal hardware) and estimate each channel's
   noise floor (:mod:`dtoc.identify.noise`) unless ``sigma_*`` is given.
2. Screen every candidate of the library (:mod:`dtoc.identify.candidates`) against the current residual:
   linearised / exact-grid fit on each fold's training units, chi-square on its test units, score =
   held-out chi-square decrease - n_params ln(n).
3. If the best score exceeds ``threshold`` (default 10), add that effect, refit every found parameter
   jointly through the differentiable twin (:class:`dtoc.identify.twin.Twin`), confirm that the full-data
   chi-square dropped by more than the threshold too, and repeat; otherwise stop.  At most ``max_effects``.
   A measurement the declared model already explains gets nothing: spurious candidates gain ~chi2(p) in
   held-out chi-square, far below the ln(n) penalty.
4. Held-out error of the final model: every fold refitted on its training samples, scored on its test samples.
   Then every adopted effect of a kind in :data:`RETEST_KINDS` (the slew limit) is re-tested: the whole search
   and gate again without it; the final model with the lower held-out error is kept (:func:`_retest`).
5. ``explained`` = for every measured channel the held-out RMS residual is <= ``explained_ratio`` (1.2) x
   the noise floor AND no significant narrow-band structure is left (:func:`diagnostics.spectral_peaks`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from dtoc.constants import AXES
from dtoc.errors import InputError
from dtoc.hardware.effects import SlewLimit
from dtoc.hardware.model import HardwareModel
from dtoc.identify import adopt, diagnostics, energy, separability
from dtoc.identify.candidates import Context, excited_band_hz, lti_features, lti_physical_text, screen_all
from dtoc.identify.data import IdentData
from dtoc.identify.folds import Folds, make_folds, waveform_groups
from dtoc.identify.kinds import effect_name
from dtoc.identify.noise import NoiseEstimate, difference_sigma, estimate_sigma, quiet_samples
from dtoc.identify.twin import Twin
from dtoc.identify.workspace import Workspace

#: Relative standard error x sqrt(n) of the robust difference estimator of the noise floor (MAD of
#: correlated differences; measured on pure noise: 1.1-1.5).
DIFF_REL_SE = 1.5

#: Rounds of search + adoption gate: after the gate removes an effect, the search resumes without it.
GATE_ATTEMPTS = 3

#: Kinds that may be added more than once on the same axes (multi-exponential eddy currents, several
#: mechanical resonances).
REPEATABLE = {"exp_eddy", "cross_eddy", "b0_eddy", "resonance"}


@dataclass
class IdentifyResult:
    """Everything the report, the plots and the updated model file need."""

    data: IdentData
    twin: Twin
    noise: dict  # channel -> NoiseEstimate
    folds: Folds
    before: dict
    after: dict
    heldout_before: dict
    heldout_after: dict
    explained: bool
    remaining: list
    residual_before: dict
    residual_after: dict
    history: list = field(default_factory=list)  # per round: list of (name, score) of the top proposals
    rejected: list = field(default_factory=list)  # effects the adoption gate removed, with the reasons
    energy: dict = field(default_factory=dict)  # channel -> dtoc.identify.energy.describe of the final residual

    @property
    def adopted(self) -> bool:
        """True when at least one found *hardware* effect passed the adoption gate (an updated model exists;
        a measurement-side effect such as ``time_base`` alone changes no hardware model)."""
        return any(f.position != "meas" for f in self.twin.found)

    def updated_model(self) -> HardwareModel:
        return self.twin.updated_model()


def _slew_limit_fn(dt_s: float):
    """callable(g (M, 3, N) ndarray, max_slew T/m/s, axis=None) -> slew-limited g (one axis or all), via the
    twin's SlewLimit effect."""

    def fn(g: np.ndarray, max_slew: float, axis: str | None = None) -> np.ndarray:
        eff = SlewLimit(max_slew, axis=axis)
        with torch.no_grad():
            gt = torch.as_tensor(g, dtype=torch.float64)
            G, _ = eff(gt, torch.zeros(g.shape[0], g.shape[-1], dtype=torch.float64), dt_s)
        return G.numpy()

    return fn


def _excluded(twin: Twin) -> set:
    """Names of candidates that would duplicate a found effect (multi-exponentials stay allowed)."""
    names = set()
    for f in twin.found:
        e = f.effect
        if e.kind in REPEATABLE:
            continue
        names.add(effect_name(e))
        if e.kind in ("delay", "delay_bandlimited"):  # one delay per axis, whichever interpolation
            for k in ("delay", "delay_bandlimited"):
                names.add(k if e.axis is None else f"{k}[{e.axis}]")
                if e.axis is None:
                    names.update(f"{k}[{a}]" for a in AXES)
                else:
                    names.add(k)
    return names


def _chi2(ws: Workspace) -> float:
    return float(ws.c_units.sum())


def identify(
    data: IdentData,
    declared: HardwareModel | None = None,
    *,
    max_effects: int = 6,
    threshold: float = 10.0,
    kinds=None,
    explained_ratio: float = 1.2,
    progress=None,
    threads: int | None = 1,
) -> IdentifyResult:
    """Trace the residual of ``declared`` on ``data`` to missing effects (see module docstring).

    Args:
        data: the measurement.
        declared: declared hardware model (None: ideal hardware).
        max_effects: cap on added effects.
        threshold: minimum held-out score (chi-square units) to add an effect.
        kinds: restrict the candidate library to these kinds (default: all).
        explained_ratio: held-out RMS / noise bound for ``explained``.
        progress: optional callable(str) for progress lines.
        threads: torch intra-op threads while identifying (restored afterwards; None: leave as is).  The
            work is many medium-sized operations: one thread is as fast on an idle machine and many times
            faster on a shared one (measured: docs/benchmarks.md).
    """
    old = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(int(threads))
    try:
        return _identify(
            data,
            declared,
            max_effects=max_effects,
            threshold=threshold,
            kinds=kinds,
            explained_ratio=explained_ratio,
            progress=progress,
        )
    finally:
        torch.set_num_threads(old)


def _identify(
    data: IdentData,
    declared: HardwareModel | None = None,
    *,
    max_effects: int = 6,
    threshold: float = 10.0,
    kinds=None,
    explained_ratio: float = 1.2,
    progress=None,
) -> IdentifyResult:
    """Body of :func:`identify` (same arguments), run under its thread setting."""
    say = progress or (lambda s: None)
    twin = Twin(declared, data, {c: 1.0 for c in data.channels()})
    pred0 = twin.predict()
    folds = make_folds(data.M, data.N, groups=waveform_groups(data.g))
    # Noise floors from the declared residual.
    ws0 = Workspace(data, {c: 1.0 for c in data.channels()}, folds, pred0)
    noise = {}
    for c in data.channels():
        noise[c] = estimate_sigma(data.sigma.get(c), data.g, data.measured(c), ws0.res[c], data.mask(c))
        if noise[c].method == "none":
            raise InputError(
                f"measurement: too few measured samples to estimate the {c} noise floor; give 'sigma_{c}' in the file"
            )
    sigma = {c: noise[c].sigma for c in noise}
    twin.sigma = sigma
    ws = Workspace(data, sigma, folds, pred0)
    res_before = ws.res
    eddy_cache: dict = {}  # eddy columns are driven by the demanded g: the same in every round
    heldout_before = diagnostics.rmse(data, res_before)
    noise_first = dict(noise)

    def run(twin_: Twin, excluded: set) -> _Run:
        return _search_and_gate(
            twin_,
            data,
            sigma,
            folds,
            noise_first,
            heldout_before,
            excluded,
            kinds=kinds,
            max_effects=max_effects,
            threshold=threshold,
            say=say,
            eddy_cache=eddy_cache,
        )

    best_run = run(twin, set())
    best_run = _retest(best_run, declared, data, sigma, noise_first, run, say)
    twin, history, rejected = best_run.twin, best_run.history, best_run.rejected
    noise, res_after = best_run.noise, best_run.res_after
    heldout_after: Any = best_run.heldout_after
    sigma = {c: noise[c].sigma for c in noise}
    twin.sigma = sigma
    before = diagnostics.rmse(data, res_before)
    after = diagnostics.rmse(data, res_after)
    # Explained?
    remaining = []
    energy_desc: dict = {}
    explained = True
    for c in data.channels():
        ratio = heldout_after[c] / sigma[c]
        if ratio > explained_ratio:
            explained = False
            worst = ""
            if c != "b0":
                per = {ax: heldout_after.get(f"{c}_{ax}") for ax in AXES if heldout_after.get(f"{c}_{ax}") is not None}
                if per:
                    ax = max(per, key=per.get)
                    worst = f" (worst axis {ax}: {per[ax] / sigma[c]:.2f}x)"
            remaining.append(f"held-out {c} residual is {ratio:.2f}x the noise floor{worst}")
        z = res_after[c] / sigma[c]
        desc = energy.describe(data, c, res_after[c], sigma[c])
        if desc is not None:
            energy_desc[c] = desc
        during = desc is not None and desc["windows"].get("during demanded gradients", 0.0) >= 0.5
        for pk in diagnostics.spectral_peaks(data, c, z):
            explained = False
            if pk["narrow"]:
                remaining.append(
                    f"narrow-band {c} residual near {pk['f_hz'] / 1e3:.2f} kHz ({pk['ratio']:.1f}x the broadband level)"
                )
            else:
                remaining.append(
                    f"broadband {c} residual from {pk['f_lo_hz'] / 1e3:.2f} to {pk['f_hi_hz'] / 1e3:.2f} kHz "
                    f"(up to {pk['ratio']:.1f}x the high-frequency level, peak near {pk['f_hz'] / 1e3:.2f} "
                    f"kHz in 256-sample segments): "
                    + ("structure that follows the waveforms, " if during else "")
                    + "not a resonance"
                )
        if desc is not None:
            remaining.append(energy.note(c, desc, UNITS[c]))
    gres = diagnostics.gradient_residual(data, res_after, sigma)
    if gres is not None:
        rG, sG, how = gres
        zG = rG / sG
        for what in ("slew", "amplitude"):
            note = diagnostics.dependence_note(data, zG, what)
            if note:
                remaining.append(note + how)
                explained = False
        note = diagnostics.direction_note(data, rG, sG, quiet_samples(data.g))
        if note:
            remaining.append(note)
            explained = False
    for fo in twin.found:
        if fo.effect.kind == "slew_limit":
            remaining.append(
                "a non-linear slew-rate limit was modelled"
                + (f" on {fo.effect.axis}" if fo.effect.axis else "")
                + ": the amplifier cannot follow the demanded slew"
            )
        if fo.effect.kind == "time_base":
            ppm = float(fo.effect.ppm.detach())
            remaining.append(
                f"the measurement's time base is off by {ppm:+.2f} ppm (a delay growing linearly with time: "
                f"{-ppm * 1e-6 * data.N * data.dt_s * 1e6:+.3f} us at the end of the record): a clock error of the "
                "measuring device, applied to the measurement, not written into the hardware model"
            )
        if fo.effect.kind == "resonance":
            e = fo.effect
            remaining.append(
                f"a damped mechanical resonance was modelled on {e.axis or 'all axes'}: f0 {float(e.f0_hz.detach()):.1f}"
                f" Hz, Q {float(e.q.detach()):.1f}, amplitude {float(e.amplitude.detach()):.3g} per mT/m of ramp"
            )
        if fo.effect.kind == "lti":
            e = fo.effect
            band = excited_band_hz(data.g[:, e._ax][data.axes_measured[:, e._ax]], data.dt_s)
            n = lti_features(e.taps.detach().numpy().reshape(-1), int(round(e.t0_s / e.dt_s)), e.dt_s, band)
            fo.notes = {**fo.notes, "features": n}
            remaining.append(
                f"lti correction on {fo.effect.axis}: {lti_physical_text(n)}; largest |dH| {n['peak_abs']:.3f} near "
                f"{n['peak_hz'] / 1e3:.2f} kHz within the excited band 0-{band / 1e3:.1f} kHz, DC change "
                f"{n['dc_change']:+.4f} (a linear response no parametric effect explained)"
            )
    remaining.extend(best_run.notes)
    if len(twin.found) >= max_effects:
        remaining.append(f"stopped at the cap of {max_effects} added effects")
    adopted_names = {effect_name(f.effect) for f in twin.found}
    for r in rejected:
        remaining.append(rejected_line(r, adopted_names))
    say("done")
    return IdentifyResult(
        data,
        twin,
        noise,
        folds,
        before,
        after,
        heldout_before,
        heldout_after,
        explained,
        remaining,
        res_before,
        res_after,
        history,
        rejected,
        energy_desc,
    )


@dataclass
class _Run:
    """One forward search + adoption gate: the final twin and what the report needs of it."""

    twin: Twin
    history: list
    rejected: list
    noise: dict
    res_after: dict
    heldout_after: dict
    excluded: set  # candidate names excluded from the start (a re-test run)
    notes: list = field(default_factory=list)  # re-test outcomes, for the report


def _search_and_gate(
    twin: Twin,
    data: IdentData,
    sigma: dict,
    folds: Folds,
    noise_first: dict,
    heldout_before: dict,
    excluded: set,
    *,
    kinds,
    max_effects: int,
    threshold: float,
    say,
    eddy_cache: dict,
) -> _Run:
    """Steps 2-4 of the module docstring from ``twin`` (the declared model, nothing found yet), with the
    candidates named in ``excluded`` never screened; then the adoption gate (:mod:`dtoc.identify.adopt`)."""
    history: list = []
    rejected: list[dict] = []
    gate_excluded = set(excluded)
    for _attempt in range(GATE_ATTEMPTS):
        # Forward stepwise search from the current (possibly pruned) model.
        ws = Workspace(data, sigma, folds, twin.predict())
        while len(twin.found) < max_effects:
            ctx = Context(
                dt_s=data.dt_s,
                g=data.g,
                P=ws.pred.G,
                P_b0=ws.pred.b0,
                chain=twin.predict_fn(),
                slew_limit=_slew_limit_fn(data.dt_s),
                cache=eddy_cache,
            )
            props = screen_all(ws, ctx, kinds=kinds, exclude=_excluded(twin) | gate_excluded)
            limited = [f.effect.axis for f in twin.found if f.effect.kind == "slew_limit"]
            if limited:  # a shared limit excludes per-axis ones and vice versa
                props = [p for p in props if p.kind != "slew_limit" or (None not in limited and p.axis is not None)]
            history.append([(p.name, round(p.score, 2)) for p in props[:5]])
            if not props:
                break
            best = props[0]
            say(
                f"round {len(history)}: best {best.name} score {best.score:.1f}"
                + (f", next {props[1].name} {props[1].score:.1f}" if len(props) > 1 else "")
            )
            if best.score < threshold:
                break
            chi_old = _chi2(ws)
            saved = [copy.deepcopy(f.effect.state_dict()) for f in twin.found]
            second = best.notes.get("second")
            twin.add(
                best.kind,
                best.axis,
                best.input_axis,
                best.params,
                best.score,
                best.position,
                {k: v for k, v in best.notes.items() if k != "second"},
            )
            if second is not None:  # a pair of exponentials is added as two effects
                twin.add(best.kind, best.axis, best.input_axis, second, best.score, best.position)
            twin.refit()
            if second is not None:  # keep the second exponential only if the refitted pair beats one term
                chi_pair = _chi2(Workspace(data, sigma, folds, twin.predict()))
                pair_state = [copy.deepcopy(f.effect.state_dict()) for f in twin.found]
                last = twin.found.pop()
                twin.refit()
                if _chi2(Workspace(data, sigma, folds, twin.predict())) > chi_pair + threshold:
                    twin.found.append(last)
                    for fo, st in zip(twin.found, pair_state):
                        fo.effect.load_state_dict(st)
                else:
                    second = None
            ws_new = Workspace(data, sigma, folds, twin.predict())
            if not (_chi2(ws_new) < chi_old - threshold):
                say(f"  {best.name} rejected after the non-linear refit (chi2 {chi_old:.1f} -> {_chi2(ws_new):.1f})")
                twin.found.pop()
                if second is not None:
                    twin.found.pop()
                for fo, st in zip(twin.found, saved):
                    fo.effect.load_state_dict(st)
                break
            ws = ws_new
        ltis_to_physical(twin, data, sigma, folds, kinds, say, exclude=gate_excluded)
        lti_delays_to_delay(twin, data, sigma, folds, kinds, threshold, say, exclude=gate_excluded)
        # Final full-data refit, standard errors, noise floors and held-out errors; then the adoption gate
        # (dtoc.identify.adopt): effects the data do not support are removed one at a time and the rest
        # refitted; the search then resumes without them (another effect may explain what they could not).
        n_rejected = len(rejected)
        while True:
            fit, noise, res_after, heldout_after = _evaluate(twin, data, noise_first, folds)
            if not twin.found:
                break
            problems = adopt.bound_problems(twin.found, data.dt_s) + adopt.identification_problems(
                twin.found, fit.get("at_bound", [])
            )
            also_exclude: dict = {}
            if not problems:  # what the waveforms can separate (dtoc.identify.separability)
                problems = [
                    adopt.Problem(i, r) for i, r in separability.stability_problems(twin, fit, *fit["fold_est"])
                ]
            if not problems:
                labels = separability.label_problems(twin, fit["chi2"], threshold)
                problems = [adopt.Problem(i, r) for i, r, _ in labels]
                also_exclude = {i: names for i, _, names in labels}
            if not problems:
                n_meas = int(sum(np.sum(data.mask(c) > 0) for c in data.channels()))
                red = separability.redundancy_problems(twin, fit, threshold, n_meas)
                problems = [adopt.Problem(i, r) for i, r in red]
            problems += adopt.heldout_problems(heldout_before, heldout_after, data.channels())
            if not problems:
                rt = adopt.roundtrip_problem(twin.updated_model(), data.g, data.dt_s)
                problems = [rt] if rt is not None else []
            if not problems:
                break
            i = adopt.pick_offender(problems, twin.found)
            gate_excluded.update(also_exclude.get(i, []))
            f = twin.found[i]
            reasons = [p.reason for p in problems if p.index == i] or [p.reason for p in problems]
            rejected.append(
                {
                    "effect": effect_name(f.effect),
                    "kind": f.effect.kind,
                    "axis": f.effect.axis,
                    "input_axis": f.effect.input_axis,
                    "params": f.effect.params_dict(),
                    "score": float(f.score),
                    "reasons": reasons,
                }
            )
            say(f"  {effect_name(f.effect)} not adopted: {'; '.join(reasons)}")
            gate_excluded.add(effect_name(f.effect))
            twin.found.pop(i)
        if len(rejected) == n_rejected:
            break
    return _Run(twin, history, rejected, noise, res_after, heldout_after, set(excluded))


#: Kinds re-tested once the forward search and the gate are done (:func:`_retest`): non-linear effects that
#: can mimic a linear one in an early round (explain the most then) and hold the search in their optimum.
#: Each adopted one costs one more full search + gate without it; no further re-test inside that search.
RETEST_KINDS = ("slew_limit",)

#: Relative difference of the held-out scores below which the report says "as well" rather than "better" (the
#: model without the effect is still the one kept: it is simpler and not worse).
RETEST_SAME = 0.01


def _retest_exclusions(e: Any) -> set:
    """Candidate names a re-test of the found effect ``e`` leaves out: for a slew limit every limit that acts
    on its axes (a shared limit: all of them; a per-axis one: itself and the shared one), so that the same
    non-linearity cannot come back under another axis label; otherwise the effect's own name."""
    if e.kind == "slew_limit":
        if e.axis is None:
            return {"slew_limit"} | {f"slew_limit[{a}]" for a in AXES}
        return {"slew_limit", f"slew_limit[{e.axis}]"}
    return {effect_name(e)}


def _heldout_score(r: _Run, sigma0: dict, channels) -> float:
    """Held-out error of a run's final model as the sum over channels of (held-out RMS / noise floor)^2, with
    the noise floors estimated on the declared model's residual (the same for every run)."""
    return float(sum(v**2 for v in _ratios(r, sigma0, channels).values()))


def _ratios(r: _Run, sigma0: dict, channels) -> dict:
    return {c: float(r.heldout_after[c]) / sigma0[c] for c in channels}


def _retest(first: _Run, declared, data: IdentData, sigma: dict, noise_first: dict, run, say) -> _Run:
    """Re-test every adopted effect of a kind in :data:`RETEST_KINDS`: the whole search (same candidates, same
    adoption rules) again from the declared model with the effect excluded (:func:`_retest_exclusions`); the
    final model with the lower held-out error (:func:`_heldout_score`) is kept, ties to the first.  The outcome
    is reported either way: a dropped effect as a rejection with both held-out errors, a kept one as a note."""
    channels = data.channels()
    sigma0 = {c: noise_first[c].sigma for c in channels}
    best = first
    for f in list(first.twin.found):
        e: Any = f.effect
        if e.kind not in RETEST_KINDS:
            continue
        name = effect_name(e)
        ps = ", ".join(f"{k} {v:.4g}" for k, v in e.params_dict().items() if isinstance(v, float))
        say(f"re-test: the search again without {name}")
        twin = Twin(declared, data, {c: 1.0 for c in channels})
        twin.sigma = sigma
        alt = run(twin, best.excluded | _retest_exclusions(e))
        a, b = _ratios(best, sigma0, channels), _ratios(alt, sigma0, channels)
        cmp = ", ".join(f"{c} {a[c]:.2f}x -> {b[c]:.2f}x" for c in channels)
        found_alt = ", ".join(effect_name(x.effect) for x in alt.twin.found) or "nothing"
        s_best, s_alt = _heldout_score(best, sigma0, channels), _heldout_score(alt, sigma0, channels)
        if s_alt < s_best:
            how = "better" if s_alt < (1.0 - RETEST_SAME) * s_best else "as well (within 1 %)"
            reason = (
                f"{name} ({ps}) dropped on re-test: a model without it explains the held-out data {how}: "
                f"{cmp} the noise floor (a non-linear effect re-tested against the rest of the "
                "library; the model without it found " + found_alt + ")"
            )
            say(f"  {reason}")
            alt.rejected.append(
                {
                    "effect": name,
                    "kind": e.kind,
                    "axis": e.axis,
                    "input_axis": e.input_axis,
                    "params": e.params_dict(),
                    "score": float(f.score),
                    "reasons": [reason],
                }
            )
            alt.notes = best.notes + alt.notes
            best = alt
        else:
            note = (
                f"{name} re-tested and kept: the search without it explains the held-out data no better "
                f"({cmp} the noise floor; it found {found_alt})"
            )
            say(f"  {note}")
            best.notes.append(note)
    return best


#: Units of the channels, for the notes.
UNITS = {"G": "mT/m", "k": "rad/m", "b0": "uT"}


def rejected_line(r: dict, adopted_names: set) -> str:
    """ "not adopted: ..." for an effect the gate removed; when an effect of the same name (a further term of a
    repeatable kind, e.g. a second ``exp_eddy[x]``) *is* adopted, the line says so and gives the removed term's
    parameters, so that the two are never confused."""
    reasons = "; ".join(r["reasons"])
    if r["effect"] in adopted_names:
        ps = ", ".join(f"{k} {v:.4g}" for k, v in r["params"].items() if isinstance(v, float))
        return f"not adopted: a further {r['effect']} term ({ps}) beside the adopted {r['effect']}: {reasons}"
    return f"not adopted: {reasons}"


def _refined_noise(noise_first: dict, res_after: dict, data: IdentData) -> dict:
    """Noise floors re-estimated on the final residual where that is the better estimate.

    The difference estimator is only ever biased upwards by model error left in the residual.  The final
    residual on *all* samples is adopted when it is white-noise-like (its plain RMS agrees with its
    difference estimate: the model now fits, and there are many more samples than the corner-free subset)
    or when it is not significantly above the first estimate; otherwise the corner-free estimate on the
    final residual replaces the first one only if lower.  (Taking simply the lower of two noisy estimates
    would bias the floor low: measured -10 % for b0 with 2,200 corner-free samples.)
    """
    noise = dict(noise_first)
    for c in list(noise):
        if not noise[c].method.startswith("difference"):
            continue
        first = noise[c]
        note = first.method[first.method.index(" (the file") :] if " (the file" in first.method else ""
        re_all = difference_sigma(res_after[c], data.mask(c))
        rel_se = DIFF_REL_SE / np.sqrt(max(first.n_samples, 1))
        mk = data.mask(c)
        rms_after = float(np.sqrt(np.sum((res_after[c] * mk) ** 2) / max(mk.sum(), 1)))
        white = re_all is not None and rms_after <= re_all.sigma * (1.0 + 3.0 * DIFF_REL_SE / np.sqrt(re_all.n_samples))
        if re_all is not None and (white or re_all.sigma <= first.sigma * (1.0 + 3.0 * rel_se)):
            noise[c] = NoiseEstimate(re_all.sigma, re_all.method + ", final residual" + note, re_all.n_samples)
        else:
            q = quiet_samples(data.g)
            re = difference_sigma(res_after[c], data.mask(c), quiet=q.all(axis=1) if c == "b0" else q)
            if re is not None and re.sigma < first.sigma:
                noise[c] = NoiseEstimate(re.sigma, re.method + ", final residual" + note, re.n_samples)
    return noise


def _evaluate(twin: Twin, data: IdentData, noise_first: dict, folds: Folds):
    """Full-data refit (standard errors stored on the twin), refined noise floors, final residual and the
    held-out RMS (each fold refitted on its training samples, residual on its test samples).

    Returns:
        (fit, noise, res_after, heldout_after)
    """
    fit = twin.refit()
    twin.set_stderr(fit)
    sigma = {c: noise_first[c].sigma for c in noise_first}
    res_after = Workspace(data, sigma, folds, twin.predict()).res
    noise = _refined_noise(noise_first, res_after, data)
    sigma = {c: noise[c].sigma for c in noise}
    held_sq = {c: np.zeros_like(res_after[c]) for c in res_after}
    if twin.found:
        state = [copy.deepcopy(f.effect.state_dict()) for f in twin.found]
        for k in range(folds.K):
            twin.heldout_refit(fit, folds.sample_mask(k, train=True))
            r = Workspace(data, sigma, folds, twin.predict()).res
            test = folds.sample_mask(k, train=False)
            for c in r:
                t = test[:, None, :] if c != "b0" else test
                held_sq[c] += r[c] * t
            for fo, st in zip(twin.found, state):
                fo.effect.load_state_dict(st)
        held_res = held_sq
    else:
        held_res = res_after
    heldout_after = diagnostics.rmse(data, held_res)
    fit["fold_est"] = twin.fold_estimates(fit, [folds.sample_mask(k, train=False) for k in range(folds.K)])
    for c in data.channels():
        if heldout_after[c] is None or not np.isfinite(heldout_after[c]):
            heldout_after[c] = float("inf")  # a held-out refit failed: never "explained"
    return fit, noise, res_after, heldout_after


#: Parametric kinds an ``lti`` correction is tested against (the physical effects a FIR often stands for).
LTI_EQUIVALENTS = ("delay", "delay_bandlimited", "gain", "exp_eddy", "resonance")


def ltis_to_physical(twin: Twin, data: IdentData, sigma: dict, folds: Folds, kinds, say, exclude=frozenset()) -> None:
    """Replace every found ``lti`` that is equivalent within noise to one physical effect on its axis.

    For each lti: the model without it is the base; every kind of :data:`LTI_EQUIVALENTS` allowed by
    ``kinds`` is screened on the lti's axis against that base, the best one is added and refitted with the
    rest, and it replaces the lti when its information criterion is no worse: chi2_param + p ln n <=
    chi2_lti + L ln n (p its parameters, L the taps).  The report then names the physical effect (with its
    parameters and errors) instead of a filter.  Otherwise the lti is restored unchanged.  Candidates named
    in ``exclude`` (removed by the adoption gate) are not tried.
    """
    from dtoc.identify.candidates import screen_delay, screen_exp_eddy, screen_gain, screen_resonance

    allowed = [k for k in LTI_EQUIVALENTS if not kinds or k in kinds]
    for f in [f for f in twin.found if f.position == "lti"]:
        if f not in twin.found:
            continue
        ax = f.effect.axis
        state = [copy.deepcopy(x.effect.state_dict()) for x in twin.found]
        order = list(twin.found)
        ws_lti = Workspace(data, sigma, folds, twin.predict())
        n = ws_lti.n_samples
        L = int(f.effect.taps.numel())
        ic_lti = _chi2(ws_lti) + L * np.log(n)
        twin.found.remove(f)
        twin.refit()
        ws = Workspace(data, sigma, folds, twin.predict())
        ctx = Context(dt_s=data.dt_s, g=data.g, P=ws.pred.G, P_b0=ws.pred.b0)
        screens = {
            "delay": (screen_delay, {}),
            "delay_bandlimited": (screen_delay, {"bandlimited": True}),
            "gain": (screen_gain, {}),
            "exp_eddy": (screen_exp_eddy, {}),
            "resonance": (screen_resonance, {}),
        }
        props = [
            p
            for p in (screens[k][0](ws, ctx, ax, **screens[k][1]) for k in allowed)
            if p is not None and p.name not in exclude
        ]
        best = max(props, key=lambda p: p.score) if props else None
        replaced = False
        if best is not None:
            g = twin.add(best.kind, best.axis, best.input_axis, best.params, best.score, best.position, best.notes)
            twin.refit()
            ic = _chi2(Workspace(data, sigma, folds, twin.predict())) + best.n_params * np.log(n)
            if ic <= ic_lti:
                say(f"  lti[{ax}] is equivalent within noise to {best.name}: replaced")
                replaced = True
            else:
                twin.found.remove(g)
        if not replaced:
            twin.found[:] = order
            for x, st in zip(twin.found, state):
                x.effect.load_state_dict(st)


def lti_delays_to_delay(
    twin: Twin, data: IdentData, sigma: dict, folds: Folds, kinds, threshold: float, say, exclude=frozenset()
) -> None:
    """Move the delay a found ``lti`` carries (its group delay at low frequency, :func:`lti_features`) into a
    ``delay`` effect on its axis (added, or the axis's found delay adjusted), re-solve the filter and refit;
    kept when the chi-square is within ``threshold`` of before (the two descriptions are equivalent), so that
    a shift is reported as a delay and not hidden in 48 taps.  Shifts below 5 % of a sample are left, and so is
    an axis whose delay the adoption gate removed (``exclude``)."""
    if kinds and "delay" not in kinds:
        return
    for f in [f for f in twin.found if f.position == "lti"]:
        e = f.effect
        ft = lti_features(e.taps.detach().numpy().reshape(-1), int(round(e.t0_s / e.dt_s)), e.dt_s)
        tau = ft["delay_s"]
        if f"delay[{e.axis}]" in exclude or not np.isfinite(tau) or abs(tau) < 0.05 * data.dt_s:
            continue
        chi_old = _chi2(Workspace(data, sigma, folds, twin.predict()))
        order = list(twin.found)
        state = [copy.deepcopy(x.effect.state_dict()) for x in twin.found]
        have = next((x for x in twin.found if x.effect.kind == "delay" and x.effect.axis == e.axis), None)
        if have is not None:
            with torch.no_grad():
                have.effect.seconds.add_(tau)
        else:
            twin.add("delay", e.axis, None, {"seconds": tau}, f.score, "post", {"moved from lti": True})
        twin.refit()
        chi_new = _chi2(Workspace(data, sigma, folds, twin.predict()))
        if chi_new <= chi_old + threshold:
            say(
                f"  the {tau * 1e6:+.3g} us delay lti[{e.axis}] carried is now a delay effect (chi2 {chi_old:.1f} -> {chi_new:.1f})"
            )
        else:
            twin.found[:] = order
            for x, st in zip(twin.found, state):
                x.effect.load_state_dict(st)
