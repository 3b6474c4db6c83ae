"""Regression tests for defects found in the audit of `dtoc identify` (one per defect, all fast).

* a `.npy` array saved under an `.npz` name crashed with "unexpected TypeError" (exit 3);
* a `dt` written in ms (1e3 too large) passed when it fell inside the plausible dt range;
* low-frequency broadband structure (a non-linear gain) was reported as a "narrow-band" residual at the
  lowest periodogram bin, i.e. as a resonance;
* an `lti` correction's "largest |dH|" was searched up to Nyquist, where the data excite nothing
  (noise-fitting, e.g. "|dH| 1.35 near 47.9 kHz");
* a hysteresis-like offset (depends on the sign of the last ramp) had no note of its own;
* the noise floor was biased low (-10 % for b0) by taking the lower of two noisy estimates;
* the residual PNG overlaid all axes in one panel (before/after indistinguishable) and pooled the spectrum;
* `-o` equal to the measurement overwrote it with `--force`; `-o x --json x` wrote the model, then failed.
"""

import json
import struct

import numpy as np
import pytest
import torch
from cli_helpers import run_cli

from dtoc.hardware.girf_io import save_girf
from dtoc.hardware.model import HardwareModel, girf_effect
from dtoc.identify import diagnostics
from dtoc.identify.candidates import excited_band_hz, lti_features
from dtoc.identify.data import IdentData
from dtoc.identify.noise import quiet_samples
from dtoc.identify.search import identify
from dtoc.identify.synth import lowpass_girf, probe_waveforms

DT = 10e-6
SIGMA = 0.01


def _run(argv, capsys):
    return run_cli(capsys, *argv)


@pytest.fixture(scope="module")
def setup():
    gd = lowpass_girf(DT)
    decl = HardwareModel([girf_effect(gd)])
    g = probe_waveforms(4, 2500, DT, seed=3)
    with torch.no_grad():
        G0 = decl(torch.as_tensor(g), DT)[0].numpy()
    return gd, decl, g, G0


def test_npy_under_npz_name_is_a_one_line_error(tmp_path, capsys):
    p = tmp_path / "m.npz"
    with open(p, "wb") as f:
        np.save(f, np.zeros((2, 3, 50)))
    code, _, err = _run(["identify", str(p), "-o", str(tmp_path / "u.json")], capsys)
    assert code == 2 and err.startswith("dtoc: error:") and err.count("\n") == 1
    assert "not an .npz" in err and "unexpected" not in err
    assert not (tmp_path / "u.json").exists()


def test_dt_in_ms_is_caught_by_the_slew_rate(tmp_path, capsys):
    """1-us samples with dt written in ms (0.001): dt is inside the plausible range, the slew is not."""
    g = probe_waveforms(2, 3000, 1e-6, seed=1)
    p = tmp_path / "m.npz"
    np.savez(p, dt=np.float64(1e-3), g=g, G=g)
    code, _, err = _run(["identify", str(p), "-o", str(tmp_path / "u.json")], capsys)
    assert code == 2 and "'dt'" in err and "T/m/s" in err and err.count("\n") == 1
    assert not (tmp_path / "u.json").exists()


def _data(g, G):
    return IdentData(dt_s=DT, g=g, G=G)


def test_broadband_low_frequency_residual_is_not_called_narrow_band(setup):
    _, _, g, _ = setup
    rng = np.random.default_rng(0)
    z_broad = 3.0 * g / np.abs(g).max() * 10 + rng.standard_normal(g.shape)  # follows the waveforms
    peaks = diagnostics.spectral_peaks(_data(g, g), "G", z_broad)
    assert peaks and not peaks[0]["narrow"] and peaks[0]["f_hz"] < 1e3
    t = np.arange(g.shape[-1]) * DT
    z_line = rng.standard_normal(g.shape) + 0.5 * np.sin(2 * np.pi * 3.6e3 * t)  # a resonance-like line
    peaks = diagnostics.spectral_peaks(_data(g, g), "G", z_line)
    assert peaks and peaks[0]["narrow"] and abs(peaks[0]["f_hz"] - 3.6e3) < 400


