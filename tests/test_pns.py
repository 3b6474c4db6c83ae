"""SAFE PNS (dtoc.seq.pns): the same numbers as pypulseq's implementation, and the check that uses it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from cli_helpers import run_cli

from dtoc.seq.pns import SafeAxis, SafeModel, safe_pns

REPO = Path(__file__).resolve().parents[1]


def _example_model() -> SafeModel:
    from pypulseq.utils.safe_pns_prediction import safe_example_hw

    hw = safe_example_hw()  # pypulseq's EXAMPLE hardware (not a real scanner)

    def ax(a):
        return SafeAxis(
            tau1_ms=a.tau1,
            tau2_ms=a.tau2,
            tau3_ms=a.tau3,
            a1=a.a1,
            a2=a.a2,
            a3=a.a3,
            stim_limit_T_per_m_per_s=a.stim_limit,
            stim_thresh_T_per_m_per_s=a.stim_thresh,
            g_scale=a.g_scale,
        )

    return SafeModel(x=ax(hw.x), y=ax(hw.y), z=ax(hw.z))


def test_same_numbers_as_pypulseq_safe():
    from pypulseq.utils.safe_pns_prediction import safe_example_hw, safe_gwf_to_pns

    dt = 10e-6
    t = np.arange(3000) * dt
    g = np.stack([30 * np.sin(2 * np.pi * 1e3 * t), 20 * np.sign(np.sin(2 * np.pi * 700 * t)), 10 * t / t[-1]])
    ref, _ = safe_gwf_to_pns(g.T * 1e-3, np.zeros(g.shape[1]), dt, safe_example_hw(), do_padding=False)
    ours = safe_pns(g, dt, _example_model())
    np.testing.assert_allclose(ours.per_axis_percent, ref.T, atol=1e-9)
    # a steady slew s on one axis tends to (a1 + a2 + a3) s / stim_limit * g_scale * 100
    m = _example_model()
    ramp = np.zeros((3, 20000))
    ramp[0] = np.arange(20000) * 100.0 * dt * 1e3  # 100 T/m/s on x, mT/m
    r = safe_pns(ramp, dt, m)
    x = m.x
    assert r.per_axis_percent[0, -1] == pytest.approx(
        (x.a1 + x.a2 + x.a3) * 100 / x.stim_limit_T_per_m_per_s * x.g_scale * 100, rel=1e-3
    )


def _profile(tmp_path, pns: SafeModel | None) -> Path:
    d = yaml.safe_load((REPO / "scanners" / "kcl_terra_7T.yaml").read_text())
    d.pop("hardware")
    d["pns"] = None if pns is None else pns.model_dump()
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


def test_check_fails_above_the_stimulation_limit_and_says_when_it_did_not_check(capsys, tmp_path):
    strong = REPO / "sequences" / "gre_small.seq"  # 500 T/m/s spoilers: 143 % on the example hardware
    code, out, err = run_cli(capsys, "check", strong, "--scanner", _profile(tmp_path, _example_model()), "--json", "-")
    import json

    res = json.loads(out)
    pns = [v for v in res["violations"] if v["rule"] == "pns"]
    assert code == 1 and pns and pns[0]["value"] > 100 and pns[0]["unit"] == "%"
    assert any(c.startswith("PNS (SAFE): max") for c in res["checks"])
    gentle = REPO / "sequences" / "epi_esp073.seq"  # long trains but gentler peaks: 88 %
    model = _example_model().model_copy(update={"limit_percent": 100.0})
    code, out, err = run_cli(capsys, "check", gentle, "--scanner", _profile(tmp_path, model), "--json", "-")
    res = json.loads(out)
    assert "pns" not in {v["rule"] for v in res["violations"]} and "PNS (SAFE): max" in err
    code, out, err = run_cli(capsys, "check", gentle, "--scanner", _profile(tmp_path, None))
    assert "PNS: not checked" in err and "PNS (SAFE)" not in err


def test_forbidden_acoustic_band_at_the_epi_readout_frequency(capsys, tmp_path):
    """An EPI switches its readout at 1 / (2 echo spacing): 89 % of the x power of the foreign EPI sits within
    +-10 % of its 819 Hz fundamental; a band there fails the check (rule acoustic), a band elsewhere does not."""
    import json

    from foreign.writers import epi

    seq = tmp_path / "epi.seq"
    seq.write_bytes(epi())
    d = yaml.safe_load((REPO / "scanners" / "kcl_terra_7T.yaml").read_text())
    d.pop("hardware")
    for band, fails in (([740, 900], True), ([2500, 3000], False)):
        d["acoustic_forbidden_bands_hz"] = [band]
        p = tmp_path / "p.yaml"
        p.write_text(yaml.safe_dump(d))
        code, out, err = run_cli(capsys, "check", seq, "--scanner", p, "--json", "-")
        res = json.loads(out)
        ac = [v for v in res["violations"] if v["rule"] == "acoustic"]
        assert bool(ac) == fails and code == (1 if fails else 0), (band, res["violations"], err)
        assert "acoustic bands: at most" in err
        if fails:
            assert ac[0]["axis"] == "x" and ac[0]["value"] > 80


def test_optimize_writes_nothing_that_fails_the_profiles_safety_checks(capsys, tmp_path):
    from foreign.writers import epi

    seq = tmp_path / "epi.seq"
    seq.write_bytes(epi())
    d = yaml.safe_load((REPO / "scanners" / "kcl_terra_7T.yaml").read_text())
    d.pop("hardware")
    d["acoustic_forbidden_bands_hz"] = [[740, 900]]  # around the EPI's 819 Hz readout fundamental
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump(d))
    out = tmp_path / "o.seq"
    code, _, err = run_cli(capsys, "optimize", seq, "--scanner", p, "--ideal", "-o", out, "--warm-iters", "5", "-q")
    errors = [ln for ln in err.splitlines() if ln.startswith("dtoc: error:")]  # the reader's notes come first
    assert code == 1 and len(errors) == 1 and "forbidden band 740-900 Hz" in errors[0] and "Traceback" not in err
    assert sorted(x.name for x in tmp_path.iterdir()) == ["epi.seq", "p.yaml"]
