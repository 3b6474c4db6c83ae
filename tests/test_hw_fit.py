"""`girf fit`: regularised LS recovers a known 3x3 GIRF + B0 row from noisy synthetic measurements."""

import numpy as np
import pytest
import torch

from dtoc.hardware import Measurement, load_girf, save_measurement
from dtoc.hardware.effects import Girf
from dtoc.hardware.girf_analysis import girf_summary
from dtoc.identify.girf_fit import fit_girf

DT, N = 10e-6, 4096


def _triangle(t, t0, ramp, amp):
    return amp * np.clip(1 - np.abs(t - t0 - ramp) / ramp, 0, None)


def _inputs(seed, kinds):
    """(M, 3, N) demanded waveforms: each drives one axis (triangles and a chirp), M = 3 * len(kinds)."""
    t = np.arange(N) * DT
    rng = np.random.default_rng(seed)
    out = []
    for kind in kinds:
        for a in range(3):
            g = np.zeros((3, N))
            if kind == "chirp":
                T = 20e-3
                env = np.clip(t / 1e-3, 0, 1) * np.clip((T - t) / 1e-3, 0, 1)
                g[a] = 4.0 * env * np.sin(2 * np.pi * (0.5 * 30e3 / T) * t**2)
            else:
                g[a] = _triangle(t, 2e-3 + rng.uniform(0, 1e-3), kind, 20.0)
            out.append(g)
    return np.stack(out)


def _true_model(repo_root):
    gd = load_girf(repo_root / "girf" / "example_7T.npz")
    return gd, Girf(gd.h, gd.dt_s, gd.t0_s, gd.h0)


def _apply(eff, g):
    with torch.no_grad():
        G, b0 = eff(torch.as_tensor(g), torch.zeros(g.shape[0], g.shape[-1], dtype=torch.float64), DT)
    return G.numpy(), b0.numpy()


@pytest.fixture(scope="module")
def setup(repo_root):
    gd, eff = _true_model(repo_root)
    g = _inputs(0, [50e-6, 100e-6, 200e-6, "chirp"])
    G, b0 = _apply(eff, g)
    rng = np.random.default_rng(42)
    sG, sb = 0.02, 0.001
    meas = Measurement(
        DT,
        g,
        G + rng.normal(0, sG, G.shape),
        None,
        b0 + rng.normal(0, sb, b0.shape),
        sG,
        None,
        sb,
        [f"w{i}" for i in range(len(g))],
        np.ones((len(g), 3), bool),
        "synthetic",
    )
    return gd, eff, meas


def test_fit_recovers_known_girf(setup, tmp_path):
    gd, eff, meas = setup
    fit = fit_girf(meas, reg=1e-6, fmax_hz=40e3)
    f = np.linspace(0, 15e3, 301)
    Ht, H0t = gd.response(f)
    Hf, H0f = fit.response(f)
    # expected noise of H per frequency: noise DFT variance sigma^2 N over input power S_ii(f)
    nfft = 2 * N
    I = np.fft.fft(meas.g, n=nfft, axis=-1)
    Sii = np.sum(np.abs(I) ** 2, axis=0)  # (3, nfft): each waveform drives one axis, S is diagonal
    fk = np.fft.fftfreq(nfft, DT)
    band = (fk >= 0) & (fk <= 15e3)
    sH = meas.sigma_G * np.sqrt(N / Sii[:, band])  # (3, F) noise std of H[:, i]
    sH0 = meas.sigma_b0 * np.sqrt(N / Sii[:, band])
    f = fk[band]
    Ht, H0t = gd.response(f)
    Hf, H0f = fit.response(f)
    z = np.abs(Hf - Ht) / sH[None, :, :]  # (o, i, F): error in units of its noise std
    z0 = np.abs(H0f - H0t) / sH0
    # noise-limited: errors are Rayleigh-like with scale ~ noise std (max of ~1500 draws ~ 3.8)
    assert 0.4 < np.median(z) < 1.5, np.median(z)
    assert np.max(z) < 6.0, np.max(z)
    assert 0.4 < np.median(z0) < 1.5 and np.max(z0) < 6.0, (np.median(z0), np.max(z0))
    assert np.max(sH) < 0.02  # and that noise level is small against the 1 % cross terms
    rows = {r["term"]: r for r in girf_summary(fit)}
    assert rows["x->x"]["dc_gain"] == pytest.approx(1.0, abs=1e-2)  # noise std of H at DC ~3e-3
    assert rows["y->y"]["bandwidth_3db_hz"] == pytest.approx(10.7e3, rel=0.02)
    assert rows["x->x"]["group_delay_s"] == pytest.approx(2e-6, abs=0.5e-6)
    # file round trip through the CLI-facing writer
    p = save_measurement(meas, tmp_path / "meas.npz")
    assert p.exists()


def test_fit_predicts_heldout_waveforms_at_noise_level(setup):
    gd, eff, meas = setup
    opts = dict(reg=1e-4, fmax_hz=40e3, time_window_s=(-2e-3, 8e-3))  # windows cut noise-only taps/bins
    fit = fit_girf(meas, **opts)
    eff_fit = Girf(fit.h, fit.dt_s, fit.t0_s, fit.h0)
    held = _inputs(7, [150e-6, 300e-6])  # other triangles, never used for fitting
    G_true, b0_true = _apply(eff, held)
    G_fit, b0_fit = _apply(eff_fit, held)
    win = slice(int(1e-3 / DT), int(8e-3 / DT))  # where the held-out waveforms and their responses live
    rms = lambda a: float(np.sqrt(np.mean(a[..., win] ** 2)))  # noqa: E731
    rms_fit, rms_ideal = rms(G_fit - G_true), rms(held - G_true)  # baseline: ideal hardware (G = g)
    print("held-out RMS error: fitted", rms_fit, "ideal", rms_ideal, "noise sigma", meas.sigma_G)
    assert rms_fit < 0.25 * meas.sigma_G  # prediction error well below the per-sample noise
    assert np.max(np.abs(G_fit - G_true)) < 1.5 * meas.sigma_G
    assert rms_ideal > 10 * rms_fit
    assert rms(b0_fit - b0_true) < 0.5 * meas.sigma_b0
    # fitted on fewer waveforms (triangles of one width only): the full fit predicts better
    fit_small = fit_girf(meas.subset(slice(0, 3)), **opts)
    G_small, _ = _apply(Girf(fit_small.h, fit_small.dt_s, fit_small.t0_s, fit_small.h0), held)
    assert rms_fit < rms(G_small - G_true)


def test_fit_rejects_unmeasured_axis_and_bad_options(setup):
    from dtoc.errors import InputError

    gd, eff, meas = setup
    m2 = meas.subset(slice(None))
    m2.axes_measured = m2.axes_measured.copy()
    m2.axes_measured[:, 2] = False
    with pytest.raises(InputError, match="axis z is never measured"):
        fit_girf(m2)
    with pytest.raises(InputError, match="reg"):
        fit_girf(meas, reg=-1)
