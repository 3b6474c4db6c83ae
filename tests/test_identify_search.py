"""`identify` on synthetic measurements: declared GIRF + ONE missing effect + white noise.

For each named kind the missing effect must be the first one added, its parameters must lie within the
stated tolerances of the truth, and the held-out residual must end within 20 % of the true noise floor.
A null measurement gets nothing; a slew-limited scanner is modelled or reported as not explained.
"""

import numpy as np
import pytest

from dtoc.hardware.model import HardwareModel, build_effect, girf_effect
from dtoc.identify.search import identify
from dtoc.identify.synth import lowpass_girf, probe_waveforms, simulate_measurement

DT = 10e-6
M, N = 4, 2500
SIGMA_G = 0.01  # mT/m
SIGMA_K = 0.05  # rad/m
SIGMA_B0 = 0.01  # uT


@pytest.fixture(scope="module")
def girf():
    return lowpass_girf(DT, b0_uT_per_mT_per_m=0.002)


@pytest.fixture(scope="module")
def g():
    return probe_waveforms(M, N, DT, seed=3)


def _taps():
    n = np.arange(40)
    return (0.03 * np.exp(-n * DT / 150e-6) * np.sin(2 * np.pi * 3.6e3 * n * DT)).tolist()


# kind -> (true extra effect spec, {param: (true value, absolute tolerance)}, expected axis, input_axis)
CASES = {
    "delay": (dict(kind="delay", params={"seconds": 2.2e-6}, axis="y"), {"seconds": (2.2e-6, 0.05e-6)}, "y", None),
    "gain": (dict(kind="gain", params={"factor": 0.985}, axis="x"), {"factor": (0.985, 0.002)}, "x", None),
    "offset": (dict(kind="offset", params={"mT_per_m": 0.05}, axis="z"), {"mT_per_m": (0.05, 0.003)}, "z", None),
    "exp_eddy": (
        dict(kind="exp_eddy", params={"alpha": 0.02, "tau_s": 2e-3}, axis="x"),
        {"alpha": (0.02, 0.001), "tau_s": (2e-3, 0.1e-3)},
        "x",
        None,
    ),
    "cross_eddy": (
        dict(kind="cross_eddy", params={"alpha": 0.01, "tau_s": 1e-3}, axis="y", input_axis="x"),
        {"alpha": (0.01, 0.0005), "tau_s": (1e-3, 0.05e-3)},
        "y",
        "x",
    ),
    "b0_eddy": (
        dict(kind="b0_eddy", params={"alpha_uT_per_mT_per_m": 0.05, "tau_s": 3e-3}, input_axis="z"),
        {"alpha_uT_per_mT_per_m": (0.05, 0.0025), "tau_s": (3e-3, 0.15e-3)},
        None,
        "z",
    ),
    "lti": (dict(kind="lti", params={"taps": _taps(), "dt_s": DT, "t0_s": 0.0}, axis="x"), {}, "x", None),
}


def _measure(girf, g, extra=None, pre=False, channels="G", seed=1):
    effs = [girf_effect(girf)]
    if extra is not None:
        e = build_effect(extra["kind"], extra["params"], axis=extra.get("axis"), input_axis=extra.get("input_axis"))
        effs = [e] + effs if pre else effs + [e]
    kw = {
        "sigma_G": SIGMA_G if "G" in channels else None,
        "sigma_k": SIGMA_K if "k" in channels else None,
        "sigma_b0": SIGMA_B0 if "b0" in channels else None,
    }
    return simulate_measurement(HardwareModel(effs), g, DT, seed=seed, **kw)


def _declared(girf):
    return HardwareModel([girf_effect(girf)])


def _true_sigma(c):
    return {"G": SIGMA_G, "k": SIGMA_K, "b0": SIGMA_B0}[c]


