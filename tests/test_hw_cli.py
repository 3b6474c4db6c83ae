"""CLI of the hardware twin: girf import/fit/show, predict; one-line errors; deterministic outputs."""

import json

import numpy as np
import pytest
from cli_helpers import run_cli as _run  # noqa: E402

from dtoc.hardware.npzio import save_npz


def _synthetic_ir():
    """A tiny EPI-like IR: alternating readout lobes on x with one ADC per lobe, blips on y."""
    from dtoc.seq.ir import ADCEvent, RFEvent, SequenceIR, edges_to_fine

    r = 10e-6
    lobe = np.concatenate([np.linspace(0, 20, 11), np.full(30, 20.0), np.linspace(20, 0, 11)[1:]])  # edges
    gx = [np.zeros(20)]
    adc = []
    t = 20 * r
    for i in range(8):
        gx.append(lobe * (1 if i % 2 == 0 else -1))
        adc.append(ADCEvent(block=1 + i, t_start_s=t + 10 * r, num_samples=30, dwell_s=r))
        t += (lobe.size) * r
    gx.append(np.zeros(21))
    ex = np.concatenate(gx)
    edges = np.zeros((3, ex.size))
    edges[0] = ex
    fine = edges_to_fine(edges)
    return SequenceIR(
        raster_s=r,
        grad_mT_per_m=fine,
        block_edges_s=np.array([0, (ex.size - 1) * r]),
        rf=[RFEvent(0, 0.0, 0.0, 0.0, np.pi / 2, 0.0, 0.0, "excitation")],
        adc=adc,
        fov_m=(0.25, 0.25, 0.003),
        kind="epi",
        readout_axis=0,
        phase_axis=1,
    )


def test_girf_show_json_and_png(capsys, repo_root, tmp_path):
    code, out, err = _run(
        capsys, "girf", "show", repo_root / "girf" / "example_7T.npz", "--json", "-", "--png", tmp_path / "g.png"
    )
    assert code == 0, err
    rows = {r["term"]: r for r in json.loads(out)["terms"]}
    assert rows["x->x"]["dc_gain"] == pytest.approx(1.0, abs=1e-9)
    assert rows["x->x"]["bandwidth_3db_hz"] == pytest.approx(10.7e3, rel=0.01)
    assert rows["x->x"]["group_delay_s"] == pytest.approx(2e-6, abs=0.05e-6)
    assert (tmp_path / "g.png").stat().st_size > 10_000


def test_girf_fit_cli_and_determinism(capsys, repo_root, tmp_path):
    import torch

    from dtoc.hardware import load_girf
    from dtoc.hardware.effects import Girf

    gd = load_girf(repo_root / "girf" / "example_7T.npz")
    eff = Girf(gd.h, gd.dt_s, gd.t0_s, gd.h0)
    N, dt = 2048, 10e-6
    t = np.arange(N) * dt
    g = np.zeros((6, 3, N))
    for m in range(6):
        ramp = (60e-6, 150e-6)[m // 3]
        g[m, m % 3] = 15 * np.clip(1 - np.abs(t - 2e-3 - ramp) / ramp, 0, None)
    with torch.no_grad():
        G, b0 = eff(torch.as_tensor(g), torch.zeros(6, N, dtype=torch.float64), dt)
    save_npz(tmp_path / "meas.npz", {"dt": np.float64(dt), "g": g, "G": G.numpy(), "b0": b0.numpy()})
    args = ["girf", "fit", tmp_path / "meas.npz", "--fmax-khz", "40", "--tmin-ms", "-2", "--tmax-ms", "8"]
    code, out, err = _run(capsys, *args, "-o", tmp_path / "a.npz", "--json", "-")
    assert code == 0, err
    rows = {r["term"]: r for r in json.loads(out)["terms"]}
    assert rows["y->y"]["dc_gain"] == pytest.approx(1.0, abs=1e-3)
    assert rows["x->y"]["peak_gain"] == pytest.approx(0.01, rel=0.1)
    code, _, err = _run(capsys, *args, "-o", tmp_path / "b.npz")
    assert code == 0
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    code, _, err = _run(capsys, *args, "-o", tmp_path / "b.npz")
    assert code != 0 and "exists" in err and err.count("\n") == 1


def test_predict_on_synthetic_epi(capsys, repo_root, tmp_path, monkeypatch):
    import dtoc.seq.load as rd

    ir = _synthetic_ir()
    monkeypatch.setattr(rd, "load_sequence", lambda p, **k: ir)
    code, out, err = _run(
        capsys,
        "predict",
        "x.seq",
        "--girf",
        repo_root / "girf" / "example_7T.npz",
        "--json",
        "-",
        "--png",
        tmp_path / "p.png",
    )
    assert code == 0, err
    res = json.loads(out)
    assert res["grad_error"]["x"]["max_mT_per_m"] > 0.1
    assert 0.01 < res["grad_error"]["z"]["max_mT_per_m"] < 0.05 * 20  # z only sees the ~1 % x->z cross term
    assert res["k_error"]["x"]["max_dk"] > 0.05
    assert res["b0_phase_max_rad"] > 0  # the example GIRF has B0 terms
    ro = res["epi"]["readout"]
    assert ro["odd_minus_even_dk"] != 0 and len(ro["line_offsets_rad_per_m"]) == 8
    # ideal hardware: exactly zero errors
    code, out, _ = _run(capsys, "predict", "x.seq", "--json", "-")
    res = json.loads(out)
    assert res["k_error"]["x"]["max_rad_per_m"] == 0.0 and res["b0_phase_max_rad"] == 0.0


@pytest.mark.parametrize(
    "argv,match",
    [
        (["girf", "show", "missing.npz"], "not found"),
        (["girf", "import", "missing.mat", "-o", "x.npz"], "not found"),
        (["girf", "fit", "missing.npz", "-o", "x.npz"], "not found"),
        (["predict", "x.seq", "--girf", "a.npz", "--model", "m.json"], "either"),
    ],
)
def test_cli_errors_are_one_line(capsys, tmp_path, monkeypatch, argv, match):
    monkeypatch.chdir(tmp_path)
    code, _, err = _run(capsys, *argv)
    assert code != 0 and match in err and err.count("\n") == 1 and "Traceback" not in err


def test_cli_bad_model_file(capsys, tmp_path, monkeypatch):
    import dtoc.seq.load as rd

    monkeypatch.setattr(rd, "load_sequence", lambda p, **k: _synthetic_ir())
    (tmp_path / "m.json").write_text('{"effects": [{"kind": "eddy", "params": {}}]}')
    code, _, err = _run(capsys, "predict", "x.seq", "--model", tmp_path / "m.json")
    assert code != 0 and "unknown effect kind 'eddy'" in err and err.count("\n") == 1


def test_cli_bad_girf_file(capsys, tmp_path):
    save_npz(tmp_path / "bad.npz", {"h": np.full((3, 3, 4), np.nan), "dt": np.float64(1e-5)})
    code, _, err = _run(capsys, "girf", "show", tmp_path / "bad.npz")
    assert code != 0 and "'h' contains NaN" in err and err.count("\n") == 1
