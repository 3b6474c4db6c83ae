"""Scanner profiles (docs/scanner.md): typed, relative paths, explicit options win, "not checked" never "passed"."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_helpers import run_cli

from dtoc.errors import InputError
from dtoc.hardware.profile import load_profile

REPO = Path(__file__).resolve().parents[1]
EPI = REPO / "sequences" / "epi_small.seq"
PROFILES = sorted((REPO / "scanners").glob("*.yaml"))


@pytest.mark.parametrize("path", PROFILES, ids=[p.stem for p in PROFILES])
def test_example_profiles_load_and_point_at_real_girfs(path, shared_data):
    lp = load_profile(path)
    s = lp.profile.system_spec()
    assert s.max_grad_mT_per_m > 0 and s.grad_raster_s == 1e-5
    girfs, _ = lp.hardware_files()
    assert girfs and all(str(shared_data) in str(g.resolve()) or g.exists() for g in girfs)
    model = lp.hardware_model()
    assert model is not None and not model.is_identity


def test_bad_profiles_are_one_line(tmp_path):
    good = (REPO / "scanners" / "kcl_terra_7T.yaml").read_text()
    cases = {
        "unknown key": good + "wormhole: 1\n",
        "negative limit": good.replace("gmax_mT_per_m: 72", "gmax_mT_per_m: -72"),
        "missing b0": good.replace("b0_T: 6.98\n", ""),
        "raster in us": good.replace("grad_s: 1.0e-5", "grad_s: 10"),
        "not a mapping": "- 1\n- 2\n",
    }
    for name, text in cases.items():
        p = tmp_path / "p.yaml"
        p.write_text(text)
        with pytest.raises(InputError) as e:
            load_profile(p)
        assert "\n" not in str(e.value), name
    p.write_text(good.replace("7T_GIRF.mat", "missing.mat"))
    with pytest.raises(InputError, match="not found"):
        load_profile(p).hardware_model()


def test_commands_take_the_profile_and_explicit_options_win(capsys, tmp_path, shared_data):
    from foreign.writers import gre

    prof = REPO / "scanners" / "kcl_terra_7T.yaml"
    g = tmp_path / "gre.seq"
    g.write_bytes(gre())  # written with a 10 us ADC dead time, as the profile's
    code, out, err = run_cli(capsys, "check", g, "--scanner", prof)
    assert code == 0 and "--scanner KCL-Terra-7T-2024: 72 mT/m, 180 T/m/s" in out
    assert "PNS: not checked" in err and "acoustic bands: not checked" in err
    code, out, _ = run_cli(capsys, "check", g, "--scanner", prof, "--gmax", "5")
    assert code == 1 and "5 mT/m" in out  # --gmax overrides the profile
    o = tmp_path / "o.seq"
    argv = ["optimize", EPI, "--scanner", prof, "--smax", "175", "-o", o, "--json", tmp_path / "m.json", "-q"]
    code, _, err = run_cli(capsys, *argv, "--warm-iters", "20", "--iters", "1")
    assert code == 0, err
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["limits"]["source"] == {"gmax_mT_per_m": "--scanner KCL-Terra-7T-2024", "smax_T_per_m_per_s": "--smax"}
    assert m["limits"]["smax_T_per_m_per_s"] == 175 and m["options"]["b0_T"] == 6.98
    assert m["inputs"]["scanner"]["path"].endswith("kcl_terra_7T.yaml") and m["inputs"]["girf"] is None
    assert m["after"]["kspace_max_error_dk"] < m["before"]["kspace_max_error_dk"]


def test_simulate_predict_identify_take_the_profiles_model(capsys, tmp_path):
    """A profile pointing at a GIRF .npz (relative path): simulate, predict and identify use its model and B0."""
    import yaml

    from dtoc.hardware.girf_io import save_girf
    from dtoc.hardware.model import HardwareModel, build_effect, girf_effect
    from dtoc.identify.synth import lowpass_girf, probe_waveforms, save_measurement, simulate_measurement

    (tmp_path / "g").mkdir()
    d = yaml.safe_load((REPO / "scanners" / "kcl_terra_7T.yaml").read_text())
    d["hardware"] = {"girf": "g/example.npz"}
    (tmp_path / "g" / "example.npz").write_bytes((REPO / "girf" / "example_7T.npz").read_bytes())
    prof = tmp_path / "p.yaml"
    prof.write_text(yaml.safe_dump(d))
    code, out, _ = run_cli(capsys, "simulate", EPI, "--scanner", prof, "--json", "-", "-q")
    ref_code, ref, _ = run_cli(
        capsys, "simulate", EPI, "--girf", REPO / "girf" / "example_7T.npz", "--b0", "6.98", "--json", "-", "-q"
    )
    r, r0 = json.loads(out), json.loads(ref)
    assert code == ref_code == 0 and r["nrmse_percent"] == r0["nrmse_percent"] and r["phantom"]["field_T"] == 6.98
    code, out, _ = run_cli(capsys, "predict", EPI, "--scanner", prof, "--json", "-")
    assert code == 0 and json.loads(out)["k_error"]["x"]["max_rad_per_m"] > 0  # not ideal hardware
    dt = 10e-6
    gd = lowpass_girf(dt)
    save_girf(gd, tmp_path / "g" / "declared.npz")
    d["hardware"] = {"girf": "g/declared.npz"}
    prof.write_text(yaml.safe_dump(d))
    true = HardwareModel([girf_effect(gd), build_effect("delay", {"seconds": 3e-6}, axis="x")])
    meas = simulate_measurement(true, probe_waveforms(3, 1500, dt, seed=5), dt, sigma_G=0.01, seed=6)
    save_measurement(meas, tmp_path / "m.npz")
    code, out, err = run_cli(capsys, "identify", tmp_path / "m.npz", "--scanner", prof, "-o", tmp_path / "u.json", "-q")
    assert code == 0, err
    assert "delay" in out  # the profile's GIRF was the declared model: only the delay is missing
