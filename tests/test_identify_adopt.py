"""The adoption gate of `dtoc identify` (dtoc/identify/adopt.py, docs/identify.md "Adoption").

A model is adopted only if every parameter is physical and identified, the held-out error is no worse than
the declared model's on every channel, and the model file loads back and predicts the same; otherwise the
offending effect is removed (and reported) and nothing is written when nothing is left.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from cli_helpers import run_cli

from dtoc.hardware.girf_io import save_girf
from dtoc.hardware.model import HardwareModel, build_effect, girf_effect, load_model
from dtoc.identify import adopt
from dtoc.identify.search import identify
from dtoc.identify.synth import lowpass_girf, probe_waveforms, save_measurement, simulate_measurement

DT = 10e-6


def _found(kind, params, axis=None, input_axis=None, stderr=None, score=100.0):
    return SimpleNamespace(
        effect=build_effect(kind, params, axis=axis, input_axis=input_axis), score=score, stderr=stderr or {}
    )


def test_unphysical_parameters_are_named():
    """The fit the issue saw on a real field-camera measurement: cross terms with |alpha| > 1 and tau below a
    sample; plus a 150 us delay and a gain of 1.7.  Each is a problem naming the effect and the bound."""
    found = [
        _found("cross_eddy", {"alpha": 1.26, "tau_s": 0.31e-6}, axis="x", input_axis="y"),
        _found("cross_eddy", {"alpha": -4.06, "tau_s": 0.31e-6}, axis="y", input_axis="x"),
        _found("delay", {"seconds": 150e-6}, axis="z"),
        _found("gain", {"factor": 1.7}, axis="x"),
        _found("exp_eddy", {"alpha": 0.02, "tau_s": 2e-3}, axis="x"),  # physical: no problem
    ]
    probs = adopt.bound_problems(found, DT)
    by = {}
    for p in probs:
        by.setdefault(p.index, []).append(p.reason)
    assert sorted(by) == [0, 1, 2, 3]
    assert any("alpha = 1.26" in r and "|alpha| < 1" in r for r in by[0])
    assert any("tau_s = 3.1e-07" in r for r in by[0])
    assert any("alpha = -4.06" in r for r in by[1])
    assert "seconds = 0.00015" in by[2][0]
    assert "factor = 1.7" in by[3][0]


def test_identification_rule():
    ok = _found("exp_eddy", {"alpha": 0.02, "tau_s": 2e-3}, axis="x", stderr={"alpha": 0.006, "tau_s": 1e-4})
    weak = _found("exp_eddy", {"alpha": 0.02, "tau_s": 2e-3}, axis="x", stderr={"alpha": 0.007, "tau_s": 1e-4})
    gain = _found("gain", {"factor": 1.0003}, axis="y", stderr={"factor": 0.0002})  # |1.0003 - 1| / 3 = 1e-4
    nan = _found("delay", {"seconds": 2e-6}, axis="y", stderr={"seconds": float("nan")})
    probs = adopt.identification_problems([ok, weak, gain, nan], at_bound=[])
    assert sorted({p.index for p in probs}) == [1, 2, 3]
    assert all("not identified" in p.reason for p in probs)
    assert adopt.identification_problems([ok], at_bound=[(0, "tau_s")])[0].reason.endswith("bound of its fit")


def test_heldout_rule_and_offender():
    before = {"G": 0.05, "k": None, "b0": 0.02}
    assert adopt.heldout_problems(before, {"G": 0.049, "b0": 0.02}, ["G", "b0"]) == []
    probs = adopt.heldout_problems(before, {"G": 9.9e6, "b0": 0.01}, ["G", "b0"])
    assert len(probs) == 1 and "worse than the declared" in probs[0].reason and probs[0].index is None
    found = [_found("delay", {"seconds": 1e-6}, score=50.0), _found("gain", {"factor": 1.01}, score=20.0)]
    assert adopt.pick_offender(probs, found) == 1  # model-level problem: the effect added last
    assert adopt.pick_offender([adopt.Problem(0, "a"), adopt.Problem(1, "b")], found) == 1  # the lower score


def test_roundtrip_refuses_a_model_its_own_loader_rejects():
    g = probe_waveforms(2, 300, DT, seed=1)
    ok = HardwareModel([build_effect("exp_eddy", {"alpha": 0.05, "tau_s": 1e-3}, axis="x")])
    assert adopt.roundtrip_problem(ok, g, DT) is None
    bad = HardwareModel([build_effect("exp_eddy", {"alpha": 1.5, "tau_s": 1e-3}, axis="x")])
    p = adopt.roundtrip_problem(bad, g, DT)
    assert p is not None and "does not load back" in p.reason


def _random_declared(rng) -> HardwareModel:
    gi = lowpass_girf(
        DT,
        bandwidth_hz=float(rng.uniform(4e3, 25e3)),
        cross=float(rng.uniform(0.0, 0.03)),
        b0_uT_per_mT_per_m=float(rng.uniform(0.0, 0.01)) if rng.random() < 0.5 else None,
    )
    effs = [girf_effect(gi)]
    ax = ["x", "y", "z"]
    for _ in range(int(rng.integers(0, 3))):
        k = rng.choice(["delay", "gain", "exp_eddy", "cross_eddy", "offset"])
        a = str(rng.choice(ax))
        if k == "delay":
            effs.append(build_effect("delay", {"seconds": float(rng.uniform(-5e-6, 5e-6))}, axis=a))
        elif k == "gain":
            effs.append(build_effect("gain", {"factor": float(rng.uniform(0.95, 1.05))}, axis=a))
        elif k == "offset":
            effs.append(build_effect("offset", {"mT_per_m": float(rng.uniform(-0.1, 0.1))}, axis=a))
        elif k == "exp_eddy":
            p = {"alpha": float(rng.uniform(-0.05, 0.05)), "tau_s": float(rng.uniform(1e-4, 5e-3))}
            effs.append(build_effect("exp_eddy", p, axis=a))
        else:
            i = str(rng.choice([x for x in ax if x != a]))
            p = {"alpha": float(rng.uniform(-0.02, 0.02)), "tau_s": float(rng.uniform(1e-4, 5e-3))}
            effs.append(build_effect("cross_eddy", p, axis=a, input_axis=i))
    return HardwareModel(effs)


@pytest.mark.slow  # (22 s)
def test_fifty_random_declared_models_without_undeclared_effect_adopt_nothing():
    """Property: when the scanner is exactly the declared model (random GIRF bandwidth, cross terms, B0 row,
    declared delays/gains/offsets/eddy currents), identify adopts nothing and writes no model."""
    g = probe_waveforms(3, 800, DT, seed=3)
    adopted = []
    for seed in range(50):
        rng = np.random.default_rng(1000 + seed)
        declared = _random_declared(rng)
        with_b0 = any(getattr(e, "h0", None) is not None for e in declared.effects)
        data = simulate_measurement(declared, g, DT, sigma_G=0.01, sigma_b0=0.005 if with_b0 else None, seed=seed + 7)
        r = identify(data, declared)
        if r.adopted:
            adopted.append((seed, [f.effect.kind for f in r.twin.found]))
    assert adopted == []


class _Saturation(torch.nn.Module):
    """Amplifier saturation on x (not in the library): G = gmax tanh(G_decl / gmax)."""

    def __init__(self, declared, gmax):
        super().__init__()
        self.declared, self.gmax = declared, gmax

    def forward(self, g, dt_s):
        G, b0 = self.declared(g, dt_s)
        G = G.clone()
        G[:, 0] = self.gmax * torch.tanh(G[:, 0] / self.gmax)
        return G, b0


class _Resonance(torch.nn.Module):
    """A damped mechanical resonance on y driven by the slew (f0 3.1 kHz, Q 40): not in the library."""

    def __init__(self, declared, amp):
        super().__init__()
        self.declared, self.amp = declared, amp

    def forward(self, g, dt_s):
        G, b0 = self.declared(g, dt_s)
        t = torch.arange(int(0.02 / dt_s), dtype=g.dtype) * dt_s
        w0 = 2 * np.pi * 3.1e3
        h = torch.exp(-w0 / 80 * t) * torch.sin(w0 * t) * dt_s
        s = torch.diff(g[:, 1], dim=-1, prepend=torch.zeros_like(g[:, 1, :1]))  # mT/m per sample
        ring = torch.nn.functional.conv1d(
            torch.nn.functional.pad(s.unsqueeze(1), (len(t) - 1, 0)), h.flip(0).reshape(1, 1, -1)
        )[:, 0]
        G = G.clone()
        G[:, 1] = G[:, 1] + self.amp * ring / dt_s * 1e-3
        return G, b0


@pytest.mark.parametrize("case", [pytest.param(0, marks=pytest.mark.slow), *range(1, 6)])  # (case 0: 14 s)
def test_a_written_model_is_never_worse_held_out_and_always_loads(case, tmp_path):
    """Property over truths the library may or may not represent (a saturating amplifier, a resonance, an
    undeclared delay or eddy current, and the search forced to add noise with threshold -inf): whatever is
    adopted is identified, physical, no worse held out on every channel, and loads back predicting the same."""
    declared = HardwareModel([girf_effect(lowpass_girf(DT))])
    g = probe_waveforms(4, 1500, DT, seed=11 + case)
    threshold = 10.0
    if case == 0:
        truth = _Saturation(declared, 25.0)
    elif case == 1:
        truth = _Resonance(declared, 0.3)
    elif case == 2:
        truth = HardwareModel([*declared.effects, build_effect("delay", {"seconds": 3e-6}, axis="x")])
    elif case == 3:
        truth = HardwareModel([*declared.effects, build_effect("exp_eddy", {"alpha": 0.03, "tau_s": 8e-3}, axis="z")])
    else:
        truth, threshold = declared, -1e9
    data = simulate_measurement(truth, g, DT, sigma_G=0.01, seed=case)
    r = identify(data, declared, threshold=threshold, max_effects=4)
    if case in (2, 3):
        assert r.adopted  # a modellable effect is still found
    for f in r.twin.found:
        e = f.effect
        for n in e.param_names if e.kind != "lti" else ():
            v = float(getattr(e, n).detach())
            size = abs(v - 1.0) if e.kind == "gain" else abs(v)
            assert f.stderr[n] < size / 3, (e.kind, n, v, f.stderr[n])
    assert adopt.bound_problems(r.twin.found, DT) == []
    for c in data.channels():
        assert r.heldout_after[c] <= r.heldout_before[c], (c, r.heldout_after[c], r.heldout_before[c])
    if r.adopted:
        from dtoc.hardware.model import save_model

        save_girf(lowpass_girf(DT), tmp_path / "h.npz")
        m = r.updated_model()
        m.effects[0].file = str(tmp_path / "h.npz")
        save_model(m, tmp_path / "updated.json")
        back = load_model(tmp_path / "updated.json")
        gt = torch.as_tensor(g)
        with torch.no_grad():
            torch.testing.assert_close(back(gt, DT)[0], m(gt, DT)[0], rtol=1e-12, atol=1e-12)


def test_cli_writes_no_model_when_nothing_is_adopted(tmp_path, capsys):
    """A measurement the declared model explains: exit 0, report adopted false, -o not written, and an
    existing -o (with --force) left byte-for-byte untouched."""
    gi = lowpass_girf(DT)
    save_girf(gi, tmp_path / "h.npz")
    data = simulate_measurement(HardwareModel([girf_effect(gi)]), probe_waveforms(3, 800, DT, seed=2), DT, seed=4)
    save_measurement(data, tmp_path / "m.npz")
    args = ["identify", tmp_path / "m.npz", "--girf", tmp_path / "h.npz", "-o", tmp_path / "u.json"]
    code, out, err = run_cli(capsys, *args, "--json", tmp_path / "r.json")
    assert code == 0, err
    assert not (tmp_path / "u.json").exists()
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["adopted"] is False and rep["effects"] == [] and rep["rejected"] == []
    assert "no model written" in err and "no updated model" in out
    (tmp_path / "u.json").write_text("keep me\n")
    code, out, err = run_cli(capsys, *args, "--force", "-q")
    assert code == 0, err
    assert (tmp_path / "u.json").read_text() == "keep me\n"


@pytest.mark.parametrize(
    "truth, kind, param, true, tol",
    [
        (dict(kind="delay", params={"seconds": 3.3e-6}, axis="y"), "delay", "seconds", 3.3e-6, 0.05e-6),
        (dict(kind="exp_eddy", params={"alpha": 0.03, "tau_s": 1e-4}, axis="x"), "exp_eddy", "tau_s", 1e-4, 5e-6),
    ],
)
def test_an_lti_equivalent_to_a_physical_effect_is_reported_as_that_effect(truth, kind, param, true, tol):
    """An lti fitted (here: the library restricted to lti) to what is a plain delay / short eddy current is
    replaced by that physical effect, with its parameter, when the information criterion says they are
    equivalent within noise."""
    from dtoc.identify.search import ltis_to_physical

    decl = HardwareModel([girf_effect(lowpass_girf(DT))])
    g = probe_waveforms(6, 3000, DT, seed=3)
    data = simulate_measurement(HardwareModel([*decl.effects, build_effect(**truth)]), g, DT, seed=5)
    r = identify(data, decl, kinds=["lti", "offset"])
    assert [f.effect.kind for f in r.twin.found] == ["lti"]
    ltis_to_physical(r.twin, data, r.twin.sigma, r.folds, None, lambda s: None)
    (f,) = r.twin.found
    assert f.effect.kind == kind and f.effect.axis == truth["axis"]
    assert abs(float(getattr(f.effect, param).detach()) - true) < tol


def test_a_model_file_refuses_the_measurement_clock(tmp_path):
    """time_base belongs to the measurement: a hardware model file holding it is refused with one line."""
    from dtoc.errors import InputError

    (tmp_path / "m.json").write_text(json.dumps({"effects": [{"kind": "time_base", "params": {"ppm": 50.0}}]}))
    with pytest.raises(InputError, match=r"effects\[0\] \(time_base\): describes the measuring device"):
        load_model(tmp_path / "m.json")