def test_lti_features_stay_in_the_excited_band(setup):
    _, _, g, _ = setup
    band = excited_band_hz(g[:, 0], DT)
    assert 3e3 < band < 30e3
    taps = np.zeros(48)
    taps[4] = 0.01  # small DC change ...
    taps[10:20] = 0.3 * (-1.0) ** np.arange(10)  # ... and a large response near Nyquist (unconstrained there)
    full = lti_features(taps, -4, DT)
    inband = lti_features(taps, -4, DT, band)
    assert full["peak_hz"] > 40e3
    assert inband["peak_hz"] <= band and inband["band_hz"] == pytest.approx(band)


def _hysteresis(g, h):
    s = diagnostics.last_ramp_direction(g)
    return h * s


def test_direction_note_flags_hysteresis_not_noise_or_amplitude(setup):
    _, _, g, _ = setup
    rng = np.random.default_rng(1)
    q = quiet_samples(g)
    d = _data(g, g)
    noise = SIGMA * rng.standard_normal(g.shape)
    assert diagnostics.direction_note(d, noise, SIGMA, q) is None
    amp = 2e-3 * g * np.abs(g)  # amplitude-dependent gain: nothing at zero demand
    assert diagnostics.direction_note(d, amp + noise, SIGMA, q) is None
    note = diagnostics.direction_note(d, _hysteresis(g, 0.02) + noise, SIGMA, q)
    assert note and "last ramp" in note and "hysteresis" in note


def test_amplitude_dependent_gain_is_not_explained_with_a_meaningful_note(setup):
    _, decl, g, G0 = setup
    rng = np.random.default_rng(2)
    d = _data(g, G0 * (1 + 2e-3 * np.abs(G0)) + SIGMA * rng.standard_normal(g.shape))
    r = identify(d, decl, max_effects=2)
    assert not r.explained
    notes = " | ".join(r.remaining)
    assert "amplitude" in notes
    assert not any(
        n.startswith("narrow-band") and float(n.split("near ")[1].split(" kHz")[0]) < 1.0 for n in r.remaining
    ), notes  # the waveforms' own low-frequency content is not a resonance


def test_hysteresis_is_not_explained_and_noted(setup):
    _, decl, g, G0 = setup
    rng = np.random.default_rng(3)
    d = _data(g, G0 + _hysteresis(g, 0.05) + SIGMA * rng.standard_normal(g.shape))
    r = identify(d, decl, max_effects=1)
    assert not r.explained
    assert any("last ramp" in n for n in r.remaining), r.remaining


def test_slew_limit_left_out_of_the_library_is_never_explained(setup):
    from dtoc.hardware.model import build_effect
    from dtoc.identify.synth import simulate_measurement

    gd, decl, g, _ = setup
    true = HardwareModel([build_effect("slew_limit", {"max_slew_T_per_m_per_s": 100.0}), girf_effect(gd)])
    d = simulate_measurement(true, g, DT, sigma_G=SIGMA, seed=9)
    r = identify(d, decl, max_effects=2, kinds=["delay", "gain", "offset", "exp_eddy", "lti"])
    assert not r.explained
    assert any("slew rate" in n for n in r.remaining), r.remaining


