"""Regression tests for defects found in the audit of `dtoc girf import/fit/show` and `dtoc predict`:
implausible magnitudes (unit mistakes), bad option values, the Prisma out-of-band noise, plots, JSON."""

import json

import numpy as np
import pytest
from cli_helpers import run_cli as _run  # noqa: E402

from dtoc.errors import InputError
from dtoc.hardware.girf_io import load_girf
from dtoc.hardware.measurement import k_from_G, load_measurement
from dtoc.hardware.npzio import save_npz


def _strict_json(text):
    def bad(c):
        raise ValueError(f"non-standard JSON constant {c}")

    return json.loads(text, parse_constant=bad)


def _lowpass(L=64, dt=10e-6):
    """A plausible 3x3 GIRF: unit-DC self terms (centred triangle), 1 % cross terms, small B0 terms."""
    tri = np.bartlett(9)
    tri = tri / tri.sum()
    h = np.zeros((3, 3, L))
    for a in range(3):
        h[a, a, L // 2 - 4 : L // 2 + 5] = tri
    h[1, 0, L // 2] = 0.01
    h0 = np.zeros((3, L))
    h0[:, L // 2] = 0.05
    return {"dt": np.float64(dt), "t0": np.float64(-(L // 2) * dt), "h": h, "h0": h0}


@pytest.mark.parametrize(
    "change,match",
    [
        (lambda z: {**z, "h": z["h"] * 1000}, "DC gain of self term x->x is 1000.*units off by 1e3"),
        (lambda z: {**z, "h": z["h"] / z["dt"]}, "density in 1/s"),
        (lambda z: {**z, "h": -z["h"]}, "DC gain of self term x->x is -1"),
        (lambda z: {**z, "h": 0 * z["h"]}, "DC gain of self term x->x is 0"),
        (lambda z: {**z, "dt": z["dt"] * 1e3}, "'dt' = 0.01 s is implausible"),
        (lambda z: {**z, "t0": z["t0"] * 1e6}, "'t0' = -320 s is implausible"),
        (lambda z: {**z, "h": z["h"] + 0.8 * np.eye(3)[::-1][..., None] * (np.arange(64) == 32)}, "cross term"),
        (lambda z: {**z, "h0": z["h0"] * 1e4}, "B0 term x->b0 is 500 uT per mT/m"),
    ],
)
def test_implausible_girf_magnitudes_rejected(tmp_path, change, match):
    # defect: a GIRF with DC gain 1000 loaded fine and predicted 450 dk errors; one with dt in ms made
    # `dtoc predict` resample a 20 s kernel onto a 5 us grid and get killed for memory
    good = _lowpass()
    save_npz(tmp_path / "good.npz", good)
    assert load_girf(tmp_path / "good.npz").h.shape == (3, 3, 64)
    save_npz(tmp_path / "bad.npz", change(good))
    with pytest.raises(InputError, match=match):
        load_girf(tmp_path / "bad.npz")


def test_girf_load_messages(tmp_path):
    with pytest.raises(InputError, match="is a directory"):
        load_girf(tmp_path)
    (tmp_path / "h.mat").write_bytes(b"MATLAB")
    with pytest.raises(InputError, match="convert it first with 'dtoc girf import"):
        load_girf(tmp_path / "h.mat")


def _meas(tmp_path, name, scale_G=1.0, scale_g=1.0, dt=10e-6, use_k=False, k_scale=1.0):
    t = np.arange(1500) * 10e-6
    g = np.zeros((3, 3, t.size))
    for m in range(3):
        g[m, m] = 15 * np.clip(1 - np.abs(t - 3e-3) / 1e-4, 0, None)
    arr = {"dt": np.float64(dt), "g": g * scale_g}
    if use_k:
        arr["k"] = k_from_G(g, 10e-6) * k_scale
    else:
        arr["G"] = g * scale_G
    save_npz(tmp_path / name, arr)
    return tmp_path / name


@pytest.mark.parametrize(
    "kw,match",
    [
        ({"scale_G": 1e-3}, "key 'G' is 0.001 times the demanded 'g'"),
        ({"scale_G": 1e3}, "key 'G' is 1e\\+03 times"),
        ({"use_k": True, "k_scale": 1 / (2 * np.pi)}, "key 'k' is 0.159 times"),
        ({"scale_g": 1e-3, "scale_G": 1e-3}, "key 'g' peaks at 0.015 mT/m"),
        ({"dt": 10e-3}, "key 'dt' = 0.01 s is implausible"),
    ],
)
def test_implausible_measurement_units_rejected(tmp_path, kw, match):
    # defect: a measurement in T/m instead of mT/m was fitted into a GIRF with DC gain 0.001
    assert load_measurement(_meas(tmp_path, "ok.npz")).n_waveforms == 3
    assert load_measurement(_meas(tmp_path, "okk.npz", use_k=True)).k is not None
    with pytest.raises(InputError, match=match):
        load_measurement(_meas(tmp_path, "bad.npz", **kw))


@pytest.mark.parametrize(
    "argv,match",
    [
        (["girf", "import", "{g}", "-o", "{o}", "--shift-us", "nan"], "--shift-us must be a finite number"),
        (["girf", "fit", "{m}", "-o", "{o}", "--fmax-khz", "nan"], "--fmax-khz must be a finite number > 0"),
        (["girf", "fit", "{m}", "-o", "{o}", "--reg", "inf"], "--reg must be a finite number > 0"),
        (["girf", "import", "{g}", "-o", "{o}"], "already a .npz"),
        (["girf", "import", "{d}", "-o", "{o}"], "is a directory"),
        (["predict", "{s}", "--device", "foo"], "--device 'foo' is not a torch device"),
        (["predict", "{s}", "--girf", "{g}", "--png", "{g}"], "would overwrite the --girf input"),
    ],
)
def test_cli_bad_option_values(capsys, tmp_path, repo_root, argv, match):
    # defect: NaN options were accepted (a NaN delay was written into the GIRF), an unknown --device
    # ended in "unexpected RuntimeError"
    save_npz(tmp_path / "g.npz", _lowpass())
    m = _meas(tmp_path, "m.npz")
    subs = {
        "{g}": tmp_path / "g.npz",
        "{o}": tmp_path / "o.npz",
        "{m}": m,
        "{d}": tmp_path,
        "{s}": repo_root / "sequences" / "epi_small.seq",
    }
    code, out, err = _run(capsys, *[subs.get(a, a) for a in argv])
    assert code == 2 and err.startswith("dtoc: error: ") and err.count("\n") == 1, err
    assert match in err and out == ""
    assert not (tmp_path / "o.npz").exists()


def test_fit_reports_supported_band_and_is_cwd_independent(capsys, tmp_path, monkeypatch):
    # slow triangles carry no energy at high f: the notes must say where the data stop supporting H;
    # the output records the input's name and hash, not the path typed, so it is byte-identical from any cwd
    m = _meas(tmp_path, "m.npz")
    code, out, err = _run(capsys, "girf", "fit", m, "-o", tmp_path / "a.npz", "--json", "-")
    assert code == 0, err
    res = _strict_json(out)
    note = [n for n in res["notes"] if n.startswith("data support the fit up to")]
    assert note and 1e3 < float(note[0].split()[6]) < 50e3
    monkeypatch.chdir(tmp_path)
    code, _, err = _run(capsys, "girf", "fit", "m.npz", "-o", "b.npz")
    assert code == 0, err
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()


def test_prisma_import_is_band_limited_like_the_published_kernel(shared_data, tmp_path):
    # defect: the Prisma GIRF_FT holds measurement noise up to |H| ~ 3e3 above 63 kHz; converted to taps
    # it filled the whole 82 ms kernel with noise (taps summing to |h| ~ 4e3), so `dtoc predict` showed a
    # slice-select echo 41 ms later and a 29 mT B0.  The import now uses the band of the file's own
    # GIRF_Temporal and keeps the 16384-point grid (taps exactly 5 us apart).
    import h5py

    from dtoc.hardware.girf_import import import_girf

    d = shared_data / "girf" / "siemens_prisma_3T_2020"
    gd = import_girf([d / f"GIRF_{a}.mat" for a in "XYZ"])
    td = gd.to_time_domain()
    assert td.dt_s == pytest.approx(5e-6, rel=1e-12) and td.h.shape[-1] == 16384
    assert np.max(np.abs(gd.H[[0, 1, 2], [0, 1, 2]])) < 3.0
    assert any("band-limited to |f| <= 63354.5 Hz" in n for n in gd.notes)
    for a, ax in enumerate("XYZ"):
        with h5py.File(d / f"GIRF_{ax}.mat", "r") as z:
            ref = np.asarray(z["GIRF_Temporal"]).ravel()
        ref = ref["real"] if ref.dtype.names else ref
        # same kernel as the publishers' time-domain one (their imaginary residue is 2.4e-5)
        assert np.max(np.abs(td.h[a, a] - ref)) < 5e-5
        assert np.sum(np.abs(td.h[a, a])) < 20  # was ~4e3 of noise
        assert td.h[a, a].sum() == pytest.approx(1.0, abs=1e-3)


def test_show_png_and_predict_png(capsys, tmp_path, repo_root):
    from dtoc.hardware.girf_plot import plot_girf
    from dtoc.hardware.model import HardwareModel, girf_effect
    from dtoc.seq.read import read_seq
    from dtoc.sim.predict import plot_prediction, predict, zoom_window_ms

    save_npz(tmp_path / "g.npz", _lowpass())
    gd = load_girf(tmp_path / "g.npz")
    p = plot_girf(gd, tmp_path / "g.png", title="t")
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 20_000
    with pytest.raises(InputError, match="output exists"):
        plot_girf(gd, tmp_path / "g.png")
    ir = read_seq(repo_root / "sequences" / "gre_small.seq")
    res = predict(ir, HardwareModel([girf_effect(gd)]))
    # defect: a GRE's repeated readouts were reported as EPI odd/even lines
    assert res["epi"] is None
    lo, hi = zoom_window_ms(ir)
    assert 0 < hi - lo < 6.0
    q = plot_prediction(ir, res, tmp_path / "p.png", title="gre")
    assert q.stat().st_size > 20_000
    code, out, err = _run(
        capsys, "predict", repo_root / "sequences" / "gre_small.seq", "--girf", tmp_path / "g.npz", "--json", "-"
    )
    assert code == 0 and _strict_json(out)["epi"] is None


def test_is_epi_without_kind():
    from dtoc.seq.ir import ADCEvent, SequenceIR, edges_to_fine
    from dtoc.sim.predict import is_epi

    r = 10e-6
    e = np.zeros((3, 61))
    e[0, 10:20], e[0, 30:40] = 5.0, -5.0
    ir = SequenceIR(
        raster_s=r,
        grad_mT_per_m=edges_to_fine(e),
        block_edges_s=np.array([0.0, 60 * r]),
        adc=[ADCEvent(0, 11 * r, 4, 2 * r), ADCEvent(0, 31 * r, 4, 2 * r)],
        readout_axis=0,
    )
    assert is_epi(ir)
    e[0, 30:40] = 5.0
    ir.grad_mT_per_m = edges_to_fine(e)
    assert not is_epi(ir)


@pytest.mark.parametrize(
    "effect,match",
    [
        ('{"kind": "gain", "axis": "x", "params": {"factor": 1000}}', "factor = 1000 is implausible"),
        ('{"kind": "delay", "axis": "x", "params": {"seconds": 2}}', "seconds = 2 is implausible"),
        ('{"kind": "exp_eddy", "params": {"alpha": [0.1, 0.1], "tau_s": [1, 100]}}', "tau_s = 100 is implausible"),
        ('{"kind": "slew_limit", "params": {"max_slew_T_per_m_per_s": 0.18}}', "max_slew_T_per_m_per_s = 0.18"),
    ],
)
def test_implausible_model_file_parameters(tmp_path, effect, match):
    # defect: {"gain": 1000} in a model file predicted k errors of 1.3e4 rad/m without a word
    from dtoc.hardware.model import load_model

    (tmp_path / "ok.json").write_text(
        '{"effects": [{"kind": "exp_eddy", "params": {"alpha": [0.1], "tau_s": [1e-3]}}]}'
    )
    assert len(load_model(tmp_path / "ok.json").effects) == 1
    (tmp_path / "m.json").write_text(f'{{"effects": [{effect}]}}')
    with pytest.raises(InputError, match=match):
        load_model(tmp_path / "m.json")


def test_measurement_edge_files(tmp_path):
    p = tmp_path / "a.npz"
    with open(p, "wb") as f:
        np.save(f, np.zeros(3))
    with pytest.raises(InputError, match="not an .npz archive"):
        load_measurement(p)
    g = np.zeros((1, 3, 10))
    g[0, 0, 3:6] = 1.0
    np.savez(tmp_path / "b.npz", dt="abc", g=g, G=g)
    with pytest.raises(InputError, match="must be a scalar number"):
        load_measurement(tmp_path / "b.npz")
    np.savez(tmp_path / "c.npz", dt=1e-5, g=g, G=g, sigma_G=0.0)
    with pytest.raises(InputError, match="sigma_G"):
        load_measurement(tmp_path / "c.npz")
