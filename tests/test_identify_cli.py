"""`dtoc identify` end to end: files in, §2.3 report + updated model + PNG out; bad files -> one-line errors."""

import json

import numpy as np
import pytest
import torch
from cli_helpers import run_cli

from dtoc.hardware.girf_io import save_girf
from dtoc.hardware.model import HardwareModel, build_effect, girf_effect, load_model
from dtoc.identify.synth import lowpass_girf, probe_waveforms, save_measurement, simulate_measurement

DT = 10e-6
REPORT_KEYS = {"before", "after", "heldout_before", "heldout_after", "noise", "effects", "explained", "remaining"}
RMSE_KEYS = {"G_rmse", "k_rmse", "b0_rmse"}


def _run(argv, capsys):
    return run_cli(capsys, *argv)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("ident")
    gd = lowpass_girf(DT)
    save_girf(gd, d / "declared.npz")
    g = probe_waveforms(4, 2000, DT, seed=21)
    true = HardwareModel([girf_effect(gd), build_effect("exp_eddy", {"alpha": 0.03, "tau_s": 1.5e-3}, axis="y")])
    meas = simulate_measurement(true, g, DT, sigma_G=0.01, seed=22)
    save_measurement(meas, d / "meas.npz")
    return d, meas


def test_end_to_end(files, capsys):
    d, meas = files
    argv = [
        "identify",
        str(d / "meas.npz"),
        "--girf",
        str(d / "declared.npz"),
        "--json",
        str(d / "rep.json"),
        "-o",
        str(d / "updated.json"),
        "--png",
        str(d / "res.png"),
        "-q",
    ]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    assert "exp_eddy" in out and "explained" in out  # the table is on stdout
    rep = json.loads((d / "rep.json").read_text())
    assert REPORT_KEYS <= set(rep)
    for k in ("before", "after", "heldout_before", "heldout_after"):
        assert set(rep[k]) >= RMSE_KEYS
        assert rep[k]["k_rmse"] is None and rep[k]["b0_rmse"] is None
    assert set(rep["noise"]) == {"G", "k", "b0"}
    assert rep["noise"]["G"] == pytest.approx(0.01, rel=0.1)
    e = rep["effects"][0]
    assert {"kind", "axis", "input_axis", "params", "stderr", "score"} <= set(e)
    assert (e["kind"], e["axis"], e["input_axis"]) == ("exp_eddy", "y", None)
    assert e["params"]["alpha"] == pytest.approx(0.03, abs=0.0015)
    assert rep["explained"] is True
    assert rep["after"]["G_rmse"] < 0.2 * rep["before"]["G_rmse"]
    assert (d / "res.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # The updated model loads and predicts the measurement to the noise floor.
    m = load_model(d / "updated.json")
    assert [x.kind for x in m.effects] == ["girf", "exp_eddy"]
    with torch.no_grad():
        G, _ = m(torch.as_tensor(meas.g), DT)
    assert np.sqrt(np.mean((G.numpy() - meas.G) ** 2)) < 1.1 * 0.01
    # Outputs are not clobbered without --force; with --force the run is byte-identical.
    code, _, err = _run(argv, capsys)
    assert code != 0 and "--force" in err and err.count("\n") == 1
    first = ((d / "rep.json").read_bytes(), (d / "updated.json").read_bytes(), (d / "res.png").read_bytes())
    code, _, err = _run(argv + ["--force"], capsys)
    assert code == 0, err
    again = ((d / "rep.json").read_bytes(), (d / "updated.json").read_bytes(), (d / "res.png").read_bytes())
    assert first == again


def _bad(tmp_path, **arrays):
    p = tmp_path / "bad.npz"
    np.savez(p, **arrays)
    return p


GOOD = dict(dt=np.float64(1e-5), g=np.zeros((2, 3, 50)), G=np.zeros((2, 3, 50)))


@pytest.mark.parametrize(
    "change, key",
    [
        (dict(g=None), "'g'"),
        (dict(G=np.zeros((2, 3, 49))), "'G'"),
        (dict(G=np.full((2, 3, 50), np.nan)), "'G'"),
        (dict(G=None), "'G'"),
        (dict(dt=np.float64(0.0)), "'dt'"),
        (dict(dt=np.float64(-1e-5)), "'dt'"),
        (dict(b0=np.zeros((2, 49))), "'b0'"),
    ],
    ids=["missing-g", "shape-mismatch", "nan", "no-G-or-k", "dt-zero", "dt-negative", "b0-shape"],
)
def test_bad_measurement_files(tmp_path, capsys, change, key):
    arrays = dict(GOOD)
    for k, v in change.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    p = _bad(tmp_path, **arrays)
    code, out, err = _run(["identify", str(p), "-o", str(tmp_path / "u.json")], capsys)
    assert code != 0
    assert err.startswith("dtoc: error:") and err.count("\n") == 1 and "Traceback" not in err
    assert key in err
    assert not (tmp_path / "u.json").exists()


def test_unknown_kind_is_rejected(files, capsys, tmp_path):
    d, _ = files
    code, _, err = _run(
        ["identify", str(d / "meas.npz"), "-o", str(tmp_path / "u.json"), "--kinds", "delay,warp"], capsys
    )
    assert code != 0 and "warp" in err


def test_axes_measured_are_respected(capsys, tmp_path):
    """Unmeasured axes (NaN in the file) are ignored; the delay on the measured axis is still found."""
    g = probe_waveforms(3, 2000, DT, seed=31)
    true = HardwareModel([build_effect("delay", {"seconds": 4e-6}, axis="x")])
    meas = simulate_measurement(true, g, DT, sigma_G=0.01, seed=32)
    G = meas.G.copy()
    axes = np.ones((3, 3), dtype=bool)
    axes[:, 2] = False
    G[:, 2] = np.nan
    p = tmp_path / "m.npz"
    np.savez(p, dt=DT, g=g, G=G, axes_measured=axes)
    code, out, err = _run(
        ["identify", str(p), "-o", str(tmp_path / "u.json"), "--json", str(tmp_path / "r.json"), "-q"], capsys
    )
    assert code == 0, err
    rep = json.loads((tmp_path / "r.json").read_text())
    e = rep["effects"][0]
    assert (e["kind"], e["axis"]) == ("delay", "x")
    assert e["params"]["seconds"] == pytest.approx(4e-6, abs=0.1e-6)
    assert "G_z" not in rep["per_axis"]["before"]