def _png_size(b: bytes):
    assert b[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", b[16:24])


def test_png_has_one_row_per_measured_axis(setup, tmp_path, capsys):
    gd, _, g, G0 = setup
    rng = np.random.default_rng(4)
    save_girf(gd, tmp_path / "h.npz")
    axes = np.ones((4, 3), dtype=bool)
    axes[:, 2] = False  # z never measured: garbage there must not matter
    G = G0 + SIGMA * rng.standard_normal(g.shape)
    G[:, 2] = 1e6
    np.savez(tmp_path / "m.npz", dt=DT, g=g, G=G, axes_measured=axes)
    argv = [
        "identify",
        str(tmp_path / "m.npz"),
        "--girf",
        str(tmp_path / "h.npz"),
        "-o",
        str(tmp_path / "u.json"),
        "--json",
        str(tmp_path / "r.json"),
        "--png",
        str(tmp_path / "r.png"),
        "-q",
        "--max-effects",
        "1",
    ]
    code, _, err = _run(argv, capsys)
    assert code == 0, err
    w, h = _png_size((tmp_path / "r.png").read_bytes())
    assert w == 15 * 80 and h == int((2.6 * 2 + 0.8) * 80)  # 3 panels x 2 rows (G x, G y)
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["effects"] == [] and rep["explained"] is True
    assert rep["heldout_after"]["G_rmse"] == pytest.approx(SIGMA, rel=0.05)


def _tiny(tmp_path):
    p = tmp_path / "m.npz"
    g = probe_waveforms(2, 400, DT, seed=2)
    np.savez(p, dt=DT, g=g, G=g)
    return p


def test_output_may_not_overwrite_an_input_even_with_force(tmp_path, capsys):
    p = _tiny(tmp_path)
    before = p.read_bytes()
    code, _, err = _run(["identify", str(p), "-o", str(p), "--force", "-q"], capsys)
    assert code == 2 and "would overwrite the MEASURED input" in err and err.count("\n") == 1
    assert p.read_bytes() == before


def test_same_path_for_two_outputs_is_refused_before_any_work(tmp_path, capsys):
    p = _tiny(tmp_path)
    out = tmp_path / "same.json"
    code, _, err = _run(["identify", str(p), "-o", str(out), "--json", str(out), "-q"], capsys)
    assert code == 2 and "-o" in err and "--json" in err
    assert not out.exists()  # was: model written, then the report refused after the whole run


def test_declared_model_variants(tmp_path, capsys):
    p = _tiny(tmp_path)
    gd = lowpass_girf(DT)
    save_girf(gd, tmp_path / "h.npz")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "m.json").write_text(
        json.dumps({"effects": [{"kind": "girf", "file": "h.npz", "params": {}, "axis": None, "input_axis": None}]})
    )
    code, _, err = _run(
        ["identify", str(p), "--model", str(tmp_path / "sub" / "m.json"), "-o", str(tmp_path / "u.json")], capsys
    )
    assert code == 2 and "h.npz" in err and err.count("\n") == 1  # a model JSON whose GIRF file is missing
    code, _, err = _run(
        [
            "identify",
            str(p),
            "--model",
            str(tmp_path / "sub" / "m.json"),
            "--girf",
            str(tmp_path / "h.npz"),
            "-o",
            str(tmp_path / "u.json"),
        ],
        capsys,
    )
    assert code == 2 and "--girf" in err and "--model" in err
    assert not (tmp_path / "u.json").exists()


def test_zero_sigma_in_the_file_is_estimated_and_said(setup):
    _, decl, g, G0 = setup
    rng = np.random.default_rng(6)
    d = IdentData(dt_s=DT, g=g, G=G0 + SIGMA * rng.standard_normal(g.shape), sigma={"G": 0.0})
    r = identify(d, decl, max_effects=0)
    assert r.noise["G"].sigma == pytest.approx(SIGMA, rel=0.05)
    assert "not usable" in r.noise["G"].method


def test_repeated_waveforms_stay_in_one_fold():
    """Held-out waveforms must be unseen: a repeat of a training waveform is not held-out data."""
    from dtoc.identify.folds import make_folds, waveform_groups

    g = probe_waveforms(3, 200, DT, seed=7)
    g = np.concatenate([g, g])  # waveforms 3, 4, 5 repeat 0, 1, 2
    f = make_folds(6, 200, groups=waveform_groups(g))
    fold = {u.m: k for u, k in zip(f.units, f.fold_of_unit)}
    assert f.K == 3 and all(fold[m] == fold[m + 3] for m in range(3))
    one = make_folds(4, 200, groups=waveform_groups(np.repeat(g[:1], 4, 0)))  # one distinct waveform
    assert one.mode == "time blocks" and one.K == 4 and len(one.units) == 16
    assert one.sample_mask(0, train=False).sum() == 4 * 50
