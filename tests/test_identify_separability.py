"""What `dtoc identify` says the data can and cannot separate (issue 37; docs/identify.md, steps 5b and 6).

Axis labels the waveforms cannot support are not adopted; a delay carried by an lti filter becomes a delay;
a parameter that moves between held-out folds is not adopted; the remaining error is described by where its
energy is (frequency band, time window, axis); a one-axis slew limit is modelled or named on its axis.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from dtoc.hardware.model import HardwareModel, build_effect, girf_effect
from dtoc.identify import energy
from dtoc.identify.candidates import lti_features
from dtoc.identify.data import IdentData, integrate_k
from dtoc.identify.search import identify, rejected_line
from dtoc.identify.synth import lowpass_girf, probe_waveforms, simulate_measurement

DT = 10e-6


@pytest.fixture(scope="module")
def declared():
    return HardwareModel([girf_effect(lowpass_girf(DT))])


def _truth(declared, *effects, pre=()):
    return HardwareModel(
        [*[build_effect(k, p, **kw) for k, p, kw in pre], *declared.effects]
        + [build_effect(k, p, **kw) for k, p, kw in effects]
    )


def _names(r):
    return [(f.effect.kind, f.effect.axis, f.effect.input_axis) for f in r.twin.found]


def test_identical_waveforms_on_all_axes_give_no_axis_label(declared):
    """All three axes play the same waveform: cross_eddy y<-x, y<-z and exp_eddy[y] predict the same.  Nothing
    is adopted with an axis label; the report says why and what to play instead.  Control: the same truth with
    different waveforms per axis is adopted as cross_eddy[y]<-x."""
    cross = ("cross_eddy", {"alpha": 0.01, "tau_s": 1e-3}, {"axis": "y", "input_axis": "x"})
    g1 = probe_waveforms(2, 1500, DT, seed=3, axes=(0,))
    g = np.repeat(g1[:, :1], 3, axis=1)
    kinds = ["exp_eddy", "cross_eddy"]
    r = identify(simulate_measurement(_truth(declared, cross), g, DT), declared, kinds=kinds)
    assert not any(k in ("exp_eddy", "cross_eddy") for k, _, _ in _names(r)), _names(r)
    assert not r.adopted
    notes = " | ".join(r.remaining)
    assert "not identifiable from these waveforms" in notes, notes
    assert "the three axes played identical waveforms" in notes and "one axis at a time" in notes, notes
    g2 = probe_waveforms(2, 1500, DT, seed=3)
    r2 = identify(simulate_measurement(_truth(declared, cross), g2, DT), declared, kinds=kinds)
    assert ("cross_eddy", "y", "x") in _names(r2), (_names(r2), r2.remaining)
    assert not any("not identifiable" in n for n in r2.remaining)


def test_lti_carrying_a_delay_reports_it_as_a_delay(declared):
    """A 5 us delay plus a short eddy current on x (alpha 0.03, tau 30 us: low-frequency group delay alpha tau =
    0.9 us, plus a high-frequency shape) with only lti and delay in the library: the filter's shift is moved
    into delay[x] (5.9 us), the filter keeps the shape (its own low-frequency delay ~0) and its physical names
    are printed."""
    truth = _truth(
        declared,
        ("delay", {"seconds": 5e-6}, {"axis": "x"}),
        ("exp_eddy", {"alpha": 0.03, "tau_s": 30e-6}, {"axis": "x"}),
    )
    r = identify(
        simulate_measurement(truth, probe_waveforms(4, 2000, DT, seed=8), DT), declared, kinds=["lti", "delay"]
    )
    delays = [f for f in r.twin.found if f.effect.kind == "delay" and f.effect.axis == "x"]
    assert len(delays) == 1, _names(r)
    assert float(delays[0].effect.seconds.detach()) == pytest.approx(5.9e-6, abs=0.15e-6)
    for f in r.twin.found:
        if f.effect.kind == "lti":
            e = f.effect
            ft = lti_features(e.taps.detach().numpy(), int(round(e.t0_s / e.dt_s)), e.dt_s)
            assert abs(ft["delay_s"]) < 0.05 * DT
    assert any("group delay at low frequency" in n and "DC gain" in n for n in r.remaining) or not any(
        f.effect.kind == "lti" for f in r.twin.found
    )


def test_lti_physical_names():
    """h = delta + taps: taps -delta_0 + delta_2 is a pure 2-sample delay (DC gain 1, no -3 dB point); a
    two-tap average 0.5 (delta_0 + delta_1) has delay dt/2 and its -3 dB point at 1/(4 dt)."""
    taps = np.zeros(10)
    taps[4], taps[6] = -1.0, 1.0  # first lag -4: lag 0 and lag 2
    ft = lti_features(taps, -4, DT)
    assert ft["delay_s"] == pytest.approx(2 * DT) and ft["dc_gain"] == pytest.approx(1.0)
    assert ft["bandwidth_hz"] is None
    taps = np.zeros(10)
    taps[4], taps[5] = -0.5, 0.5
    ft = lti_features(taps, -4, DT)
    assert ft["delay_s"] == pytest.approx(DT / 2)
    assert ft["bandwidth_hz"] == pytest.approx(1 / (4 * DT), rel=0.01)


def test_parameter_that_moves_between_folds_is_not_adopted(declared):
    """Gain 0.96 on x in waveforms 0-3 and 1.00 in 4-7 (the folds see different gains): not adopted, and the
    report says it is not stable.  Control: a gain of 0.97 on every waveform is adopted."""
    g = probe_waveforms(8, 2000, DT, seed=4)
    kinds = ["gain", "offset", "delay"]
    d = simulate_measurement(_truth(declared, ("gain", {"factor": 0.96}, {"axis": "x"})), g, DT)
    d.G[4:] = simulate_measurement(declared, g, DT).G[4:]
    r = identify(d, declared, kinds=kinds)
    assert ("gain", "x", None) not in _names(r)
    assert any("gain[x]: factor is not stable across the held-out folds" in n for n in r.remaining), r.remaining
    r2 = identify(
        simulate_measurement(_truth(declared, ("gain", {"factor": 0.97}, {"axis": "x"})), g, DT), declared, kinds=kinds
    )
    assert ("gain", "x", None) in _names(r2)
    assert not any("not stable" in n for n in r2.remaining)


def test_one_axis_slew_limit_is_modelled_or_named_on_k_data(declared):
    """One slower amplifier (x limited to 100 T/m/s), k-space data only: modelled as slew_limit[x]; without the
    kind in the library the report says the residual grows with slew rate on x (and not on y or z)."""
    g = probe_waveforms(4, 2000, DT, seed=7)
    truth = _truth(declared, pre=[("slew_limit", {"max_slew_T_per_m_per_s": 100.0}, {"axis": "x"})])
    d = simulate_measurement(truth, g, DT, sigma_G=None, sigma_k=0.05)
    r = identify(d, declared, kinds=["slew_limit", "gain", "delay"])
    lim = [f for f in r.twin.found if f.effect.kind == "slew_limit"]
    assert len(lim) == 1 and lim[0].effect.axis == "x", _names(r)
    assert float(lim[0].effect.max_slew_T_per_m_per_s.detach()) == pytest.approx(100.0, rel=0.01)
    dG = simulate_measurement(truth, g, DT)
    r2 = identify(dG, declared, kinds=["gain", "offset"])
    slew = [n for n in r2.remaining if "grows with slew rate" in n]
    assert slew and "slew rate on x:" in slew[0], r2.remaining


def test_clock_error_on_k_data_without_spurious_gains(declared):
    """A +50 ppm clock error of the measuring device on k-space data: time_base alone, no gains."""
    g = probe_waveforms(2, 4000, DT, seed=11)
    d = simulate_measurement(_truth(declared, ("time_base", {"ppm": 50.0}, {})), g, DT, sigma_G=None, sigma_k=0.05)
    r = identify(d, declared, kinds=["time_base", "gain", "delay"])
    assert [k for k, _, _ in _names(r)] == ["time_base"], (_names(r), r.remaining)
    assert float(r.twin.found[0].effect.ppm.detach()) == pytest.approx(50.0, abs=1.0)


def test_degenerate_pair_is_named():
    """Redundancy test on its own: long plateaus from t ~ 0 measured in k (k = gamma G t: a clock error
    k(t (1 + e)) - k(t) = e k is then exactly a gain); a twin holding time_base and a gain on x, fitted to
    data made by the clock alone: the gain is 'not needed beside time_base', their correlation named.
    Control: on random trapezoid trains the two are not degenerate and nothing is flagged."""
    from dtoc.identify.separability import redundancy_problems
    from dtoc.identify.twin import Twin

    N = 3000
    g = np.zeros((2, 3, N))
    ramp = np.arange(1, 21) / 20
    for m, amp in enumerate((20.0, -12.0)):
        g[m, 0, 5:25], g[m, 0, 25:2800], g[m, 0, 2800:2820] = amp * ramp, amp, amp * (1 - ramp)
    truth = HardwareModel([build_effect("time_base", {"ppm": 80.0})])
    for waveforms, degenerate in ((g, True), (probe_waveforms(2, N, DT, seed=12, axes=(0,)), False)):
        d = simulate_measurement(truth, waveforms, DT, sigma_G=None, sigma_k=0.05)
        d.axes_measured[:, 1:] = False
        twin = Twin(None, d, {"k": 0.05})
        twin.add("time_base", None, None, {"ppm": 70.0}, 100.0, "meas")
        twin.add("gain", "x", None, {"factor": 1.0001}, 50.0, "post")
        fit = twin.refit()
        probs = redundancy_problems(twin, fit, 10.0, int(d.mask("k").sum()))
        if degenerate:
            assert len(probs) == 1 and probs[0][0] == 1, probs
            assert "not needed beside time_base" in probs[0][1] and "nearly degenerate" in probs[0][1]
        else:
            assert probs == []


def test_concomitant_field_is_named_on_k_data(declared):
    """A field quadratic in the other axes' gradients on x (concomitant-like), k-space data only, library
    without anything that can absorb it: the report names a field quadratic in the gradients."""
    g = probe_waveforms(4, 2000, DT, seed=9)
    with torch.no_grad():
        G, _ = declared(torch.as_tensor(g), DT)
    G = G.numpy().copy()
    G[:, 0] += 2e-4 * (G[:, 1] ** 2 + G[:, 2] ** 2)
    rng = np.random.default_rng(1)
    d = IdentData(dt_s=DT, g=g, sigma={}, k=integrate_k(G, DT) + 0.05 * rng.standard_normal(g.shape))
    r = identify(d, declared, kinds=["gain", "offset"])
    assert not r.explained
    assert any("concomitant" in n for n in r.remaining), r.remaining


def test_low_frequency_drift_is_described_by_its_band(declared):
    """A slow (5 ms) eddy current on x left unmodelled (library without eddy kinds): the description of the
    remaining error puts most of its energy below 1 kHz and on x."""
    truth = _truth(declared, ("exp_eddy", {"alpha": 0.02, "tau_s": 5e-3}, {"axis": "x"}))
    r = identify(simulate_measurement(truth, probe_waveforms(4, 2500, DT, seed=5), DT), declared, kinds=["offset"])
    note = [n for n in r.remaining if n.startswith("remaining G error")]
    assert note, r.remaining
    m = re.search(r"(\d+) % below ([\d.]+) kHz", note[0])
    assert m and int(m.group(1)) >= 50 and float(m.group(2)) <= 1.0, note[0]
    assert r.energy["G"]["axes"]["x"] > 0.9


def test_energy_description_time_window_and_band():
    """White noise everywhere plus a 300 Hz wave only after the last demanded gradient: the excess is
    described as after the last demanded gradient and below 0.5 kHz; pure noise is not described."""
    N, M = 4000, 2
    g = np.zeros((M, 3, N))
    g[:, 0, 100:1500] = 10.0
    rng = np.random.default_rng(0)
    res = 0.01 * rng.standard_normal((M, 3, N))
    d = IdentData(dt_s=DT, g=g, sigma={}, G=g + res)
    assert energy.describe(d, "G", res, 0.01) is None
    t = np.arange(N) * DT
    res[:, 1, 2000:] += 0.05 * np.sin(2 * np.pi * 300 * t[2000:])
    desc = energy.describe(d, "G", res, 0.01)
    assert desc["windows"]["after the last demanded gradient"] > 0.9
    assert desc["below_hz"][0] <= 500 and desc["below_hz"][1] > 0.5
    assert desc["axes"]["y"] > 0.95
    assert "after the last demanded gradient" in energy.note("G", desc, "mT/m")


def test_energy_windows_below_the_noise_floor_are_named_so_the_shares_add_up():
    """Quieter than the stated noise floor during the gradients (0.002 against 0.01) and a 300 Hz wave after
    them: the window shares of the excess sum to 100 %, the after-window's exceeds 100 %, and the line names
    the negative window instead of printing shares that seem to add to more than 100 %."""
    N, M = 4000, 2
    g = np.zeros((M, 3, N))
    g[:, 0, 100:1500] = 10.0
    rng = np.random.default_rng(1)
    res = 0.01 * rng.standard_normal((M, 3, N))
    res[:, :, 100:1500] *= 0.2
    t = np.arange(N) * DT
    res[:, 1, 2000:] += 0.05 * np.sin(2 * np.pi * 300 * t[2000:])
    d = IdentData(dt_s=DT, g=g, sigma={}, G=g + res)
    desc = energy.describe(d, "G", res, 0.01)
    assert abs(sum(desc["windows"].values()) - 1.0) < 1e-9
    assert desc["windows"]["during demanded gradients"] < -0.1
    line = energy.note("G", desc, "mT/m")
    assert re.search(r"-\d+ % during demanded gradients \(less energy than the noise floor predicts", line), line


def test_rejected_line_never_contradicts_an_adopted_effect():
    r = {"effect": "exp_eddy[x]", "params": {"alpha": 0.001, "tau_s": 3e-6}, "reasons": ["exp_eddy[x]: tau_s ..."]}
    line = rejected_line(r, {"exp_eddy[x]"})
    assert line.startswith("not adopted: a further exp_eddy[x] term (alpha 0.001, tau_s 3e-06) beside the adopted")
    assert rejected_line(r, set()) == "not adopted: exp_eddy[x]: tau_s ..."


def test_clock_error_that_changes_within_the_record_is_not_adopted():
    """One waveform measured in k with a clock error of -40 ppm in its first half and -90 ppm in its second (the
    issue's spiral: -41.6 ppm on the whole window, -87.6 ppm on the spiral part): the time-block folds disagree
    and time_base is not adopted, with the fold estimates named.  Control: -40 ppm throughout is adopted."""
    g = probe_waveforms(1, 8000, DT, seed=21)
    clock = lambda ppm, seed: simulate_measurement(  # noqa: E731
        HardwareModel([build_effect("time_base", {"ppm": ppm})]), g, DT, sigma_G=None, sigma_k=0.02, seed=seed
    )
    d = clock(-40.0, 1)
    d.k[..., 4000:] = clock(-90.0, 2).k[..., 4000:]
    kinds = ["time_base", "gain", "delay"]
    r = identify(d, None, kinds=kinds)
    assert "time_base" not in [k for k, _, _ in _names(r)]
    note = [n for n in r.remaining if n.startswith("not adopted: time_base: ppm is not stable")]
    assert note and "-90" in note[0] and "-40" in note[0], r.remaining
    r2 = identify(clock(-40.0, 1), None, kinds=kinds)
    assert [k for k, _, _ in _names(r2)] == ["time_base"]
    assert float(r2.twin.found[0].effect.ppm.detach()) == pytest.approx(-40.0, abs=0.5)