@pytest.mark.parametrize("kind", list(CASES))
def test_missing_effect_is_found_first(kind, girf, g):
    extra, tol, axis, input_axis = CASES[kind]
    data = _measure(girf, g, extra, channels="G,b0" if kind == "b0_eddy" else "G")
    r = identify(data, _declared(girf))
    assert r.twin.found, f"{kind}: nothing found"
    first = r.twin.found[0].effect
    assert first.kind == kind
    assert first.axis == axis and first.input_axis == input_axis
    params = first.params_dict()
    for name, (true, atol) in tol.items():
        assert abs(params[name] - true) <= atol, f"{kind}.{name} = {params[name]} vs {true} ± {atol}"
        se = r.twin.found[0].stderr[name]
        assert 0 < se < atol  # the stated uncertainty is meaningful and tighter than the test tolerance
    for c in data.channels():
        assert r.heldout_after[c] <= 1.2 * _true_sigma(c), (
            f"{kind}: held-out {c} {r.heldout_after[c]} vs noise {_true_sigma(c)}"
        )
        # The noise floor is estimated (not given) and must be accurate (was -10 % for b0 before the audit).
        assert abs(r.noise[c].sigma / _true_sigma(c) - 1) < 0.05, f"{kind}: noise {c} {r.noise[c]}"
        assert r.before[c] > 1.3 * _true_sigma(c) or c != ("b0" if kind == "b0_eddy" else "G")  # the effect was visible
    assert r.explained, r.remaining


def test_null_measurement_gets_nothing(girf, g):
    data = _measure(girf, g, None, channels="G,b0", seed=5)
    r = identify(data, _declared(girf))
    assert r.twin.found == []
    assert r.explained
    assert r.after["G"] == pytest.approx(r.before["G"])
    assert abs(r.heldout_after["G"] / SIGMA_G - 1) < 0.05


def test_slew_limit_is_modelled_or_not_explained(girf, g):
    extra = dict(kind="slew_limit", params={"max_slew_T_per_m_per_s": 100.0})
    data = _measure(girf, g, extra, pre=True)
    r = identify(data, _declared(girf))
    kinds = [f.effect.kind for f in r.twin.found]
    if "slew_limit" in kinds:
        s = r.twin.found[kinds.index("slew_limit")].effect.params_dict()["max_slew_T_per_m_per_s"]
        assert abs(s - 100.0) < 1.0
        assert kinds[0] == "slew_limit"
        assert any("slew" in note for note in r.remaining)  # reported as the non-linear effect it is
        # re-tested (a search without it) and kept: a real slew limit is not dropped (issue 37)
        assert any(note.startswith("slew_limit re-tested and kept") for note in r.remaining), r.remaining
    else:
        assert not r.explained
    if r.explained:
        assert r.heldout_after["G"] <= 1.2 * SIGMA_G


def test_k_input_works(girf, g):
    """Measured k only (no G): the same delay is found from the k-space residual."""
    extra, tol, axis, _ = CASES["delay"]
    data = _measure(girf, g, extra, channels="k")
    assert data.G is None and data.k is not None
    r = identify(data, _declared(girf))
    first = r.twin.found[0].effect
    assert (first.kind, first.axis) == ("delay", axis)
    assert abs(first.params_dict()["seconds"] - 2.2e-6) < 0.05e-6
    assert r.heldout_after["k"] <= 1.2 * SIGMA_K
    assert r.before["G"] is None and r.after["k"] < r.before["k"]


def test_single_waveform_uses_time_blocks(girf):
    g1 = probe_waveforms(1, 6000, DT, seed=11)
    extra = dict(kind="exp_eddy", params={"alpha": 0.03, "tau_s": 1e-3}, axis="z")
    data = _measure(girf, g1, extra)
    r = identify(data, _declared(girf))
    assert r.folds.mode == "time blocks"
    first = r.twin.found[0].effect
    assert (first.kind, first.axis) == ("exp_eddy", "z")
    assert abs(first.params_dict()["alpha"] - 0.03) < 0.002
    assert r.heldout_after["G"] <= 1.2 * SIGMA_G


def test_unexplained_structure_is_reported_not_hidden(girf, g):
    """A resonance the (restricted) library cannot model: not explained, with a narrow-band note."""
    extra, _, _, _ = CASES["lti"]
    data = _measure(girf, g, extra)
    r = identify(data, _declared(girf), kinds=["delay", "gain", "offset"])
    assert not r.explained
    assert r.heldout_after["G"] > 1.2 * SIGMA_G
    notes = " ".join(r.remaining)
    assert "held-out G residual" in notes
    peaks = [float(s.split("near ")[1].split(" kHz")[0]) for s in r.remaining if s.startswith("narrow-band G")]
    assert peaks and min(abs(p - 3.3) for p in peaks) < 0.8, r.remaining  # the resonance (|dH| peaks ~3.3 kHz)
