"""Hardware model chain, model files, GIRF files and measurement files: contracts and bad inputs."""

import json

import numpy as np
import pytest
import torch

from dtoc.errors import InputError
from dtoc.hardware import (
    GirfData,
    build_effect,
    load_girf,
    load_measurement,
    load_model,
    resolve_model,
    save_girf,
    save_measurement,
    save_model,
)
from dtoc.hardware.measurement import G_from_k, k_from_G
from dtoc.hardware.npzio import save_npz


def _girf(L=21, dt=10e-6):
    rng = np.random.default_rng(0)
    h = np.zeros((3, 3, L))
    h[[0, 1, 2], [0, 1, 2], L // 2] = 1.0
    h += rng.normal(0, 1e-3, h.shape)
    return GirfData(dt_s=dt, t0_s=-(L // 2) * dt, h=h, h0=rng.normal(0, 1e-3, (3, L)))


def test_identity_model_and_shapes():
    m = resolve_model()
    g = torch.randn(3, 100, dtype=torch.float64)
    G, b0 = m(g, 1e-5)
    assert m.is_identity and G.shape == (3, 100) and b0.shape == (100,)
    torch.testing.assert_close(G, g)
    assert float(b0.abs().max()) == 0.0
    G, b0 = m(torch.randn(4, 3, 100), 1e-5)
    assert G.shape == (4, 3, 100) and b0.shape == (4, 100)
    with pytest.raises(InputError):
        m(torch.randn(2, 100), 1e-5)


def test_chain_order_and_json_roundtrip(tmp_path):
    save_girf(_girf(), tmp_path / "h.npz")
    spec = {
        "effects": [
            {"kind": "girf", "file": "h.npz"},
            {"kind": "delay", "axis": "x", "params": {"seconds": 2.5e-6}},
            {"kind": "exp_eddy", "params": {"alpha": [0.1, 0.1], "tau_s": [1e-3, 0.1]}},
            {"kind": "cross_eddy", "axis": "y", "input_axis": "x", "params": {"alpha": 0.01, "tau_s": 1e-3}},
            {"kind": "b0_eddy", "input_axis": "z", "params": {"alpha_uT_per_mT_per_m": 0.05, "tau_s": 2e-3}},
            {"kind": "gain", "axis": "z", "params": {"factor": 0.98}},
            {"kind": "offset", "axis": "y", "params": {"mT_per_m": 0.01}},
            {"kind": "lti", "axis": "x", "params": {"taps": [0.0, 0.01, -0.01], "dt_s": 1e-5, "t0_s": -1e-5}},
            {"kind": "slew_limit", "params": {"max_slew_T_per_m_per_s": 200.0}},
        ]
    }
    (tmp_path / "m.json").write_text(json.dumps(spec))
    m = load_model(tmp_path / "m.json")
    assert [e.kind for e in m.effects] == [e["kind"] for e in spec["effects"]]
    g = torch.randn(2, 3, 400, dtype=torch.float64).cumsum(-1) * 0.1
    G, b0 = m(g, 1e-5)
    # chain = effects applied one after the other; eddy kinds driven by the demanded g (docs/contracts.md §3)
    Gr, br = g, torch.zeros(2, 400, dtype=torch.float64)
    for e in m.effects:
        Gr, br = e(Gr, br, 1e-5, demand=g) if e.kind.endswith("eddy") else e(Gr, br, 1e-5)
    torch.testing.assert_close(G, Gr)
    torch.testing.assert_close(b0, br)
    assert float(b0.detach().abs().max()) > 0
    # save -> load gives the same model output; the save is deterministic
    out = tmp_path / "sub"
    out.mkdir()
    save_model(m, out / "m2.json")
    m2 = load_model(out / "m2.json")
    torch.testing.assert_close(m2(g, 1e-5)[0], G)
    assert json.loads((out / "m2.json").read_text())["effects"][0]["file"] == "../h.npz"
    save_model(m, out / "m3.json")
    assert (out / "m2.json").read_bytes() == (out / "m3.json").read_bytes()
    with pytest.raises(InputError, match="exists"):
        save_model(m, out / "m2.json")


def test_girf_shortcut_equals_model_file(tmp_path):
    save_girf(_girf(), tmp_path / "h.npz")
    (tmp_path / "m.json").write_text(json.dumps({"effects": [{"kind": "girf", "file": "h.npz"}]}))
    g = torch.randn(3, 300, dtype=torch.float64)
    a = resolve_model(girf=tmp_path / "h.npz")(g, 1e-5)
    b = resolve_model(model=tmp_path / "m.json")(g, 1e-5)
    torch.testing.assert_close(a[0], b[0])
    torch.testing.assert_close(a[1], b[1])
    with pytest.raises(InputError, match="either"):
        resolve_model(girf=tmp_path / "h.npz", model=tmp_path / "m.json")


def test_girf_save_is_deterministic_and_freq_domain_roundtrip(tmp_path):
    gd = _girf(L=64)
    save_girf(gd, tmp_path / "a.npz")
    save_girf(gd, tmp_path / "b.npz")
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    # frequency-domain file on the two-sided DFT grid of the same kernel -> identical taps
    N, dt = 64, gd.dt_s
    f = (np.arange(N) - N // 2) / (N * dt)
    H, H0 = gd.response(f)
    save_npz(tmp_path / "f.npz", {"f": f, "H": H, "H0": H0})
    back = load_girf(tmp_path / "f.npz").to_time_domain()
    assert back.dt_s == pytest.approx(dt, rel=1e-12) and back.t0_s == pytest.approx(gd.t0_s, rel=1e-12)
    np.testing.assert_allclose(back.h, gd.h, atol=1e-12)
    np.testing.assert_allclose(back.h0, gd.h0, atol=1e-12)
    # one-sided grid
    f1 = np.arange(N // 2 + 1) / (N * dt)
    H1, _ = gd.response(f1)
    save_npz(tmp_path / "f1.npz", {"f": f1, "H": H1})
    np.testing.assert_allclose(load_girf(tmp_path / "f1.npz").to_time_domain().h, gd.h, atol=1e-12)


@pytest.mark.parametrize(
    "arrays,match",
    [
        ({"h": np.zeros((3, 3, 5))}, "'dt' missing"),
        ({"h": np.zeros((3, 3, 5)), "dt": np.float64(np.nan)}, "'dt'"),
        ({"h": np.zeros((3, 3, 5)), "dt": np.float64(-1e-5)}, "'dt' must be > 0"),
        ({"h": np.zeros((2, 2, 5)), "dt": np.float64(1e-5)}, r"'h' must have shape \(3, 3, L\)"),
        ({"h": np.full((3, 3, 5), np.nan), "dt": np.float64(1e-5)}, "'h' contains NaN"),
        ({"h": np.zeros((3, 3, 5)), "dt": np.float64(1e-5), "h0": np.zeros((3, 4))}, "'h0' must have shape"),
        ({"f": np.array([0.0, 2.0, 1.0, 3.0]), "H": np.zeros((3, 3, 4), complex)}, "'f' must be strictly increasing"),
        ({"f": np.array([0.0, 1.0, 3.0, 4.0]), "H": np.zeros((3, 3, 4), complex)}, "'f' must be a uniform"),
        ({"f": np.arange(4.0), "H": np.zeros((3, 4), complex)}, r"'H' must have shape \(3, 3, 4\)"),
        ({"H": np.zeros((3, 3, 4), complex)}, "'f' missing"),
        ({"x": np.zeros(3)}, "not a GIRF file"),
    ],
)
def test_bad_girf_files(tmp_path, arrays, match):
    save_npz(tmp_path / "bad.npz", arrays)
    with pytest.raises(InputError, match=match):
        load_girf(tmp_path / "bad.npz")


def test_bad_girf_not_npz_and_missing(tmp_path):
    (tmp_path / "x.npz").write_text("hello")
    with pytest.raises(InputError, match="not a readable"):
        load_girf(tmp_path / "x.npz")
    with pytest.raises(InputError, match="not found"):
        load_girf(tmp_path / "nope.npz")


@pytest.mark.parametrize(
    "text,match",
    [
        ('{"effects": [{"kind": "wobble"}]}', "unknown effect kind 'wobble'"),
        ('{"effects": [{"kind": "gain", "params": {}}]}', "missing parameter"),
        ('{"effects": [{"kind": "gain", "params": {"factor": 1, "x": 2}}]}', "unknown parameter"),
        ('{"effects": [{"kind": "gain", "axis": "q", "params": {"factor": 1}}]}', "axis"),
        ('{"effects": [{"kind": "exp_eddy", "params": {"alpha": 0.1, "tau_s": NaN}}]}', "finite"),
        ('{"effects": [{"kind": "exp_eddy", "params": {"alpha": [0.1, 0.2], "tau_s": 1e-3}}]}', "same length"),
        ('{"effects": [{"kind": "girf"}]}', "needs 'file'"),
        ('{"effects": [{"kind": "girf", "file": "missing.npz"}]}', "not found"),
        ('{"effects": [{"kind": "cross_eddy", "axis": "x", "params": {"alpha": 0.1, "tau_s": 1e-3}}]}', "input_axis"),
        ('{"effecs": []}', "effecs"),
        ("[1, 2]", "JSON object"),
        ('{"effects": [', "not valid JSON"),
    ],
)
def test_bad_model_files(tmp_path, text, match):
    p = tmp_path / "m.json"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as ei:
        load_model(p)
    assert "\n" not in str(ei.value)


def test_build_effect_api():
    e = build_effect("exp_eddy", {"alpha": 0.1, "tau_s": 1e-3}, axis="x")
    assert e.spec() == {"kind": "exp_eddy", "axis": "x", "input_axis": None, "params": {"alpha": 0.1, "tau_s": 0.001}}
    with pytest.raises(InputError):
        build_effect("gain", {"factor": 1.0}, input_axis="x")


# ---------------------------------------------------------------- measurement files
def _meas_arrays(M=3, N=200, dt=1e-5):
    rng = np.random.default_rng(1)
    g = rng.normal(0, 1, (M, 3, N)).cumsum(-1)
    return {
        "dt": np.float64(dt),
        "g": g,
        "G": g * 0.99,
        "b0": rng.normal(0, 0.1, (M, N)),
        "sigma_G": np.float64(0.01),
        "labels": np.array(["a", "b", "c"][:M]),
        "axes_measured": np.array([[1, 1, 0]] * M, dtype=bool),
    }


def test_measurement_roundtrip_and_k_derivation(tmp_path):
    arr = _meas_arrays()
    arr["G"][:, 2] = np.nan  # unmeasured entries may hold anything
    save_npz(tmp_path / "m.npz", arr)
    m = load_measurement(tmp_path / "m.npz")
    assert m.n_waveforms == 3 and m.n_samples == 200 and m.labels == ["a", "b", "c"] and m.sigma_G == 0.01
    assert m.k is None and np.isnan(m.G[:, 2]).all() and m.axes_measured[:, :2].all()
    k = m.realized_k()
    from dtoc.constants import GAMMA_RAD_PER_S_PER_MT

    np.testing.assert_allclose(
        k[:, :2, -1], GAMMA_RAD_PER_S_PER_MT * np.trapezoid(m.G[:, :2], dx=m.dt_s, axis=-1), rtol=1e-12
    )
    # smooth waveform: k -> G by central differences is accurate
    t = np.arange(1000) * 1e-5
    G = np.sin(2 * np.pi * 200 * t)[None, None].repeat(3, 1)
    np.testing.assert_allclose(G_from_k(k_from_G(G, 1e-5), 1e-5)[..., 1:-1], G[..., 1:-1], atol=2e-3)
    save_measurement(m, tmp_path / "m2.npz")
    m2 = load_measurement(tmp_path / "m2.npz")
    np.testing.assert_array_equal(m2.G[:, :2], m.G[:, :2])
    assert m.subset([0, 2]).labels == ["a", "c"]


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda a: a.pop("dt"), "'dt' missing"),
        (lambda a: a.update(dt=np.float64(0.0)), "'dt' must be > 0"),
        (lambda a: a.update(dt=np.zeros(2)), "'dt' must be a scalar"),
        (lambda a: a.pop("g"), "'g' missing"),
        (lambda a: a.update(g=np.zeros((3, 2, 200))), r"'g' must have shape \(M, 3, N\)"),
        (lambda a: (a.pop("G"), a.pop("b0")), "needs key 'G'"),
        (lambda a: a.update(G=np.zeros((3, 3, 199))), r"'G' must have shape \(3, 3, 200\)"),
        (lambda a: a["G"].__setitem__((0, 0, 3), np.nan), "'G' contains NaN"),
        (lambda a: a.update(b0=np.zeros((3, 3, 200))), r"'b0' must have shape \(3, 200\)"),
        (lambda a: a.update(sigma_G=np.float64(-1)), "'sigma_G'"),
        (lambda a: a.update(labels=np.array(["a"])), "'labels'"),
        (lambda a: a.update(axes_measured=np.ones((3, 2), bool)), "'axes_measured'"),
    ],
)
def test_bad_measurement_files(tmp_path, mutate, match):
    arr = _meas_arrays()
    mutate(arr)
    save_npz(tmp_path / "m.npz", arr)
    with pytest.raises(InputError, match=match) as ei:
        load_measurement(tmp_path / "m.npz")
    assert "\n" not in str(ei.value)


def _exp_conv_slew(x: np.ndarray, dt: float, tau: float) -> np.ndarray:
    """Independent reference: dx/dt conv exp(-t/tau) at the samples of the piecewise-linear x (zero before
    t = 0), by dense quadrature of the analytic segment integrals (not the twin's recursion)."""
    N = x.shape[-1]
    t = np.arange(N) * dt
    out = np.zeros_like(x)
    # the jump at t = 0 (x is zero before it) and the constant slew of each segment
    out += x[..., :1] * np.exp(-t / tau)
    s = np.diff(x, axis=-1) / dt
    for j in range(N - 1):  # segment [t_j, t_j+1]: integral of s_j exp(-(t - u)/tau) du for u < t
        t0, t1 = j * dt, (j + 1) * dt
        live = t > t0
        hi = np.minimum(t, t1)
        val = s[..., j : j + 1] * tau * (np.exp(-(t - hi) / tau) - np.exp(-(t - t0) / tau))
        out += np.where(live, val, 0.0)
    return out


def test_eddy_kinds_are_driven_by_the_demanded_waveform(tmp_path):
    """After a GIRF, exp_eddy / cross_eddy / b0_eddy follow docs/contracts.md §3: the slew of the *demanded*
    g drives them (G = GIRF(g) - alpha dg/dt conv exp); the *_chain variants are driven by the GIRF's output."""
    save_girf(_girf(), tmp_path / "h.npz")
    dt, tau, alpha, beta, c0 = 1e-5, 3e-4, 0.08, 0.03, 0.2
    rng = np.random.default_rng(3)
    g = np.cumsum(rng.normal(size=(1, 3, 300)), -1) * 0.2
    gt = torch.as_tensor(g)
    girf_only = load_model_from(tmp_path, [{"kind": "girf", "file": "h.npz"}])
    P, P0 = (v.detach().numpy() for v in girf_only(gt, dt))
    eddies = [
        {"kind": "girf", "file": "h.npz"},
        {"kind": "exp_eddy", "axis": "x", "params": {"alpha": alpha, "tau_s": tau}},
        {"kind": "cross_eddy", "axis": "z", "input_axis": "y", "params": {"alpha": beta, "tau_s": tau}},
        {"kind": "b0_eddy", "input_axis": "y", "params": {"alpha_uT_per_mT_per_m": c0, "tau_s": tau}},
    ]
    for suffix, src in (("", g), ("_chain", P)):
        spec = [dict(e, kind=e["kind"] + suffix) if "eddy" in e["kind"] else e for e in eddies]
        G, b0 = (v.detach().numpy() for v in load_model_from(tmp_path, spec, f"m{suffix}.json")(gt, dt))
        np.testing.assert_allclose(G[0, 0], P[0, 0] - alpha * _exp_conv_slew(src[0, 0], dt, tau), atol=1e-10)
        np.testing.assert_allclose(G[0, 1], P[0, 1], atol=1e-12)
        np.testing.assert_allclose(G[0, 2], P[0, 2] - beta * _exp_conv_slew(src[0, 1], dt, tau), atol=1e-10)
        np.testing.assert_allclose(b0[0], P0[0] - c0 * _exp_conv_slew(src[0, 1], dt, tau), atol=1e-10)
    # the two drives differ measurably behind a GIRF (its ~group delay and band limit)
    Gd = load_model_from(tmp_path, eddies, "d.json")(gt, dt)[0].detach().numpy()
    Gc = load_model_from(tmp_path, spec, "c.json")(gt, dt)[0].detach().numpy()
    assert np.abs(Gd - Gc).max() > 1e-3


def load_model_from(folder, effects, name="m.json"):
    (folder / name).write_text(json.dumps({"effects": effects}))
    return load_model(folder / name)
